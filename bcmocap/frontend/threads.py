"""How many threads the frontend's pools use."""

from __future__ import annotations

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
