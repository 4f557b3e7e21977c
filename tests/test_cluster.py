"""bcmocap.pipeline.cluster: the --cluster spec, and independent calls run in this process or as Dask tasks
on a LocalCluster of worker processes; bcmocap batch's run folders."""

import functools
import os
import signal
import time

import numpy as np
import pytest

from bcmocap.pipeline.batch import batch_items, summary_table
from bcmocap.pipeline.cluster import ClusterSpec, Executor, open_executor, parse_cluster
from bcmocap.pipeline.config import RunConfig


def test_cluster_specs_are_parsed_or_refused_by_name():
    assert parse_cluster("") is None and parse_cluster("  ") is None
    assert parse_cluster("local:2") == ClusterSpec(local_workers=2)
    assert parse_cluster("tcp://10.0.0.5:8786") == ClusterSpec(address="tcp://10.0.0.5:8786")
    assert parse_cluster("tls://sched.lab.org:8786").text == "tls://sched.lab.org:8786"
    for bad in ("local:0", "local:", "local:x", "local:-1", "10.0.0.5:8786", "tcp://host", "http://h:1",
                "tcp://h:1; rm -rf /"):
        with pytest.raises(ValueError, match="cluster"):
            parse_cluster(bad)


def test_the_cluster_setting_is_checked_and_changes_no_fingerprint():
    from bcmocap.pipeline.run import fingerprints

    with pytest.raises(ValueError, match="cluster.address"):
        RunConfig().with_overrides({"cluster.address": "local:zero"})
    with pytest.raises(ValueError, match="solver.windows"):
        RunConfig().with_overrides({"solver.windows": "parallel"})
    base = RunConfig()
    on_cluster = base.with_overrides({"cluster.address": "local:4"})
    assert fingerprints(on_cluster) == fingerprints(base)
    independent = fingerprints(base.with_overrides({"solver.windows": "independent"}))
    assert independent["initial"] == fingerprints(base)["initial"] and independent["solve"] != fingerprints(base)["solve"]


def test_fingerprints_of_runs_made_before_the_windows_setting_stay_the_same():
    """A run folder made before ``solver.windows`` (and ``solver.registered_pose``, ``registered_pose_below``, ``gyro_turn``,
    ``skeleton.centre_trials``, ``unregistered_ends``, ``unregistered_rest``, ``frontend.rolling_shutter_readout``, ``frontend.self_calibration``, ``gyro_timing`` and
    ``estimate_readout``) existed is still reused with the settings it was made with (those settings at
    the values that meant what the run did: no registered-pose prior, centres from the ROM trial)."""
    import hashlib
    import json

    from bcmocap.pipeline.run import STAGES, _STAGE_SECTIONS, fingerprints

    config = RunConfig().with_overrides({"solver.registered_pose": [0.0, 0.0], "skeleton.centre_trials": ["rom"]})
    data = config.to_dict()
    for key in ("windows", "registered_pose", "registered_pose_below", "gyro_turn"):
        del data["solver"][key]
    del data["skeleton"]["centre_trials"]
    del data["skeleton"]["unregistered_ends"]  # added later, at a value that changes nothing a run that finished did
    del data["skeleton"]["unregistered_rest"]  # likewise: it places only what stopped a run before it
    for key in ("rolling_shutter_readout", "self_calibration", "gyro_timing", "estimate_readout"):  # added later, off
        del data["frontend"][key]
    acc, old = [], {}
    for stage in STAGES:
        acc += [data[s] for s in _STAGE_SECTIONS[stage]]
        old[stage] = hashlib.sha256(json.dumps(acc, sort_keys=True).encode()).hexdigest()[:16]
    assert fingerprints(config) == old


def _square_and_pid(x: int) -> tuple[int, int]:
    return x * x, os.getpid()


def _fail_on_three(x: int) -> int:
    if x == 3:
        raise ValueError("three is refused")
    return x


def test_an_executor_without_a_cluster_runs_in_this_process_in_order():
    done = []
    ex = Executor()
    out = ex.map(_square_and_pid, [3, 1, 2], label="sq", on_done=lambda i, r: done.append(i))
    assert [o[0] for o in out] == [9, 1, 4] and {o[1] for o in out} == {os.getpid()}
    assert done == [0, 1, 2] and [t[0] for t in ex.tasks] == ["sq"] * 3 and not ex.distributed and ex.workers == 1


def test_a_local_cluster_runs_tasks_in_worker_processes_and_passes_errors_on():
    lines = []
    with open_executor("local:2", log=lines.append) as ex:
        assert ex.distributed and ex.workers == 2 and "2 local worker" in lines[0]
        done = []
        out = ex.map(_square_and_pid, range(6), label="sq", on_done=lambda i, r: done.append(i))
        assert [o[0] for o in out] == [x * x for x in range(6)]
        assert os.getpid() not in {o[1] for o in out} and sorted(done) == list(range(6))
        assert len(ex.tasks) == 6 and all(seconds >= 0 and cpu >= 0 for _, seconds, cpu in ex.tasks)
        with pytest.raises(ValueError, match="three is refused"):
            ex.map(_fail_on_three, range(5))


def _slow_offset_square(offset: np.ndarray, x: int) -> tuple[int, int]:
    time.sleep(0.3)
    return int(x * x + offset.sum()), os.getpid()


def test_a_map_survives_losing_every_worker_that_holds_its_function():
    """The mapped function goes to the cluster as a task's result, so the scheduler computes it again when
    the workers holding it die (scattered data would be lost for good, and its tasks cancelled)."""
    fn = functools.partial(_slow_offset_square, np.zeros(200_000))  # big enough to be worth sending once
    with open_executor("local:2", log=lambda line: None) as ex:
        killed = []

        def kill_every_worker(i, result):
            if not killed:
                pids = ex.client.run(os.getpid)
                for pid in pids.values():
                    os.kill(pid, signal.SIGKILL)
                killed.extend(pids.values())

        out = ex.map(fn, range(8), label="sq", on_done=kill_every_worker)
    assert len(killed) == 2 and [o[0] for o in out] == [x * x for x in range(8)]


def _busy_pid(data: np.ndarray, seconds: float) -> int:
    clock = time.perf_counter()
    while time.perf_counter() - clock < seconds:
        pass
    return os.getpid()


def test_a_map_goes_on_where_copying_its_function_to_every_worker_fails():
    # The function's copies to every worker only spread the load: where the scheduler cannot make them (a worker lost
    # meanwhile made distributed's replicate sample more workers than it has: ValueError), the map still runs.
    with open_executor("local:2", log=lambda line: None) as ex:
        def replicate(*args, **kwargs):
            raise ValueError("Sample larger than population or is negative")

        ex.client.replicate = replicate
        out = ex.map(functools.partial(_busy_pid, np.zeros(10)), [0.0] * 4, label="sq")
    assert len(out) == 4 and all(isinstance(pid, int) for pid in out)


def test_two_maps_at_once_share_the_workers_to_the_end():
    """Two trials' maps at once, each function held by one worker at first: when the short map is done, the
    long map's remaining tasks go to both workers (they were queued on one worker and ran there one by one)."""
    import threading

    with open_executor("local:2", log=lambda line: None) as ex:
        pids = {}

        def trial(label, count):
            pids[label] = ex.map(functools.partial(_busy_pid, np.zeros(200_000)), [0.7] * count, label=label)

        threads = [threading.Thread(target=trial, args=args) for args in (("rom", 2), ("capture", 8))]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    assert len(pids["capture"]) == 8 and len(set(pids["capture"][-4:])) == 2, pids


def _camera_dtype(camera) -> str:
    return str(camera.focal.dtype)


def test_tasks_receive_camera_models_in_float64_even_on_workers_started_without_it():
    """A task's JAX arrays are unpickled before it runs: the workers must be in float64 from the start (local
    workers by their environment; any worker by the plugin open_executor registers)."""
    from bcmocap.cameras import PinholeCamera
    from bcmocap.pipeline.cluster import WORKER_ENVIRONMENT

    camera = PinholeCamera(width=64, height=48, focal=[50.123456789012345, 50.0], principal_point=[32.0, 24.0])
    with open_executor("local:1", log=lambda line: None) as ex:
        assert ex.map(_camera_dtype, [camera]) == ["float64"]
        assert ex.client.run(lambda: os.environ.get("JAX_ENABLE_X64")) and WORKER_ENVIRONMENT["JAX_ENABLE_X64"] == "1"
        plugins = ex.client.run(lambda dask_worker: sorted(dask_worker.plugins))
        assert all("bcmocap-worker-setup" in names for names in plugins.values())


def _worker_settings() -> tuple:
    import dask

    return (dask.config.get("distributed.worker.profile.enabled"), dask.config.get("distributed.admin.tick.interval"),
            os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.environ.get("OMP_NUM_THREADS"))


def test_local_workers_start_with_less_housekeeping_and_glibc_s_own_trimming():
    with open_executor("local:1", log=lambda line: None) as ex:
        assert list(ex.client.run(_worker_settings).values()) == [(False, "1s", None, "1")]
    import dask

    assert dask.config.get("distributed.worker.profile.enabled")  # this process's settings are Dask's again


def test_an_unreachable_scheduler_is_one_clear_error():
    with pytest.raises(ValueError, match="cannot reach the scheduler"):
        with open_executor("tcp://127.0.0.1:9", log=lambda line: None, connect_timeout_s=1):
            pass


def test_batch_run_folders_are_named_after_the_captures_and_unique(tmp_path):
    (tmp_path / "a" / "walk").mkdir(parents=True)
    (tmp_path / "b" / "walk").mkdir(parents=True)
    (tmp_path / "run").mkdir()
    items = batch_items([tmp_path / "a" / "walk", tmp_path / "b" / "walk", tmp_path / "run"], tmp_path / "out")
    assert [i.out.name for i in items] == ["walk", "walk-2", "run"]
    assert all(i.out.parent == tmp_path / "out" for i in items)
    with pytest.raises(ValueError, match="given twice"):
        batch_items([tmp_path / "run", tmp_path / "a" / ".." / "run"], tmp_path / "out")
    with pytest.raises(ValueError, match="no capture"):
        batch_items([], tmp_path / "out")


def test_the_batch_table_says_what_failed():
    rows = [{"capture": "/x/walk", "ok": True, "registered_rom": 0.99, "registered_capture": 0.95,
             "joint_position_error_cm": 1.234, "joint_angle_error_deg": 0.5, "seconds": 12.0},
            {"capture": "/x/bad", "ok": False, "error": "/x/bad: no such folder", "seconds": 0.1}]
    table = summary_table(rows).splitlines()
    assert "99.0%" in table[1] and "1.23" in table[1] and table[1].endswith("ok")
    assert table[2].endswith("/x/bad: no such folder") and "–" in table[2]


def test_the_commands_refuse_a_bad_cluster_in_one_line_and_a_batch_reports_its_failures(tmp_path, capsys):
    from bcmocap.cli import main

    assert main(["run", str(tmp_path), "--out", str(tmp_path / "o"), "--cluster", "local:zero"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cluster" in err and not (tmp_path / "o").exists()
    assert main(["batch", str(tmp_path / "missing"), "--out", str(tmp_path / "b")]) == 1
    out = capsys.readouterr().out
    assert "FAILED" in out and "0 of 1 captures done" in out and (tmp_path / "b" / "batch.json").is_file()
