"""The peak resident memory of this process over a stretch of work (each stage of ``bcmocap run``).

Linux keeps a process's high-water mark of resident memory (``VmHWM`` in ``/proc/self/status``) and resets it when
``5`` is written to ``/proc/self/clear_refs``; a stage's peak is the mark read at its end after a reset at its
start. Where that is not possible (another OS, a kernel that refuses the reset) the peak since the process
started is reported instead (``getrusage``), which is an upper bound. Work done in other processes (Dask workers)
is not counted.
"""

from __future__ import annotations

import re
import resource
import sys

#: What lowers each stage's memory, for the message of a stage that ran out of it.
LOWER_MEMORY = {
    "frontend": "lower [frontend] chunk_frames (frames registered at once) or max_features",
    "world": "lower [frontend] chunk_frames (the registered poses are re-fitted a chunk at a time)",
    "skeleton": "shorten the rest or range-of-motion trial, or raise [frontend] rom_stride",
    "initial": "lower [frontend] max_measurements (measurements kept per camera and frame)",
    "solve": "lower [solver] window (frames solved at once) or [frontend] max_measurements",
    "outputs": "lower [outputs] settings that draw pictures, or raise [frontend] stride",
}
_OUT_OF_MEMORY = re.compile(r"RESOURCE_EXHAUSTED|[Oo]ut of memory|Failed to allocate|Insufficient memory|bad_alloc")


def reset_peak() -> bool:
    """Start a new high-water mark; False where the kernel does not allow it (then :func:`peak_mb` is the
    process's peak so far)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_mb() -> float:
    """The resident memory's high-water mark since :func:`reset_peak` (else since the process started), in MB."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return round(int(line.split()[1]) / 1024, 1)
    except (OSError, ValueError, IndexError):
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return round(peak / (1024 * 1024 if sys.platform == "darwin" else 1024), 1)


def out_of_memory(exc: BaseException) -> bool:
    """Whether ``exc`` is an allocation that failed: Python's MemoryError, or XLA's or OpenCV's errors for one."""
    return isinstance(exc, MemoryError) or bool(_OUT_OF_MEMORY.search(str(exc)[:2000]))


def stage_out_of_memory(stage: str, exc: BaseException) -> MemoryError:
    """The one-line error of a stage that could not allocate: the stage, its peak so far and what lowers it."""
    detail = " ".join(str(exc).split())[:160]
    return MemoryError(f"the {stage} stage ran out of memory at a peak of {peak_mb():,.0f} MB"
                       f"{f' ({detail})' if detail else ''}; to lower it, {LOWER_MEMORY[stage]}")
