"""The cameras' gyro turns (bcmocap.residuals.gyro, bcmocap.pipeline.gyro_turns): read at each camera's shift on the gyro's clock they vanish at the
true motion, the solver's gradient is the finite-difference one, and ``[solver] gyro_turn`` reaches them."""

from __future__ import annotations

import dataclasses
import json
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bcmocap.io.sensors import read_imu, write_imu
from bcmocap.pipeline.config import RunConfig, SolverConfig
from bcmocap.residuals import TermWindow
from bcmocap.pipeline.gyro_turns import gyro_turns
from bcmocap.residuals.gyro import GyroTurn
from bcmocap.sim import standard_capture
from bcmocap.sim.sensors import simulate_imu
from bcmocap.solver.window import cost, make_window_problem, normal_equations, residuals, window_history

CLOCK_OFFSET_S = 0.02  # the IMU's clock is ahead of the video's by this much


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """Eighteen frames of the standard walk and its exact gyros, their clock 20 ms ahead, in a trial folder."""
    capture = standard_capture("walk", seconds=0.3, width=64, height=36)
    folder = tmp_path_factory.mktemp("trial")
    imu = simulate_imu(capture.skeleton, capture.rig, capture.motion, capture.fps, np.array([0, capture.num_frames - 1]),
                       seed=1, gyro_noise=0.0, gyro_bias=0.0, accel_noise=0.0, accel_bias=0.0)
    write_imu(folder / "imu.npz", type(imu)(**{**imu.__dict__, "time": imu.time + CLOCK_OFFSET_S}))
    return capture, folder


def _window_problem(capture, term, start=3, stop=13):
    cut = [term.window(start, stop)]
    h = window_history(cut)
    reference = jax.tree.map(lambda a: a[start - h : stop], capture.motion)
    return make_window_problem(capture.skeleton, capture.rig, cut, reference, h)


def _term(capture, folder, shift_s, sigma_deg=0.5) -> GyroTurn:
    window = TermWindow(0, capture.num_frames, capture.fps, capture.skeleton, capture.rig, trial_folder=folder)
    return gyro_turns(window, sigma_deg, [shift_s] * capture.rig.num_cameras)


def test_gyro_turns_vanish_at_the_true_motion_when_read_at_the_gyros_clock(walk):
    capture, folder = walk
    term = _term(capture, folder, CLOCK_OFFSET_S)
    term.check(capture.num_frames, capture.rig.num_cameras)
    weights = np.asarray(term.data["weights"])
    assert (weights[0] == 0).all() and (weights[1:] > 0).all()  # the first frame's interval starts before the gyro
    problem = _window_problem(capture, term)
    (r,) = residuals(problem, jnp.zeros((problem.num_frames, problem.frame_size)))
    assert np.abs(np.asarray(r)).max() < 1e-6  # rad × √weight (1/σ = 115 per rad): 1e-8 rad
    (off,) = residuals(_window_problem(capture, _term(capture, folder, 0.0)),
                       jnp.zeros((problem.num_frames, problem.frame_size)))
    assert np.abs(np.asarray(off)).max() > 1e-2  # read 20 ms early, the turns are the earlier ones


def test_gyro_turn_gradient_is_the_finite_difference_one(walk):
    """The normal equations' gradient (the exact gradient) against central differences of the window's cost, at a
    motion off the truth."""
    capture, folder = walk
    problem = _window_problem(capture, _term(capture, folder, CLOCK_OFFSET_S))
    rng = np.random.default_rng(3)
    y = jnp.asarray(rng.normal(scale=0.03, size=(problem.num_frames, problem.frame_size)))
    grad = np.asarray(jax.jit(lambda motion: normal_equations(problem, motion).grad)(y))  # compiled once
    assert np.abs(grad).max() > 1.0
    window_cost = jax.jit(lambda motion: cost(problem, motion))
    eps = 1e-6
    for _ in range(8):
        i, j = rng.integers(problem.num_frames), rng.integers(problem.frame_size)
        step = jnp.zeros_like(y).at[i, j].set(eps)
        fd = (float(window_cost(y + step)) - float(window_cost(y - step))) / (2 * eps)
        assert abs(fd - grad[i, j]) <= 1e-6 * max(1.0, abs(grad[i, j])), (i, j, fd, grad[i, j])


def test_gyro_turns_say_what_is_wrong(walk, tmp_path):
    capture, folder = walk
    window = TermWindow(0, capture.num_frames, capture.fps, capture.skeleton, capture.rig, trial_folder=folder)
    with pytest.raises(ValueError, match="σ must be > 0"):
        gyro_turns(window, 0.0)
    with pytest.raises(ValueError, match="2 time shifts for 18 cameras"):
        gyro_turns(window, 0.5, [0.0, 0.0])
    empty = TermWindow(0, capture.num_frames, capture.fps, capture.skeleton, capture.rig, trial_folder=tmp_path)
    with pytest.raises(ValueError, match="imu.npz: missing"):
        gyro_turns(empty, 0.5)
    imu = read_imu(folder / "imu.npz")
    write_imu(tmp_path / "imu.npz", type(imu)(**{**imu.__dict__, "cameras": tuple(f"cam{i}" for i in range(18))}))
    with pytest.raises(ValueError, match="imu.npz: holds none of the rig's cameras"):
        gyro_turns(empty, 0.5)
    bad = GyroTurn({"turn": np.zeros((4, 18, 1, 4)), "weights": np.ones((4, 18, 2))}, name="gyro turns")
    with pytest.raises(ValueError, match=r"gyro turns: data\['weights'\] has shape \(4, 18, 2\)"):
        bad.check(4, 18)


def test_the_run_reads_the_gyros_at_the_frontends_shifts(walk, tmp_path):
    """``[solver] gyro_turn``: off by default, redoing only the solve when set, one line for a capture without gyros,
    else the term read at the frontend's absolute gyro shifts."""
    from bcmocap.pipeline.run import RunContext, _gyro_terms, fingerprints

    capture, folder = walk
    with pytest.raises(ValueError, match="solver.gyro_turn"):
        RunConfig(solver=SolverConfig(gyro_turn=-1.0))
    default, config = RunConfig(), RunConfig(solver=SolverConfig(gyro_turn=0.5))
    before, after = fingerprints(default), fingerprints(config)
    assert [before[s] == after[s] for s in before] == [True] * 4 + [False] * 2  # only the solve and outputs redone
    ctx = RunContext(capture=None, config=default, out=tmp_path, log=print)
    assert _gyro_terms(ctx, folder) == []
    ctx = RunContext(capture=None, config=config, out=tmp_path, log=print)
    with pytest.raises(ValueError, match="imu.npz: missing; \\[solver\\] gyro_turn needs the cameras' gyros"):
        _gyro_terms(ctx, tmp_path)
    registration = tmp_path / "frontend" / "capture" / "registration.json"
    registration.parent.mkdir(parents=True)
    # each camera's own shift; the second camera's 4 ms off the others', the third's not determined
    shifts_ms = [1e3 * CLOCK_OFFSET_S] * capture.rig.num_cameras
    shifts_ms[1] += 4.0
    determined = [True] * len(shifts_ms)
    determined[2] = False
    shifts_ms[2] = 50.0
    registration.write_text(json.dumps({"gyro_timing": {"time_shift_ms": shifts_ms, "determined": determined}}))
    window = TermWindow(0, capture.num_frames, capture.fps, capture.skeleton, capture.rig, trial_folder=folder)
    cameras = types.SimpleNamespace(cameras=[None] * capture.rig.num_cameras)

    def read(config):
        (factory,) = _gyro_terms(RunContext(capture=cameras, config=config, out=tmp_path, log=print), folder)
        (term,) = factory(window)
        return np.asarray(term.data["turn"]), np.asarray(term.data["weights"])

    turn, weights = read(config)
    alone = {shift: _term(capture, folder, shift / 1e3) for shift in set(shifts_ms)}
    for c, shift in enumerate(shifts_ms):
        np.testing.assert_array_equal(turn[:, c], np.asarray(alone[shift].data["turn"])[:, c])
        np.testing.assert_array_equal(weights[:, c], np.asarray(alone[shift].data["weights"])[:, c])
    # with the solver's time offsets, its frame times are the determined shifts' mean for every camera
    turn, weights = read(RunConfig(solver=SolverConfig(gyro_turn=0.5, estimate_time_offsets=True)))
    mean = np.mean([v for v, d in zip(shifts_ms, determined) if d]) / 1e3
    common = _term(capture, folder, mean)
    np.testing.assert_allclose(turn, np.asarray(common.data["turn"]), atol=1e-12)  # the mean's last bit
    np.testing.assert_array_equal(weights, np.asarray(common.data["weights"]))
    assert np.abs(turn[:, 1] - np.asarray(alone[shifts_ms[1]].data["turn"])[:, 1]).max() > 1e-4
    registration.write_text(json.dumps({"gyro_timing": {"time_shift_ms": [1.0, 2.0]}}))
    with pytest.raises(ValueError, match="registration.json: gyro_timing.time_shift_ms has 2 values for 18 cameras"):
        read(config)


def _leg_trial():
    """The leg model, its exact range-of-motion trial (30 fps, the rest held for 0.5 s first) and its frame count."""
    from test_sim_rom import TRIAL, leg_model

    from bcmocap.sim import range_of_motion_trial

    skeleton, rig = leg_model()
    trial = range_of_motion_trial(skeleton, rig, rotation_sigma_deg=0.0, position_sigma_m=0.0, missing_fraction=0.0, **TRIAL)
    return skeleton, rig, trial, trial.registered.shape[0]


def _gyro_timed_run(tmp_path, trial_name, skeleton, rig, trial):
    """A run context over a capture whose ``trial_name`` holds the trial's gyros (studio noise, no bias) on an IMU clock
    40 ms behind the frames, and the frontend's gyro timing that found it: ``(ctx, logged lines, registration.json)``."""
    from test_sim_rom import TRIAL

    from bcmocap.pipeline import run

    imu = simulate_imu(skeleton, rig, trial.motion, TRIAL["fps"], (0, trial.registered.shape[0] - 1), seed=3,
                       gyro_bias=0.0)
    capture = tmp_path / "capture"
    (capture / "trials" / trial_name).mkdir(parents=True)
    write_imu(capture / "trials" / trial_name / "imu.npz", dataclasses.replace(imu, time=imu.time + 0.04))
    timing = tmp_path / "run" / "frontend" / trial_name / "registration.json"
    timing.parent.mkdir(parents=True)
    timing.write_text(json.dumps({"gyro_timing": {"time_shift_ms": [40.0] * rig.num_cameras}}))
    cameras = [types.SimpleNamespace(name=n, segment=skeleton.names[s]) for n, s in zip(rig.names, rig.segments)]
    logged = []
    ctx = run.RunContext(capture=types.SimpleNamespace(path=capture, cameras=cameras), config=RunConfig(),
                         out=tmp_path / "run", log=logged.append)
    return ctx, logged, timing


def test_a_gyro_carries_a_camera_to_the_rest_pose_it_was_not_registered_in():
    # A range-of-motion trial (the leg model, 30 fps, the rest held for 0.5 s first) whose shin camera registers in
    # 12 frames 5 s after the rest frames only, while the hip swings the leg (35-63 deg from its rest orientation):
    # its gyro carries it back to the rest pose, within 0.05 deg with the studio's gyro noise and no bias; with the
    # studio's turn-on bias (up to 0.5 deg/s per axis), which is not taken off, within |bias| times the 5.3 s carried.
    from test_sim_rom import TRIAL

    from bcmocap.pipeline.gyro_turns import rest_orientations_from_gyros
    skeleton, rig, trial, frames = _leg_trial()
    shin = rig.index("shin")
    registered = trial.registered.copy()
    registered[:, shin] = False
    registered[150:162, shin] = True
    rest = np.zeros(frames, bool)
    rest[trial.rest_frames] = True
    truth = trial.world_from_camera[rest, shin, :4].mean(axis=0)
    truth /= np.linalg.norm(truth)

    def angle(q):
        return np.degrees(2 * np.arccos(min(1.0, abs(q @ truth))))

    assert min(angle(q) for q in trial.world_from_camera[150:162, shin, :4]) > 30.0  # the carry has work to do
    angles = []
    for bias in (0.0, np.radians(0.5)):
        imu = simulate_imu(skeleton, rig, trial.motion, TRIAL["fps"], (0, frames - 1), seed=3, gyro_bias=bias)
        carried, report = rest_orientations_from_gyros(trial.world_from_camera, registered, rest, TRIAL["fps"], imu,
                                                       rig.names)
        assert np.isnan(np.delete(carried, shin, axis=0)).all() and list(report) == ["shin"]
        assert report["shin"]["frames"] == 12 and 4.7 < report["shin"]["nearest_s"] < 4.8
        angles.append(angle(carried[shin]))
    assert angles[0] < 0.05 and angles[1] < 0.05 + 5.3 * 0.5 * np.sqrt(3), angles
    only = np.zeros(rig.num_cameras, bool)
    carried, report = rest_orientations_from_gyros(trial.world_from_camera, registered, rest, TRIAL["fps"], imu,
                                                   rig.names, cameras=only)
    assert np.isnan(carried).all() and not report  # only the cameras asked for
    with pytest.raises(ValueError, match=r"3 time shifts for 7 cameras"):
        rest_orientations_from_gyros(trial.world_from_camera, registered, rest, TRIAL["fps"], imu, rig.names, [0.0] * 3)


def test_the_skeleton_stage_carries_rest_orientations_on_the_gyro_clock_of_the_frontends_timing(tmp_path, monkeypatch):
    # The run's glue: the ROM trial's imu.npz, read at the shifts the frontend's gyro timing found for that trial
    # (here the IMU clock runs 40 ms behind the frames: read on the frames' clock, the shin is carried 10° off), only for cameras no rest frame registered.
    from test_sim_rom import TRIAL

    import bcmocap.correspondence_store as store_module
    from bcmocap.pipeline import run

    skeleton, rig, trial, frames = _leg_trial()
    ctx, logged, timing = _gyro_timed_run(tmp_path, "rom", skeleton, rig, trial)
    monkeypatch.setattr(store_module.CorrespondenceStore, "open", staticmethod(lambda path: types.SimpleNamespace(fps=TRIAL["fps"])))
    rest = np.zeros(frames, bool)
    rest[trial.rest_frames] = True
    assert run._gyro_rest_orientations(ctx, trial.world_from_camera, trial.registered, rest, logged.append) is None
    waist = trial.registered.copy()
    waist[rest, rig.index("waist_left")] = False  # the pelvis's other cameras place it at rest: nothing to carry
    assert run._gyro_rest_orientations(ctx, trial.world_from_camera, waist, rest, logged.append) is None
    shin = rig.index("shin")
    registered = trial.registered.copy()
    registered[:, shin] = False
    registered[150:162, shin] = True  # while the hip swings the leg
    carried = run._gyro_rest_orientations(ctx, trial.world_from_camera, registered, rest, logged.append)
    truth = trial.world_from_camera[rest, shin, :4].mean(axis=0)
    assert np.degrees(2 * np.arccos(min(1.0, abs(carried[shin] @ truth / np.linalg.norm(truth))))) < 0.05
    assert np.isnan(np.delete(carried, shin, axis=0)).all()
    assert len(logged) == 1 and "camera 'shin' is registered in no rest frame" in logged[0] and "12 registered frames" in logged[0]
    timing.write_text("{}")  # without the timing: read 40 ms off
    off = run._gyro_rest_orientations(ctx, trial.world_from_camera, registered, rest, logged.append)
    assert np.degrees(2 * np.arccos(min(1.0, abs(off[shin] @ truth / np.linalg.norm(truth))))) > 3.0


def test_a_gyro_orients_a_camera_through_the_frames_it_was_not_registered_in():
    # The leg model's range-of-motion trial (30 fps) with the shin camera unregistered for 1 s while the hip swings
    # the leg, and before its first registration: its gyro carries it through both, within 0.05 deg with the studio's
    # gyro noise (its turn-on bias, 0.5 deg/s per axis, blended out between the registrations on either side of the
    # gap: within 0.3 deg), where interpolating between the registered orientations is degrees off.
    from test_sim_rom import TRIAL

    from bcmocap.geometry import quat_multiply, quat_conjugate
    from bcmocap.kinematics.ik import fill_gaps
    from bcmocap.pipeline.gyro_turns import fill_orientations_from_gyros
    skeleton, rig, trial, frames = _leg_trial()
    shin = rig.index("shin")
    registered = trial.registered.copy()
    registered[:, shin] = True
    registered[150:180, shin] = False  # a gap of 1 s
    registered[:10, shin] = False  # and the start
    poses = np.where(registered[..., None], trial.world_from_camera, np.nan)
    truth = trial.world_from_camera[:, shin, :4]

    def error_deg(q, at):
        d = quat_multiply(quat_conjugate(truth[at]), q[at])
        return np.degrees(2 * np.arccos(np.clip(np.abs(d[:, 0]), 0, 1)))

    gap = np.r_[0:10, 150:180]
    slerped = fill_gaps(np.where(registered[:, shin, None], truth, 0.0), registered[:, shin], rotations=True)
    assert error_deg(slerped, gap).max() > 5.0  # interpolation does not know how the leg swung
    for bias, within in ((0.0, 0.05), (np.radians(0.5), 0.3)):
        imu = simulate_imu(skeleton, rig, trial.motion, TRIAL["fps"], (0, frames - 1), seed=3, gyro_bias=bias)
        filled_poses, filled = fill_orientations_from_gyros(poses, registered, TRIAL["fps"], imu, rig.names)
        assert (filled == ~registered).all()
        assert error_deg(filled_poses[:, shin, :4], gap).max() < within
        np.testing.assert_array_equal(filled_poses[registered], poses[registered])  # registered rows as given
    only = np.zeros(rig.num_cameras, bool)
    same, none = fill_orientations_from_gyros(poses, registered, TRIAL["fps"], imu, rig.names, cameras=only)
    assert not none.any() and np.array_equal(same, poses, equal_nan=True)
    with pytest.raises(ValueError, match=r"3 time shifts for 7 cameras"):
        fill_orientations_from_gyros(poses, registered, TRIAL["fps"], imu, rig.names, [0.0] * 3)


def test_the_initial_stage_orients_unregistered_frames_on_the_gyro_clock_of_the_frontends_timing(tmp_path):
    # The run's glue: the capture trial's imu.npz, read at the shifts the frontend's gyro timing found (the IMU clock
    # 40 ms behind the frames); the root's cameras, whose positions the initial motion reads, are never filled; without
    # the timing nothing is.
    from test_sim_rom import TRIAL

    from bcmocap.pipeline import run

    skeleton, rig, trial, frames = _leg_trial()
    ctx, logged, timing = _gyro_timed_run(tmp_path, "capture", skeleton, rig, trial)
    registered = trial.registered.copy()
    registered[150:180] = False  # every camera, the root's too
    poses = np.where(registered[..., None], trial.world_from_camera, np.nan)
    filled_poses, filled = run._gyro_filled_poses(ctx, rig, poses, registered, TRIAL["fps"])
    root = np.asarray(rig.segments) == 0
    assert not filled[:, root].any() and filled[150:180, ~root].all() and filled.sum() == 30 * (~root).sum()
    shin = rig.index("shin")
    d = np.abs(np.sum(filled_poses[150:180, shin, :4] * trial.world_from_camera[150:180, shin, :4], axis=1))
    assert np.degrees(2 * np.arccos(np.clip(d, 0, 1))).max() < 0.05
    assert np.isfinite(filled_poses[filled]).all()  # positions interpolated
    assert len(logged) == 1 and "120 unregistered camera-frames of 4 cameras" in logged[0]
    timing.write_text("{}")
    same, none = run._gyro_filled_poses(ctx, rig, poses, registered, TRIAL["fps"])
    assert not none.any() and same is poses


@pytest.mark.slow  # 24 s; moved out of the fast tier for its 5-minute budget
def test_homography_matches_a_gyro_contradicts_are_dropped(walk):
    """A homography match on the static scene agrees with the camera's gyro turn; one on something that moved with
    the camera (the wearer's body) does not and is dropped. A frame pair where fewer than half agree, or fewer than
    30, loses them all; a pair of fewer matches all agreeing keeps them; a frame without a gyro reading (the first)
    keeps its own."""
    from bcmocap.cameras import camera_at
    from bcmocap.geometry import matrix_from_quat
    from bcmocap.kinematics.rig import camera_poses
    from bcmocap.pipeline.gyro_turns import homography_weights_gyros_agree_with

    capture, folder = walk
    angle = np.radians(4.0)  # the body's matches: 4° off the camera's turn, past the 1.5° tolerance
    body_turn = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    poses = np.asarray(camera_poses(capture.skeleton, capture.rig, capture.motion).wxyz_xyz)  # (T, C, 7) world_from_camera
    rng = np.random.default_rng(0)
    t_count, m = capture.num_frames, 80
    on_body = {0: 20, 1: 48, 2: 56}  # by t % 3 — 60 agree: the 20 go; 32 of 80: fewer than half; 24: fewer than 30
    pixels, prev, weights = np.zeros((t_count, 18, m, 2)), np.zeros((t_count, 18, m, 2)), np.zeros((t_count, 18, m))
    moved = np.zeros((t_count, m), bool)
    for c, count in ((11, m), (3, 10)):  # the left foot's camera (turning several degrees a frame); the chest's: 10
        camera = camera_at(capture.rig.intrinsics, c)
        for t in range(1, t_count):
            prev_from_curr = matrix_from_quat(poses[t - 1, c, :4]).T @ matrix_from_quat(poses[t, c, :4])
            rays = rng.normal(size=(m, 3)) * [0.3, 0.3, 0.0] + [0.0, 0.0, 1.0]
            if c == 11:
                moved[t] = np.arange(m) < on_body[t % 3]
            carried = np.where(moved[t][:, None] & (c == 11), rays @ (prev_from_curr @ body_turn).T,
                               rays @ prev_from_curr.T)
            pixels[t, c] = np.asarray(camera.project(rays)[0])
            prev[t, c] = np.asarray(camera.project(carried)[0])
            weights[t, c, :count] = 1.0
    weights[0, 11] = 1.0  # frame 0: no gyro reading (its interval starts before the recording)
    corr = dataclasses.replace(capture.correspondences(), homography_pixels=pixels, homography_pixels_prev=prev,
                               homography_weights=weights)
    window = TermWindow(0, t_count, capture.fps, capture.skeleton, capture.rig, corr, folder)
    kept = homography_weights_gyros_agree_with(window, 1.5, [CLOCK_OFFSET_S] * 18)
    assert kept.shape == weights.shape and (kept[0, 11] == 1).all()
    np.testing.assert_array_equal(kept[:, 3], weights[:, 3])  # 10 of 10 agree: kept
    frames = np.arange(1, t_count)
    for rest, what in ((0, "the body's go"), (1, "fewer than half agree"), (2, "fewer than 30 agree")):
        chosen = frames[frames % 3 == rest]
        expected = np.where(moved[chosen], 0.0, 1.0) if rest == 0 else np.zeros((len(chosen), m))
        np.testing.assert_array_equal(kept[chosen, 11], expected, err_msg=what)
    assert (np.delete(kept, [3, 11], axis=1) == 0).all()


def test_the_run_checks_homographies_by_the_gyros_only_with_gyro_turns(tmp_path):
    """``[solver] gyro_turn`` with the homography term: the solve's homography filter gates at 2 σ of the gyro, each
    camera at the frontend's gyro shift (none found here: the trial's times); without either, no filter."""
    from bcmocap.pipeline import run

    def context(overrides):
        return types.SimpleNamespace(config=RunConfig().with_overrides(overrides), capture=None,
                                     path=lambda *parts: tmp_path.joinpath(*parts))

    assert run._gyro_homography_check(context({})) is None
    check = run._gyro_homography_check(context({"solver.gyro_turn": 0.5}))
    assert check.func.__name__ == "homography_weights_gyros_agree_with"
    assert check.keywords == {"tolerance_deg": 1.0, "time_shifts_s": None}
    assert run._gyro_homography_check(context({"solver.gyro_turn": 0.5,
                                               "solver.terms": ["reprojection", "smoothness"]})) is None


def test_a_camera_registered_nowhere_sits_by_its_gyro_against_its_segments_other_camera():
    # The leg model's waist_back camera registers in no frame of its range-of-motion trial (its two siblings on the
    # pelvis do). Its gyro's turns against waist_front's registered turns give the rotation between them within
    # 0.02 deg (the studio's gyro noise, no bias; 0.2 deg with its turn-on bias), and the skeleton estimate takes its
    # mount from waist_front's turned by it: the rotation is the one the full estimate finds from the camera's own
    # frames, the skeleton the one without the camera, at waist_front's position.
    from test_rom import assert_same_mounts
    from test_sim_rom import TRIAL

    from bcmocap.geometry import quat_conjugate, quat_multiply
    from bcmocap.kinematics.rom import skeleton_from_range_of_motion
    from bcmocap.pipeline.gyro_turns import rotations_from_siblings_by_gyro
    skeleton, rig, trial, frames = _leg_trial()
    back, front = rig.index("waist_back"), rig.index("waist_front")
    registered = trial.registered.copy()
    registered[:, back] = False
    mounts = np.asarray(rig.segment_from_camera)
    truth = quat_multiply(quat_conjugate(mounts[front, :4]), mounts[back, :4])
    only = np.zeros(rig.num_cameras, bool)
    only[back] = True
    segments = [skeleton.names[s] for s in rig.segments]
    angles = []
    for bias in (0.0, np.radians(0.5)):
        imu = simulate_imu(skeleton, rig, trial.motion, TRIAL["fps"], (0, frames - 1), seed=3, gyro_bias=bias)
        placed, report = rotations_from_siblings_by_gyro(
            [(trial.world_from_camera, registered, TRIAL["fps"], imu, np.zeros(rig.num_cameras))], rig.names, segments, only)
        assert list(placed) == ["waist_back"] and placed["waist_back"][0] == "waist_front"
        assert report["waist_back"]["placed"] and report["waist_back"]["pairs"] > 50, report
        angles.append(np.degrees(2 * np.arccos(min(1.0, abs(placed["waist_back"][1] @ truth)))))
    assert angles[0] < 0.02 and angles[1] < 0.2, angles
    imu = simulate_imu(skeleton, rig, trial.motion, TRIAL["fps"], (0, frames - 1), seed=3, gyro_bias=0.0)
    placed, _ = rotations_from_siblings_by_gyro(
        [(trial.world_from_camera, registered, TRIAL["fps"], imu, np.zeros(rig.num_cameras))], rig.names, segments, only)
    args = (skeleton, trial.assignment, trial.world_from_camera)
    with pytest.raises(ValueError, match=r"camera 'waist_back' is never registered"):
        skeleton_from_range_of_motion(*args, registered, rest_frames=trial.rest_frames)
    with pytest.warns(UserWarning, match=r"camera 'waist_back' is registered in no frame of the trials: its mount is "
                                         r"'waist_front''s turned"):
        est = skeleton_from_range_of_motion(*args, registered, rest_frames=trial.rest_frames, sibling_rotations=placed)
    full = skeleton_from_range_of_motion(*args, trial.registered, rest_frames=trial.rest_frames)
    np.testing.assert_allclose(est.skeleton.offsets, full.skeleton.offsets, atol=1e-9)
    keep = [i for i in range(rig.num_cameras) if i != back]
    assert_same_mounts(est.segment_from_camera[keep], full.segment_from_camera[keep], 1e-9)
    got, want = est.segment_from_camera[back], full.segment_from_camera[back]
    assert np.degrees(2 * np.arccos(min(1.0, abs(got[:4] @ want[:4])))) < 0.05
    np.testing.assert_allclose(got[4:], est.segment_from_camera[front, 4:])
    with pytest.raises(ValueError, match=r"'waist_back' → 'chest': the sibling must be on the same segment"):
        skeleton_from_range_of_motion(*args, registered, rest_frames=trial.rest_frames,
                                      sibling_rotations={"waist_back": ("chest", truth)})
    with pytest.raises(ValueError, match=r"camera 'waist_back' is registered in \d+ frames; its own frames place it"):
        skeleton_from_range_of_motion(*args, trial.registered, rest_frames=trial.rest_frames, sibling_rotations=placed)


def test_the_skeleton_stage_places_a_camera_registered_nowhere_by_its_gyro(tmp_path, monkeypatch):
    # The run's glue: only a camera registered in no frame of the trials, on a segment with a camera that registered,
    # is placed; the ROM trial's imu.npz is read at the frontend's gyro timing of the sibling's frames (the IMU clock
    # 40 ms behind them; the unregistered camera's own shift, 120 ms here, is not where the sibling's poses were), and
    # the log names the camera, its sibling and the fit. Without a gyro file, nothing is placed.
    from test_sim_rom import TRIAL

    import bcmocap.correspondence_store as store_module
    from bcmocap.geometry import quat_conjugate, quat_multiply
    from bcmocap.pipeline import run

    skeleton, rig, trial, frames = _leg_trial()
    ctx, logged, timing = _gyro_timed_run(tmp_path, "rom", skeleton, rig, trial)
    monkeypatch.setattr(store_module.CorrespondenceStore, "open", staticmethod(lambda path: types.SimpleNamespace(fps=TRIAL["fps"])))
    assert run._sibling_rotations_from_gyros(ctx, [("rom", trial.world_from_camera, trial.registered)], 20, logged.append) == {}
    registered = trial.registered.copy()
    back, shin = rig.index("waist_back"), rig.index("shin")
    registered[:, [back, shin]] = False  # the shin has no other camera: the skeleton stage will name it
    shifts = [40.0] * rig.num_cameras
    shifts[back] = 120.0
    timing.write_text(json.dumps({"gyro_timing": {"time_shift_ms": shifts}}))
    placed = run._sibling_rotations_from_gyros(ctx, [("rom", trial.world_from_camera, registered)], 20, logged.append)
    mounts = np.asarray(rig.segment_from_camera)
    assert list(placed) == ["waist_back"] and placed["waist_back"][0] in ("waist_front", "waist_left")
    sibling = rig.index(placed["waist_back"][0])
    truth = quat_multiply(quat_conjugate(mounts[sibling, :4]), mounts[back, :4])
    assert np.degrees(2 * np.arccos(min(1.0, abs(placed["waist_back"][1] @ truth)))) < 0.05
    assert len(logged) == 1 and logged[0].startswith(f"skeleton: camera 'waist_back' is registered in no frame; by its "
                                                     f"gyro it sits relative to '{rig.names[sibling]}'")
    timing.write_text("{}")  # without the timing: the turns are read 40 ms off
    off = run._sibling_rotations_from_gyros(ctx, [("rom", trial.world_from_camera, registered)], 20, logged.append)
    assert np.degrees(2 * np.arccos(min(1.0, abs(off["waist_back"][1] @ truth)))) > 0.5
    (tmp_path / "capture" / "trials" / "rom" / "imu.npz").unlink()
    assert run._sibling_rotations_from_gyros(ctx, [("rom", trial.world_from_camera, registered)], 20, logged.append) == {}
