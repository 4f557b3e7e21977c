"""The Dask worker plugin of :mod:`~bcmocap.pipeline.cluster` (a module of its own: it imports ``distributed``,
which a run without a cluster never loads)."""

from __future__ import annotations

from distributed.diagnostics.plugin import WorkerPlugin

from .worker_setup import worker_setup


class WorkerSetup(WorkerPlugin):
    """Runs :func:`~bcmocap.pipeline.worker_setup.worker_setup` (float64 JAX, compilation cache, one OpenCV thread)
    on every worker as it joins, before it runs a task: the workers of a cluster started elsewhere
    (``tcp://``) do not have :data:`~bcmocap.pipeline.cluster.WORKER_ENVIRONMENT`."""

    name = "bcmocap-worker-setup"

    def setup(self, worker) -> None:
        worker_setup()
