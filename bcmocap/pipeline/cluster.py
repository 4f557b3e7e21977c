"""Where a run's independent pieces of work go: this process, or a Dask cluster.

``bcmocap run --cluster SPEC`` (or ``[cluster] address = SPEC`` in the config) hands the run's
independent work to Dask's distributed scheduler: each camera's tracking, each chunk's registration,
the two trials of the frontend side by side, and, with ``solver.windows = "independent"``, the solver's
windows. ``SPEC`` is

- ``local:N``: a ``LocalCluster`` of ``N`` worker processes on this machine, one thread each (started
  for the run, stopped after it);
- ``tcp://HOST:PORT`` (or ``tls://``, ``ws://``): the scheduler of a cluster that already runs (e.g.
  started by ``dask-jobqueue`` on SLURM/PBS, or ``dask scheduler`` / ``dask worker``); its workers must
  see the capture and output folders at the same paths (a shared file system) and have bcmocap installed.

Tasks read their inputs from and write their outputs to the run folder and return small summaries, so a
lost worker's task is rerun by the scheduler and an interrupted run resumes from what finished. The
cluster never changes a result: a setting does (``frontend.chunk_frames``, ``solver.windows``), and the
same settings give the same outputs with or without a cluster.

Every task runs one piece of work on one core (OpenCV and XLA are held to one thread in a worker): the
number of workers is the parallelism, as Dask's scheduler expects.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import time
from collections.abc import Callable, Iterable, Iterator

from .worker_setup import worker_setup

#: Environment of each local worker process: numeric libraries on one thread (one task = one core).
WORKER_ENVIRONMENT = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false",
    "BCMOCAP_THREADS": "1",  # the frontend's own thread pools (bcmocap.frontend.threads.default_threads)
    # float64 from the start: a task's arguments (a capture's camera models) are JAX arrays, unpickled before
    # the task runs; in float32 they would silently lose their last digits
    "JAX_ENABLE_X64": "1",
}
#: Dask settings of the local workers started here: less of Dask's own housekeeping, which on a machine whose
#: cores all run tasks takes their time (two registration chunks at once on two workers of two cores: 7 %
#: slower than each alone with Dask's defaults, 3 % with these, 0 % outside Dask; benchmarks/task_contention.py).
#: For a cluster started from Python, start it inside ``dask.config.set(LOCAL_WORKER_CONFIG)``.
LOCAL_WORKER_CONFIG = {
    "distributed.worker.profile.enabled": False,  # the dashboard's profiler: every task's stack every 10 ms
    "distributed.admin.tick.interval": "1s",  # the event loop's blocked-time check (default every 20 ms)
    "distributed.admin.system-monitor.interval": "5s",  # CPU, memory, disk and network readings (500 ms)
    "distributed.worker.memory.monitor-interval": "1s",  # the nanny's look at its worker's memory (100 ms)
    # without Dask's MALLOC_TRIM_THRESHOLD_=65536: glibc then returns every large array freed to the system and
    # faults in the next one's pages anew (twice the system time of a chunk's registration)
    "distributed.nanny.pre-spawn-environ": {key: WORKER_ENVIRONMENT[key]
                                            for key in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")},
}
MAX_LOCAL_WORKERS = 1024
_ADDRESS = re.compile(r"^(tcp|tls|ws|wss)://[A-Za-z0-9._\-\[\]:]+:\d{1,5}$")


@dataclasses.dataclass(frozen=True)
class ClusterSpec:
    """A parsed ``--cluster`` value: ``local`` workers to start, or the ``address`` of a running scheduler."""

    local_workers: int = 0
    address: str = ""

    @property
    def text(self) -> str:
        return f"local:{self.local_workers}" if self.local_workers else self.address


def parse_cluster(text: str) -> ClusterSpec | None:
    """``"local:N"`` / ``"tcp://HOST:PORT"`` → :class:`ClusterSpec`; ``""`` → None (no cluster).

    Raises:
        ValueError: naming the value and the two accepted forms.
    """
    text = str(text).strip()
    if not text:
        return None
    if text.startswith("local:"):
        count = text.removeprefix("local:")
        if not count.isdigit() or not 1 <= int(count) <= MAX_LOCAL_WORKERS:
            raise ValueError(f"cluster {text!r}: local:N needs a number of workers N in 1..{MAX_LOCAL_WORKERS}")
        return ClusterSpec(local_workers=int(count))
    if _ADDRESS.match(text):
        return ClusterSpec(address=text)
    raise ValueError(f"cluster {text!r}: expected local:N (N worker processes on this machine) or "
                     "tcp://HOST:PORT (a running Dask scheduler)")


class Executor:
    """Runs independent calls: in this process (no cluster) or as Dask tasks.

    ``map(fn, items, label=...)`` returns ``fn(item)`` for each item, in order; with a cluster the calls
    are tasks that may run at once on different workers (``fn`` and the items are pickled: pass paths
    and small values, not big arrays). For timing reports, ``tasks`` records ``(label, seconds, cpu_seconds)``
    of each finished call, measured where it ran (wall time and the CPU time of its process), and ``calls``
    the ``(label, start, stop)`` of each ``map`` call on this process's ``time.perf_counter`` clock (the
    caller waits for its tasks meanwhile).
    """

    def __init__(self, client=None):
        self.client = client
        self.tasks: list[tuple[str, float, float]] = []
        self.calls: list[tuple[str, float, float]] = []

    @property
    def distributed(self) -> bool:
        return self.client is not None

    @property
    def workers(self) -> int:
        """Worker threads of the cluster (1 without one)."""
        if self.client is None:
            return 1
        return max(1, sum(self.client.nthreads().values()))

    def map(self, fn: Callable, items: Iterable, *, label: str = "task",
            on_done: Callable[[int, object], None] | None = None) -> list:
        """``[fn(item) for item in items]``, as tasks on the cluster when there is one; ``on_done(i, result)``
        is called as each finishes (in completion order with a cluster)."""
        items = list(items)
        if not items:
            return []
        clock = time.perf_counter()
        try:
            return self._map(fn, items, label, on_done)
        finally:
            self.calls.append((label, clock, time.perf_counter()))

    def _map(self, fn: Callable, items: list, label: str, on_done) -> list:
        if self.client is None:
            out = []
            for i, item in enumerate(items):
                result, seconds, cpu = _timed(fn, item)
                self.tasks.append((label, seconds, cpu))
                out.append(result)
                if on_done is not None:
                    on_done(i, result)
            return out
        from distributed import as_completed, wait

        # fn goes to the cluster once, not once per task (it may hold a reference index), as the result of a
        # task rather than scattered data: a worker lost with it makes the scheduler compute it again, while
        # lost scattered data cannot be recovered and would cancel every task that needs it.
        # fn and the items travel as bytes, unpickled on the worker after worker_setup: the scheduler unpickles a task's
        # arguments, and one started without float64 JAX (as `dask scheduler` is) turned a capture's float64 camera
        # models into float32 ones on their way to the workers.
        from distributed.protocol.pickle import dumps

        shared = self.client.submit(_unpickled, dumps(fn), pure=False, key=f"{label}-function-{os.urandom(4).hex()}")
        # ... and to every worker, so that no worker is preferred for holding it.
        wait([shared])
        if shared.status == "finished" and len(self.client.nthreads()) > 1:
            try:
                self.client.replicate([shared])
            except (ValueError, OSError, AssertionError, TimeoutError):
                # a worker lost meanwhile: the scheduler samples more workers than it has (ValueError), a connection
                # closes (OSError), or the lost worker held the only copy (the scheduler's AssertionError). The copies
                # only spread the load: the tasks fetch fn as they need it, and the scheduler computes it again if
                # every copy is lost.
                pass
        # At most one task per worker thread is handed to the scheduler at a time, the next as one finishes:
        # tasks given at once are queued on workers up front, and a worker's queue was not moved to a worker
        # left idle (the last chunks of one trial ran one after another on one worker while the other waited).
        todo = iter(range(len(items)))
        running = {}  # future → index of its item
        done = as_completed()

        def hand_over_next() -> None:
            i = next(todo, None)
            if i is not None:
                future = self.client.submit(_timed_pickled, shared, dumps(items[i]), pure=False,
                                            key=f"{label}-{i}-{os.urandom(4).hex()}")
                running[future] = i
                done.add(future)

        out = [None] * len(items)
        try:
            for _ in range(self.workers):
                hand_over_next()
            for future in done:
                result, seconds, cpu = future.result()
                self.tasks.append((label, seconds, cpu))
                i = running.pop(future)
                out[i] = result
                hand_over_next()
                if on_done is not None:
                    on_done(i, result)
        finally:
            for future in (*running, shared):  # what is left after an error
                future.cancel()
        return out


def _unpickled(data: bytes):
    """``data`` unpickled on a worker, after :func:`worker_setup` (float64 JAX)."""
    from distributed.protocol.pickle import loads

    worker_setup()
    return loads(data)


def _timed_pickled(fn: Callable, item: bytes) -> tuple[object, float, float]:
    """:func:`_timed` of the item pickled in ``item``."""
    return _timed(fn, _unpickled(item))


def _timed(fn: Callable, item) -> tuple[object, float, float]:
    """``(fn(item), wall seconds, CPU seconds of this process meanwhile)`` (a worker runs one task at a time)."""
    worker_setup()
    clock, cpu = time.perf_counter(), time.process_time()
    result = fn(item)
    return result, time.perf_counter() - clock, time.process_time() - cpu


@contextlib.contextmanager
def open_executor(spec: ClusterSpec | str | None, log: Callable[[str], None] = print, *,
                  connect_timeout_s: float = 20.0) -> Iterator[Executor]:
    """An :class:`Executor` on the cluster ``spec`` (started here for ``local:N``, connected to otherwise,
    waiting at most ``connect_timeout_s``), closed on exit; ``None`` or ``""``: no cluster.

    Raises:
        ValueError: a bad spec, or a scheduler that cannot be reached (one line).
    """
    if isinstance(spec, str):
        spec = parse_cluster(spec)
    if spec is None:
        yield Executor()
        return
    import logging

    import dask
    from distributed import Client, LocalCluster

    with contextlib.ExitStack() as stack:
        # a map sends the function its tasks share (it may hold a reference index of some 10 MB) once, as a
        # task of its own: by design, not the repeated data Dask's large-graph warning is about
        stack.enter_context(dask.config.set({"distributed.admin.large-graph-warning-threshold": "1GiB"}))
        if spec.local_workers:
            stack.enter_context(dask.config.set(LOCAL_WORKER_CONFIG))  # read by the workers as they start
            cluster = stack.enter_context(LocalCluster(
                n_workers=spec.local_workers, threads_per_worker=1, processes=True, dashboard_address=None,
                silence_logs=logging.ERROR, env=dict(WORKER_ENVIRONMENT)))
            client = stack.enter_context(Client(cluster))
            log(f"cluster: {spec.local_workers} local worker process(es) at {cluster.scheduler_address}")
        else:
            try:
                client = stack.enter_context(Client(spec.address, timeout=f"{connect_timeout_s}s"))
            except (OSError, TimeoutError) as exc:
                raise ValueError(f"cluster {spec.address}: cannot reach the scheduler ({exc})") from None
            log(f"cluster: {spec.address}, {len(client.nthreads())} worker(s)")
        from .worker_plugin import WorkerSetup

        client.register_plugin(WorkerSetup())
        yield Executor(client)
