"""Tests for the gyro rolling-shutter correction of frames (bcmocap.frontend.rolling_shutter)."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from test_frontend_capture import CAMERAS, make_capture

from bcmocap.cameras import OpenCVFisheyeCamera
from bcmocap.frontend import read_capture
from bcmocap.frontend.command import trial_settings
from bcmocap.frontend.rolling_shutter import GyroUnwarp, gyro_fingerprint, gyro_unwarp
from bcmocap.geometry import matrix_from_quat, quat_exp
from bcmocap.io.sensors import ImuRecording, write_imu
from bcmocap.pipeline.config import RunConfig

W, H, FPS, READOUT = 320, 180, 60.0, 0.015
#: The IMU's rotation in its camera's frame (camera_from_imu), away from the identity so the mount matters.
MOUNT = quat_exp(np.array([0.4, -0.3, 1.0]))


def _lens() -> OpenCVFisheyeCamera:
    return OpenCVFisheyeCamera(W, H, focal=[95.0, 95.0], principal_point=[161.0, 88.5], distortion=[0.05, -0.01, 0.0, 0.0])


def _imu(omega_of_t, seconds: float = 2.0, rate: float = 400.0) -> ImuRecording:
    """A one-camera IMU whose camera turns at ``omega_of_t(t) (3,)`` rad/s (camera frame)."""
    time = np.arange(0.0, seconds, 1.0 / rate)
    imu_from_camera = matrix_from_quat(MOUNT).T
    gyro = np.stack([imu_from_camera @ omega_of_t(t) for t in time])[:, None]
    return ImuRecording(time, rate, ("cam",), np.r_[MOUNT, 0.0, 0.0, 0.0][None], gyro, np.zeros_like(gyro))


def _rotate(rotvec, v):
    return v @ matrix_from_quat(quat_exp(rotvec)).T


def _rolling_shutter_pixel(lens, omega, bearing):
    """Where a direction with bearing ``bearing (3,)`` at the frame time appears in a rolling-shutter frame: the row
    ``y`` it is seen in sees it at ``exp(−τ(y) ω) bearing`` (iterated to convergence)."""
    pixel = np.asarray(lens.project(bearing)[0])
    for _ in range(30):
        tau = (pixel[1] / (H - 1) - 0.5) * READOUT
        pixel = np.asarray(lens.project(_rotate(-tau * omega, bearing))[0])
    return pixel


def test_the_map_finds_where_a_turning_camera_saw_each_pixel():
    omega = np.array([1.5, -3.0, 2.0])  # rad/s in the camera frame: 220 deg/s, a fast arm
    unwarp = GyroUnwarp((_lens(),), _imu(lambda t: omega), (0,), (4,), FPS, READOUT)
    np.testing.assert_allclose(unwarp.angular_velocity(0, 30), omega, atol=1e-9)
    source = unwarp.source_pixels(0, 30)
    assert source.shape == (H, W, 2) and source.dtype == np.float32
    lens = _lens()
    rng = np.random.default_rng(0)
    pixels = np.stack([rng.integers(20, W - 20, 40), rng.integers(10, H - 10, 40)], 1)
    expected = np.stack([_rolling_shutter_pixel(lens, omega, np.asarray(lens.unproject(p.astype(float))))
                         for p in pixels])
    moved = np.linalg.norm(expected - pixels, axis=1)
    assert moved.max() > 2.5  # the rolling shutter moves these pixels by pixels ...
    np.testing.assert_allclose(source[pixels[:, 1], pixels[:, 0]], expected, atol=0.02)  # ... the map finds where


def test_the_angular_velocity_is_read_at_the_frame_time_through_the_mount():
    ramp = np.array([0.5, 1.0, -2.0])  # rad/s²: ω(t) = ramp · t, so the mean over a readout is ω at its middle
    unwarp = GyroUnwarp((_lens(),), _imu(lambda t: ramp * t), (0,), (12,), FPS, READOUT)
    for index in (20, 72):  # video frame i shows time (i − 12) / fps
        np.testing.assert_allclose(unwarp.angular_velocity(0, index), ramp * (index - 12) / FPS, atol=1e-6)
    # before the gyro's first sample: the first readout's
    np.testing.assert_allclose(unwarp.angular_velocity(0, 0), ramp * READOUT / 2, atol=1e-6)


def test_a_rolling_shutter_frame_becomes_the_global_shutter_frame():
    """A scene of smooth brightness over directions, seen once by a global shutter and once by a rolling shutter
    while the camera turns; corrected, the second is the first up to resampling."""
    lens = _lens()
    omega = np.array([-4.0, 5.0, 2.0])  # 390 deg/s
    grid = np.stack(np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float)), -1)
    bearing = np.asarray(lens.unproject(grid))

    def scene(d):
        return 127.5 + 120.0 * np.sin(9.0 * d[..., 0] + 3.0 * d[..., 2]) * np.cos(7.0 * d[..., 1])

    tau = (grid[..., 1:2] / (H - 1) - 0.5) * READOUT
    global_shutter = scene(bearing)
    turned = np.einsum("hij,hwj->hwi", matrix_from_quat(quat_exp(tau[:, 0, :] * omega)), bearing)
    rolling = scene(turned)  # row y looks through the camera as it is τ(y) after the frame time
    unwarp = GyroUnwarp((lens,), _imu(lambda t: omega), (0,), (0,), FPS, READOUT)
    corrected = unwarp(0, 30, np.clip(np.round(rolling), 0, 255).astype(np.uint8))
    inner = (slice(8, H - 8), slice(8, W - 8))
    before = np.abs(rolling - global_shutter)[inner].mean()
    after = np.abs(corrected.astype(float) - global_shutter)[inner].mean()
    assert before > 4.0 and after < 0.1 * before
    with pytest.raises(ValueError, match="320x180"):
        unwarp(0, 30, np.zeros((H, W + 1), np.uint8))


def test_readout_and_shapes_are_checked():
    imu = _imu(lambda t: np.zeros(3))
    with pytest.raises(ValueError, match="one frame period"):
        GyroUnwarp((_lens(),), imu, (0,), (0,), FPS, 0.02)
    with pytest.raises(ValueError, match="one of each per camera"):
        GyroUnwarp((_lens(), _lens()), imu, (0,), (0,), FPS, READOUT)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    return make_capture(tmp_path_factory.mktemp("rolling_shutter") / "capture")


def test_a_capture_passes_one_trials_frames_through_its_correction(capture_dir):
    seen = []

    class AddOne:
        settings = {"add": 1}

        def __call__(self, camera, index, image):
            seen.append((camera, index))
            return image + 1

    capture = read_capture(capture_dir)
    corrected = capture.corrected("rom", AddOne())
    assert corrected.correction_settings("rom") == {"add": 1} and corrected.correction_settings("capture") == {}
    raw = [im for _, im in capture.frames("rom", 1, stride=2, gray=True)]
    out = [im for _, im in corrected.frames("rom", "left_foot", stride=2, gray=True)]
    assert seen == [(1, i) for i in range(0, 9, 2)]
    assert all(np.array_equal(a + 1, b) for a, b in zip(raw, out))
    assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(capture.frames("capture", 0), corrected.frames("capture", 0)))
    with pytest.raises(ValueError, match="no trial 'walk'"):
        capture.corrected("walk", AddOne())


def test_gyro_unwarp_needs_a_gyro_in_every_camera(capture_dir):
    capture = read_capture(capture_dir)
    with pytest.raises(ValueError, match=r"imu\.npz: missing"):
        gyro_unwarp(capture, "rom", [0, 0], 1 / 60)
    imu = _imu(lambda t: np.zeros(3))
    write_imu(capture_dir / "trials" / "rom" / "imu.npz",
              ImuRecording(imu.time, imu.rate, ("head",), imu.camera_from_imu, imu.gyro, imu.accel))
    with pytest.raises(ValueError, match="no IMU for camera 'left_foot'"):
        gyro_unwarp(capture, "rom", [0, 0], 1 / 60)
    with pytest.raises(ValueError, match="frontend.rolling_shutter_readout"):
        gyro_unwarp(capture, "rom", [0, 0], 0.05)  # beyond a frame period at 30 fps
    two = ImuRecording(imu.time, imu.rate, CAMERAS, np.repeat(imu.camera_from_imu, 2, 0),
                       np.repeat(imu.gyro, 2, 1), np.repeat(imu.accel, 2, 1))
    write_imu(capture_dir / "trials" / "rom" / "imu.npz", two)
    unwarp = gyro_unwarp(capture, "rom", [3, 5], 1 / 60)
    assert unwarp.offsets == (3, 5) and unwarp.imu_index == (0, 1) and unwarp.settings["gyro_unwarp"]["readout_s"] == 1 / 60
    fingerprint = gyro_fingerprint(capture, "rom")
    # the corrected frames depend on the lenses and the gyro: both are in the settings the caches are keyed on
    other_lens = gyro_unwarp(capture.with_lenses([_lens(), _lens()]), "rom", [3, 5], 1 / 60)
    assert other_lens.settings["gyro_unwarp"]["lenses"] != unwarp.settings["gyro_unwarp"]["lenses"]
    write_imu(capture_dir / "trials" / "rom" / "imu.npz", dataclasses.replace(two, gyro=two.gyro + 0.01))
    other_gyro = gyro_unwarp(capture, "rom", [3, 5], 1 / 60)
    assert other_gyro.settings["gyro_unwarp"]["gyro"] != unwarp.settings["gyro_unwarp"]["gyro"]
    assert gyro_fingerprint(capture, "rom") != fingerprint
    assert trial_settings(stride=1, frames=None, max_features=100, homographies=False, chunk_frames=0,
                          registration="tracking", max_measurements=None, rolling_shutter_readout=1 / 60,
                          gyro=fingerprint)["gyro"] == fingerprint
    short = ImuRecording(two.time[:3], two.rate, CAMERAS, two.camera_from_imu, two.gyro[:3], two.accel[:3])
    write_imu(capture_dir / "trials" / "rom" / "imu.npz", short)
    with pytest.raises(ValueError, match="less than one"):
        gyro_unwarp(capture, "rom", [0, 0], 1 / 60)
    (capture_dir / "trials" / "rom" / "imu.npz").unlink()


def test_the_frontend_readout_is_a_setting_that_excludes_the_solvers():
    assert RunConfig().with_overrides({"frontend.rolling_shutter_readout": 0.015}).frontend.rolling_shutter_readout == 0.015
    with pytest.raises(ValueError, match="solver.rolling_shutter_readout"):
        RunConfig().with_overrides({"frontend.rolling_shutter_readout": 0.015, "solver.rolling_shutter_readout": 0.015})
    with pytest.raises(ValueError, match="frontend.rolling_shutter_readout"):
        RunConfig().with_overrides({"frontend.rolling_shutter_readout": -0.01})


def test_a_frame_before_the_gyros_first_sample_reads_its_first_readout():
    """A frame time before the recording is clipped to its first readout; (t0 + half) − half can fall an ulp before
    t0, which integrate_gyro refused (a realistic capture whose gyro timing moved frames before the IMU's start)."""
    ramp = np.array([0.5, 1.0, -2.0])
    imu = _imu(lambda t: ramp * t)
    late = dataclasses.replace(imu, time=imu.time + 0.010018)  # (0.010018 + 0.0075) − 0.0075 < 0.010018
    assert (0.010018 + READOUT / 2) - READOUT / 2 < 0.010018
    unwarp = GyroUnwarp((_lens(),), late, (0,), (12,), FPS, READOUT, time_shifts=(-0.05,))
    np.testing.assert_allclose(unwarp.angular_velocity(0, 0), ramp * READOUT / 2, atol=1e-6)
