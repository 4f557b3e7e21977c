"""bcmocap.native_crashes: pycolmap's import installs glog's failure signal handler (not async-signal-safe: a fault
in the C++ unwinder then hangs the process); load_pycolmap() puts the fatal signals back, so a native fault ends the
process at once with Python's faulthandler report."""

import signal
import subprocess
import sys

import pytest

CRASH = """
import ctypes, faulthandler, sys
faulthandler.enable()
{load}
ctypes.string_at(0)  # a segmentation fault in native code
"""


def _crash(load: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", CRASH.format(load=load)], capture_output=True, text=True, timeout=60)


def test_a_native_fault_after_load_pycolmap_ends_the_process_with_pythons_report():
    result = _crash("from bcmocap.native_crashes import load_pycolmap; load_pycolmap()")
    assert result.returncode == -signal.SIGSEGV
    assert "Fatal Python error: Segmentation fault" in result.stderr
    assert "*** SIGSEGV" not in result.stderr  # glog's handler is gone


def test_a_plain_pycolmap_import_hands_the_fault_to_glog():
    """The reason for the module: after a plain import glog's handler takes the fault (here it still ends the
    process; inside the unwinder it waits for ever)."""
    result = _crash("import pycolmap")
    assert "SIGSEGV" in result.stderr and "received by PID" in result.stderr


def test_a_python_sigterm_handler_survives_the_import():
    code = ("import os, signal, time\n"
            "signal.signal(signal.SIGTERM, lambda *a: print('handled', flush=True))\n"
            "from bcmocap.native_crashes import load_pycolmap; load_pycolmap()\n"
            "os.kill(os.getpid(), signal.SIGTERM); time.sleep(0.2); print('alive')\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.split() == ["handled", "alive"], result


@pytest.mark.parametrize("name", ["SIGSEGV", "SIGABRT", "SIGBUS", "SIGFPE", "SIGILL"])
def test_no_fatal_signal_keeps_a_native_handler_in_the_test_process(name):
    """conftest loads pycolmap through bcmocap.native_crashes: beneath faulthandler (if on) each fatal signal has
    its default action, not glog's handler."""
    import ctypes
    import faulthandler

    class SigAction(ctypes.Structure):
        _fields_ = [("handler", ctypes.c_void_p), ("mask", ctypes.c_ulong * 16), ("flags", ctypes.c_int),
                    ("restorer", ctypes.c_void_p)]

    import pycolmap  # noqa: F401  (imported before: no new handlers)

    enabled = faulthandler.is_enabled()
    faulthandler.disable()
    try:
        action = SigAction()
        assert ctypes.CDLL(None).sigaction(getattr(signal, name), None, ctypes.byref(action)) == 0
    finally:
        if enabled:
            faulthandler.enable()
    assert action.handler is None  # SIG_DFL
