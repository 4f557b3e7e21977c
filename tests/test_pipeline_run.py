"""bcmocap.pipeline.run: the stages after the frontend, on simulated frontend output.

The frontend's files (``DIR/frontend/{rom,capture}/correspondences/`` and ``registration.json``) are
made from the simulator in an arbitrary structure-from-motion frame (a random similarity of the true
world), so the run must find the metric world, the skeleton, the motion and the outputs by itself; the
frontend itself is tested on rendered pixels in the test_frontend_* files.
"""

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest

from bcmocap.correspondence_store import CorrespondenceStore, write_store
from bcmocap.correspondences import Correspondences
from bcmocap.frontend.capture import Capture, CaptureCamera
from bcmocap.frontend.command import trial_settings
from bcmocap.geometry import SO3
from bcmocap.pipeline import RunConfig, run_pipeline
from bcmocap.pipeline.outputs import evaluate_run
from bcmocap.pipeline.run import load_model, load_motion
from bcmocap.pipeline.world import Similarity
from bcmocap.sim import standard_capture
from bcmocap.sim.rom import range_of_motion_trial
from bcmocap.sim.studio import studio_subject

pytestmark = pytest.mark.slow  # the full run on a simulated capture


FPS = 20.0


@pytest.fixture(scope="module")
def simulated_run(tmp_path_factory):
    import pycolmap

    root = tmp_path_factory.mktemp("run")
    capture = standard_capture("walk", seconds=1.5, fps=FPS, seed=2)
    skeleton, rig = capture.skeleton, capture.rig
    rom = range_of_motion_trial(skeleton, rig, fps=FPS, hold_seconds=1.0, seconds_per_joint=2.0,
                                rotation_sigma_deg=0.3, position_sigma_m=0.003, seed=3)
    sfm_from_world = Similarity(0.37, np.asarray(SO3.exp(np.array([0.4, -1.1, 2.0])).as_matrix()), np.array([3.0, -1.0, 0.5]))
    frontend = root / "out" / "frontend"
    # joint centres from the ROM trial alone (the paper), so that a test can pool the capture's motion
    config = RunConfig().with_overrides({"frontend.stride": 1, "frontend.rom_stride": 1, "solver.window": 20,
                                         "solver.overlap": 5, "skeleton.centre_trials": ["rom"]})
    f = config.frontend
    for trial, corr in (("rom", _rom_correspondences(rom)), ("capture", capture.correspondences())):
        sfm = dataclasses.replace(corr, points=sfm_from_world.points(corr.points),
                                  world_from_camera=sfm_from_world.poses(corr.world_from_camera))
        write_store(frontend / trial / "correspondences", [sfm], block_frames=7)
        settings = trial_settings(stride=1, frames=None, max_features=f.max_features, homographies=trial == "capture",
                                  chunk_frames=f.chunk_frames, registration=f.registration,
                                  max_measurements=f.max_measurements or None, points=f.points)
        (frontend / trial / "registration.json").write_text(json.dumps(
            {"stride": 1, "frames": sfm.num_frames, "registered_fraction": float(sfm.registered.mean()),
             "cameras": list(rig.names), "settings": settings}))
    (frontend / "reference" / "model").mkdir(parents=True)
    pycolmap.Reconstruction().write(str(frontend / "reference" / "model"))
    subject = studio_subject(skeleton, 0, FPS)
    subject["rest"] = {"trial": "rom", "after_first_clap_s": [0.0, 0.9]}
    cameras = tuple(CaptureCamera(n, skeleton.names[s], None, None) for n, s in zip(rig.names, rig.segments))
    from bcmocap.cameras import camera_at

    cameras = tuple(dataclasses.replace(c, intrinsics=camera_at(rig.intrinsics, i)) for i, c in enumerate(cameras))
    fake = Capture(root / "capture", {"subject": subject}, FPS, None, cameras, tuple(skeleton.names), ("rom", "capture"), (), None)
    lines = []
    run_log = run_pipeline(fake, root / "out", config, log=lines.append)
    return root / "out", run_log, lines, capture, sfm_from_world, fake, config


def _rom_correspondences(rom) -> Correspondences:
    t, c = rom.registered.shape
    empty = lambda *shape: np.zeros(shape)
    return Correspondences(np.zeros((1, 3)), np.full((t, c, 1), -1, np.int32), empty(t, c, 1, 2), empty(t, c, 1),
                           empty(t, c, 1, 2), empty(t, c, 1, 2), empty(t, c, 1), rom.world_from_camera, rom.registered, FPS)


def test_run_finds_the_metric_world_skeleton_and_motion(simulated_run):
    out, run_log, lines, capture, sfm_from_world, _, _ = simulated_run
    assert list(run_log["stages"]) == ["frontend", "world", "skeleton", "initial", "solve", "outputs"]
    sim = Similarity.from_dict(json.loads((out / "world" / "similarity.json").read_text()))
    assert sim.scale == pytest.approx(1 / sfm_from_world.scale, rel=0.02)
    skeleton, rig = load_model(out)
    truth = {"skeleton": capture.skeleton, "rig": capture.rig, "motion": capture.motion,
             "world_from_camera": np.asarray(__import__("bcmocap.kinematics.rig", fromlist=["camera_poses"])
                                             .camera_poses(capture.skeleton, capture.rig, capture.motion).wxyz_xyz),
             "valid": np.ones(capture.num_frames, bool)}
    corr = CorrespondenceStore.open(out / "solve" / "correspondences")
    metrics, _ = evaluate_run(skeleton, rig, {"initial": load_motion(out / "solve" / "initial.npz"),
                                               "solved": load_motion(out / "solve" / "motion.npz")}, corr, truth)
    solved, initial = metrics["solved"], metrics["initial"]
    assert solved["joint_position_error_cm"]["mean"] < 1.5 < initial["joint_position_error_cm"]["mean"]
    assert solved["joint_angle_error_deg"]["mean"] < 2.5
    # Z up: the head is above the feet in every frame
    joints = np.load(out / "motion.npz")["joint_positions"]
    names = list(skeleton.names)
    assert np.all(joints[:, names.index("head"), 2] > joints[:, names.index("left_foot"), 2] + 1.0)


def test_run_writes_every_output_a_reader_opens(simulated_run):
    out, *_ = simulated_run
    from bcmocap.io import read_bvh, read_ply

    skeleton, _ = load_model(out)
    motion = load_motion(out / "solve" / "motion.npz")
    assert read_bvh(out / "motion.bvh").motion.num_frames == motion.num_frames
    points, _ = read_ply(out / "scene.ply")
    assert len(points) > 100 and np.isfinite(points).all()
    assert read_ply(out / "camera_paths.ply")[0].shape == (motion.num_frames * 18, 3)
    angles = np.loadtxt(out / "joint_angles.csv", delimiter=",", skiprows=1)
    assert angles.shape == (motion.num_frames, 1 + 3 * (skeleton.num_segments - 1))
    header = (out / "joint_positions.csv").read_text().splitlines()[0].split(",")
    assert header[:4] == ["time_s", "pelvis.x_m", "pelvis.y_m", "pelvis.z_m"]
    for name in ("joint_angles", "joint_positions", "camera_centres", "top_view", "skeleton_poses"):
        assert (out / "pictures" / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "reference_colmap" / "points3D.bin").exists()
    assert json.loads((out / "config.json").read_text())["solver"]["window"] == 20


def test_rerun_reuses_finished_stages_and_changed_settings_redo_only_what_they_affect(simulated_run):
    out, _, _, _, _, fake, config = simulated_run
    before = (out / "solve" / "motion.npz").stat().st_mtime_ns
    lines = []
    run_pipeline(fake, out, config, log=lines.append)
    assert sum("reused" in line for line in lines) == 6
    assert (out / "solve" / "motion.npz").stat().st_mtime_ns == before
    lines = []
    run_pipeline(fake, out, config.with_overrides({"outputs.pictures": False}), log=lines.append)
    assert sum("reused" in line for line in lines) == 5 and any("outputs: settings changed" in line for line in lines)
    (out / "motion.bvh").unlink()  # a deleted output is written again, not taken as done
    lines = []
    run_pipeline(fake, out, config.with_overrides({"outputs.pictures": False}), log=lines.append)
    assert sum("reused" in line for line in lines) == 5 and (out / "motion.bvh").is_file()
    assert any("motion.bvh is missing, redoing it" in line for line in lines)


def test_an_interrupted_solve_resumes_at_the_next_window(simulated_run, tmp_path):
    import shutil

    out, _, _, _, _, fake, config = simulated_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    solved = load_motion(copy / "solve" / "motion.npz")
    # keep the checkpoint of the first two windows only, as if the run had been stopped there
    reports = json.loads((copy / "solve" / "checkpoint.json").read_text())
    first_two = reports["reports"][:2]
    log = json.loads((copy / "run.json").read_text())
    for stage in ("solve", "outputs"):
        log["stages"].pop(stage)
    (copy / "run.json").write_text(json.dumps(log))
    (copy / "solve" / "checkpoint.json").write_text(json.dumps({**reports, "reports": first_two}))
    partial = load_motion(copy / "solve" / "checkpoint.npz")
    stop = first_two[-1]["stop"]
    rot = np.array(partial.rotations)
    root = np.array(partial.root_position)
    initial = load_motion(copy / "solve" / "initial.npz")
    rot[stop:], root[stop:] = np.asarray(initial.rotations)[stop:], np.asarray(initial.root_position)[stop:]
    np.savez(copy / "solve" / "checkpoint.npz", root_position=root, rotations=rot)
    lines = []
    run_pipeline(fake, copy, config, log=lines.append)
    assert any("resuming after window 2" in line for line in lines)
    resumed = load_motion(copy / "solve" / "motion.npz")
    np.testing.assert_allclose(np.asarray(resumed.rotations), np.asarray(solved.rotations), atol=1e-9)
    # A stage before the solve redone (its inputs changed, the settings did not): the solve starts over, never from a
    # checkpoint that stood on the old model or initial motion.
    (copy / "solve" / "checkpoint.json").write_text(json.dumps({**reports, "reports": first_two}))
    log = json.loads((copy / "run.json").read_text())
    for stage in ("initial", "solve", "outputs"):
        log["stages"].pop(stage)
    (copy / "run.json").write_text(json.dumps(log))
    lines = []
    run_pipeline(fake, copy, config, log=lines.append)
    assert not any("resuming" in line for line in lines) and any("[5/6] solve ..." in line for line in lines)


def test_missing_subject_is_a_clear_error(simulated_run, tmp_path):
    out, _, _, _, _, fake, config = simulated_run
    import shutil

    copy = tmp_path / "out"
    shutil.copytree(out / "frontend", copy / "frontend")
    bare = dataclasses.replace(fake, manifest={})
    lines = []
    with pytest.raises(ValueError, match="capture.json: no 'subject' entry"):
        run_pipeline(bare, copy, config, log=lines.append)
    assert lines == []  # found before the first stage starts, not after the frontend
    no_rest = dataclasses.replace(fake, manifest={"subject": {**fake.manifest["subject"], "rest": {}}})
    with pytest.raises(ValueError, match=r"subject\.rest\.after_first_clap_s missing"):
        run_pipeline(no_rest, tmp_path / "other", config, log=lines.append)
    assert lines == []


def test_a_second_run_on_the_same_output_is_refused(simulated_run, tmp_path, monkeypatch):
    import sys

    from bcmocap.io.output_folder import locked_output

    monkeypatch.setattr(sys.modules["bcmocap.pipeline.run"], "LOCK_WAIT_S", 0.2)
    _, _, _, _, _, fake, config = simulated_run
    out = tmp_path / "out"
    out.mkdir()
    with locked_output(out):  # another run holds the folder (flock: a second open file description conflicts)
        with pytest.raises(ValueError, match=rf"another bcmocap command \(pid {os.getpid()}\) is writing"):
            run_pipeline(fake, out, config, log=lambda line: None)
    assert sorted(p.name for p in out.iterdir()) == ["run.lock"]


def _resumable_copy(simulated_run, tmp_path, forget_from: str):
    """A copy of the finished run whose stages from ``forget_from`` on are to be done again."""
    import shutil

    out, _, _, _, _, fake, config = simulated_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    from bcmocap.io.run_folder import RunLog

    log = RunLog(copy, fake.path)
    log.forget_from(forget_from)
    return copy, fake, config


def _own_capture(fake, copy, tmp_path):
    """``fake`` moved to a capture folder of this test's own (the run copy ``copy`` pointed at it), so that files the
    test adds there leave the other tests' capture alone."""
    capture = tmp_path / "capture"
    capture.mkdir()
    log = json.loads((copy / "run.json").read_text())
    (copy / "run.json").write_text(json.dumps({**log, "capture": str(capture.resolve())}))
    return dataclasses.replace(fake, path=capture)


def _during_stage(monkeypatch, stage: str, action):
    """Run ``action()`` at the start of ``stage`` (before its own work)."""
    import sys

    run_module = sys.modules["bcmocap.pipeline.run"]
    original = run_module._STAGE_FUNCTIONS[stage]

    def wrapped(ctx):
        action()
        return original(ctx)

    monkeypatch.setitem(run_module._STAGE_FUNCTIONS, stage, wrapped)


def test_each_stage_records_its_peak_memory(simulated_run):
    _, run_log, *_ = simulated_run
    peaks = {stage: rec.get("peak_mb") for stage, rec in run_log["stages"].items()}
    assert all(isinstance(p, float) and 50.0 < p < 24_000.0 for p in peaks.values()), peaks


def test_an_output_folder_deleted_mid_run_stops_it_with_one_line(simulated_run, tmp_path, monkeypatch):
    import shutil

    copy, fake, config = _resumable_copy(simulated_run, tmp_path, "skeleton")
    _during_stage(monkeypatch, "skeleton", lambda: shutil.rmtree(copy))
    with pytest.raises(ValueError, match=rf"{copy} was deleted or replaced while the run was going; nothing more"):
        run_pipeline(fake, copy, config, log=lambda line: None)
    assert not (copy / "run.json").exists()  # no new run log claims stages whose files are gone


def test_a_capture_file_changed_mid_run_stops_it_and_a_rerun_finishes(simulated_run, tmp_path, monkeypatch):
    capture = tmp_path / "capture"
    (capture / "trials" / "capture").mkdir(parents=True)
    measured = capture / "trials" / "capture" / "contacts.txt"  # a data file read after the frontend
    measured.write_text("0\n")
    copy, fake, config = _resumable_copy(simulated_run, tmp_path, "initial")
    fake = dataclasses.replace(fake, path=capture)
    log = json.loads((copy / "run.json").read_text())
    (copy / "run.json").write_text(json.dumps({**log, "capture": str(capture.resolve())}))
    with monkeypatch.context() as m:
        _during_stage(m, "initial", lambda: measured.write_text("0\n1\n1\n0\n"))
        with pytest.raises(ValueError, match=r"contacts\.txt \(modified, 2 → 8 bytes\) changed while the run was reading"):
            run_pipeline(fake, copy, config, log=lambda line: None)
    stages = json.loads((copy / "run.json").read_text())["stages"]
    assert list(stages) == ["frontend", "world", "skeleton"]  # what was finished before is kept
    lines = []
    run_pipeline(fake, copy, config, log=lines.append)
    assert "[1/6] frontend: done before, reused" in lines  # a data file: the frontend's work stays
    assert list(json.loads((copy / "run.json").read_text())["stages"]) == list(
        __import__("bcmocap.io.run_folder", fromlist=["STAGES"]).STAGES)


@pytest.mark.parametrize("error", [MemoryError(), RuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 8 GB")])
def test_a_stage_out_of_memory_says_which_setting_lowers_it(simulated_run, tmp_path, monkeypatch, error):
    copy, fake, config = _resumable_copy(simulated_run, tmp_path, "solve")

    def fail():
        raise error

    _during_stage(monkeypatch, "solve", fail)
    with pytest.raises(MemoryError, match=r"the solve stage ran out of memory at a peak of [\d,]+ MB.*lower \[solver\] window"):
        run_pipeline(fake, copy, config, log=lambda line: None)


def test_the_run_log_never_follows_a_symlink(tmp_path):
    from bcmocap.pipeline.run import _append_line

    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    (tmp_path / "log.txt").symlink_to(victim)
    with pytest.raises(ValueError, match=r"log\.txt: is a symlink"):
        _append_line(tmp_path / "log.txt", "a line")
    assert victim.read_text() == "keep"
    _append_line(tmp_path / "plain.txt", "one")
    _append_line(tmp_path / "plain.txt", "two")
    assert (tmp_path / "plain.txt").read_text() == "one\ntwo\n"


def test_run_command_refuses_bad_input_without_writing(tmp_path, capsys):
    from bcmocap.cli import main

    assert main(["run", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "missing" in capsys.readouterr().err
    capture = tmp_path / "capture"
    capture.mkdir()
    bad = tmp_path / "bad.toml"
    bad.write_text("[solver]\nwindo = 3\n")
    assert main(["run", str(capture), "--out", str(tmp_path / "o"), "--config", str(bad)]) == 2
    assert "solver.windo is not a setting" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_saved_registration_is_reused_only_with_the_same_settings(simulated_run, tmp_path, monkeypatch):
    import shutil

    import bcmocap.frontend.command as frontend_command

    out, _, _, _, _, fake, config = simulated_run
    copy = tmp_path / "out"
    shutil.copytree(out / "frontend", copy / "frontend")
    lines = []
    run_pipeline(fake, copy, config, log=lines.append, stop_after="frontend")
    assert sum("registration found" in line for line in lines) == 2

    def redo(*args, **kwargs):
        raise RuntimeError("registration redone")

    monkeypatch.setattr(frontend_command, "process_trial", redo)
    monkeypatch.setattr(frontend_command, "prepare_reference", lambda *args, **kwargs: None)
    monkeypatch.setattr("bcmocap.frontend.register.reference_index", lambda model: None)
    with pytest.raises(RuntimeError, match="registration redone"):  # --max-features changed: not reused
        run_pipeline(fake, copy, config.with_overrides({"frontend.max_features": 1234}), log=lines.append)


USER_TERM_MODULE = '''
import numpy as np
from bcmocap.residuals import FrameTerm

CALLS = []


class RootHeight(FrameTerm):
    def residual(self, state, data, variables):
        return (state.motion.root_position[2] - data)[None, None], np.ones(1, bool)


def root_height(window, weight):
    """The root's height read from the trial folder's own file (m), one value per solver frame."""
    CALLS.append((window.start, window.stop, window.times.copy()))
    heights = np.loadtxt(window.trial_folder / "root_height.txt")
    return RootHeight(heights[window.start : window.stop], weight=weight, name="root height")
'''


def test_refinement_rounds_refine_the_model_in_the_solve_stage(simulated_run, tmp_path):
    """``solver.refine_rounds = 1``: after the windowed solve the skeleton and mounts are refined with the
    motion on the same problem and the motion solved again; the refined model is saved in ``solve/`` (the
    estimate in ``model/`` stays), reported, and used by the outputs; a rerun without refinement drops it."""
    import shutil

    out, _, _, _, _, fake, config = simulated_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    refined_config = RunConfig.from_dict({**config.to_dict(), "solver": {**config.to_dict()["solver"], "refine_rounds": 1}})
    lines = []
    run_pipeline(fake, copy, refined_config, log=lines.append)
    assert any("refinement round 1 of 1" in line for line in lines)
    (report,) = json.loads((copy / "solve" / "reports.json").read_text())["refinements"]
    assert report["num_parameters"] > 0 and report["final_cost"] < report["initial_cost"]
    estimate, refined = load_model(copy), load_model(copy, "solve")
    assert np.abs(np.asarray(estimate[0].offsets) - np.asarray(refined[0].offsets)).max() > 1e-5
    np.testing.assert_array_equal(np.asarray(load_model(out)[0].offsets), np.asarray(estimate[0].offsets))
    run_pipeline(fake, copy, config, log=lines.append)
    assert not (copy / "solve" / "skeleton.json").exists()


def _summary_frames(out) -> dict[str, int]:
    """Joint → frames of its centre fit, from ``model/rom_summary.txt``."""
    rows = (out / "model" / "rom_summary.txt").read_text().splitlines()[1:]
    return {row.split()[0]: int(row.split()[2]) for row in rows}


def test_centre_trials_fit_the_joint_centres_to_the_capture_too(simulated_run, tmp_path):
    """``skeleton.centre_trials = ["rom", "capture"]``: the frontend is reused, the world and later stages are
    redone with every joint's centre fitted to both trials' frames, and the skeleton stays near the truth."""
    import shutil

    out, _, _, capture, _, fake, config = simulated_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    lines = []
    run_pipeline(fake, copy, config.with_overrides({"skeleton.centre_trials": ["rom", "capture"]}), log=lines.append)
    assert sum("reused" in line for line in lines) == 1 and any("world: settings changed" in line for line in lines)
    alone, pooled = _summary_frames(out), _summary_frames(copy)
    assert alone.keys() == pooled.keys()
    assert all(pooled[j] - alone[j] > 0.8 * capture.num_frames for j in alone)
    bones = [np.linalg.norm(np.asarray(sk.offsets), axis=1) for sk in (capture.skeleton, load_model(copy)[0])]
    assert np.abs(bones[1] - bones[0]).max() < 0.02


def test_a_user_term_named_in_the_config_reaches_the_solve(simulated_run, tmp_path, monkeypatch):
    """``[[solver.user_terms]]`` names a factory by import path; bcmocap run imports it before any stage, calls
    it for every window with the window's frames, times and the capture's trial folder, and solves with its
    terms (here a strong pull of the root to a height read from the trial folder)."""
    import importlib
    import shutil

    out, _, _, _, _, fake, config = simulated_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    (tmp_path / "user_terms_for_run.py").write_text(USER_TERM_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module("user_terms_for_run")
    fake = _own_capture(fake, copy, tmp_path)
    trial = fake.path / "trials" / "capture"
    trial.mkdir(parents=True, exist_ok=True)
    frames = load_motion(out / "solve" / "motion.npz").num_frames
    np.savetxt(trial / "root_height.txt", np.full(frames, 5.0))
    user = RunConfig.from_dict({**config.to_dict(), "solver": {**config.to_dict()["solver"], "user_terms": [
        {"factory": "user_terms_for_run:root_height", "weight": 1e8}]}})
    lines = []
    run_pipeline(fake, copy, user, log=lines.append)
    # the new measurement file redoes the stages after the frontend
    assert sum("reused" in line for line in lines) == 1 and any("data files changed" in line for line in lines)
    starts = [r["start"] for r in json.loads((copy / "solve" / "reports.json").read_text())["windows"]]
    assert [c[0] for c in module.CALLS] == starts
    for start, stop, times in module.CALLS:
        np.testing.assert_allclose(times, (start + np.arange(stop - start)) / FPS)
    solved = load_motion(copy / "solve" / "motion.npz")
    np.testing.assert_allclose(np.asarray(solved.root_position)[:, 2], 5.0, atol=1e-3)
    assert abs(np.asarray(load_motion(out / "solve" / "motion.npz").root_position)[:, 2] - 5.0).min() > 0.5

    broken = RunConfig.from_dict({**user.to_dict(), "solver": {**user.to_dict()["solver"], "user_terms": [
        {"factory": "user_terms_for_run:missing"}]}})
    with pytest.raises(ValueError, match="term factory 'user_terms_for_run:missing': module 'user_terms_for_run' has no 'missing'"):
        run_pipeline(fake, tmp_path / "other", broken, log=lines.append)
    assert not (tmp_path / "other" / "frontend").exists()


def test_the_tutorial_gyroscope_term_runs_from_its_config_entry(simulated_run, tmp_path, monkeypatch):
    """docs/residual-terms.md's term (examples/gyro_term): named by examples/gyro_term/config.toml, it reads the
    trial folder's imu.npz in every window of `bcmocap run`'s solve; with an exact gyro the solved joint rotations
    stay within a degree of the run without it."""
    import shutil

    from bcmocap.io.sensors import write_imu
    from bcmocap.pipeline.config import load_config
    from bcmocap.sim.sensors import simulate_imu

    out, _, _, capture, _, fake, config = simulated_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    fake = _own_capture(fake, copy, tmp_path)
    examples = Path(__file__).resolve().parents[1] / "examples" / "gyro_term"
    monkeypatch.syspath_prepend(str(examples))
    trial = fake.path / "trials" / "capture"
    trial.mkdir(parents=True, exist_ok=True)
    claps = np.array([0, capture.num_frames - 1])
    write_imu(trial / "imu.npz", simulate_imu(capture.skeleton, capture.rig, capture.motion, FPS, claps, seed=4,
                                              gyro_noise=0.0, gyro_bias=0.0, accel_noise=0.0, accel_bias=0.0))
    entry = load_config(examples / "config.toml").solver.user_terms
    assert [u.factory for u in entry] == ["gyro_term:gyroscope"]
    with_gyro = RunConfig.from_dict({**config.to_dict(), "solver": {**config.to_dict()["solver"],
                                                                      "user_terms": [{"factory": u.factory, **u.settings}
                                                                                     for u in entry]}})
    lines = []
    run_pipeline(fake, copy, with_gyro, log=lines.append)
    # the new IMU file redoes the stages after the frontend, the frontend's work kept
    assert "the capture's data files changed since the last run (trials/capture/imu.npz (added)): redoing the " \
           "stages after the frontend" in lines and "[1/6] frontend: done before, reused" in lines
    reports = json.loads((copy / "solve" / "reports.json").read_text())["windows"]
    assert reports and all(r["converged"] for r in reports)
    plain, gyro = load_motion(out / "solve" / "motion.npz"), load_motion(copy / "solve" / "motion.npz")
    turned = SO3(np.asarray(plain.rotations)[:, 1:]).inverse() @ SO3(np.asarray(gyro.rotations)[:, 1:])
    assert np.degrees(np.linalg.norm(np.asarray(turned.log()), axis=-1)).mean() < 1.0


def test_independent_windows_on_a_local_cluster_equal_those_without_one(simulated_run, tmp_path):
    """solver.windows = "independent": the windows and seams are tasks on a LocalCluster of worker processes,
    with the result of the same setting without a cluster, and close to the sequential solve."""
    import shutil

    from bcmocap.pipeline.cluster import open_executor

    out, _, _, _, _, fake, config = simulated_run
    independent = config.with_overrides({"solver.windows": "independent", "outputs.pictures": False})
    motions, tasks = {}, {}
    for name, spec in (("alone", None), ("cluster", "local:2")):
        copy = tmp_path / name
        shutil.copytree(out, copy)
        lines = []
        with open_executor(spec, log=lines.append) as executor:
            run_pipeline(fake, copy, independent, log=lines.append, executor=executor)
        assert any("solved independently" in line for line in lines)
        motions[name], tasks[name] = load_motion(copy / "solve" / "motion.npz"), [t[0] for t in executor.tasks]
    assert tasks["alone"] == tasks["cluster"] and {"window", "seam"} <= set(tasks["cluster"])
    for field in ("root_position", "rotations"):
        np.testing.assert_allclose(np.asarray(getattr(motions["cluster"], field)),
                                   np.asarray(getattr(motions["alone"], field)), atol=1e-7)
    sequential = load_motion(out / "solve" / "motion.npz")
    assert np.max(np.abs(np.asarray(motions["alone"].root_position) - np.asarray(sequential.root_position))) < 0.01


def test_a_camera_model_in_the_solver_settings_refits_the_registered_poses(simulated_run, tmp_path):
    """With a readout or self-calibration the world stage re-fits both trials' registered poses under that model
    (``DIR/world/registered/``) and the later stages read them; without, the folder goes and the frontend's are used."""
    import shutil

    from bcmocap.correspondence_store import CorrespondenceStore

    out, _, _, capture, sfm_from_world, fake, config = simulated_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    lines = []
    modelled = config.with_overrides({"solver.rolling_shutter_readout": 0.004, "solver.self_calibration": True})
    run_pipeline(fake, copy, modelled, log=lines.append, stop_after="initial")
    assert any("world: settings changed" in line for line in lines)
    folder = copy / "world" / "registered"
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["rom"]["refined_frames"] == 0  # the fixture's ROM trial has no measurement
    assert summary["capture"]["refined_frames"] == int(capture.correspondences().registered.sum())
    # both trials calibrate the lenses together: here the capture alone, the ROM trial measuring nothing
    correction = np.asarray(summary["intrinsics_correction"])
    with np.load(folder / "intrinsics.npz") as saved:
        np.testing.assert_array_equal(saved["correction"], correction)
    assert correction.shape == (capture.rig.num_cameras, 3) and np.abs(correction[:, 0]).max() < 0.01
    rig_lens = load_model(copy)[1].intrinsics
    np.testing.assert_allclose(np.asarray(rig_lens.focal), np.asarray(capture.rig.intrinsics.focal) * np.exp(correction[:, :1]))
    frontend = CorrespondenceStore.open(copy / "frontend" / "capture" / "correspondences")
    with np.load(folder / "capture.npz") as refined:
        refined_poses = refined["world_from_camera"]
        moved = np.linalg.norm(refined_poses[..., 4:] - frontend.world_from_camera[..., 4:], axis=-1)
        np.testing.assert_array_equal(refined["registered"], frontend.registered)
        metric = CorrespondenceStore.open(copy / "solve" / "correspondences")
        sim = Similarity.from_dict(json.loads((copy / "world" / "similarity.json").read_text()))
        np.testing.assert_allclose(metric.world_from_camera, sim.poses(refined["world_from_camera"]), atol=1e-12)
    # the fixture's registered poses carry SfM-like noise (2 cm, 1°) and its measurements are exact but for pixel
    # noise and outliers: the re-fitted centres are nearer the truth
    from bcmocap.kinematics.rig import camera_poses

    true = sfm_from_world.poses(np.asarray(camera_poses(capture.skeleton, capture.rig, capture.motion).wxyz_xyz))
    reg = frontend.registered
    before = np.linalg.norm(frontend.world_from_camera[..., 4:] - true[..., 4:], axis=-1)[reg]
    after = np.linalg.norm(refined_poses[..., 4:] - true[..., 4:], axis=-1)[reg]
    assert np.median(after) < 0.3 * np.median(before) and moved[reg].max() > 0
    run_pipeline(fake, copy, config, log=lines.append, stop_after="world")
    assert not folder.exists()


def test_frontend_self_calibration_registers_again_through_the_corrected_lenses(simulated_run, tmp_path, monkeypatch):
    """``frontend.self_calibration``: the first registration (here the fixture's, made through the true lenses while
    the capture's files are 1 % and 2 px off) gives each camera's correction, the trials are registered again
    through the corrected lenses, and the later stages start from those."""
    import shutil

    import bcmocap.frontend.command as frontend_command
    from bcmocap.cameras import camera_at
    from bcmocap.residuals.self_calibration import corrected_cameras

    out, _, _, capture, _, fake, config = simulated_run
    copy = tmp_path / "out"
    shutil.copytree(out / "frontend", copy / "frontend" / "calibration_pass")
    error = np.array([np.log(1.01), 2.0, -2.0])  # the capture's files: focal 1 % long, centre moved by (2, -2) px
    wrong = corrected_cameras(capture.rig.intrinsics, np.tile(error, (capture.rig.num_cameras, 1)))
    given = fake.with_lenses([camera_at(wrong, i) for i in range(capture.rig.num_cameras)])
    for trial in ("rom", "capture"):  # the first registration, made through the lenses given
        path = copy / "frontend" / "calibration_pass" / trial / "registration.json"
        report = json.loads(path.read_text())
        report["settings"]["given_lenses"] = given.lens_fingerprint()
        path.write_text(json.dumps(report))
    registered_through = []

    def register_again(capture_, index, trial, folder, *, extra_settings, **kwargs):  # the fixture's stores again
        registered_through.append(np.array([np.asarray(cam.intrinsics.focal)[0] for cam in capture_.cameras]))
        shutil.copytree(copy / "frontend" / "calibration_pass" / trial, folder / trial, dirs_exist_ok=True)
        report = json.loads((folder / trial / "registration.json").read_text())
        report["settings"] = {**report["settings"], **extra_settings}
        (folder / trial / "registration.json").write_text(json.dumps(report))
        return report

    monkeypatch.setattr(frontend_command, "process_trial", register_again)
    monkeypatch.setattr(frontend_command, "prepare_reference", lambda *args, **kwargs: None)
    monkeypatch.setattr("bcmocap.frontend.register.reference_index", lambda model: None)
    calibrated = config.with_overrides({"frontend.self_calibration": True})
    lines = []
    run_pipeline(given, copy, calibrated, log=lines.append, stop_after="skeleton")
    assert sum("registration found" in line for line in lines) == 2  # the first pass: reused
    with np.load(copy / "frontend" / "intrinsics.npz") as saved:
        correction = saved["correction"]
        assert [str(n) for n in saved["cameras"]] == list(capture.rig.names)
    np.testing.assert_allclose(correction[:, 0], -error[0], atol=2e-3)  # the capture trial alone measures (ROM: none)
    np.testing.assert_allclose(correction[:, 1:], -np.tile(error[1:], (capture.rig.num_cameras, 1)), atol=0.3)
    true_focal = np.asarray(capture.rig.intrinsics.focal)[:, 0]
    assert len(registered_through) == 2  # both trials registered again, through lenses near the true ones
    for focal in registered_through:
        np.testing.assert_allclose(focal, true_focal, rtol=2e-3)
    report = json.loads((copy / "frontend" / "capture" / "registration.json").read_text())
    assert report["settings"]["lens_correction"] == np.round(correction, 6).tolist()
    assert report["settings"]["given_lenses"] == given.lens_fingerprint()
    np.testing.assert_allclose(np.asarray(load_model(copy)[1].intrinsics.focal)[:, 0], true_focal, rtol=2e-3)
    (copy / "frontend" / "intrinsics.npz").unlink()  # a finished frontend without its correction is done again
    lines.clear()
    run_pipeline(given, copy, calibrated, log=lines.append, stop_after="frontend")
    assert any("intrinsics.npz is missing, redoing it" in line for line in lines)
    assert (copy / "frontend" / "intrinsics.npz").is_file()
