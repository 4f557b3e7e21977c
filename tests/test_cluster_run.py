"""bcmocap run on a cluster started as a user starts one (``dask scheduler`` and two ``dask worker`` processes by
their command lines, reached at ``tcp://``) and bcmocap batch on a LocalCluster, on a small rendered capture: the
frontend's cameras and chunks as tasks give the same correspondences as a run without a cluster, also when a
worker is killed mid-task (its nanny starts it again and the scheduler reruns its task); a batch reports a failed
capture and finishes the others.

The run without a cluster is a ``bcmocap run`` process of its own, as a user starts it. (This test found that
workers unpickled a task's camera models before switching JAX to float64, so the cluster tracked with float32
intrinsics: workers now start in float64.)"""

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from bcmocap.correspondence_store import CorrespondenceStore
from bcmocap.pipeline.batch import run_batch
from bcmocap.pipeline.cluster import WORKER_ENVIRONMENT, open_executor
from bcmocap.pipeline.config import RunConfig
from bcmocap.sim.studio import StudioSettings, write_capture

pytestmark = pytest.mark.slow

CONFIG = RunConfig().with_overrides({"frontend.registration": "tracking", "frontend.stride": 1,
                                     "frontend.rom_stride": 1, "frontend.max_features": 2000,
                                     "frontend.chunk_frames": 5})
#: ``bcmocap`` as a user runs it, in a process of its own
BCMOCAP = [sys.executable, "-c", "import sys; from bcmocap.cli import main; sys.exit(main(sys.argv[1:]))"]


@pytest.fixture(scope="module")
def capture_and_run(tmp_path_factory):
    """A 0.5 s walk and a 0.5 s ROM trial at 20 frames/s through the 18-camera rig, and its frontend run
    without a cluster by ``bcmocap run`` in a process of its own."""
    root = tmp_path_factory.mktemp("cluster")
    write_capture(root / "capture", StudioSettings(seconds=0.5, rom_seconds=0.5, fps=20.0, reference_photos=24,
                                                   reference_width=640, reference_height=480, seed=1), progress=False)
    (root / "config.json").write_text(json.dumps(CONFIG.to_dict()))
    done = subprocess.run([*BCMOCAP, "run", str(root / "capture"), "--out", str(root / "alone"),
                           "--config", str(root / "config.json"), "--stop-after", "frontend"],
                          capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, done.stderr[-2000:]
    return root


@pytest.fixture
def command_line_cluster(tmp_path):
    """``dask scheduler`` and two ``dask worker`` processes (one thread each, with their nannies), started by their
    command lines as on a machine of a real cluster, each in a session of its own (its logs in ``tmp_path``); yields
    the scheduler's ``tcp://`` address. Afterwards each session is ended, a nanny's worker with it."""
    dask = [str(Path(sys.executable).with_name("dask"))]
    scheduler_file = tmp_path / "scheduler.json"
    environment = {**os.environ, **WORKER_ENVIRONMENT}

    def start(name, command, env=None):
        with open(tmp_path / f"{name}.log", "w") as log:  # the process keeps its own copy of the file
            return subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)

    processes = [start("scheduler", [*dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                     "--scheduler-file", str(scheduler_file)])]
    try:
        deadline, address = time.monotonic() + 60, None
        while address is None and time.monotonic() < deadline:
            try:  # the file may be there before its whole text
                address = json.loads(scheduler_file.read_text())["address"]
            except (OSError, ValueError, KeyError):
                time.sleep(0.2)
        assert address, "the scheduler wrote no address: " + (tmp_path / "scheduler.log").read_text()[-2000:]
        for k in range(2):
            processes.append(start(f"worker-{k}", [*dask, "worker", "--scheduler-file", str(scheduler_file), "--nthreads",
                                                   "1", "--no-dashboard", "--name", f"worker-{k}", "--local-directory",
                                                   str(tmp_path / f"worker-{k}")], environment))
        yield address
    finally:
        for process in reversed(processes):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGTERM)
        for process in reversed(processes):
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGKILL)
                process.wait()


def test_a_cluster_run_with_a_worker_killed_mid_task_equals_the_run_without_one(capture_and_run, command_line_cluster):
    """``bcmocap run --cluster tcp://...`` on the command-line cluster, as a user runs it; a worker running a chunk's
    registration is killed from a client of the same scheduler, its nanny starts it again, and the run's stores equal
    the run without a cluster's bit for bit. (This test found that ``dask scheduler``, started without float64 JAX,
    unpickled the tasks' camera models as float32 on their way to the workers: tasks now travel as bytes.)"""
    from distributed import Client

    root = capture_and_run
    # the reference model is built in the run's own process, not as a task: the cluster run reads the plain run's
    # (as a rerun would) instead of building it again
    shutil.copytree(root / "alone" / "frontend" / "reference", root / "cluster" / "frontend" / "reference")
    with Client(command_line_cluster, timeout="60s") as client:
        deadline = time.monotonic() + 120
        while len(client.nthreads()) < 2 and time.monotonic() < deadline:
            time.sleep(0.5)
        assert len(client.nthreads()) == 2, "the two workers did not join the scheduler"
        run = subprocess.Popen([*BCMOCAP, "run", str(root / "capture"), "--out", str(root / "cluster"),
                                "--config", str(root / "config.json"), "--stop-after", "frontend", "--cluster",
                                command_line_cluster], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            output = []
            reader = threading.Thread(target=lambda: output.extend(run.stdout), daemon=True)
            reader.start()
            killed = []
            deadline = time.monotonic() + 1500
            while run.poll() is None and not killed and time.monotonic() < deadline:
                registering = [address for address, keys in client.processing().items()  # a chunk, not the function
                               if any(key.startswith("register") and "-function-" not in key for key in keys)]
                if registering:
                    pid = client.run(os.getpid, workers=[registering[0]])[registering[0]]
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
                time.sleep(0.2)
            assert run.wait(timeout=max(1.0, deadline - time.monotonic())) == 0, "".join(output)[-3000:]
            reader.join()
        finally:
            if run.poll() is None:
                run.kill()
                run.wait()
    assert killed, "no worker was killed during a chunk's registration"
    log = "".join(output)
    assert f"cluster: {command_line_cluster}, 2 worker(s)" in log and "chunks as tasks" in log
    assert "reference: read" in log
    alone = json.loads((root / "alone" / "run.json").read_text())["stages"]["frontend"]
    assert json.loads((root / "cluster" / "run.json").read_text())["stages"]["frontend"]["capture"] == alone["capture"]
    for trial in ("rom", "capture"):
        x = CorrespondenceStore.open(root / "alone" / "frontend" / trial / "correspondences").load()
        y = CorrespondenceStore.open(root / "cluster" / "frontend" / trial / "correspondences").load()
        assert x.registered.mean() > 0.5 and np.array_equal(x.registered, y.registered), trial
        for field in ("world_from_camera", "pixels", "point_ids", "points", "weights"):
            assert np.array_equal(np.asarray(getattr(x, field)), np.asarray(getattr(y, field)), equal_nan=True), (trial, field)


def test_a_batch_reports_a_failed_capture_and_finishes_the_others(capture_and_run, tmp_path):
    root = capture_and_run
    shutil.copytree(root / "alone", tmp_path / "batch" / "capture")  # resumed: the batch machinery, not the frontend
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "capture.json").write_text("{not json")
    lines = []
    with open_executor("local:2", log=lines.append) as executor:
        rows = run_batch([root / "capture", tmp_path / "broken", tmp_path / "missing"], tmp_path / "batch", CONFIG,
                         executor, log=lines.append, stop_after="frontend")
    assert [r["ok"] for r in rows] == [True, False, False]
    alone = json.loads((root / "alone" / "run.json").read_text())["stages"]["frontend"]
    assert rows[0]["registered_capture"] == alone["capture"]["registered_fraction"]
    assert "capture.json" in rows[1]["error"] and "missing" in rows[2]["error"]
    saved = json.loads((tmp_path / "batch" / "batch.json").read_text())
    assert [r["ok"] for r in saved["rows"]] == [True, False, False]
    assert sum("FAILED" in line for line in lines) == 2
