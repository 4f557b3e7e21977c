"""Tests for the synthetic capture studio (bcmocap.sim.studio, ``bcmocap simulate``).

One tiny capture (64x36 px, 6 frames per trial, 2 reference photos) is written once through the command
line and shared by every test; the resume test re-renders parts of a copy of it.
"""

import dataclasses
import filecmp
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import one_line_error

from bcmocap.cameras import FOVCamera, camera_at
from bcmocap.cli import main
from bcmocap.geometry import SE3, matrix_from_quat
from bcmocap.io import read_bvh
from bcmocap.io.capture_folder import read_passerby_truth
from bcmocap.io.opencv_calibration import read_opencv_fisheye_calibration
from bcmocap.io.wav import read_wav
from bcmocap.kinematics import forward_kinematics
from bcmocap.sim.audio import clap_onsets
from bcmocap.sim.render import Renderer
from bcmocap.sim.studio import StudioSettings, capsule_ends, load_ground_truth, write_capture

pytestmark = pytest.mark.slow  # rendering capture folders


ARGS = ["--seconds", "0.1", "--rom-seconds", "0.1", "--width", "64", "--height", "36", "--reference-photos", "2",
        "--reference-size", "64x48", "--seed", "3", "--no-progress"]
SETTINGS = StudioSettings(seconds=0.1, rom_seconds=0.1, width=64, height=36, reference_photos=2, reference_width=64,
                          reference_height=48, seed=3)


OLD_SETTINGS = ("motion", "seconds", "rom_seconds", "seed", "fps", "width", "height", "lens", "reference_photos",
                "reference_width", "reference_height", "reference_fov_deg", "motion_blur", "rolling_shutter",
                "audio_rate", "markers_per_segment")  # a capture.json of the first studio (before "container")


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("studio") / "capture"
    assert main(["simulate", str(folder), *ARGS]) == 0
    return folder


def all_files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def test_folder_layout_and_ground_truth_round_trip(capture):
    manifest = json.loads((capture / "capture.json").read_text())
    assert manifest["complete"] and manifest["settings"] == SETTINGS.to_dict()
    gt = load_ground_truth(capture)
    assert gt.settings == SETTINGS and gt.rig.num_cameras == 18 and set(gt.trials) == {"rom", "capture"}
    rig_json = json.loads((capture / "rig.json").read_text())
    assert [c["segment"] for c in rig_json["cameras"]] == [gt.skeleton.names[s] for s in gt.rig.segments]
    files = set(all_files(capture))
    for name in gt.rig.names:
        for trial in ("rom", "capture"):
            assert {f"trials/{trial}/{name}.mp4", f"trials/{trial}/{name}.wav"} <= files
        # The exact lens and its cv2.fisheye calibration file agree to a fraction of a pixel.
        lens = json.loads((capture / "intrinsics" / f"{name}.json").read_text())
        assert lens["model"] == "FOV" and lens["opencv_fisheye_fit_max_error_px"] < 0.3
        exact = camera_at(gt.rig.intrinsics, gt.rig.index(name))
        assert isinstance(exact, FOVCamera)
        fitted = read_opencv_fisheye_calibration(capture / "intrinsics" / f"{name}.yml")
        uv = np.array([[5.0, 4.0], [32.0, 18.0], [60.0, 30.0]])
        back, _ = fitted.project(np.asarray(exact.unproject(uv)))
        np.testing.assert_allclose(np.asarray(back), uv, atol=0.3)
    assert not any(".partial" in f for f in files)
    for i in range(2):
        photo = cv2.imread(str(capture / "reference" / gt.reference_names[i]))
        assert photo.shape == (48, 64, 3)
    assert gt.reference_poses.shape == (2, 7) and gt.reference_camera.width == 64
    assert gt.world_points.shape[1] == 3 and len(gt.world_points) > 300
    assert not gt.scene.inside_clutter(gt.world_points).any()

    for name, trial in gt.trials.items():
        frames = trial.motion.num_frames
        assert frames == 6
        fk = forward_kinematics(gt.skeleton, trial.motion)
        np.testing.assert_allclose(trial.joint_positions, np.asarray(fk.translation()), atol=1e-12)
        np.testing.assert_allclose(trial.world_from_camera, np.asarray(gt.rig.world_from_camera(fk).wxyz_xyz), atol=1e-12)
        # Markers: offsets on their segments, 1 mm noise, NaN in gaps.
        markers = trial.markers
        assert markers.positions.shape == (frames, len(markers.names), 3) and len(markers.names) >= 3 * 15
        truth = np.asarray(SE3(np.asarray(fk.wxyz_xyz)[:, markers.segments]) @ markers.offsets[None])
        seen = ~np.isnan(markers.positions[..., 0])
        assert 0.5 < seen.mean() <= 1.0
        assert np.abs(markers.positions[seen] - truth[seen]).max() < 0.006
        bvh = read_bvh(capture / "ground_truth" / f"{name}.bvh")
        assert bvh.motion.num_frames == frames
        # Videos: one frame per video frame of the timeline, at the body cameras' size.
        for c in (0, 17):
            video = cv2.VideoCapture(str(capture / "trials" / name / f"{gt.rig.names[c]}.mp4"))
            assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == trial.num_video_frames[c]
            ok, image = video.read()
            assert ok and image.shape == (36, 64, 3)
        assert len(set(trial.video_start_frame.tolist())) > 3  # random start per camera


def test_claps_in_each_track_at_the_written_samples(capture):
    gt = load_ground_truth(capture)
    for name, trial in gt.trials.items():
        per_frame = trial.audio_rate / trial.fps
        for c, camera in enumerate(gt.rig.names):
            samples, rate = read_wav(capture / "trials" / name / f"{camera}.wav")
            assert rate == trial.audio_rate == 48000
            assert len(samples) == round(trial.num_video_frames[c] * per_frame)
            np.testing.assert_array_equal(clap_onsets(samples, rate), trial.clap_samples[c])
            np.testing.assert_array_equal(trial.clap_samples[c],
                                          np.round((trial.clap_frames + trial.video_start_frame[c]) * per_frame))
        # Synchronising by the first clap gives each camera's start offset in whole frames.
        offsets = (trial.clap_samples[:, 0] - trial.clap_samples[0, 0]) / per_frame
        np.testing.assert_array_equal(offsets, trial.video_start_frame - trial.video_start_frame[0])


def test_resume_renders_missing_parts_byte_for_byte(capture, tmp_path):
    """Deleted videos, tracks and photos come back identical to the first run; complete ones are skipped."""
    copy = tmp_path / "copy"
    shutil.copytree(capture, copy)
    missing = ["trials/capture/head.mp4", "trials/rom/left_foot.wav", "reference/photo_001.jpg"]
    for rel in missing:
        (copy / rel).unlink()
    (copy / "trials/capture/.head.partial.mp4").write_bytes(b"left by an interrupted run")
    manifest = json.loads((copy / "capture.json").read_text())
    # Written before the degradations of issue 20 existed: the settings lack them, and mean their defaults.
    old_settings = {k: v for k, v in manifest["settings"].items() if k in OLD_SETTINGS}
    (copy / "capture.json").write_text(json.dumps({**manifest, "settings": old_settings, "complete": False}))
    kept = copy / "trials/capture/chest.mp4"
    stamp = kept.stat().st_mtime_ns
    write_capture(copy, SETTINGS, progress=False)
    assert kept.stat().st_mtime_ns == stamp  # a complete camera is not rendered again
    assert all_files(copy) == all_files(capture)
    match, mismatch, errors = filecmp.cmpfiles(capture, copy, all_files(capture), shallow=False)
    assert not mismatch and not errors


def test_refuses_folders_it_must_not_write(capture, tmp_path):
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    assert main(["simulate", str(foreign), *ARGS]) == 2
    assert all_files(foreign) == ["notes.txt"] and (foreign / "notes.txt").read_text() == "keep me"
    before = (capture / "capture.json").read_bytes()
    assert main(["simulate", str(capture), *ARGS[:-3], "--seed", "4", "--no-progress"]) == 2  # other settings
    assert (capture / "capture.json").read_bytes() == before
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(FileExistsError, match="not a folder"):
        write_capture(a_file, SETTINGS, progress=False)
    with pytest.raises(ValueError, match="lens"):
        StudioSettings(lens="pinhole")
    with pytest.raises(ValueError, match="StudioSettings.room must be one of"):
        StudioSettings(room="cave")
    from bcmocap.sim import studio, studio_command

    assert studio_command.ROOMS == studio.ROOMS  # the command line lists them without importing JAX
    assert studio_command.ROM_PROTOCOLS == studio.ROM_PROTOCOLS
    with pytest.raises(ValueError, match="missing"):
        load_ground_truth(foreign)


def test_rom_tempo_slows_the_same_sweeps():
    """Half the tempo in twice the time: the same sweeps at half the angular speed."""
    from bcmocap.sim.motions import load_body_motion
    from bcmocap.sim.studio import studio_range_of_motion

    skeleton, walk = load_body_motion("walk", fps=60.0, seconds=0.1)
    speeds = []
    for seconds, tempo in ((3.0, 1.0), (6.0, 0.5)):
        rot = np.asarray(studio_range_of_motion(skeleton, walk, seconds, 60.0, np.random.default_rng(5), tempo).rotations)
        step = 2 * np.arccos(np.clip(np.abs(np.sum(rot[1:] * rot[:-1], axis=-1)), 0, 1))  # (T - 1, J) rad per frame
        speeds.append((step.max(axis=0)[1:], step.sum(axis=0)[1:]))
    assert 0.4 < np.median(speeds[1][0] / speeds[0][0]) < 0.6  # peak speed per joint about halves
    assert 0.8 < np.median(speeds[1][1] / speeds[0][1]) < 1.3  # the path swept stays about the same


def test_rom_protocol_feet_after_turns_the_ankles_on_still_legs():
    """feet_after: the ankles stay at rest while the other joints swing, then turn while every other joint rests;
    together: the ankles turn while the legs swing. Both start with the rest hold."""
    from bcmocap.sim.motions import load_body_motion
    from bcmocap.sim.studio import rom_rest_frames, studio_range_of_motion

    skeleton, walk = load_body_motion("walk", fps=60.0, seconds=0.1)
    feet = np.array([name.endswith("_foot") for name in skeleton.names])
    others = ~feet
    others[0] = False  # the root turns throughout
    angles = {}
    for protocol in ("together", "feet_after"):
        rot = np.asarray(studio_range_of_motion(skeleton, walk, 6.0, 60.0, np.random.default_rng(5), 0.5,
                                                protocol).rotations)
        angles[protocol] = np.degrees(2 * np.arccos(np.clip(np.abs(rot[..., 0]), 0, 1)))  # (T, J) from rest
        assert np.all(angles[protocol][rom_rest_frames(len(rot), 60.0)] < 1e-6)
    together, after = angles["together"], angles["feet_after"]
    feet_moving = after[:, feet].max(axis=1) > 1.0
    others_moving = after[:, others].max(axis=1) > 1.0
    assert feet_moving.sum() > 100 and others_moving.sum() > 100  # each for more than 1.7 s of the 6
    assert not np.any(feet_moving & others_moving)
    assert after[:, feet].max() > 20.0  # the ankles' full range, as when every joint moves at once
    assert np.sum((together[:, feet].max(axis=1) > 1.0) & (together[:, others].max(axis=1) > 1.0)) > 100
    with pytest.raises(ValueError, match="StudioSettings.rom_protocol must be one of"):
        StudioSettings(rom_protocol="ankles")


@pytest.mark.parametrize("flag, value", [("--seconds", "inf"), ("--fps", "inf"), ("--seconds", "nan"),
                                         ("--rom-seconds", "1e9"), ("--fps", "1e6"), ("--rom-tempo", "nan"),
                                         ("--rom-tempo", "5")])
def test_refuses_non_finite_or_huge_lengths_and_rates(tmp_path, capsys, flag, value):
    folder = tmp_path / "capture"
    assert main(["simulate", str(folder), *ARGS, flag, value]) == 2
    one_line_error(capsys, "simulate", f"{flag} must be in (0, ")
    assert not folder.exists()
    field = flag[2:].replace("-", "_")
    with pytest.raises(ValueError, match=f"StudioSettings.{field} must be in"):
        StudioSettings(**{field: float(value)})


def test_board_videos_are_added_per_rendered_lens(capture, tmp_path, capsys):
    from bcmocap.sim.board_video import STUDIO_BOARD, write_board_videos

    copy = tmp_path / "capture"
    shutil.copytree(capture, copy)
    lenses = write_board_videos(copy, views=2, frames_per_view=2)
    gt = load_ground_truth(copy)
    assert sorted(c for cams in lenses.values() for c in cams) == sorted(gt.rig.names)
    record = json.loads((copy / "calibration" / "lenses.json").read_text())
    assert record["board"] == STUDIO_BOARD and record["lenses"] == lenses
    video = cv2.VideoCapture(str(copy / "calibration" / "lens_0.mp4"))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 4 and video.read()[1].shape[:2] == (36, 64)
    video.release()
    assert main(["simulate", str(tmp_path / "nothing"), "--board-videos"]) == 2
    assert "capture.json" in capsys.readouterr().err


def _video_frames(path: Path) -> np.ndarray:
    video = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, image = video.read()
        if not ok:
            video.release()
            return np.array(frames, int)
        frames.append(image[..., ::-1])


def test_passerby_room_shows_a_second_person_in_the_videos_only(capture, tmp_path):
    """The shared capture's settings in the room "passerby": the same static room and photos, the passer-by's truth
    written, and each video differs from the textured room's exactly where the passer-by is seen."""
    folder = tmp_path / "passerby"
    assert main(["simulate", str(folder), *ARGS, "--room", "passerby"]) == 0
    gt = load_ground_truth(folder)
    assert gt.settings == dataclasses.replace(SETTINGS, room="passerby")
    for rel in ("ground_truth/scene.json", "ground_truth/world_points.npz", "reference/photo_000.jpg",
                "reference/photo_001.jpg", "ground_truth/capture.npz"):
        assert filecmp.cmp(capture / rel, folder / rel, shallow=False), rel  # photos of the empty room
    assert read_passerby_truth(capture, "capture") is None
    trial = gt.trials["capture"]
    walker = read_passerby_truth(folder, "capture")
    assert walker.motion == "run" and walker.present.all() and read_passerby_truth(folder, "rom").present.any()
    k = len(walker.radii)
    assert walker.capsules.shape == (6, k, 2, 3) and walker.joint_positions.shape == (6, len(walker.segment_names), 3)
    assert np.isfinite(walker.capsules).all() and walker.colors.shape == (k, 3)
    ends, radii, _ = capsule_ends(gt.skeleton, trial.motion)
    both, both_radii = np.concatenate([ends, walker.capsules], axis=1), np.concatenate([radii, walker.radii])
    seen = {}
    for c, name in enumerate(gt.rig.names):
        renderer = Renderer(gt.scene, camera_at(gt.rig.intrinsics, c))
        mine = _video_frames(folder / "trials" / "capture" / f"{name}.mp4")
        textured = _video_frames(capture / "trials" / "capture" / f"{name}.mp4")
        for t in range(6):
            rotation = np.asarray(matrix_from_quat(trial.world_from_camera[t, c, :4]))
            origin = trial.world_from_camera[t, c, 4:]
            _, with_walker = renderer.depth(rotation, origin, both[t], both_radii)
            _, subject_only = renderer.depth(rotation, origin, ends[t], radii)
            walker_pixels = with_walker & ~subject_only  # where the passer-by is in front of everything else
            diff = np.abs(mine - textured)[trial.video_start_frame[c] + t].mean(axis=-1)
            seen[name, t] = int(walker_pixels.sum())
            if walker_pixels.sum() >= 8:
                assert diff[walker_pixels].mean() > 15 and diff[~walker_pixels].mean() < 3, (name, t)
            elif not walker_pixels.any():
                assert diff.mean() < 0.5, (name, t)
    assert all(seen[name, t] > 30 for name in ("head", "chest", "waist_front") for t in range(6))  # ahead of them
    assert all(seen["back", t] == 0 for t in range(6))  # and not behind
