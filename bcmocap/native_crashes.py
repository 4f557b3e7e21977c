"""pycolmap, imported with the process's fatal-signal handling restored.

Importing pycolmap installs glog's failure signal handler for SIGSEGV, SIGABRT, SIGBUS, SIGFPE, SIGILL and SIGTERM.
That handler prints a native stack trace with ``backtrace()``, which is not async-signal-safe: a fault inside the C++
unwinder (while any native library unwinds an exception) makes the handler wait for a lock the faulting thread holds,
and the process hangs for ever instead of dying. The test suite met it: a worker stuck in ``_Unwind_Find_FDE`` under
glog's handler while JAX wrote a compilation-cache entry, until CI's time ran out. :func:`load_pycolmap` imports pycolmap
and puts those signals back to their defaults, so such a fault ends the process (with Python's :mod:`faulthandler`,
when enabled, printing every thread's Python stack first, which is async-signal-safe); a run then resumes from its
last complete stage instead of waiting forever.
"""

from __future__ import annotations

import signal
import threading
from types import ModuleType

__all__ = ["load_pycolmap"]

_FATAL = ("SIGSEGV", "SIGABRT", "SIGBUS", "SIGFPE", "SIGILL", "SIGTERM")
_lock = threading.Lock()
_module: ModuleType | None = None


def _restore_default_handlers() -> None:
    """Fatal signals back to what Python had (a Python handler of SIGTERM such as a Dask worker's, else the
    default), then faulthandler's handler again if it was enabled. Only the main thread may set handlers; from
    another the import's handlers stay."""
    if threading.current_thread() is not threading.main_thread():
        return
    import faulthandler

    enabled = faulthandler.is_enabled()
    if enabled:
        faulthandler.disable()
    for name in _FATAL:
        number = getattr(signal, name, None)
        if number is None:
            continue
        previous = signal.getsignal(number)  # what Python set: native code's handler is invisible to it
        signal.signal(number, previous if callable(previous) else signal.SIG_DFL)
    if enabled:
        faulthandler.enable()


def load_pycolmap() -> ModuleType:
    """The ``pycolmap`` module (imported on first use, then the fatal signals' handlers restored)."""
    global _module
    with _lock:
        if _module is None:
            import pycolmap as module

            _restore_default_handlers()
            _module = module
    return _module
