"""Do two cluster tasks on this machine slow each other down, and how much of it is Dask's? The limit of
issue 23's speedup.

Takes a finished ``bcmocap run`` folder (e.g. ``out-local1`` of ``benchmarks/scale_out.py``, whose SIFT cache
and reference model it reads, never writes) and runs some of its tasks, each in a fresh process set up as a
cluster worker is (:data:`~bcmocap.pipeline.cluster.WORKER_ENVIRONMENT`, OpenCV on one thread): first each
alone, one after the other, then all at once, one process each. Two kinds of task:

- ``register``: chunks ``--chunks`` of trial ``--trial`` registered as on a cluster (written to a temporary
  folder);
- ``sift``: ``--sift-frames`` frames of one camera's video through SIFT (decoded first, then timed).

Prints each task's wall and CPU seconds alone and together and the slowdown (together / alone). Then the
same chunks at once as tasks of a ``LocalCluster`` with one worker per chunk, twice: with Dask's default
settings and with those ``bcmocap run`` starts its local workers with
(:data:`~bcmocap.pipeline.cluster.LOCAL_WORKER_CONFIG`). With ``--profile`` (needs ``py-spy``) also the share
of a chunk's samples in its heaviest functions, alone.

    python benchmarks/task_contention.py --run /tmp/bcmocap-scale-out/out-local1 \\
        --json benchmarks/results/task_contention.json
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json  # noqa: E402


class _Captured(Exception):
    """Raised by :func:`_chunk_function`'s ``map_tasks`` once it holds the chunks' task function."""


def _chunk_function(run: Path, out: Path, trial: str):
    """The function ``k → chunk k registered`` that ``bcmocap run`` hands a cluster for ``trial`` of ``run``,
    writing under ``out`` (the run's SIFT cache is linked, not copied)."""
    from bcmocap.frontend.capture import read_capture
    from bcmocap.frontend.command import TrialOptions, prepare_reference, process_trial
    from bcmocap.frontend.register import reference_index
    from bcmocap.pipeline.config import RunConfig

    config = RunConfig.from_dict(json.loads((run / "config.json").read_text()), where=str(run / "config.json"))
    capture = read_capture(json.loads((run / "run.json").read_text())["capture"])
    (out / "features").symlink_to((run / "frontend" / "features").resolve())
    # one process at a time opens the reference database: COLMAP's open fails while another process opens it
    with open(Path(tempfile.gettempdir()) / "bcmocap-contention.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        index = reference_index(prepare_reference(capture, run / "frontend" / "reference", log=lambda line: None))
    found = {}

    def map_tasks(fn, items, label, on_done=None):
        if label.startswith("register"):
            found["fn"] = fn
            raise _Captured
        for i, item in enumerate(items):  # a camera's SIFT: read back from the linked cache
            result = fn(item)
            if on_done is not None:
                on_done(i, result)

    f = config.frontend
    try:
        options = TrialOptions(stride=f.rom_stride if trial == "rom" else f.stride, frames=f.frames or None,
                               max_features=f.max_features, homographies=trial == "capture",
                               chunk_frames=f.chunk_frames, registration=f.registration,
                               max_measurements=f.max_measurements or None, points=f.points)
        process_trial(capture, index, trial, out, options, log=lambda line: None, map_tasks=map_tasks)
    except _Captured:
        return found["fn"]
    raise ValueError(f"{run}: trial {trial!r} is registered in one chunk (frontend.chunk_frames), not as tasks")


def _seconds(work) -> dict:
    """Wall and CPU seconds (of this process) of ``work()``."""
    clock, cpu = time.perf_counter(), time.process_time()
    work()
    return {"wall": time.perf_counter() - clock, "cpu": time.process_time() - cpu}


def _one_task(kind: str, run: Path, trial: str, item: int, frames: int) -> dict:
    """In a worker-like process (a child of :func:`_start` or a Dask worker): task ``item`` of ``kind``; its wall
    and CPU seconds."""
    import cv2

    from bcmocap.precision import enable_float64

    enable_float64()
    cv2.setNumThreads(1)
    if kind == "register":
        with tempfile.TemporaryDirectory(prefix="bcmocap-contention-") as tmp:
            fn = _chunk_function(run, Path(tmp), trial)
            return _seconds(lambda: fn(item))
    from bcmocap.frontend.capture import read_capture
    from bcmocap.frontend.reference import extract_sift

    capture = read_capture(json.loads((run / "run.json").read_text())["capture"])
    camera = capture.camera_names[item % len(capture.camera_names)]
    images = [gray for _, gray in capture.frames(trial, camera, stop=frames, gray=True)]
    max_features = json.loads((run / "config.json").read_text())["frontend"]["max_features"]
    return _seconds(lambda: [extract_sift(gray, max_features=max_features) for gray in images])


def _start(kind: str, run: Path, trial: str, item: int, frames: int, profile: Path | None = None):
    """A fresh worker-like process running :func:`_one_task` (under ``py-spy`` when ``profile`` is given)."""
    from bcmocap.pipeline.cluster import WORKER_ENVIRONMENT

    command = [sys.executable, __file__, "--child", kind, str(run), trial, str(item), str(frames)]
    if profile is not None:
        command = [_py_spy(), "record", "--rate", "50", "--format", "raw", "--output", str(profile), "--", *command]
    return subprocess.Popen(command, env={**os.environ, **WORKER_ENVIRONMENT}, stdout=subprocess.PIPE, text=True)


def _py_spy() -> str:
    """The ``py-spy`` on the path or beside this Python."""
    beside = Path(sys.executable).parent / "py-spy"
    found = shutil.which("py-spy") or (str(beside) if beside.is_file() else None)
    if found is None:
        raise SystemExit("--profile needs py-spy (pip install py-spy)")
    return found


def _result(process) -> dict:
    output, _ = process.communicate()
    if process.returncode != 0:
        raise RuntimeError(f"a task process failed (exit {process.returncode})")
    return json.loads([line for line in output.splitlines() if line.startswith("{")][-1])


def measure(kind: str, run: Path, trial: str, items: list[int], frames: int) -> dict:
    """Each of ``items`` alone, then all at once: seconds and slowdowns."""
    alone = [_result(_start(kind, run, trial, i, frames)) for i in items]
    together = [_result(p) for p in [_start(kind, run, trial, i, frames) for i in items]]
    rows = [{"item": i, "alone": a, "together": t, "slowdown": t["wall"] / a["wall"]}
            for i, a, t in zip(items, alone, together)]
    return {"tasks": rows, "mean_slowdown": sum(r["slowdown"] for r in rows) / len(rows)}


def on_dask(run: Path, trial: str, chunks: list[int], settings: dict) -> list[dict]:
    """``chunks`` at once on a ``LocalCluster`` of one worker each, started with the Dask ``settings``."""
    import logging

    import dask
    from distributed import Client, LocalCluster

    from bcmocap.pipeline.cluster import WORKER_ENVIRONMENT

    environment = {**WORKER_ENVIRONMENT, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parent),
                                                                          os.environ.get("PYTHONPATH", "")])}
    with dask.config.set(settings), LocalCluster(n_workers=len(chunks), threads_per_worker=1, processes=True,
                                                 dashboard_address=None, silence_logs=logging.ERROR,
                                                 env=environment) as cluster, Client(cluster) as client:
        futures = [client.submit(_one_task, "register", run, trial, k, 0, pure=False) for k in chunks]
        return [future.result() for future in futures]


def profile_share(kind: str, run: Path, trial: str, item: int, frames: int, top: int = 6) -> list:
    """``[(function, share of samples), …]`` of one task alone: the heaviest functions by own time (Python
    frames; native code counts towards the Python function that called it)."""
    import collections

    with tempfile.TemporaryDirectory(prefix="bcmocap-contention-") as tmp:
        raw = Path(tmp) / "profile.txt"
        _result(_start(kind, run, trial, item, frames, profile=raw))
        counts, total = collections.Counter(), 0
        for line in raw.read_text().splitlines():
            stack, _, samples = line.rpartition(" ")
            frames_ = [f.split(" (")[0] for f in stack.split(";") if ".py:" in f]
            counts[frames_[-1] if frames_ else "(other)"] += int(samples)
            total += int(samples)
    return [(name, n / total) for name, n in counts.most_common(top)]


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        kind, run, trial, item, frames = sys.argv[2:7]
        print(json.dumps(_one_task(kind, Path(run), trial, int(item), int(frames))), flush=True)
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a finished bcmocap run folder")
    parser.add_argument("--trial", default="capture")
    parser.add_argument("--chunks", type=int, nargs="+", default=[2, 3], help="chunks registered together")
    parser.add_argument("--sift-frames", type=int, default=40)
    parser.add_argument("--profile", action="store_true", help="py-spy profile of the first chunk alone")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    needed = ("run.json", "config.json", "frontend/features", "frontend/reference/reference.json")
    missing = [name for name in needed if not (args.run / name).exists()]
    if missing:  # (the reference model would otherwise be built into the given folder)
        raise SystemExit(f"{args.run}: not a finished bcmocap run folder ({missing[0]} is missing)")
    report = {"run": str(args.run), "trial": args.trial}
    for kind, items in (("sift", list(range(len(args.chunks)))), ("register", args.chunks)):
        print(f"{kind}: {len(items)} task(s) alone, then at once ...", flush=True)
        report[kind] = measure(kind, args.run, args.trial, items, args.sift_frames)
        for row in report[kind]["tasks"]:
            print(f"  {kind} {row['item']}: alone {row['alone']['wall']:.2f} s (CPU {row['alone']['cpu']:.2f}), "
                  f"together {row['together']['wall']:.2f} s (CPU {row['together']['cpu']:.2f}): "
                  f"× {row['slowdown']:.3f}", flush=True)
    from bcmocap.pipeline.cluster import LOCAL_WORKER_CONFIG

    alone = {row["item"]: row["alone"]["wall"] for row in report["register"]["tasks"]}
    for name, settings in (("dask_defaults", {}), ("bcmocap_local_workers", LOCAL_WORKER_CONFIG)):
        print(f"register on a LocalCluster, {name.replace('_', ' ')} ...", flush=True)
        rows = [{"item": k, "together": t, "slowdown": t["wall"] / alone[k]}
                for k, t in zip(args.chunks, on_dask(args.run, args.trial, args.chunks, settings))]
        report[name] = {"tasks": rows, "mean_slowdown": sum(r["slowdown"] for r in rows) / len(rows)}
        for row in rows:
            print(f"  register {row['item']}: {row['together']['wall']:.2f} s (CPU {row['together']['cpu']:.2f}): "
                  f"× {row['slowdown']:.3f} of alone", flush=True)
    if args.profile:
        report["register_profile"] = profile_share("register", args.run, args.trial, args.chunks[0], 0)
        for name, share in report["register_profile"]:
            print(f"  {100 * share:5.1f} %  {name}")
    report["machine"] = machine()
    write_json(args.json, report)


if __name__ == "__main__":
    main()
