"""Tests for the gyro's timing and the readout found in a trial's own frames (bcmocap.frontend.gyro_timing)."""

import numpy as np
import pytest
from test_frontend_rolling_shutter import FPS, MOUNT, READOUT, _imu, _lens

from bcmocap.frontend.command import TrialOptions, trial_settings
from bcmocap.frontend.gyro_timing import (
    RotationPairs,
    alignment_cost,
    estimate_gyro_timing,
    gyro_orientation,
    rotation_pairs,
)
from bcmocap.frontend.rolling_shutter import GyroUnwarp
from bcmocap.geometry import quat_conjugate, quat_multiply, rotate_by_quat
from bcmocap.io.sensors import ImuRecording
from bcmocap.pipeline.config import RunConfig

H = 180


def _turning(t):
    """A body camera's angular velocity (rad/s, camera frame): a few rad/s, changing within tens of milliseconds."""
    return np.array([2.0 * np.sin(3.0 * t), 3.0 * np.cos(2.3 * t + 0.4), 1.5 * np.sin(5.0 * t + 1.0)])


def _two_sensors(first, second, seconds=3.0) -> ImuRecording:
    a, b = _imu(first, seconds), _imu(second, seconds)
    return ImuRecording(a.time, a.rate, ("cam", "still"), np.concatenate([a.camera_from_imu, b.camera_from_imu]),
                        np.concatenate([a.gyro, b.gyro], 1), np.concatenate([a.accel, b.accel], 1))


def _pairs(imu, sensor, zero_frame, shift, readout, *, seed=0, noise=0.001, outliers=0.1, frames=range(10, 150)):
    """Pairs of world directions seen in frame i and i + 1 of a camera whose frame i's middle row is exposed at
    ``(i − zero_frame) / fps + shift`` on the IMU's clock, row y at ``(y / (H − 1) − ½) readout`` from it."""
    rng = np.random.default_rng(seed)
    orientation = gyro_orientation(imu, sensor)
    imu_from_camera = quat_conjugate(imu.camera_from_imu[sensor, :4])
    frame = np.repeat(np.asarray(list(frames)), 40)
    direction = rng.normal(size=(len(frame), 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    bearings, rows = [], []
    for f in (frame, frame + 1):
        row = rng.uniform(0, H - 1, len(frame))
        t = (f - zero_frame) / FPS + shift + (row / (H - 1) - 0.5) * readout
        world_from_camera = quat_multiply(orientation(t), imu_from_camera)
        b = rotate_by_quat(quat_conjugate(world_from_camera), direction) + noise * rng.normal(size=direction.shape)
        bad = rng.random(len(frame)) < outliers / 2  # mismatched features
        b[bad] = rng.normal(size=(int(bad.sum()), 3))
        bearings.append(b / np.linalg.norm(b, axis=1, keepdims=True))
        rows.append(row)
    return RotationPairs(frame, bearings[0], bearings[1], rows[0], rows[1], H)


def test_the_cost_is_least_at_the_true_shift_and_readout():
    imu = _imu(_turning, 3.0)
    pairs = _pairs(imu, 0, 7, 0.0231, 0.0123, noise=0.0, outliers=0.0)
    orientation = gyro_orientation(imu, 0)
    mount = quat_conjugate(imu.camera_from_imu[0, :4])
    best = alignment_cost(pairs, orientation, mount, 7, FPS, 0.0231, 0.0123)
    assert best < 1e-6 * len(pairs)
    for shift, readout in ((0.0221, 0.0123), (0.0241, 0.0123), (0.0231, 0.0103), (0.0231, 0.0143), (0.0, 0.0148)):
        assert alignment_cost(pairs, orientation, mount, 7, FPS, shift, readout) > 100 * max(best, 1e-9)


def test_each_cameras_shift_and_the_shared_readout_are_recovered():
    imu = _imu(_turning, 3.0)
    shifts, readout, zero = np.array([0.0231, -0.0412, 0.0057]), 0.0123, np.array([7, 12, 3])
    pairs = [_pairs(imu, 0, zero[c], shifts[c], readout, seed=c) for c in range(3)]
    found = estimate_gyro_timing(pairs, imu, [0, 0, 0], zero, FPS, 0.0148)
    # a shift shows only through how the turn changes within a frame period, so 1 mrad of noise per pair leaves a
    # few tenths of a millisecond: 0.5 ms is 0.03 frames at 60 fps
    np.testing.assert_allclose(found.time_shift_s, shifts, atol=5e-4)
    assert abs(found.readout_s - readout) < 3e-4 and found.readout_estimated and found.determined.all()
    assert found.pairs.tolist() == [len(p) for p in pairs]
    given = estimate_gyro_timing(pairs, imu, [0, 0, 0], zero, FPS, readout, estimate_readout=False)
    assert given.readout_s == readout and not given.readout_estimated
    np.testing.assert_allclose(given.time_shift_s, shifts, atol=5e-4)
    assert set(found.as_dict()) == {"time_shift_ms", "readout_ms", "readout_estimated", "pairs", "determined"}


def test_the_cameras_searched_in_threads_give_the_one_threads_result_bit_for_bit(monkeypatch):
    imu = _imu(_turning, 3.0)
    zero = np.array([7, 12, 3, 5])
    pairs = [_pairs(imu, 0, zero[c], s, 0.0123, seed=c) for c, s in enumerate((0.0231, -0.0412, 0.0057, 0.011))]
    found = {}
    for threads in ("1", "3"):
        monkeypatch.setenv("BCMOCAP_THREADS", threads)
        found[threads] = estimate_gyro_timing(pairs, imu, [0] * 4, zero, FPS, 0.0148)
    assert np.array_equal(found["1"].time_shift_s, found["3"].time_shift_s)
    assert found["1"].readout_s == found["3"].readout_s


def test_a_camera_that_does_not_turn_gets_the_others_median_shift_and_none_raises():
    imu = _two_sensors(_turning, lambda t: np.zeros(3))
    turning = [_pairs(imu, 0, 4, s, READOUT, seed=k) for k, s in enumerate((0.010, 0.012, 0.014))]
    still = _pairs(imu, 1, 4, 0.05, READOUT, seed=9)
    notes = []
    found = estimate_gyro_timing([*turning, still], imu, [0, 0, 0, 1], [4, 4, 4, 4], FPS, READOUT,
                                 estimate_readout=False, log=notes.append)
    assert found.determined.tolist() == [True, True, True, False]
    assert found.time_shift_s[3] == pytest.approx(np.median(found.time_shift_s[:3])) and "[3]" in notes[0]
    with pytest.raises(ValueError, match="no camera turned enough"):
        estimate_gyro_timing([still], imu, [1], [4], FPS, READOUT)
    # a shift beyond the search: its least cost at the search's edge, so not found
    beyond = estimate_gyro_timing([*turning, _pairs(imu, 0, 4, 0.15, READOUT, seed=7)], imu, [0, 0, 0, 0], [4] * 4, FPS,
                                  READOUT, estimate_readout=False)
    assert beyond.determined.tolist() == [True, True, True, False]
    with pytest.raises(ValueError, match="2 cameras' pairs, 1 IMU indices"):
        estimate_gyro_timing([still, still], imu, [1], [4, 4], FPS, READOUT)


def test_pairs_follow_features_from_one_frame_to_the_next():
    import cv2

    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (H + 40, 360)).astype(np.float32), (0, 0), 2.0)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    frames = [(k, np.ascontiguousarray(texture[20 - k: 20 - k + H, 20: 340])) for k in range(4)]  # moves 1 px down per frame
    frames.append((6, frames[0][1]))  # after a gap: no pair across it
    lens = _lens()
    pairs = rotation_pairs(frames, lens)
    assert len(pairs) > 300 and set(pairs.frame.tolist()) == {0, 1, 2}
    np.testing.assert_allclose(pairs.row_b - pairs.row_a, 1.0, atol=0.05)
    np.testing.assert_allclose(np.linalg.norm(pairs.bearing_a, axis=1), 1.0)
    for bearing, row in ((pairs.bearing_a, pairs.row_a), (pairs.bearing_b, pairs.row_b)):  # each its own frame's
        np.testing.assert_allclose(np.asarray(lens.project(bearing)[0])[:, 1], row, atol=1e-6)
    assert pairs.height == H
    assert len(rotation_pairs([(0, frames[0][1])], lens)) == 0


def test_bearings_are_the_lens_rays_and_one_compiled_unprojection_serves_a_bucket():
    from bcmocap.cameras import _unproject
    from bcmocap.frontend.gyro_timing import _BEARING_BUCKET, _bearings

    lens = _lens()
    rng = np.random.default_rng(2)
    for count in (1, 37, _BEARING_BUCKET, _BEARING_BUCKET + 1):
        pixels = rng.uniform([0.0, 0.0], [lens.width, lens.height], (count, 2))
        rays = np.asarray(lens.unproject(pixels))
        np.testing.assert_allclose(_bearings(lens, pixels), rays / np.linalg.norm(rays, axis=1, keepdims=True),
                                   rtol=0, atol=1e-14)  # the same rays but for rounding (XLA's code per shape)
    before = _unproject._cache_size()
    for count in (5, 300, 999):  # the counts of pairs vary by window; one bucket, no new program
        _bearings(lens, rng.uniform(0.0, 100.0, (count, 2)))
    assert _unproject._cache_size() == before


def test_gyro_unwarp_reads_the_gyro_at_the_shifted_frame_time():
    ramp = np.array([0.5, 1.0, -2.0])
    plain = GyroUnwarp((_lens(),), _imu(lambda t: ramp * t), (0,), (12,), FPS, READOUT)
    shifted = GyroUnwarp((_lens(),), _imu(lambda t: ramp * t), (0,), (12,), FPS, READOUT, time_shifts=(0.02,))
    np.testing.assert_allclose(shifted.angular_velocity(0, 40), ramp * ((40 - 12) / FPS + 0.02), atol=1e-6)
    assert shifted.frame_time(0, 40) == pytest.approx(plain.frame_time(0, 40) + 0.02)
    assert shifted.settings != plain.settings
    with pytest.raises(ValueError, match="time_shifts"):
        GyroUnwarp((_lens(),), _imu(lambda t: ramp * t), (0,), (12,), FPS, READOUT, time_shifts=(0.0, 0.1))


def test_the_settings_say_how_the_gyro_is_timed():
    with pytest.raises(ValueError, match="gyro_timing"):
        TrialOptions(gyro_timing="audio")
    with pytest.raises(ValueError, match="estimate_readout needs"):
        TrialOptions(estimate_readout=True)
    base = {"stride": 1, "frames": None, "max_features": 100, "homographies": False, "chunk_frames": 0,
            "registration": "tracking", "max_measurements": None, "rolling_shutter_readout": 0.0148, "gyro": "abc"}
    assert "gyro_timing" not in trial_settings(**base)
    framed = trial_settings(**base, gyro_timing="frames", estimate_readout=True)
    assert framed["gyro_timing"] == "frames" and framed["estimate_readout"] is True
    config = RunConfig().with_overrides({"frontend.rolling_shutter_readout": 0.0148, "frontend.gyro_timing": "frames",
                                         "frontend.estimate_readout": True})
    assert config.frontend.estimate_readout
    with pytest.raises(ValueError, match="frontend.estimate_readout"):
        RunConfig().with_overrides({"frontend.estimate_readout": True})
    with pytest.raises(ValueError, match="frontend.gyro_timing"):
        RunConfig().with_overrides({"frontend.gyro_timing": "audio"})
    with pytest.raises(ValueError, match="needs a rolling_shutter_readout"):
        RunConfig().with_overrides({"frontend.gyro_timing": "frames"})
    assert MOUNT.shape == (4,)


def test_trials_share_the_readout_and_each_falls_back_on_its_own_cameras():
    """Cameras of two trials (two gyro recordings, each with its own clock offset) estimated together: one readout,
    and a camera that did not turn gets the median of its own trial's cameras."""
    first, second = _imu(_turning, 3.0), _two_sensors(lambda t: _turning(t + 0.7), lambda t: np.zeros(3))
    rom = [_pairs(first, 0, 5, s, 0.0111, seed=k) for k, s in enumerate((0.031, 0.029))]
    capture = [_pairs(second, 0, 8, s, 0.0111, seed=5 + k) for k, s in enumerate((-0.012, -0.010))]
    still = _pairs(second, 1, 8, 0.0, 0.0111, seed=9)
    found = estimate_gyro_timing([*rom, *capture, still], [first, first, second, second, second], [0, 0, 0, 0, 1],
                                 [5, 5, 8, 8, 8], FPS, 0.0148, groups=["rom", "rom", "capture", "capture", "capture"])
    np.testing.assert_allclose(found.time_shift_s[:4], [0.031, 0.029, -0.012, -0.010], atol=5e-4)
    assert found.time_shift_s[4] == pytest.approx(np.median(found.time_shift_s[2:4]))
    assert abs(found.readout_s - 0.0111) < 3e-4
    with pytest.raises(ValueError, match="no camera of 'capture'"):
        estimate_gyro_timing([*rom, still], [first, first, second], [0, 0, 1], [5, 5, 8], FPS, 0.0148,
                             groups=["rom", "rom", "capture"])
    with pytest.raises(ValueError, match="2 gyro recordings"):
        estimate_gyro_timing([*rom, still], [first, first], [0, 0, 1], [5, 5, 8], FPS, 0.0148)


def test_the_windows_are_where_the_gyro_turns_fastest():
    from bcmocap.frontend.gyro_timing import turning_windows

    burst = _imu(lambda t: np.array([0.0, 0.0, 5.0]) * ((0.5 < t < 0.8) or (2.0 < t < 2.3)), 3.0)
    starts = turning_windows(burst, 0, 170, FPS, 2, 15)
    assert len(starts) == 2 and 30 <= starts[0] <= 33 and 120 <= starts[1] <= 123  # inside the bursts
    assert turning_windows(burst, 0, 10, FPS, 2, 15).tolist() == [0]
    assert len(turning_windows(burst, 0, 40, FPS, 8, 15)) == 2  # as many as fit without overlapping


def test_a_cameras_windows_are_cut_from_one_read_of_its_video():
    from bcmocap.frontend.gyro_timing import _windows

    frames = ((i, f"image {i}") for i in range(40, 100))
    out = list(_windows(frames, np.array([40, 60, 85]), 5))
    assert [[i for i, _ in w] for w in out] == [[40, 41, 42, 43, 44], [60, 61, 62, 63, 64], [85, 86, 87, 88, 89]]
    assert out[1][0][1] == "image 60"
    assert [len(w) for w in _windows(((i, None) for i in range(0, 10)), np.array([0, 8]), 5)] == [5, 2]  # cut short


def test_the_solve_reads_the_gyro_time_offsets_relative_to_their_mean(tmp_path):
    import json

    from bcmocap.pipeline.run import RunContext, gyro_time_offsets

    from types import SimpleNamespace

    three_cameras = SimpleNamespace(cameras=[None] * 3)  # the check reads only the capture's camera count
    ctx = RunContext(capture=three_cameras, config=RunConfig(), out=tmp_path, log=print)
    assert gyro_time_offsets(ctx) is None
    (tmp_path / "frontend" / "capture").mkdir(parents=True)
    (tmp_path / "frontend" / "capture" / "registration.json").write_text(json.dumps({"trial": "capture"}))
    assert gyro_time_offsets(ctx) is None  # registered with the clock's timing
    (tmp_path / "frontend" / "capture" / "registration.json").write_text(
        json.dumps({"gyro_timing": {"time_shift_ms": [31.0, 29.0, 36.0], "determined": [True, True, True]}}))
    offsets, measured = gyro_time_offsets(ctx)
    np.testing.assert_allclose(offsets, [-0.001, -0.003, 0.004])
    assert measured.all()
    # a camera its gyro could not time is no measurement: left out of the mean, and the solver's default prior
    (tmp_path / "frontend" / "capture" / "registration.json").write_text(json.dumps(
        {"gyro_timing": {"time_shift_ms": [31.0, 30.0, 36.0], "determined": [True, False, True]}}))
    offsets, measured = gyro_time_offsets(ctx)
    np.testing.assert_allclose(offsets, [-0.0025, 0.0, 0.0025])
    assert measured.tolist() == [True, False, True]
    # a shift count other than the capture's cameras is refused, naming the file
    (tmp_path / "frontend" / "capture" / "registration.json").write_text(
        json.dumps({"gyro_timing": {"time_shift_ms": [31.0, 30.0], "determined": [True, True]}}))
    with pytest.raises(ValueError, match=r"registration\.json: gyro_timing\.time_shift_ms has 2 values for 3"):
        gyro_time_offsets(ctx)
