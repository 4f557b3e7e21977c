"""How many threads the frontend's pools use, and handing the memory their work freed back to the system."""

from __future__ import annotations

import functools
import os


def default_threads() -> int:
    """Threads the frontend's pools use when not told: ``BCMOCAP_THREADS`` if set (a cluster's worker process
    sets 1: one task, one core), else the CPU count. Results do not depend on it (threads' results are used
    in order)."""
    try:
        given = int(os.environ.get("BCMOCAP_THREADS", "0"))
    except ValueError:
        given = 0
    return given if given > 0 else (os.cpu_count() or 1)


def give_back_freed_memory() -> None:
    """Return the memory freed so far to the operating system (glibc's ``malloc_trim``; nothing elsewhere).

    glibc keeps what threads free in its arenas: after a registration has dropped its FLANN indexes (gigabytes on a
    long trial) the process would still hold them, and the next chunk's indexes come on top under a memory limit.
    """
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    """glibc's ``malloc_trim``, or None where the C library has none."""
    import ctypes
    import ctypes.util

    try:
        trim = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None
    trim.argtypes = [ctypes.c_size_t]
    return trim
