"""bcmocap run and bcmocap batch on a LocalCluster of worker processes, on a small rendered capture: the
frontend's cameras and chunks as tasks give the same correspondences as a run without a cluster, also when a
worker is killed mid-task; a batch reports a failed capture and finishes the others.

The run without a cluster is a ``bcmocap run`` process of its own, as a user starts it. (This test found that
workers unpickled a task's camera models before switching JAX to float64, so the cluster tracked with float32
intrinsics: workers now start in float64.)"""

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from bcmocap.correspondence_store import CorrespondenceStore
from bcmocap.pipeline.batch import run_batch
from bcmocap.pipeline.cluster import open_executor
from bcmocap.pipeline.config import RunConfig
from bcmocap.pipeline.run import run_pipeline
from bcmocap.sim.studio import StudioSettings, write_capture

pytestmark = pytest.mark.slow

CONFIG = RunConfig().with_overrides({"frontend.registration": "tracking", "frontend.stride": 1,
                                     "frontend.rom_stride": 1, "frontend.max_features": 2000,
                                     "frontend.chunk_frames": 5})
FIELDS = ("point_ids", "pixels", "weights", "registered", "world_from_camera", "points")


@pytest.fixture(scope="module")
def capture_and_run(tmp_path_factory):
    """A 0.5 s walk and a 0.5 s ROM trial at 20 frames/s through the 18-camera rig, and its frontend run
    without a cluster by ``bcmocap run`` in a process of its own."""
    root = tmp_path_factory.mktemp("cluster")
    write_capture(root / "capture", StudioSettings(seconds=0.5, rom_seconds=0.5, fps=20.0, reference_photos=24,
                                                   reference_width=640, reference_height=480, seed=1), progress=False)
    (root / "config.json").write_text(json.dumps(CONFIG.to_dict()))
    code = "import sys; from bcmocap.cli import main; sys.exit(main(sys.argv[1:]))"
    done = subprocess.run([sys.executable, "-c", code, "run", str(root / "capture"), "--out", str(root / "alone"),
                           "--config", str(root / "config.json"), "--stop-after", "frontend"],
                          capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, done.stderr[-2000:]
    return root


def _same_frontend(a, b) -> None:
    for trial in ("rom", "capture"):
        x = CorrespondenceStore.open(a / "frontend" / trial / "correspondences").load()
        y = CorrespondenceStore.open(b / "frontend" / trial / "correspondences").load()
        assert x.registered.mean() > 0.5, (trial, x.registered.mean())
        for field in FIELDS:
            assert np.array_equal(getattr(x, field), getattr(y, field), equal_nan=True), (trial, field)


def test_a_cluster_run_with_a_worker_killed_mid_task_equals_the_run_without_one(capture_and_run):
    root = capture_and_run
    killed = []

    def kill_a_busy_worker(client, stop):
        while not stop.is_set():
            busy = [addr for addr, keys in client.processing().items() if keys]
            if busy and any(k.startswith("register") for keys in client.processing().values() for k in keys):
                pid = client.run(os.getpid, workers=[busy[0]])[busy[0]]
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                return
            time.sleep(0.2)

    lines = []
    with open_executor("local:2", log=lines.append) as executor:
        stop = threading.Event()
        killer = threading.Thread(target=kill_a_busy_worker, args=(executor.client, stop), daemon=True)
        killer.start()
        try:
            log = run_pipeline(root / "capture", root / "cluster", CONFIG, log=lines.append, stop_after="frontend",
                               executor=executor)
        finally:
            stop.set()
            killer.join()
    assert killed, "no worker was killed during a chunk's registration"
    alone = json.loads((root / "alone" / "run.json").read_text())["stages"]["frontend"]
    assert log["stages"]["frontend"]["capture"] == alone["capture"] and any("chunks as tasks" in line for line in lines)
    labels = {label for label, *_ in executor.tasks}
    assert {"track rom", "track capture", "register rom", "register capture"} <= labels
    _same_frontend(root / "alone", root / "cluster")


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
