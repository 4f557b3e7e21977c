"""bcmocap view without a browser: posing, edits and their checks, the overlay, the run folder reader, saving
an edited model as a new version, the app driven through viser's Python API, the folders of bcmocap markers
and bcmocap kcs, and the command's errors."""

import argparse
import json
import os
import socket
import threading
import time

import numpy as np
import pytest

from bcmocap.geometry import matrix_from_quat, quat_exp, quat_multiply
from bcmocap.viewer import CameraFrame, EditableModel, GroundTruth, Posing
from conftest import make_rig, make_skeleton, random_motion
from viewer_run import make_run_folder


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A small run folder and its truth: ``(folder, (skeleton, rig, motion, true_joints))``."""
    folder = tmp_path_factory.mktemp("viewer") / "run"
    return folder, make_run_folder(folder)


def _fresh_run(run, tmp_path):
    import shutil

    folder = tmp_path / "run"
    shutil.copytree(run[0], folder)
    return folder


# ---- posing ---------------------------------------------------------------------------------------
def test_posing_matches_forward_kinematics_and_camera_poses(run):
    from bcmocap.kinematics.fk import joint_positions
    from bcmocap.kinematics.rig import camera_poses
    from bcmocap.pipeline.run import load_model, load_motion

    skeleton, rig = load_model(run[0])
    motion = load_motion(run[0] / "solve" / "motion.npz")[:7]
    posing = Posing(skeleton.parents, motion.root_position, motion.rotations)
    joints = posing.joint_positions(np.asarray(skeleton.offsets))
    np.testing.assert_allclose(joints, np.asarray(joint_positions(skeleton, motion)), atol=1e-12)
    poses = posing.camera_poses(joints, rig.segments, rig.segment_from_camera)
    expected = np.asarray(camera_poses(skeleton, rig, motion).wxyz_xyz)
    np.testing.assert_allclose(poses[..., 4:], expected[..., 4:], atol=1e-12)
    same_rotation = np.abs(np.sum(poses[..., :4] * expected[..., :4], axis=-1))
    np.testing.assert_allclose(same_rotation, 1.0, atol=1e-12)


# ---- edits ----------------------------------------------------------------------------------------
def _posed_model(frames: int, seed: int):
    """The test skeleton, a random motion of ``frames`` frames posed on it, and the editable model with its rig."""
    skeleton = make_skeleton()
    motion = random_motion(skeleton, frames, np.random.default_rng(seed))
    return skeleton, Posing(skeleton.parents, motion.root_position, motion.rotations), EditableModel.of(skeleton, make_rig(skeleton))


def test_moving_a_joint_keeps_children_and_cameras_in_place():
    skeleton, posing, model = _posed_model(4, 3)
    before = posing.joint_positions(model.offsets)
    cams_before = posing.camera_poses(before, model.camera_segments, model.mounts)
    j, t, delta = skeleton.index("thigh"), 2, np.array([0.01, -0.02, 0.015])
    moved = model.with_joint_moved(j, delta, posing.world_matrices[t, skeleton.parents[j]], posing.world_matrices[t, j])
    after = posing.joint_positions(moved.offsets)
    np.testing.assert_allclose(after[t, j], before[t, j] + delta, atol=1e-12)
    others = [k for k in range(len(skeleton.names)) if k != j]
    np.testing.assert_allclose(after[t, others], before[t, others], atol=1e-12)
    ancestors = [0]  # the joint moved in its parent's frame: in every frame, only it and its subtree move
    np.testing.assert_allclose(after[:, ancestors], before[:, ancestors], atol=1e-12)
    assert np.linalg.norm(after[:, j] - before[:, j], axis=-1) == pytest.approx(np.linalg.norm(delta))
    cams_after = posing.camera_poses(after, moved.camera_segments, moved.mounts)
    np.testing.assert_allclose(cams_after[t], cams_before[t], atol=1e-12)
    with pytest.raises(ValueError, match="root"):
        model.with_joint_moved(0, delta, np.eye(3), np.eye(3))


def test_moving_a_camera_gives_it_that_world_pose_relative_to_its_segment():
    skeleton, posing, model = _posed_model(3, 4)
    joints = posing.joint_positions(model.offsets)
    c, t = 1, 1
    s = model.camera_segments[c]
    turn = np.array([np.cos(0.1), 0.0, np.sin(0.1), 0.0])
    target = np.concatenate([quat_multiply(posing.world_rotations[t, s], quat_multiply(model.mounts[c, :4], turn)),
                             joints[t, s] + np.array([0.01, 0.02, -0.01])])
    moved = model.with_camera_moved(c, target, np.concatenate([posing.world_rotations[t, s], joints[t, s]]))
    poses = posing.camera_poses(joints, moved.camera_segments, moved.mounts)
    np.testing.assert_allclose(poses[t, c, 4:], target[4:], atol=1e-12)
    assert abs(abs(poses[t, c, :4] @ target[:4]) - 1) < 1e-12
    untouched = [k for k in range(len(model.camera_names)) if k != c]
    np.testing.assert_allclose(moved.mounts[untouched], model.mounts[untouched])


def test_checks_refuse_a_zero_length_bone_and_a_camera_on_the_wrong_side():
    skeleton, _, model = _posed_model(1, 0)
    j = skeleton.index("shin")
    collapsed = model.with_joint_moved(j, -np.asarray(skeleton.offsets)[j], np.eye(3), np.eye(3))
    problems = collapsed.problems_after_editing(joint=j, before=model)
    assert any("bone thigh → shin" in p and "0.00 cm" in p for p in problems), problems
    c = 0
    mounts = model.mounts.copy()
    axis = matrix_from_quat(mounts[c, :4])[:, 2]
    ends = [model.offsets[k] for k in model.children(model.camera_segments[c])]
    mounts[c, 4:] = -0.1 * axis  # behind the bone's origin, looking towards it
    if ends:
        mounts[c, 4:] += 0.5 * ends[0]
    inward = EditableModel(model.names, model.parents, model.offsets, model.camera_names, model.camera_segments, mounts)
    assert any("wrong side" in p for p in inward.camera_problems([c])), inward.camera_problems([c])
    mounts[c, 4:] = 0.5 * ends[0] if ends else 0.0
    inside = EditableModel(model.names, model.parents, model.offsets, model.camera_names, model.camera_segments, mounts)
    assert any("inside the body" in p for p in inside.camera_problems([c]))


def test_the_estimated_rig_of_a_run_passes_the_checks(run):
    from bcmocap.pipeline.run import load_model

    model = EditableModel.of(*load_model(run[0]))
    assert model.camera_problems() == [] and model.problems_after_editing(before=model) == []
    assert model.bone_problems() == ["bone pelvis → torso would be 0.26 cm long (at least 1 cm)"]  # its own


# ---- overlay and video ----------------------------------------------------------------------------
def test_residual_image_draws_measurements_and_reports_residuals(run):
    from bcmocap.cameras import camera_at
    from bcmocap.viewer.overlay import reprojections, residual_image

    skeleton, rig, motion, _ = run[1]
    from bcmocap.correspondence_store import CorrespondenceStore

    store = CorrespondenceStore.open(run[0] / "solve" / "correspondences")
    data = store.block(0)
    keep = data["point_ids"][3, 5] >= 0
    pose = store.world_from_camera[3, 5]
    camera = camera_at(rig.intrinsics, 5)
    frame = CameraFrame(np.full((camera.height, camera.width, 3), 40, np.uint8), data["pixels"][3, 5][keep],
                        np.asarray(store.points[data["point_ids"][3, 5][keep]]), 7)
    image, stats = residual_image(frame, camera, pose, width=camera.width)
    assert stats["measurements"] == stats["reprojected"] == keep.sum() > 5
    assert 0.1 < stats["median_px"] < 2.0  # the 0.5 px noise of the measurements
    assert (image != 40).any(axis=-1).sum() > 10 * keep.sum()
    moved = pose.copy()
    moved[:4] = quat_multiply(pose[:4], quat_exp(np.array([0.0, np.deg2rad(5.0), 0.0])))  # turned 5°: long lines
    _, far = residual_image(frame, camera, moved, width=camera.width)
    assert far["median_px"] > 5 * stats["median_px"]
    uv, ok = reprojections(camera, np.full(7, np.nan), frame.points)
    assert not ok.any()


def test_video_frames_forward_and_seek(tmp_path):
    import cv2

    from bcmocap.viewer.video import VideoFrames

    path = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    for i in range(30):
        writer.write(np.full((48, 64, 3), 8 * i, np.uint8))
    writer.release()
    video = VideoFrames(path)
    values = {i: float(video.frame(i).mean()) for i in (0, 1, 5, 29, 3)}
    for i, v in values.items():
        assert abs(v - 8 * i) < 3, (i, v)
    assert video.frame(30) is None and video.frame(-1) is None
    video.close()
    with pytest.raises(ValueError, match="missing"):
        VideoFrames(tmp_path / "none.mp4").frame(0)


# ---- run folder reader ----------------------------------------------------------------------------
def test_load_view_input_reads_the_run(run):
    from bcmocap.pipeline.view_input import load_view_input

    data = load_view_input(run[0])
    assert list(data.motions) == ["solved", "initial"]
    assert data.num_frames == 30 and data.fps == 30
    assert data.registered.shape == (30, 18, 7) and np.isnan(data.registered).any()
    assert data.scene_points.shape[1] == 3 and len(data.scene_points) > 50
    assert [p.name for p in data.pictures] == ["joint_angles.png"]
    assert data.metrics["solved"]["joint_position_error_cm"]["mean"] == 0.6
    assert data.truth is None and data.save_model is not None and data.notes == []
    shot = data.camera_frame(4, 7)
    assert shot.video_frame == 9 and shot.image.shape == (90, 160, 3) and len(shot.pixels) == len(shot.points) > 5
    bright = shot.image.max(axis=-1) > 200  # the video's dots are where the measurements are
    u, v = np.round(shot.pixels).astype(int).T
    assert bright[np.clip(v, 0, 89), np.clip(u, 0, 159)].mean() > 0.8
    assert load_view_input(run[0], max_points=10).scene_points.shape[0] <= 10
    assert load_view_input(run[0], editable=False).save_model is None


def test_a_run_without_its_capture_still_opens(run, tmp_path):
    from bcmocap.pipeline.view_input import load_view_input

    data = load_view_input(run[0], capture=tmp_path / "gone")
    assert data.camera_frame is None and any("videos not shown" in n for n in data.notes)


def test_load_view_input_errors_name_the_file(run, tmp_path):
    from bcmocap.pipeline.view_input import load_view_input

    with pytest.raises(ValueError, match="no such folder"):
        load_view_input(tmp_path / "nothing")
    with pytest.raises(ValueError, match="no run.json"):
        load_view_input(tmp_path)
    (tmp_path / "run.json").write_text("{not json")
    with pytest.raises(ValueError, match="run.json: cannot read"):
        load_view_input(tmp_path)
    (tmp_path / "run.json").write_text(json.dumps({"format": "bcmocap-run", "capture": "/x", "stages": {}}))
    with pytest.raises(ValueError, match="skeleton.json: missing"):
        load_view_input(tmp_path)
    folder = _fresh_run(run, tmp_path / "b")
    for name in ("motion.npz", "initial.npz", "checkpoint.npz"):
        (folder / "solve" / name).unlink()
    with pytest.raises(ValueError, match="no motion yet"):
        load_view_input(folder)


def test_pictures_outside_the_run_folder_are_not_read(run, tmp_path):
    from bcmocap.pipeline.view_input import load_view_input

    folder = _fresh_run(run, tmp_path)
    outside = tmp_path / "secret.png"
    outside.write_bytes((folder / "pictures" / "joint_angles.png").read_bytes())
    os.symlink(outside, folder / "pictures" / "zz_link.png")
    assert [p.name for p in load_view_input(folder).pictures] == ["joint_angles.png"]


# ---- saving an edited model -----------------------------------------------------------------------
def test_save_model_version_keeps_the_old_one_and_marks_later_stages_stale(run, tmp_path):
    from bcmocap.pipeline.model_edit import model_versions, save_model_version
    from bcmocap.pipeline.run import load_model

    folder = _fresh_run(run, tmp_path)
    original = (folder / "model" / "skeleton.json").read_text()
    skeleton, rig = load_model(folder)
    model = EditableModel.of(skeleton, rig)
    offsets = model.offsets.copy()
    offsets[3, 0] += 0.02
    edited, _ = EditableModel(model.names, model.parents, offsets, model.camera_names, model.camera_segments,
                              model.mounts).applied_to(skeleton, rig)
    message = save_model_version(folder, edited, rig)
    assert "version 2" in message and "stale: initial, solve, outputs" in message
    assert json.loads((folder / "model" / "versions" / "001" / "skeleton.json").read_text()) == json.loads(original)
    saved = json.loads((folder / "model" / "skeleton.json").read_text())
    assert saved == json.loads((folder / "model" / "versions" / "002" / "skeleton.json").read_text())
    np.testing.assert_allclose(saved["offsets_m"], offsets)
    assert [v["version"] for v in model_versions(folder)] == [1, 2]
    stages = json.loads((folder / "run.json").read_text())["stages"]
    assert list(stages) == ["frontend", "world", "skeleton"] and stages["skeleton"]["model_version"] == 2
    assert not (folder / "solve" / "checkpoint.npz").exists() and not (folder / "solve" / "checkpoint.json").exists()
    # a third version; the model files edited by hand in between are kept as a version of their own
    by_hand = json.loads((folder / "model" / "skeleton.json").read_text())
    by_hand["offsets_m"][4][1] += 0.01
    (folder / "model" / "skeleton.json").write_text(json.dumps(by_hand))
    assert "version 4" in save_model_version(folder, edited, rig)
    assert [v["version"] for v in model_versions(folder)] == [1, 2, 3, 4]
    assert json.loads((folder / "model" / "versions" / "003" / "skeleton.json").read_text()) == by_hand


def test_the_pipeline_resumes_from_initial_after_a_save(run, tmp_path):
    """``bcmocap run``'s own bookkeeping (RunLog and the stage outputs) sees frontend, world and skeleton as
    done and initial as to be redone."""
    from bcmocap.pipeline.model_edit import save_model_version
    from bcmocap.pipeline.run import STAGES, RunLog, load_model

    folder = _fresh_run(run, tmp_path)
    log = json.loads((folder / "run.json").read_text())
    save_model_version(folder, *load_model(folder))
    after = RunLog(folder, __import__("pathlib").Path(log["capture"]))
    done = [s for s in STAGES if after.finished(s, log["stages"][s]["fingerprint"])]
    assert done == ["frontend", "world", "skeleton"]


def test_saves_from_many_clients_at_once_each_give_a_whole_version(run, tmp_path):
    """Viewer clients saving at the same moment take turns on the run folder's lock: every save is a version of
    its own, every version's files are one edit whole (never a mix), and the current model is the last version."""
    import threading

    from bcmocap.pipeline.model_edit import model_versions, save_model_version
    from bcmocap.pipeline.run import load_model

    folder = _fresh_run(run, tmp_path)
    skeleton, rig = load_model(folder)
    model = EditableModel.of(skeleton, rig)
    edits = []
    for k in range(6):
        offsets = model.offsets.copy()
        offsets[3, 0] += 0.01 * (k + 1)
        edits.append(EditableModel(model.names, model.parents, offsets, model.camera_names, model.camera_segments,
                                   model.mounts).applied_to(skeleton, rig)[0])
    start, errors = threading.Barrier(len(edits)), []

    def client(edit):
        start.wait()
        try:
            save_model_version(folder, edit, rig)
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=client, args=(e,)) for e in edits]
    [t.start() for t in threads]
    [t.join() for t in threads]
    assert errors == []
    versions = model_versions(folder)
    assert [v["version"] for v in versions] == list(range(1, len(edits) + 2))
    saved = sorted(json.loads((folder / "model" / "versions" / v["folder"] / "skeleton.json").read_text())
                   ["offsets_m"][3][0] for v in versions[1:])
    np.testing.assert_allclose(saved, sorted(model.offsets[3, 0] + 0.01 * (k + 1) for k in range(len(edits))))
    current = json.loads((folder / "model" / "skeleton.json").read_text())
    assert current == json.loads((folder / "model" / "versions" / versions[-1]["folder"] / "skeleton.json").read_text())


def test_a_run_waits_for_a_save_and_a_save_is_refused_during_a_run(run, tmp_path, monkeypatch):
    import threading
    import time

    from bcmocap.io.output_folder import locked_output
    from bcmocap.pipeline import model_edit
    from bcmocap.pipeline.run import load_model

    folder = _fresh_run(run, tmp_path)
    held = threading.Event()

    def short_save():  # as long as a save holds the lock
        with locked_output(folder):
            held.set()
            time.sleep(0.5)

    saver = threading.Thread(target=short_save)
    saver.start()
    held.wait()
    clock = time.monotonic()
    with locked_output(folder, wait_s=10.0):  # what bcmocap run does: waits, then goes on
        waited = time.monotonic() - clock
    saver.join()
    assert 0.2 < waited < 5.0
    monkeypatch.setattr(model_edit, "SAVE_WAIT_S", 0.3)
    with locked_output(folder):  # a run holding the folder: the save waits 0.3 s, then one line
        with pytest.raises(ValueError, match=r"another bcmocap command \(pid \d+\) is writing to this folder "
                                             r"\(waited 0.3 s\)"):
            model_edit.save_model_version(folder, *load_model(folder))


def test_save_refuses_while_another_command_writes_and_outside_paths(run, tmp_path, monkeypatch):
    from bcmocap.io.output_folder import locked_output
    from bcmocap.pipeline import model_edit
    from bcmocap.pipeline.model_edit import save_model_version
    from bcmocap.pipeline.run import load_model

    monkeypatch.setattr(model_edit, "SAVE_WAIT_S", 0.0)

    folder = _fresh_run(run, tmp_path / "a")
    model = load_model(folder)
    before = (folder / "model" / "skeleton.json").read_text()
    with locked_output(folder):
        with pytest.raises(ValueError, match="another bcmocap command"):
            save_model_version(folder, *model)
    assert (folder / "model" / "skeleton.json").read_text() == before
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    os.symlink(elsewhere, folder / "model" / "versions")
    with pytest.raises(ValueError, match="outside the run folder"):
        save_model_version(folder, *model)
    assert list(elsewhere.iterdir()) == []
    with pytest.raises(ValueError, match="not a bcmocap run folder"):
        save_model_version(tmp_path, *model)


# ---- the app, driven through viser's Python API (no browser) ---------------------------------------
@pytest.fixture(scope="module")
def viewer(run):
    from bcmocap.pipeline.view_input import load_view_input
    from bcmocap.viewer.app import Viewer
    from bcmocap.viewer.server import start_server

    data = load_view_input(run[0], editable=False)
    truth_skeleton, _, _, true_joints = run[1]
    data.truth = GroundTruth(true_joints, tuple(truth_skeleton.parents), tuple(truth_skeleton.names))
    server = start_server("127.0.0.1", 0)
    app = Viewer(data, server)
    assert app.ready.wait(60)  # the pictures are read in the background
    yield app
    app.close()
    server.stop()


def test_the_first_frame_waits_for_nothing_but_the_model_and_motions(run):
    """`bcmocap view` reads the scene points, the ground truth and the videos after the first frame is up."""
    from bcmocap.pipeline.view_input import load_view_input
    from bcmocap.viewer.app import Viewer
    from bcmocap.viewer.server import start_server

    data = load_view_input(run[0], editable=False, defer=True)
    assert data.later is not None and data.scene_points is None and data.camera_frame is None
    gate, read = threading.Event(), data.later
    data.later = lambda: (gate.wait(60), read())[1]  # hold the background reading here
    server = start_server("127.0.0.1", 0)
    app = Viewer(data, server)
    try:
        assert app.joint_meshes.batched_positions.shape == (15, 3) and app.frames_drawn == 1
        assert app.points_handle is None and app.show_points.disabled and not app.show_points.value
        assert "reading the videos" in app.camera_text.content and not app.ready.is_set()
        app.camera_menu.value = "chest"  # asked for before the videos are read: drawn once they are
        gate.set()
        assert app.ready.wait(60)
        assert data.later is None and len(data.scene_points) > 50
        assert server.scene.get_handle_by_name("/scene/points").points.shape == data.scene_points.shape
        assert app.show_points.value and not app.show_points.disabled
        assert "median residual" in app.camera_text.content and app.camera_image.visible
    finally:
        app.close()
        server.stop()


def test_scene_holds_joints_cameras_truth_and_points(viewer, run):
    scene = viewer.server.scene
    joints, cameras = len(viewer.model.names), len(viewer.model.camera_names)
    assert joints == 15 and cameras == 18
    assert scene.get_handle_by_name("/estimate/joints").batched_positions.shape == (joints, 3)
    assert scene.get_handle_by_name("/cameras/bodies").batched_positions.shape == (cameras, 3)
    assert scene.get_handle_by_name("/cameras/frusta").points.shape == (cameras * 8, 2, 3)
    assert viewer.bones.points.shape == (joints - 1, 2, 3)
    assert viewer.truth_joints.points.shape == (15, 3)
    assert viewer.registered_frusta.points.shape == (cameras * 8, 2, 3) and viewer.points_handle is not None


def test_frustum_lines_start_at_the_camera_and_look_along_z():
    from bcmocap.viewer.app import frustum_lines

    pose = np.array([np.cos(0.3), 0.0, np.sin(0.3), 0.0, 1.0, 2.0, 3.0])
    lines = frustum_lines(pose[None], 1.5, depth=0.1)
    assert lines.shape == (8, 2, 3)
    np.testing.assert_allclose(lines[:4, 0], np.tile(pose[4:], (4, 1)))
    forward = matrix_from_quat(pose[:4])[:, 2]
    np.testing.assert_allclose((lines[:4, 1] - pose[4:]) @ forward, 0.1)
    np.testing.assert_allclose(lines[4:, 0], lines[:4, 1])


def test_time_slider_moves_the_skeleton_and_colours_joints_by_error(viewer, run):
    viewer.slider.value = 12
    assert viewer.frame == 12
    np.testing.assert_allclose(viewer.joint_meshes.batched_positions[5], viewer.joints[12, 5], atol=1e-6)
    np.testing.assert_allclose(viewer.camera_meshes.batched_positions[3], viewer.cameras[12, 3, 4:], atol=1e-6)
    colours = viewer.joint_meshes.batched_colors
    worst = int(np.nanargmax(viewer.error_at(12)))
    assert colours[worst][0] >= colours[worst][1] - 60  # the largest error is the reddest joint
    errors = viewer.error_at(12)
    expected = 100 * np.linalg.norm(viewer.joints[12] - run[1][3][12], axis=-1)
    np.testing.assert_allclose(errors, expected)
    assert 0.05 < np.nanmean(errors) < 3  # the few millimetres the "estimate" was moved by
    assert "joint error mean" in viewer.time_text.content
    viewer.show_frame(10_000)
    assert viewer.frame == 29 and viewer.slider.value == 29


def test_playback_advances_frames(viewer):
    viewer.show_frame(0)
    viewer.speed_slider.value = 0.5
    drawn = viewer.frames_drawn
    viewer.play_button.value = True  # a click
    assert viewer.playing and viewer.play_button.label == "Pause"
    deadline = time.monotonic() + 20.0  # a loaded machine may starve the player's thread: wait, do not time
    while viewer.frame < 3 and time.monotonic() < deadline:
        time.sleep(0.02)
    viewer.play_button.value = True
    assert not viewer.playing and viewer.play_button.label == "Play"
    stopped = viewer.frame
    assert stopped >= 3 and viewer.frames_drawn > drawn
    time.sleep(0.3)
    assert viewer.frame == stopped  # paused means paused


def test_gizmo_edits_update_the_skeleton_and_refuse_bad_ones(viewer):
    viewer.revert()
    viewer.show_frame(4)
    knee = viewer.model.names.index("left_shin")
    viewer.edit_menu.value = "joint: left_shin"
    assert viewer.selection == ("joint", knee) and viewer.gizmo.visible
    np.testing.assert_allclose(viewer.gizmo.position, viewer.joints[4, knee], atol=1e-6)
    before = viewer.joints.copy()
    assert viewer.drag_to(before[4, knee] + [0.0, 0.03, 0.0])
    np.testing.assert_allclose(viewer.joints[4, knee], before[4, knee] + [0.0, 0.03, 0.0], atol=1e-9)
    np.testing.assert_allclose(viewer.joint_meshes.batched_positions[knee], viewer.joints[4, knee], atol=1e-6)
    assert tuple(viewer.joint_meshes.batched_colors[knee]) == (250, 190, 0)  # selected
    foot = viewer.model.names.index("left_foot")
    np.testing.assert_allclose(viewer.joints[4, foot], before[4, foot], atol=1e-9)  # at the frame of the edit
    assert np.abs(viewer.joints[:, foot] - before[:, foot]).max() > 1e-4  # elsewhere it follows the new knee
    assert "Unsaved edits: left_shin" in viewer.status
    parent = viewer.model.parents[knee]
    assert not viewer.drag_to(viewer.joints[4, parent])  # onto the hip: a zero-length thigh
    assert "Refused" in viewer.status and "left_thigh → left_shin" in viewer.status
    np.testing.assert_allclose(viewer.joints[4, knee], before[4, knee] + [0.0, 0.03, 0.0], atol=1e-9)
    np.testing.assert_allclose(viewer.gizmo.position, viewer.joints[4, knee], atol=1e-6)
    c = viewer.model.camera_names.index("chest")
    viewer.select(("camera", c))
    assert tuple(viewer.camera_meshes.batched_colors[c]) == (250, 190, 0) and not viewer.gizmo.disable_rotations
    assert (viewer.frusta.colors.reshape(18, 8, 2, 3)[c] == (250, 190, 0)).all()
    pose = viewer.cameras[4, c]
    assert viewer.drag_to(pose[4:] + 0.01, pose[:4])
    np.testing.assert_allclose(viewer.cameras[4, c, 4:], pose[4:] + 0.01, atol=1e-9)
    backwards = quat_multiply(pose[:4], np.array([0.0, 1.0, 0.0, 0.0]))  # turned to face the chest
    assert not viewer.drag_to(pose[4:] + 0.01, backwards) and "wrong side" in viewer.status
    viewer.camera_menu.value = "chest"
    assert "chest, video frame" in viewer.camera_text.content and "median residual" in viewer.camera_text.content
    assert viewer.camera_image.visible and viewer.camera_image.image.shape[:2] == (90, 160)
    viewer.select(("joint", 0))
    assert viewer.selection is None and "root" in viewer.status
    viewer.save_button.value = True
    assert "cannot be edited" in viewer.status  # loaded read-only
    viewer.revert()
    np.testing.assert_allclose(viewer.joints, before)


def test_metrics_markdown_lists_every_statistic():
    from bcmocap.viewer.app import metrics_markdown

    text = metrics_markdown({"frames_evaluated": 300, "initial": {"joint_angle_error_deg": {
        "mean": 1.0, "median": 0.5, "max": 9.0}}, "solved": {"joint_position_error_cm": {
            "mean": 1.53, "median": 1.06, "max": 4.78}}})
    assert "| solved | joint position error cm | 1.53 | 1.06 | 4.78 |" in text
    assert "| initial | joint angle error deg | 1.00 | 0.50 | 9.00 |" in text and "frames evaluated: 300" in text


def test_error_colours_run_green_to_red():
    from bcmocap.viewer.app import ERROR_RED_CM, JOINT, error_colours

    c = error_colours(np.array([0.0, ERROR_RED_CM / 2, 2 * ERROR_RED_CM, np.nan]))
    assert c[0][1] > c[0][0] and c[2][0] > c[2][1] and c[1][0] > 200 and c[1][1] > 200
    assert tuple(c[3]) == JOINT


# ---- the command's errors: one line, no traceback ------------------------------------------------
def _view(argv, capsys):
    from bcmocap.cli import main

    code = main(["view", *argv])
    return code, capsys.readouterr().err


def test_view_errors_are_one_line(run, tmp_path, capsys):
    code, err = _view([str(tmp_path / "missing")], capsys)
    assert code == 2 and err.count("\n") == 1 and "no such folder" in err and "Traceback" not in err
    code, err = _view([str(tmp_path)], capsys)
    assert code == 2 and err.count("\n") == 1 and "not an output folder of `bcmocap run` (run.json), `bcmocap " \
        "markers` (poses.npz, skeleton.json) or `bcmocap kcs` (result.npz)" in err
    code, err = _view([str(run[0] / "solve" / "correspondences")], capsys)  # a store has a poses.npz too
    assert code == 2 and err.count("\n") == 1 and "correspondences: not an output folder" in err
    code, err = _view([str(run[0]), "--port", "70000"], capsys)
    assert code == 2 and err.count("\n") == 1 and "--port" in err
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code, err = _view([str(run[0]), "--port", str(port)], capsys)
    assert code == 2 and err == f"bcmocap view: port {port} on 127.0.0.1 is in use (choose another with --port)\n"


def test_view_serves_until_stopped(run):
    from bcmocap.pipeline.view_command import add_view_command, serve

    parser = argparse.ArgumentParser()
    add_view_command(parser.add_subparsers())
    args = parser.parse_args(["view", str(run[0]), "--port", "0", "--read-only"])
    ready, stop, seen = threading.Event(), threading.Event(), []
    thread = threading.Thread(target=serve, args=(args, lambda v: (seen.append(v), ready.set()), stop))
    thread.start()
    assert ready.wait(60)
    port = seen[0].server.get_port()
    import urllib.request

    with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as page:
        assert page.status == 200 and b"<html" in page.read(2000).lower()
    stop.set()
    thread.join(10)
    assert not thread.is_alive()


# ---- bcmocap markers and bcmocap kcs folders -------------------------------------------------------
MARKERS_PER_SEGMENT = (3, 2, 2, 3, 2, 2)  # on the 6 segments of the test skeleton: 14 markers, 5 joints


def write_markers_folder(folder, frames: int = 12, seed: int = 0) -> dict:
    """A ``bcmocap markers`` output folder as :meth:`MarkerSkeleton.save` documents it (skeleton.json,
    poses.npz, report.txt), for the test skeleton moving randomly with markers fixed on its segments."""
    rng = np.random.default_rng(seed)
    skeleton = make_skeleton()
    motion = random_motion(skeleton, frames, rng)
    posing = Posing(skeleton.parents, motion.root_position, motion.rotations)
    joints = posing.joint_positions(np.asarray(skeleton.offsets))
    names, parents = list(skeleton.names), list(skeleton.parents)
    labels, segment = [], []
    for s, count in enumerate(MARKERS_PER_SEGMENT):
        labels += [f"{names[s][:3].upper()}{k}" for k in range(count)]
        segment += [s] * count
    segment = np.array(segment)
    offsets = rng.normal(0, 0.06, (len(labels), 3))
    markers = joints[:, segment] + np.einsum("tmij,mj->tmi", posing.world_matrices[:, segment], offsets)
    folder.mkdir(parents=True)
    (folder / "skeleton.json").write_text(json.dumps({
        "frames": frames, "fps": 120.0,
        "segments": [{"name": n, "parent": None if p < 0 else names[p],
                      "offset_m": np.asarray(skeleton.offsets[k]).tolist(),
                      "markers": [m for m, s in zip(labels, segment) if s == k]}
                     for k, (n, p) in enumerate(zip(names, parents))],
        "markers": {m: {"segment": names[s], "offset_m": o.tolist()} for m, s, o in zip(labels, segment, offsets)}}))
    np.savez_compressed(folder / "poses.npz", root_position=np.asarray(motion.root_position),
                        rotations=np.asarray(motion.rotations), joint_positions=joints, marker_positions=markers,
                        marker_labels=np.array(labels), segment_names=np.array(names))
    (folder / "report.txt").write_text(f"{frames} frames at 120 Hz\n")
    return {"labels": labels, "segment": segment, "markers": markers, "joints": joints, "parents": parents}


@pytest.fixture(scope="module")
def markers_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("view-markers") / "out"
    return folder, write_markers_folder(folder)


@pytest.fixture(scope="module")
def kcs_folder(tmp_path_factory):
    """The real ``bcmocap kcs`` on a small quadruped seen by a near-static camera, with one extra rigid link
    (between the front hooves): ``(folder, true joints)``."""
    from test_kcs import NAMES, PARENTS, camera_rotations, images, quadruped

    from bcmocap.cli import main

    _, joints, rest = quadruped(front_in_phase=True)
    uv = images(joints, camera_rotations(len(joints), np.random.default_rng(11)))
    folder = tmp_path_factory.mktemp("view-kcs")
    np.savez(folder / "input.npz", joints_2d=uv, names=np.array(NAMES), parents=np.array(PARENTS), rest=rest,
             links=np.array([["lfhoof", "rfhoof"]]), fps=25.0)
    assert main(["kcs", str(folder / "input.npz"), "--out", str(folder / "out")]) == 0
    return folder / "out", joints


@pytest.fixture
def track_viewer():
    """``open(folder) → TrackViewer`` on a fresh server; the servers are stopped afterwards."""
    from bcmocap.pipeline.view_tracks import load_track_folder
    from bcmocap.viewer.server import start_server
    from bcmocap.viewer.tracks import TrackViewer

    opened = []

    def open_folder(folder):
        server = start_server("127.0.0.1", 0)
        opened.append((TrackViewer(load_track_folder(folder), server), server))
        return opened[-1][0]

    yield open_folder
    for viewer, server in opened:
        viewer.close()
        server.stop()


def test_a_markers_folder_shows_markers_by_segment_joints_and_skeleton(markers_folder, track_viewer):
    from bcmocap.pipeline.view_tracks import folder_kind

    folder, made = markers_folder
    assert folder_kind(folder) == "markers"
    viewer = track_viewer(folder)
    scene = viewer.server.scene
    markers, joints = len(made["labels"]), len(made["parents"]) - 1
    assert (markers, joints) == (14, 5)
    assert scene.get_handle_by_name("/markers").points.shape == (markers, 3)
    assert scene.get_handle_by_name("/joints").points.shape == (joints, 3)
    assert scene.get_handle_by_name("/skeleton").points.shape == (joints, 2, 3)
    assert scene.get_handle_by_name("/segments").points.shape == (markers, 2, 3)
    colours = scene.get_handle_by_name("/markers").colors
    by_segment = {s: {tuple(c) for c in colours[made["segment"] == s]} for s in range(6)}
    assert all(len(c) == 1 for c in by_segment.values())  # one colour per segment
    assert len(set().union(*by_segment.values())) == 6  # and a different one for each
    viewer.slider.value = 7
    np.testing.assert_allclose(scene.get_handle_by_name("/markers").points, made["markers"][7], atol=1e-6)
    np.testing.assert_allclose(scene.get_handle_by_name("/joints").points, made["joints"][7, 1:], atol=1e-6)
    bones = scene.get_handle_by_name("/skeleton").points  # each joint to its parent's origin
    np.testing.assert_allclose(bones[:, 0], made["joints"][7, made["parents"][1:]], atol=1e-6)
    assert "t = 0.06 s · frame 7 of 11 · 120 fps" == viewer.time_text.content
    assert "14 markers on 6 segments, 5 joints" in viewer.data.notes[0] and "frames at 120 Hz" in viewer.data.report
    assert [text.split(":")[0] for text, _ in viewer.data.legend] == list(make_skeleton().names)
    viewer.boxes["markers"].value = False
    assert not scene.get_handle_by_name("/markers").visible
    viewer.boxes["markers"].value = True
    assert scene.get_handle_by_name("/markers").visible


def test_a_markers_folder_shows_each_segments_label_and_the_verdict(markers_folder, tmp_path):
    import shutil

    from bcmocap.pipeline.view_tracks import load_track_folder

    folder = tmp_path / "labelled"
    shutil.copytree(markers_folder[0], folder)
    desc = json.loads((folder / "skeleton.json").read_text())
    for k, segment in enumerate(desc["segments"]):
        segment["label"] = "pelvis" if k == 0 else "extra"
    desc["verdict"] = {"human": False, "wrong_limbs": ["left_leg", "right_arm"]}
    (folder / "skeleton.json").write_text(json.dumps(desc))
    data = load_track_folder(folder)
    assert data.legend[0][0].startswith(f"{desc['segments'][0]['name']} (pelvis): ")
    assert "NOT a human body (left_leg, right_arm wrong" in data.notes[-1]


def test_a_marker_not_seen_in_a_frame_is_left_out_of_it(markers_folder, tmp_path, track_viewer):
    import shutil

    folder = tmp_path / "gap"
    shutil.copytree(markers_folder[0], folder)
    with np.load(folder / "poses.npz") as data:
        arrays = dict(data)
    arrays["marker_positions"][3, 2] = np.nan
    np.savez(folder / "poses.npz", **arrays)
    viewer = track_viewer(folder)
    viewer.show_frame(3)
    assert viewer.handles["markers"].points.shape == (13, 3) and viewer.handles["segments"].points.shape == (13, 2, 3)
    assert len(viewer.handles["markers"].colors) == 13
    viewer.show_frame(4)
    assert viewer.handles["markers"].points.shape == (14, 3)


def test_a_kcs_folder_shows_the_chain_and_its_extra_link(kcs_folder, track_viewer):
    from bcmocap.pipeline.view_tracks import folder_kind

    folder, true_joints = kcs_folder
    assert folder_kind(folder) == "kcs"
    viewer = track_viewer(folder)
    scene = viewer.server.scene
    frames, joints = true_joints.shape[:2]
    assert (viewer.num_frames, joints, viewer.fps) == (frames, 18, 25.0)
    assert scene.get_handle_by_name("/joints").points.shape == (joints, 3)
    assert scene.get_handle_by_name("/bones").points.shape == (joints - 1, 2, 3)
    assert scene.get_handle_by_name("/links").points.shape == (1, 2, 3)
    result = np.load(folder / "result.npz")
    viewer.show_frame(frames - 1)
    np.testing.assert_allclose(scene.get_handle_by_name("/joints").points, result["joints"][-1], atol=1e-6)
    names = list(result["names"])
    link = scene.get_handle_by_name("/links").points[0]
    np.testing.assert_allclose(link, result["joints"][-1, [names.index("lfhoof"), names.index("rfhoof")]], atol=1e-6)
    assert "iterations" in viewer.data.report and "| root->chest |" in viewer.data.report


def test_view_opens_markers_and_kcs_folders(markers_folder, kcs_folder, capsys):
    from bcmocap.pipeline.view_command import add_view_command, serve

    parser = argparse.ArgumentParser()
    add_view_command(parser.add_subparsers())
    for folder, counts in ((markers_folder[0], "12 frames, 14 markers, 5 joints"),
                           (kcs_folder[0], "40 frames, 18 joints")):
        stop, seen = threading.Event(), []
        args = parser.parse_args(["view", str(folder), "--port", "0"])
        assert serve(args, lambda v: (seen.append(type(v).__name__), stop.set()), stop) == 0
        assert seen == ["TrackViewer"]
        assert counts in capsys.readouterr().out


def _damage(folder, name, content):
    path = folder / name
    if content is None:
        path.unlink()
    elif isinstance(content, dict):
        np.savez(path, **content)
    else:
        path.write_text(content)


@pytest.mark.parametrize("kind,name,content,culprit", [
    ("markers", "poses.npz", None, "poses.npz: missing"),
    ("markers", "poses.npz", "not a zip file", "poses.npz: cannot read"),
    ("markers", "poses.npz", {"joint_positions": np.zeros((3, 6, 3))}, "poses.npz: cannot read (no marker_positions"),
    ("markers", "poses.npz", {"joint_positions": np.zeros((3, 4, 3)), "marker_positions": np.zeros((3, 14, 3)),
                              "marker_labels": np.array(["a"] * 14), "segment_names": np.array(["x"] * 4)},
     "poses.npz: joint_positions has shape (3, 4, 3), expected (F, 6, 3)"),
    ("markers", "skeleton.json", "{not json", "skeleton.json: cannot read"),
    ("markers", "skeleton.json", json.dumps({"fps": 120, "segments": "pelvis"}), "skeleton.json: 'segments'"),
    ("markers", "skeleton.json", json.dumps({"fps": -1}), "skeleton.json: 'fps' must be a positive frame rate"),
    ("kcs", "result.npz", None, "result.npz: missing"),
    ("kcs", "result.npz", {"joints": np.zeros((2, 3, 3)), "names": np.array(["a", "b", "c"]),
                           "parents": np.array([-1, 2, 1])}, "result.npz: the parents of 'b' form a cycle"),
    ("kcs", "result.npz", {"joints": np.zeros((2, 3, 3)), "names": np.array(["a", "b", "c"]),
                           "parents": np.array([-1, 0, 0]), "bone_names": np.array(["a->b", "a->c", "b->z"])},
     "result.npz: bone_names entry 'b->z'"),
    ("kcs", "report.json", json.dumps({"fps": "fast"}), "report.json: 'fps' must be a positive frame rate"),
])
def test_a_damaged_folder_is_refused_in_one_line(markers_folder, kcs_folder, tmp_path, capsys, kind, name, content,
                                                 culprit):
    import shutil

    folder = tmp_path / kind
    shutil.copytree(markers_folder[0] if kind == "markers" else kcs_folder[0], folder)
    _damage(folder, name, content)
    code, err = _view([str(folder), "--port", "0"], capsys)
    assert code == 2 and err.startswith("bcmocap view: ") and err.count("\n") == 1 and culprit in err, err
    assert str(folder / name) in err and "Traceback" not in err


def test_capture_is_refused_for_a_markers_folder(markers_folder, capsys):
    code, err = _view([str(markers_folder[0]), "--capture", "/somewhere", "--port", "0"], capsys)
    assert code == 2 and err.count("\n") == 1 and "--capture is for a `bcmocap run` folder" in err


@pytest.mark.slow
def test_the_real_bcmocap_markers_output_opens(tmp_path, track_viewer):
    """`bcmocap markers` itself (about a minute, most of it compiling) on a 2 s, three-rod linkage: what it
    writes is what the viewer reads."""
    from test_io_c3d import write_c3d
    from test_markers_pipeline import linkage_capture

    from bcmocap.cli import main
    from bcmocap.sim.markers import MarkerNoise

    sim = linkage_capture(seconds=2.0, noise=MarkerNoise(sigma_m=0.0005, spike_probability=0.0, gap_rate_hz=0.0,
                                                          gap_seconds=(0.05, 0.2), relabel_after_gap=0.0,
                                                          label_break_rate_hz=0.0))
    path = write_c3d(tmp_path / "linkage.c3d", sim.positions, sim.labels, rate=60.0, units="mm")
    assert main(["markers", str(path), "--out", str(tmp_path / "out"), "--groups", "3"]) == 0
    viewer = track_viewer(tmp_path / "out")
    assert viewer.handles["markers"].points.shape == (9, 3) and viewer.handles["joints"].points.shape == (2, 3)
    assert viewer.handles["skeleton"].points.shape == (2, 2, 3) and len(viewer.data.legend) == 3
    poses = np.load(tmp_path / "out" / "poses.npz")
    viewer.show_frame(30)
    np.testing.assert_allclose(viewer.handles["markers"].points, poses["marker_positions"][30], atol=1e-6)
