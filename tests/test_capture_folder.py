"""Tests for the capture folder format's one owner (bcmocap.io.capture_folder): the manifest, the paths of the
layout, the subject record and the ground-truth reader (on a tiny hand-written folder; the studio's own folders
are read back in test_studio)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import random_motion

from bcmocap.cameras import PinholeCamera
from bcmocap.io import capture_folder as cf
from bcmocap.io.model_json import camera_to_dict, rig_to_dict, skeleton_to_dict

SUBJECT = cf.subject_record([("pelvis", None, "free"), ("torso", "pelvis", "ball")],
                            [{"from": "pelvis", "to": "torso", "metres": 0.4}],
                            {"trial": "rom", "after_first_clap_s": (0.0, 0.5)})


def write_raw_manifest(folder: Path, **changes) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    manifest = {**cf.new_manifest(fps=30.0, audio_rate=8000, cameras=["head"], trials=["rom", "capture"],
                                  subject=SUBJECT, complete=True), **changes}
    manifest = {k: v for k, v in manifest.items() if v is not ...}  # ... removes a field
    cf.manifest_path(folder).write_text(json.dumps(manifest))
    return folder


def test_manifest_round_trip(tmp_path):
    manifest = cf.new_manifest(settings={"fps": 60.0, "audio_rate": 48000, "seed": 3}, cameras=["head", "chest"],
                               trials=list(cf.TRIALS), subject=SUBJECT, complete=False)
    assert list(manifest)[:2] == ["format", "version"] and manifest["format"] == cf.CAPTURE_FORMAT
    path = cf.write_manifest(tmp_path, manifest)
    assert path == tmp_path / "capture.json" == cf.manifest_path(tmp_path)
    assert path.read_text() == json.dumps(manifest, indent=1) + "\n"  # the bytes the writers have always written
    back = cf.read_manifest(tmp_path)
    assert back.data == json.loads(json.dumps(manifest)) and back.path == path and back.folder == tmp_path
    assert back.version == cf.CAPTURE_VERSION and back.trials == ("rom", "capture") and back.complete is False
    assert back.fps == 60.0 and back.audio_rate == 48000 and back.settings["seed"] == 3  # from the settings
    with pytest.raises(ValueError, match=r"capture\.json: the capture is marked incomplete"):
        cf.read_manifest(tmp_path, require_complete=True)
    top = cf.read_manifest(write_raw_manifest(tmp_path / "init"), require_complete=True, require_fps=True)
    assert top.fps == 30.0 and top.audio_rate == 8000 and top.settings == {} and top.data["subject"] == SUBJECT
    with pytest.raises(ValueError, match="not a 'bcmocap-capture' manifest"):
        cf.write_manifest(tmp_path, {"trials": ["rom"]})


BAD_MANIFESTS = {
    "format": ({"format": "other"}, r"capture\.json: format is 'other', expected 'bcmocap-capture'"),
    "version": ({"version": "1"}, r"capture\.json: field 'version' must be a whole number"),
    "complete": ({"complete": "yes"}, r"capture\.json: field 'complete' must be true or false"),
    "settings": ({"settings": [1]}, r"capture\.json: field 'settings' must be an object"),
    "fps": ({"fps": -1}, r"capture\.json: missing or invalid frame rate \(field 'fps' or 'settings\.fps'\), got -1"),
    "fps missing": ({"fps": ...}, r"capture\.json: missing or invalid frame rate .*got None"),
    "audio_rate": ({"audio_rate": 44100.5}, r"capture\.json: field 'audio_rate' must be a whole number"),
    "trials": ({"trials": "rom"}, r"capture\.json: field 'trials' must be a non-empty list of names"),
    "trial name": ({"trials": ["rom", "../x"]}, r"capture\.json: trials\[1\] '\.\./x' is not a plain name"),
    "trial twice": ({"trials": ["rom", "rom"]}, r"capture\.json: field 'trials' names a trial twice"),
}


@pytest.mark.parametrize("case", sorted(BAD_MANIFESTS))
def test_a_bad_manifest_gives_one_line_naming_the_file_and_field(tmp_path, case):
    changes, message = BAD_MANIFESTS[case]
    folder = write_raw_manifest(tmp_path / "capture", **changes)
    with pytest.raises(ValueError, match=message) as error:
        cf.read_manifest(folder, require_fps=True)
    assert "\n" not in str(error.value) and str(error.value).startswith(str(folder / "capture.json"))


def test_an_unreadable_manifest_names_the_file(tmp_path):
    with pytest.raises(ValueError, match=r"nowhere/capture\.json: missing \(the capture folder .* does not exist\)"):
        cf.read_manifest(tmp_path / "nowhere")
    with pytest.raises(ValueError, match=r"capture\.json: missing"):
        cf.read_manifest(tmp_path)
    cf.manifest_path(tmp_path).write_text("{not json")
    with pytest.raises(ValueError, match=r"capture\.json: not valid JSON"):
        cf.read_manifest(tmp_path)
    cf.manifest_path(tmp_path).write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"capture\.json: expected a JSON object, got list"):
        cf.read_manifest(tmp_path)


def layout_paths(folder, trial="rom", camera="head"):
    return [cf.manifest_path(folder), cf.rig_path(folder), cf.intrinsics_path(folder, camera),
            cf.lens_path(folder, camera), cf.intrinsics_path(folder, camera, ".xml"), cf.reference_photo_path(folder, 7),
            cf.reference_photo_path(folder, "IMG_0001.JPG"), cf.reference_camera_path(folder),
            cf.reference_camera_path(folder, ".yml"), cf.trial_video_path(folder, trial, camera),
            cf.trial_video_path(folder, trial, camera, ".MOV"), cf.trial_audio_path(folder, trial, camera),
            cf.shared_video_path(folder, camera, ".mp4"), cf.imu_path(folder, trial), cf.contacts_path(folder, trial),
            cf.truth_skeleton_path(folder), cf.truth_rig_path(folder), cf.truth_scene_path(folder),
            cf.world_points_path(folder), cf.reference_truth_path(folder), cf.trial_truth_path(folder, trial),
            cf.trial_truth_path(folder, trial, ".bvh")]


def test_the_layout_s_paths(tmp_path):
    names = [cf.relative_name(tmp_path, p) for p in layout_paths(tmp_path)]
    assert names == ["capture.json", "rig.json", "intrinsics/head.yml", "intrinsics/head.json", "intrinsics/head.xml",
                     "reference/photo_007.jpg", "reference/IMG_0001.JPG", "reference/camera.json",
                     "reference/camera.yml", "trials/rom/head.mp4", "trials/rom/head.MOV", "trials/rom/head.wav",
                     "videos/head.mp4", "trials/rom/imu.npz", "trials/rom/contacts.npz", "ground_truth/skeleton.json",
                     "ground_truth/rig.json", "ground_truth/scene.json", "ground_truth/world_points.npz",
                     "ground_truth/reference.npz", "ground_truth/rom.npz", "ground_truth/rom.bvh"]


@pytest.mark.parametrize("name", ["..", ".", "../victim", "/tmp/victim", "a/b", "a\\b", "a\x00b", "", ".hidden",
                                  "x" * 200, 5, None])
def test_paths_stay_inside_the_folder(tmp_path, name):
    for make in (lambda: cf.trial_dir(tmp_path, name), lambda: cf.trial_video_path(tmp_path, "rom", name),
                 lambda: cf.trial_video_path(tmp_path, name, "head"), lambda: cf.trial_audio_path(tmp_path, name, "x"),
                 lambda: cf.intrinsics_path(tmp_path, name), lambda: cf.lens_path(tmp_path, name),
                 lambda: cf.shared_video_path(tmp_path, name), lambda: cf.imu_path(tmp_path, name),
                 lambda: cf.contacts_path(tmp_path, name), lambda: cf.trial_truth_path(tmp_path, name),
                 *([] if isinstance(name, int) else [lambda: cf.reference_photo_path(tmp_path, name)])):  # 5: photo_005
        with pytest.raises(ValueError, match="is not a plain name|must be a string") as error:
            make()
        assert str(error.value).startswith(str(tmp_path)) and "\n" not in str(error.value).replace(repr(name), "")
    for suffix in ("/../x", ".a/b", "x", ".toolongsuffix"):
        with pytest.raises(ValueError, match="file extension"):
            cf.trial_video_path(tmp_path, "rom", "head", suffix)
    for path in layout_paths(tmp_path, "rom", "head"):
        assert path.resolve().is_relative_to(tmp_path.resolve())


def test_subject_record_from_plain_values():
    assert SUBJECT == {"topology": [["pelvis", None, "free"], ["torso", "pelvis", "ball"]],
                       "measurements": [{"from": "pelvis", "to": "torso", "metres": 0.4}],
                       "rest": {"trial": "rom", "after_first_clap_s": [0.0, 0.5]}}
    assert cf.subject_record([]) == {"topology": [], "measurements": []}  # no rest pose known: no "rest"
    with pytest.raises(ValueError, match=r"topology\[0\] must be \(name, parent, joint\)"):
        cf.subject_record([("pelvis", "free")])


def test_importing_the_format_does_not_import_jax():
    code = "import sys, bcmocap.io.capture_folder, bcmocap.frontend.rig_file; assert 'jax' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def write_ground_truth(folder: Path, skeleton, rig, motion) -> None:
    """The studio's ground-truth files of one trial, by hand; the trial's npz is written before mount wobble."""
    write_raw_manifest(folder, trials=["capture"], fps=..., settings={"fps": 30.0, "seed": 4})
    cf.write_json(cf.truth_skeleton_path(folder), skeleton_to_dict(skeleton))
    cf.write_json(cf.truth_rig_path(folder), rig_to_dict(rig, skeleton))
    cf.write_json(cf.truth_scene_path(folder), {"surfaces": []})
    np.savez(cf.world_points_path(folder), points=np.ones((5, 3)), materials=np.zeros(5, np.int64))
    np.savez(cf.reference_truth_path(folder), names=np.array(["photo_000.jpg"]), world_from_camera=np.ones((1, 7)))
    camera = PinholeCamera(width=64, height=48, focal=[50.0, 50.0], principal_point=[31.5, 23.5])
    cf.write_json(cf.reference_camera_path(folder), camera_to_dict(camera))
    frames, cameras = motion.num_frames, rig.num_cameras
    np.savez(cf.trial_truth_path(folder, "capture"), root_position=np.asarray(motion.root_position),
             rotations=np.asarray(motion.rotations), joint_positions=np.zeros((frames, skeleton.num_segments, 3)),
             world_rotations=np.zeros((frames, skeleton.num_segments, 4)),
             world_from_camera=np.full((frames, cameras, 7), 2.0), video_start_frame=np.arange(cameras),
             num_video_frames=np.full(cameras, frames + 9), clap_frames=np.array([-2, frames + 1]),
             clap_samples=np.zeros((cameras, 2), np.int64), audio_gain=np.ones(cameras), fps=np.float64(30.0),
             audio_rate=np.int64(8000), marker_names=np.array(["a", "b"]), marker_segments=np.array([0, 1]),
             marker_offsets=np.zeros((2, 3)), markers=np.full((frames, 2, 3), np.nan))


def test_ground_truth_read_back(tmp_path, skeleton, rig, rng):
    folder = tmp_path / "capture"
    motion = random_motion(skeleton, 5, rng)
    write_ground_truth(folder, skeleton, rig, motion)
    gt = cf.load_ground_truth(folder)
    assert gt.path == folder and gt.settings == {"fps": 30.0, "seed": 4} and gt.scene == {"surfaces": []}
    assert gt.skeleton.names == skeleton.names and gt.rig.names == rig.names
    assert gt.reference_names == ("photo_000.jpg",) and gt.reference_camera.width == 64
    assert gt.world_points.shape == (5, 3) and gt.world_point_materials.shape == (5,)
    trial = gt.trials["capture"]
    assert list(gt.trials) == ["capture"] and trial.name == "capture" and trial.fps == 30.0
    np.testing.assert_array_equal(trial.motion.rotations, np.asarray(motion.rotations))
    assert trial.markers.names == ("a", "b") and np.isnan(trial.markers.positions).all()
    # written before mount wobble: rigid mounts
    np.testing.assert_array_equal(trial.world_from_mount, trial.world_from_camera)
    assert trial.camera_offsets.shape == (5, rig.num_cameras, 6) and not trial.camera_offsets.any()
    # the sim's reader turns the settings and the scene into its own types through the hooks
    parsed = cf.load_ground_truth(folder, parse_settings=lambda d, where: ("settings", where, d["seed"]),
                                  parse_scene=lambda d, where: ("scene", Path(where).name))
    assert parsed.settings == ("settings", str(folder / "capture.json"), 4) and parsed.scene == ("scene", "scene.json")
    manifest, skeleton_back, rig_back = cf.read_truth_model(folder)
    assert manifest.trials == ("capture",) and skeleton_back.names == skeleton.names and rig_back.names == rig.names


def test_a_broken_ground_truth_names_the_file(tmp_path, skeleton, rig, rng):
    folder = tmp_path / "capture"
    write_ground_truth(folder, skeleton, rig, random_motion(skeleton, 3, rng))
    data = dict(np.load(cf.trial_truth_path(folder, "capture")))
    del data["clap_frames"]
    np.savez(cf.trial_truth_path(folder, "capture"), **data)
    with pytest.raises(ValueError, match=r"ground_truth/capture\.npz: missing array 'clap_frames'"):
        cf.load_ground_truth(folder)
    cf.trial_truth_path(folder, "capture").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"ground_truth/capture\.npz: not a readable \.npz file"):
        cf.load_ground_truth(folder)
    np.savez(cf.world_points_path(folder), points=np.ones((5, 3)))
    with pytest.raises(ValueError, match=r"ground_truth/world_points\.npz: missing array 'materials'"):
        cf.load_ground_truth(folder)
    cf.truth_rig_path(folder).unlink()
    with pytest.raises(ValueError, match=r"ground_truth/rig\.json: missing"):
        cf.load_ground_truth(folder)


def test_file_stamps_see_a_file_added_removed_or_rewritten_and_skip_hidden_ones(tmp_path):
    import os

    from bcmocap.io.capture_folder import changed_files, file_stamps

    (tmp_path / "trials" / "capture").mkdir(parents=True)
    (tmp_path / "trials" / "capture" / "cam.mp4").write_bytes(b"x" * 10)
    (tmp_path / "rig.json").write_text("{}")
    (tmp_path / ".partial.mp4").write_bytes(b"being written")
    os.symlink(tmp_path / "trials", tmp_path / "linked")  # a symlinked folder is not walked into
    before = file_stamps(tmp_path)
    assert sorted(before) == ["rig.json", "trials/capture/cam.mp4"]
    assert changed_files(before, file_stamps(tmp_path)) == []
    (tmp_path / "trials" / "capture" / "cam.mp4").write_bytes(b"x" * 12)
    (tmp_path / "rig.json").unlink()
    (tmp_path / "imu.npz").write_bytes(b"")
    assert changed_files(before, file_stamps(tmp_path)) == [
        "imu.npz (added)", "rig.json (removed)", "trials/capture/cam.mp4 (modified, 10 → 12 bytes)"]
    assert file_stamps(tmp_path / "missing") == {}


def test_a_rerun_redoes_from_the_stage_that_reads_what_changed():
    """bcmocap run after a capture changed between runs: recordings, lens files and files of unknown kinds redo every
    stage without the frontend's caches; the rig or manifest every stage with them; data files under trials/ the
    stages after the frontend, or every stage (caches kept) where the frontend reads the gyros; notes nothing."""
    from bcmocap.pipeline.run import stage_to_redo

    assert stage_to_redo([]) == (None, False, "")
    assert stage_to_redo(["notes.MD (added)"]) == (None, False, "")
    stage, drop, why = stage_to_redo(["trials/capture/imu.npz (added)", "trials/capture/root_height.txt (modified)"])
    assert (stage, drop) == ("world", False) and "trials/capture/imu.npz (added)" in why
    assert stage_to_redo(["trials/capture/imu.npz (added)"], frontend_reads_gyros=True)[:2] == ("frontend", False)
    stage, drop, why = stage_to_redo(["rig.json (modified, 10 → 12 bytes)", "trials/capture/imu.npz (added)"])
    assert (stage, drop) == ("frontend", False) and why.startswith("the capture's rig or manifest changed")
    for change in ("trials/capture/cam (1).MP4 (modified, 1 → 2 bytes)", "reference/a.jpg (removed)",
                   "intrinsics/cam.yml (modified)", "trials/capture/cam.insv (added)", "imu.npz (added)"):
        stage, drop, why = stage_to_redo([change, "rig.json (modified)"])
        assert (stage, drop) == ("frontend", True), change
        assert why == f"the capture's recordings or lens files changed since the last run ({change}): redoing every " \
                      "stage, the frontend's caches included"
