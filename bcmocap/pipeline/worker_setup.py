"""What every task of ``bcmocap run`` needs in the process that runs it: float64 JAX, the persistent compilation
cache and, in a Dask worker, OpenCV on one thread. :mod:`~bcmocap.pipeline.cluster` calls it before each task and
the worker plugin (:mod:`~bcmocap.pipeline.worker_plugin`) as a worker joins; a module of its own so that neither
imports the other."""

from __future__ import annotations


def worker_setup() -> None:
    """What every task needs in a worker process (idempotent; cheap after the first call): float64 JAX, the
    persistent compilation cache, OpenCV on one thread."""
    from ..compilation_cache import enable_compilation_cache
    from ..precision import enable_float64

    enable_float64()
    enable_compilation_cache()
    if in_worker():
        import cv2

        cv2.setNumThreads(1)


def in_worker() -> bool:
    """Whether this process is a Dask worker running a task (False without ``distributed`` installed)."""
    try:
        from distributed import get_worker

        get_worker()
        return True
    except (ImportError, ValueError):
        return False
