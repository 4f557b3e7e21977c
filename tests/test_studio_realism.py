"""Tests for the studio's degradations of a real shoot (issue 20): mount wobble, the ``realistic`` preset,
compression at a bit rate, calibration error, motion files, and the command line's errors.

Renders are tiny (64x36 px, a few frames per trial) and shared through module fixtures: the preset capture
(every degradation on, H.264 at the preset's bit rate) and the same capture at constant quality. The tests that
render are marked slow (``-m slow``); the others (wobble, preset, motion names, option errors) are fast.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import one_line_error

from bcmocap.cameras import TiltedThinPrismFisheyeCamera
from bcmocap.cli import main
from bcmocap.geometry import SE3
from bcmocap.io.opencv_calibration import read_opencv_fisheye_calibration
from bcmocap.io.sensors import read_imu
from bcmocap.kinematics import JointType, forward_kinematics
from bcmocap.sim import load_body_motion, load_motion_file, standard_rig
from bcmocap.sim.lens_units import lens_design, nominal_lens
from bcmocap.sim.motions import cmu_trial_path
from bcmocap.sim.sensors import simulate_imu
from bcmocap.sim.studio import (
    READOUT_RANGE_MS,
    REALISTIC,
    StudioSettings,
    load_ground_truth,
    preset_settings,
    write_capture,
)
from bcmocap.sim.studio_command import DEGRADATIONS, PRESETS
from bcmocap.sim.wobble import CAMERA_SCALE, KNEE, mount_wobble

DATA = Path(__file__).parent / "data"
TINY = ["--seconds", "0.1", "--rom-seconds", "0.1", "--width", "64", "--height", "36", "--reference-photos", "2",
        "--reference-size", "64x48", "--seed", "5", "--no-progress"]
TINY_FIELDS = dict(seconds=0.1, rom_seconds=0.1, width=64, height=36, reference_photos=2, reference_width=64,
                   reference_height=48, seed=5)


@pytest.fixture(scope="module")
def preset_capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("realistic") / "capture"
    assert main(["simulate", str(folder), *TINY, "--preset", "realistic"]) == 0
    return folder


@pytest.fixture(scope="module")
def constant_quality_capture(tmp_path_factory) -> Path:
    """The preset capture with H.264 at constant quality (CRF 16) instead of the preset's bit rate."""
    folder = tmp_path_factory.mktemp("realistic_crf") / "capture"
    write_capture(folder, preset_settings("realistic", **TINY_FIELDS, video_bitrate_mbps=0.0), progress=False)
    return folder


# ---- mount wobble (no rendering) -------------------------------------------------------------------


@pytest.fixture(scope="module")
def walk_mounts():
    skeleton, motion = load_body_motion("walk", fps=60.0, seconds=2.0)
    rig = standard_rig(skeleton, 64, 36)
    return np.asarray(rig.world_from_camera(forward_kinematics(skeleton, motion)).wxyz_xyz)


def test_wobble_has_the_requested_amplitude_and_differs_per_camera(walk_mounts):
    mm, deg = 3.0, 1.5
    straps, offsets = mount_wobble(walk_mounts, 60.0, mm / 1000, math.radians(deg), np.random.default_rng(1))
    assert offsets.shape == walk_mounts.shape[:2] + (6,)
    rms_mm = 1000 * np.sqrt(np.mean(np.sum(offsets[..., :3] ** 2, -1), axis=0))
    rms_deg = np.degrees(np.sqrt(np.mean(np.sum(offsets[..., 3:] ** 2, -1), axis=0)))
    # Each camera's RMS is the request times its own factor in [0.5, 1.5], the same factor for both (to the
    # few peaks beyond KNEE x RMS that the strap saturates).
    factor = rms_mm / mm
    assert np.all((factor >= 0.98 * CAMERA_SCALE[0]) & (factor <= CAMERA_SCALE[1] + 1e-9))
    np.testing.assert_allclose(rms_deg / deg, factor, rtol=0.02)
    assert factor.std() > 0.15 and np.mean(factor) == pytest.approx(1.0, abs=0.25)
    # A few mm and degrees: no offset beyond twice the strap's knee.
    norms = np.linalg.norm(offsets[..., :3], axis=-1)
    assert np.all(norms <= 2 * straps.knee[None, :, 0] + 1e-12) and 1000 * norms.max() < 2 * KNEE * mm * CAMERA_SCALE[1]
    # Different straps: frequencies, damping and the offsets' time courses differ between cameras.
    assert len(np.unique(np.round(straps.natural_hz, 6))) == len(straps.natural_hz)
    corr = np.corrcoef(offsets[:, :, 0].T)
    assert np.abs(corr[np.triu_indices_from(corr, 1)]).max() < 0.999
    # The wobble moves with the motion: a camera's translation changes between frames (not a constant offset).
    assert np.abs(np.diff(offsets[..., :3], axis=0)).max() > 1e-4
    # The same straps on another trial (here the walk's second half) wobble by the same order of magnitude.
    other = straps.offsets(walk_mounts[60:], 60.0, np.random.default_rng(2))
    rms_other = 1000 * np.sqrt(np.mean(np.sum(other[..., :3] ** 2, -1), axis=0))
    assert np.all((rms_other > 0.2 * rms_mm) & (rms_other < 5 * rms_mm))
    # A violent trial (the walk played 8 times as fast) saturates on the straps instead of throwing the cameras off.
    fast = straps.offsets(walk_mounts[::8], 60.0, np.random.default_rng(3))
    assert np.all(np.linalg.norm(fast[..., 3:], axis=-1) <= 2 * straps.knee[None, :, 1] + 1e-12)
    assert np.degrees(np.linalg.norm(fast[..., 3:], axis=-1)).max() < 2 * KNEE * deg * CAMERA_SCALE[1]


def test_wobble_of_a_still_trial_stays_small():
    # Standing still (the rest pose held): no acceleration, so the spring part cannot be scaled up to the request.
    skeleton, motion = load_body_motion("walk", fps=60.0, seconds=0.5)
    still = motion[np.zeros(30, int)]
    rig = standard_rig(skeleton, 64, 36)
    mounts = np.asarray(rig.world_from_camera(forward_kinematics(skeleton, still)).wxyz_xyz)
    _, offsets = mount_wobble(mounts, 60.0, 0.003, math.radians(1.5), np.random.default_rng(0))
    rms = np.sqrt(np.mean(np.sum(offsets[..., :3] ** 2, -1), axis=0))
    assert np.all(rms <= 0.003 * CAMERA_SCALE[1] * math.sqrt(0.5) + 1e-12)  # the drift's share only


# ---- the preset -------------------------------------------------------------------------------------


def test_preset_turns_every_degradation_on():
    clean, preset = StudioSettings(), preset_settings("realistic")
    # Every option the preset may set is a degradation option of the command (blur_samples: the preset keeps 4).
    assert set(REALISTIC) == set(DEGRADATIONS) - {"blur_samples"} and PRESETS == ("realistic",)
    changed = {k for k in REALISTIC if getattr(preset, k) != getattr(clean, k)}
    assert changed == set(REALISTIC) - {"read_noise_dn"}  # the studio's read noise is already a camera's
    options, plain = preset.render_options(), clean.render_options()
    assert options.motion_blur and options.rolling_shutter and not plain.motion_blur and not plain.rolling_shutter
    assert options.exposure_frames == pytest.approx(0.48)
    assert options.readout_frames == pytest.approx(preset.readout_ms * 60 / 1000)  # drawn: test_preset_draws_the_readout
    assert options.vignetting == 0.4 and options.full_scale_electrons == pytest.approx(9900.0)
    assert plain.vignetting == 0 and plain.full_scale_electrons == 0 and plain.noise_dn == 1.0
    assert preset.video_bitrate_mbps == pytest.approx(45 * 640 * 360 / (1920 * 1080)) and preset.container == "mp4-aac"
    # Scaled to the capture: a frame period bounds exposure and readout; the bit rate follows pixels per second.
    fast = preset_settings("realistic", fps=120.0, width=1280, height=720)
    assert fast.readout_ms == pytest.approx(0.95 * 1000 / 120, abs=1e-4) and fast.exposure_ms == pytest.approx(1000 / 240, abs=1e-4)
    assert fast.video_bitrate_mbps == pytest.approx(45 * 4 / 9 * 2)
    # A degradation given explicitly replaces the preset's value.
    assert preset_settings("realistic", mount_wobble_mm=0.0).mount_wobble_mm == 0.0
    with pytest.raises(ValueError, match="unknown studio preset 'grainy'"):
        preset_settings("grainy")


def test_preset_draws_the_readout_per_capture_from_the_published_range():
    """What a user does not know: each capture's readout is drawn by its seed from action cameras' range."""
    low, high = READOUT_RANGE_MS
    assert (low, high) == (10.0, 15.8) and high <= 0.95 * 1000 / 60  # at 60 fps no draw is capped
    readouts = [preset_settings("realistic", seed=seed).readout_ms for seed in range(40)]
    assert all(low <= r <= high for r in readouts) and len(set(readouts)) == 40
    assert min(readouts) < low + 1.5 and max(readouts) > high - 1.5  # the whole range is drawn from, not one end
    a, b = preset_settings("realistic", seed=1), preset_settings("realistic", seed=2)
    assert a.readout_ms != b.readout_ms and preset_settings("realistic", seed=1).readout_ms == a.readout_ms
    # The draw is its own stream: other settings do not move it, and it moves nothing else.
    assert preset_settings("realistic", seed=1, fps=50.0, width=320, height=180, motion="run").readout_ms == a.readout_ms
    assert dataclasses.replace(a, readout_ms=b.readout_ms) == dataclasses.replace(b, seed=1)
    # Capped at 0.95 frame periods; a value given explicitly wins (and is not capped by the preset).
    assert preset_settings("realistic", seed=1, fps=120.0).readout_ms == pytest.approx(0.95 * 1000 / 120, abs=1e-4)
    assert preset_settings("realistic", seed=1, readout_ms=12.5).readout_ms == 12.5
    assert preset_settings("realistic", seed=1, readout_ms=0.0).readout_ms == 0.0


@pytest.mark.slow  # renders a capture
def test_preset_capture_settings_and_truth(preset_capture):
    manifest = json.loads((preset_capture / "capture.json").read_text())
    assert manifest["complete"] and manifest["settings"] == preset_settings("realistic", **TINY_FIELDS).to_dict()
    gt = load_ground_truth(preset_capture)
    for trial_index, (name, trial) in enumerate(gt.trials.items()):
        fk = forward_kinematics(gt.skeleton, trial.motion)
        # The bones' poses and the rigid mounts follow from the motion; the cameras are moved on their mounts.
        np.testing.assert_allclose(trial.joint_positions, np.asarray(fk.translation()), atol=1e-12)
        np.testing.assert_allclose(trial.world_from_mount, np.asarray(gt.rig.world_from_camera(fk).wxyz_xyz), atol=1e-12)
        moved = np.asarray((SE3(trial.world_from_mount) @ SE3.exp(trial.camera_offsets)).wxyz_xyz)
        np.testing.assert_allclose(moved, trial.world_from_camera, atol=1e-12)
        shift = np.linalg.norm(trial.world_from_camera[..., 4:] - trial.world_from_mount[..., 4:], axis=-1)
        assert shift.max() > 1e-4 and np.abs(trial.camera_offsets).max() < 0.5
        # The IMU is in the moving camera, not on the rigid mount.
        recorded = read_imu(preset_capture / "trials" / name / "imu.npz")
        moving = simulate_imu(gt.skeleton, gt.rig, trial.motion, trial.fps, trial.clap_frames, seed=5,
                              trial_index=trial_index, world_from_camera=trial.world_from_camera)
        rigid = simulate_imu(gt.skeleton, gt.rig, trial.motion, trial.fps, trial.clap_frames, seed=5,
                             trial_index=trial_index)
        np.testing.assert_allclose(recorded.accel, moving.accel, atol=1e-9)
        assert np.abs(recorded.accel - rigid.accel).max() > 1e-3
    for trial in ("rom", "capture"):
        video = cv2.VideoCapture(str(preset_capture / "trials" / trial / "waist_front.mp4"))
        ok, image = video.read()
        assert ok and image.shape == (36, 64, 3)
        assert not (preset_capture / "trials" / trial / "waist_front.wav").exists()  # AAC inside the MP4


@pytest.mark.slow  # renders a capture
def test_calibration_error_within_the_requested_band(preset_capture):
    gt = load_ground_truth(preset_capture)
    settings = gt.settings
    focal_errors, centre_errors = [], []
    # With lens units (the preset's), the lens a user is given is the design's nominal one, moved by the error.
    assert settings.lens_units
    nominal = nominal_lens(lens_design(64, 36), "fov")
    for c, name in enumerate(gt.rig.names):
        rendered = nominal
        given = json.loads((preset_capture / "intrinsics" / f"{name}.json").read_text())
        fx, fy, cx, cy = given["params"][:4]
        np.testing.assert_allclose(given["params"][4], float(rendered.omega))  # only focal length and centre
        rel = np.array([fx, fy]) / np.asarray(rendered.focal) - 1.0
        assert rel[0] == pytest.approx(rel[1], abs=1e-12)
        focal_errors.append(abs(rel[0]) * 100)
        centre_errors.append(np.hypot(cx - float(rendered.principal_point[0]), cy - float(rendered.principal_point[1])))
        # The cv2.fisheye file is the fit of the lens the user is given, not of the rendered one.
        fitted = read_opencv_fisheye_calibration(preset_capture / "intrinsics" / f"{name}.yml")
        np.testing.assert_allclose(np.asarray(fitted.principal_point), [cx, cy], atol=0.05)
    focal_errors, centre_errors = np.array(focal_errors), np.array(centre_errors)
    lo, hi = 0.3 * settings.focal_error_pct, settings.focal_error_pct
    assert np.all((focal_errors >= lo - 1e-9) & (focal_errors <= hi + 1e-9)) and focal_errors.std() > 0.05
    lo, hi = 0.3 * settings.centre_error_px, settings.centre_error_px
    assert np.all((centre_errors >= lo - 1e-9) & (centre_errors <= hi + 1e-9))
    # The truth keeps the rendered lenses: each camera its own unit of the design.
    units = gt.rig.intrinsics
    assert isinstance(units, TiltedThinPrismFisheyeCamera) and len(np.unique(np.asarray(units.focal)[:, 0])) == gt.rig.num_cameras
    np.testing.assert_allclose(np.asarray(units.focal), np.tile(np.asarray(lens_design(64, 36).focal), (18, 1)), rtol=0.01)


def _frames(path: Path) -> np.ndarray:
    video = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, image = video.read()
        if not ok:
            return np.asarray(frames, np.float64)
        frames.append(image)


@pytest.mark.slow  # renders a capture
def test_low_bitrate_changes_pixels_but_sync_still_works(preset_capture, constant_quality_capture):
    from bcmocap.frontend import read_capture, synchronize

    gt = load_ground_truth(preset_capture)
    assert gt.settings.video_bitrate_mbps == pytest.approx(0.05)
    diffs = []
    for name in gt.rig.names[:6]:
        low = _frames(preset_capture / "trials" / "capture" / f"{name}.mp4")
        high = _frames(constant_quality_capture / "trials" / "capture" / f"{name}.mp4")
        assert low.shape == high.shape
        diffs.append(np.abs(low - high).mean())
    # Same rendered frames (everything else is seeded alike), encoded at 0.05 Mbit/s or at CRF 16.
    assert np.mean(diffs) > 1.5, diffs
    assert (preset_capture / "trials/capture/head.mp4").stat().st_size < (
        constant_quality_capture / "trials/capture/head.mp4").stat().st_size
    capture = read_capture(preset_capture)
    for trial_name, trial in gt.trials.items():
        sync = synchronize(capture, trial_name)
        # the preset starts cameras at sub-frame times and delays their audio: the first clap's video time on each
        # camera's clock plus its audio latency, to a tenth of a frame through AAC
        first_clap = trial.video_frame_of(np.arange(len(sync.cameras)), trial.clap_frames[0])
        latency = trial.audio_latency_s * trial.clock_rate * trial.fps
        np.testing.assert_allclose(sync.frame_offsets, first_clap + latency, atol=0.1)


# ---- motion files ------------------------------------------------------------------------------------


@pytest.mark.slow  # renders a capture
def test_bvh_motion_file_renders(tmp_path):
    bvh = DATA / "cmu" / "131_02_first40.bvh"
    folder = tmp_path / "capture"
    assert main(["simulate", str(folder), *TINY, "--reference-photos", "0", "--motion", str(bvh)]) == 0
    manifest = json.loads((folder / "capture.json").read_text())
    assert manifest["settings"]["motion"] == str(bvh.resolve())
    assert manifest["motion_files"][0]["path"] == str(bvh.resolve()) and len(manifest["motion_files"][0]["sha256"]) == 64
    gt = load_ground_truth(folder)
    skeleton, motion = load_motion_file(bvh, fps=60.0, seconds=0.1, repeat=True)
    np.testing.assert_allclose(gt.trials["capture"].motion.rotations, motion.rotations, atol=1e-12)
    assert sum(t == JointType.HINGE for t in gt.skeleton.joint_types) == 4
    assert gt.rig.num_cameras == 18
    video = cv2.VideoCapture(str(folder / "trials" / "capture" / "head.mp4"))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == gt.trials["capture"].num_video_frames[gt.rig.index("head")]


@pytest.mark.slow  # renders a capture
def test_asf_amc_pair_renders(tmp_path):
    asf, amc = cmu_trial_path("walk")
    folder = tmp_path / "capture"
    assert main(["simulate", str(folder), *TINY, "--reference-photos", "0", "--motion", str(asf), str(amc)]) == 0
    gt = load_ground_truth(folder)
    assert gt.settings.motion == (str(asf.resolve()), str(amc.resolve()))
    # The bundled walk read as a file pair: the same skeleton and rotations, put on the floor.
    skeleton, motion = load_body_motion("walk", fps=60.0, seconds=0.1)
    np.testing.assert_allclose(np.asarray(gt.skeleton.offsets), np.asarray(skeleton.offsets), atol=1e-12)
    np.testing.assert_allclose(gt.trials["capture"].motion.rotations, np.asarray(motion.rotations), atol=1e-12)
    np.testing.assert_allclose(np.asarray(gt.trials["capture"].motion.root_position)[:, :2],
                               np.asarray(motion.root_position)[:, :2], atol=1e-12)
    assert (folder / "trials" / "capture" / "head.mp4").stat().st_size > 0


def test_bone_names_of_other_rigs(tmp_path):
    """A Mixamo-style BVH (namespaced names, a clavicle called LeftShoulder) reduces to the same body."""
    text = (DATA / "cmu" / "131_02_first40.bvh").read_text()
    renames = {"LeftHip": "LeftUpLeg", "RightHip": "RightUpLeg", "LeftKnee": "LeftLeg", "RightKnee": "RightLeg",
               "LeftAnkle": "LeftFoot", "RightAnkle": "RightFoot", "LeftShoulder": "LeftArm",
               "RightShoulder": "RightArm", "LeftCollar": "LeftShoulder", "RightCollar": "RightShoulder",
               "LeftElbow": "LeftForeArm", "RightElbow": "RightForeArm", "Chest2": "Spine2"}
    lines = []
    for line in text.split("\n"):
        words = line.split()
        if len(words) == 2 and words[0] in ("ROOT", "JOINT") and words[1] in renames | {"Hips": ""}:
            line = line.replace(words[1], f"mixamorig:{renames.get(words[1], words[1])}")
        lines.append(line)
    mixamo = tmp_path / "mixamo.bvh"
    mixamo.write_text("\n".join(lines))
    a_skeleton, a = load_motion_file(DATA / "cmu" / "131_02_first40.bvh")
    b_skeleton, b = load_motion_file(mixamo)
    np.testing.assert_allclose(np.asarray(b.rotations), np.asarray(a.rotations), atol=1e-12)
    np.testing.assert_allclose(np.asarray(b_skeleton.offsets), np.asarray(a_skeleton.offsets), atol=1e-12)


def test_motion_file_errors(tmp_path, capsys):
    with pytest.raises(ValueError, match="missing"):
        load_motion_file(tmp_path / "nothing.bvh")
    flat = tmp_path / "no_arms.bvh"
    text = (DATA / "cmu" / "131_02_first40.bvh").read_text()
    flat.write_text(text.replace("JOINT LeftElbow", "JOINT LeftBend"))
    with pytest.raises(ValueError, match=r"no_arms.bvh: no bone for the body's 'lradius'"):
        load_motion_file(flat)
    folder = tmp_path / "capture"
    assert main(["simulate", str(folder), *TINY, "--motion", str(tmp_path / "gone.bvh")]) == 2
    one_line_error(capsys, "simulate", "gone.bvh", "missing")
    assert not folder.exists()


# ---- the command line ---------------------------------------------------------------------------------


@pytest.mark.parametrize("args, culprit", [
    (["--motion-blur", "--exposure-ms", "50"], "--exposure-ms"),
    (["--rolling-shutter", "--readout-ms", "-1"], "--readout-ms"),
    (["--mount-wobble-mm", "-1"], "--mount-wobble-mm"),
    (["--mount-wobble-deg", "nan"], "--mount-wobble-deg"),
    (["--vignetting", "1.5"], "--vignetting"),
    (["--video-bitrate-mbps", "5"], "--video-bitrate-mbps"),
    (["--focal-error-pct", "inf"], "--focal-error-pct"),
    (["--centre-error-px", "-3"], "--centre-error-px"),
    (["--blur-samples", "0"], "--blur-samples"),
    (["--full-scale-electrons", "-10"], "--full-scale-electrons"),
    (["--read-noise-dn", "nan"], "--read-noise-dn"),
    (["--motion", "dance.txt"], "--motion"),
    (["--motion", "subject.asf"], "--motion"),
    (["--preset", "realistic", "--width", "65"], "even width"),
    (["--motion-fps", "-5"], "--motion-fps"),
])
def test_each_bad_option_is_one_line_naming_it(tmp_path, capsys, args, culprit):
    folder = tmp_path / "capture"
    assert main(["simulate", str(folder), *TINY, *args]) == 2
    one_line_error(capsys, "simulate", culprit)
    assert not folder.exists()


def test_settings_without_new_fields_still_load():
    """A capture.json written before the degradations existed reads back as the clean studio."""
    old_keys = ("motion", "seconds", "rom_seconds", "seed", "fps", "width", "height", "lens", "reference_photos",
                "reference_width", "reference_height", "reference_fov_deg", "motion_blur", "rolling_shutter",
                "audio_rate", "markers_per_segment")
    old = {k: v for k, v in StudioSettings().to_dict().items() if k in old_keys}
    assert len(old) == len(old_keys) < len(dataclasses.fields(StudioSettings))
    assert StudioSettings.from_dict(old) == StudioSettings()


def test_motion_before_the_folder(tmp_path, capsys):
    # "--motion run DIR": the folder is not taken for a second motion file (stopped by a bad option before rendering).
    folder = tmp_path / "capture"
    assert main(["simulate", "--motion", "run", str(folder), *TINY[:-1], "--vignetting", "2"]) == 2
    one_line_error(capsys, "simulate", "--vignetting")
    assert main(["simulate", "--motion", "run"]) == 2
    one_line_error(capsys, "simulate", "CAPTURE_DIR is required")
