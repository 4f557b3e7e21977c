"""Tests for tracking registration (bcmocap.frontend.tracking) and measurement selection
(bcmocap.frontend.selection): a fisheye camera moving smoothly through the rendered room of
test_frontend_register is registered by KLT tracking between keyframes, accurately, and maps new points."""

import numpy as np
import pytest

from bcmocap.io.colmap import to_pycolmap
from bcmocap.frontend.selection import measurement_score, select_measurements
from bcmocap.frontend.tracking import CameraTrack, TrackingOptions, frames_for_rounds, predict_pose, track_camera
from bcmocap.geometry import matrix_from_quat, quat_from_matrix
from bcmocap.sim import make_textured_scene

from test_frontend_register import _errors, _look, _render, studio  # noqa: F401  (module fixture)


def test_predict_pose_continues_a_constant_motion():
    step = np.eye(4)
    step[:3, :3] = np.asarray(matrix_from_quat(np.array([np.cos(0.05), 0.0, 0.0, np.sin(0.05)])))
    step[:3, 3] = [0.02, -0.01, 0.005]
    first = np.eye(4)
    first[:3, :3] = np.asarray(matrix_from_quat(np.array([0.9, 0.1, -0.3, 0.3]) / np.linalg.norm([0.9, 0.1, -0.3, 0.3])))
    first[:3, 3] = [1.0, 2.0, 1.5]
    poses = [first, first @ step, first @ step @ step]
    as7 = [np.concatenate([quat_from_matrix(m[:3, :3]), m[:3, 3]]) for m in poses]
    assert np.allclose(predict_pose(as7[0], as7[1]), poses[2], atol=1e-9)


def test_selection_spreads_over_the_image_and_keeps_the_best():
    rng = np.random.default_rng(0)
    # 200 measurements crowded into the top-left bucket, 10 spread elsewhere
    crowd = rng.uniform([0, 0], [70, 50], size=(200, 2))
    spread = np.column_stack([np.linspace(100, 620, 10), np.linspace(80, 350, 10)])
    pixels = np.concatenate([crowd, spread])
    score = np.concatenate([np.linspace(1, 2, 200), np.zeros(10)])
    keep = select_measurements(pixels, score, 20, 640, 360)
    assert len(keep) == 20 and np.all(np.diff(keep) > 0)
    assert set(range(200, 210)) <= set(keep.tolist())  # every lonely bucket's measurement first
    crowd_kept = keep[keep < 200]
    assert set(crowd_kept.tolist()) == set(range(190, 200))  # the crowd's best
    assert np.array_equal(select_measurements(pixels[:5], score[:5], 20, 640, 360), np.arange(5))
    with pytest.raises(ValueError, match="3 pixels but 2 scores"):
        select_measurements(pixels[:3], score[:2], 1, 640, 360)
    # longer tracks score higher, a pixel of error costs a doubling of track length, NaN is worst
    s = measurement_score(np.array([2, 4, 4, 4]), np.array([0.0, 0.0, 1.0, np.nan]))
    assert s[1] > s[0] == pytest.approx(s[2]) and s[3] == -np.inf


@pytest.fixture(scope="module")
def walk(studio):  # noqa: F811
    """A fisheye camera walking 3 cm and turning 1.5° per frame for 24 frames: ``(gray frames, true poses)``."""
    import cv2

    scene = make_textured_scene(np.array([[0.0, 0.0], [1.0, 0.0]]), seed=3, num_pillars=4, num_boxes=4)
    poses = np.array([_look(np.array([0.2 + 0.03 * k, 0.1 - 0.01 * k, 1.5]), 0.1 + np.radians(1.5) * k, -0.1)
                      for k in range(24)])
    frames = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in _render(scene, studio.fisheye, poses)]
    return frames, poses


@pytest.mark.slow
def test_tracking_registers_a_moving_camera_between_keyframes(studio, walk):  # noqa: F811
    frames, poses = walk
    options = TrackingOptions(keyframe_interval=10)
    track = track_camera(frames, to_pycolmap(studio.fisheye), studio.index, options)
    assert track.registered.all(), track.how
    assert track.how[0] == "keyframe" and (track.how == "tracked").sum() >= 18
    assert track.keyframe.sum() <= 6 and track.keyframe[0] and track.keyframe[10]
    for estimate, truth in zip(track.poses, poses):
        rot_deg, pos_cm = _errors(studio.align, estimate, truth)
        assert rot_deg < 0.5 and pos_cm < 2.0, (rot_deg, pos_cm)
    # Points mapped while tracking: triangulated from the walk's baseline, measured in several frames,
    # and they reproject where the frames measured them.
    assert len(track.new_points) > 20
    new_obs = 0
    for estimate, px, ids in zip(track.poses, track.pixels, track.point_ids):
        new = ids >= track.id_base
        new_obs += new.sum()
        if new.any():
            xyz = track.new_points[ids[new] - track.id_base]
            local = (xyz - estimate[4:]) @ np.asarray(matrix_from_quat(estimate[:4]))
            uv = np.asarray(studio.fisheye.project(local)[0])
            assert np.median(np.linalg.norm(uv - px[new], axis=1)) < 1.0
        assert len(np.unique(ids)) == len(ids)
    assert new_obs > 2 * len(track.new_points)


@pytest.mark.slow
def test_a_lost_frame_becomes_a_keyframe_and_the_track_saves_and_loads(studio, walk, tmp_path):  # noqa: F811
    frames, _ = walk
    blank = np.zeros_like(frames[0])
    track = track_camera([frames[0], frames[1], blank, frames[3], frames[4]], to_pycolmap(studio.fisheye),
                         studio.index)
    assert track.how.tolist() == ["keyframe", "tracked", "", "keyframe", "tracked"]
    assert track.keyframe.tolist() == [True, False, True, True, False]
    assert np.isnan(track.poses[2]).all() and len(track.point_ids[2]) == 0
    track.save(tmp_path / "t.npz")
    back = CameraTrack.load(tmp_path / "t.npz")
    assert back.how.tolist() == track.how.tolist() and np.array_equal(back.poses, track.poses, equal_nan=True)
    assert all(np.array_equal(a, b) for a, b in zip(back.point_ids, track.point_ids))
    # The rounds get SIFT of the lost frame, its camera's frames around it and every camera at its time.
    need = frames_for_rounds(np.column_stack([track.registered, np.ones(5, bool)]), gap=1)
    assert need.tolist() == [[False, False], [True, False], [True, True], [True, False], [False, False]]
    # partners limit the other cameras at the same time
    registered = np.ones((3, 3), bool)
    registered[1, 0] = False
    need = frames_for_rounds(registered, gap=0, partners=[[2], [0, 2], [0, 1]])
    assert need.tolist() == [[False] * 3, [True, False, True], [False] * 3]


@pytest.mark.slow
def test_retrack_fills_a_gap_from_the_frames_around_it(studio, walk):  # noqa: F811
    """Frames 6–9 are lost (blank) when the camera is tracked; re-tracking the real images from the
    registered frames on both sides of the gap registers them."""
    import types

    from bcmocap.frontend.tracking import relocalise, retrack

    frames, poses = walk
    seen = [f if not 6 <= k <= 9 else np.zeros_like(f) for k, f in enumerate(frames[:16])]
    cam = to_pycolmap(studio.fisheye)
    track = track_camera(seen, cam, studio.index)
    assert not track.registered[6:10].any() and track.registered[:6].all() and track.registered[10:].all()

    class FakeCapture:  # the Capture methods retrack uses; the true images
        camera_names = ("cam",)
        cameras = (types.SimpleNamespace(intrinsics=studio.fisheye),)

        def frames(self, trial, name, *, stride, start, stop, gray):
            for k in range(start, min(stop, 16)):
                yield k, frames[k]

    assert relocalise([track], [[(np.zeros((0, 2)), np.zeros((0, 128), np.uint8))] * 16], [cam], studio.index,
                      0, 16)[0] == {}  # blank keyframes have nothing to match
    count = retrack(FakeCapture(), "capture", [track], {}, [], studio.index, starts=[0], stride=1, first=0, stop=16)
    assert count == 4 and track.registered.all() and (track.how[6:10] == "tracked").all()
    for estimate, truth in zip(track.poses[6:10], poses[6:10]):
        rot_deg, pos_cm = _errors(studio.align, estimate, truth)
        assert rot_deg < 0.5 and pos_cm < 2.0, (rot_deg, pos_cm)


@pytest.mark.slow
def test_process_trial_with_tracking_registers_every_frame_and_caps_the_measurements(studio, walk, tmp_path):  # noqa: F811
    """The tracking frontend end to end on two cameras: one loses frames 6–9 (blank while tracked); they are
    registered from the frames around them, the measurements are capped, and a rerun reuses the tracks."""
    import types

    from bcmocap.correspondence_store import CorrespondenceStore
    from bcmocap.frontend.command import TrialOptions, process_trial

    frames, poses = walk
    blanked = {6, 7, 8, 9}
    names = ("a", "b")

    def frames_of(trial, name, *, stride, start, stop, gray):
        for k in range(start, min(stop, 16), stride):
            image = frames[k]
            if name == "b" and k in blanked and not reading["again"]:
                image = np.zeros_like(image)
            yield k, image

    reading = {"again": False}
    capture = types.SimpleNamespace(
        camera_names=names, fps=30.0, cameras=[types.SimpleNamespace(name=n, intrinsics=studio.fisheye) for n in names],
        video_info=lambda trial, name: types.SimpleNamespace(num_frames=16), frames=frames_of,
        correction_settings=lambda trial: {}, lens_fingerprint=lambda: "lenses")

    def frames_after_tracking(*args, **kwargs):  # the second reading of b's video sees the true images
        reading["again"] = True
        return frames_of(*args, **kwargs)

    import bcmocap.frontend.tracking as tracking

    original = tracking.track_trial

    def track_then_switch(*args, **kwargs):
        out = original(*args, **kwargs)
        capture.frames = frames_after_tracking
        return out

    tracking.track_trial = track_then_switch
    try:
        report = process_trial(capture, studio.index, "capture", tmp_path,
                               TrialOptions(homographies=True, registration="tracking", max_measurements=60),
                               offsets=[0, 0], log=lambda line: None)
    finally:
        tracking.track_trial = original
    assert report["registered_fraction"] == 1.0 and report["registration"] == "tracking"
    assert report["registered_tracked"] >= 24 and report["registered_absolute"] >= 2
    store = CorrespondenceStore.open(tmp_path / "capture" / "correspondences").load()
    assert store.registered.all() and store.point_ids.shape[2] == 60
    assert ((store.point_ids >= 0).sum(axis=2) == 60).all()
    for t in range(16):
        rot_deg, pos_cm = _errors(studio.align, store.world_from_camera[t, 1], poses[t])
        assert rot_deg < 0.5 and pos_cm < 2.0, (t, rot_deg, pos_cm)
    assert sorted(p.name for p in (tmp_path / "tracks" / "capture").iterdir()) == ["a", "b"]


def test_round_seeds_thin_each_run_of_unregistered_frames():
    from bcmocap.frontend.tracking import round_seeds

    registered = np.ones((12, 3), bool)
    registered[1:9, 0] = False  # a run of 8 frames: 1, 4, 7 and its last, 8
    registered[5, 1] = False  # a run of one frame is its own seed
    registered[:, 2] = False  # a camera never registered: every third frame and the last
    seeds = round_seeds(registered, 3)
    assert np.flatnonzero(seeds[:, 0]).tolist() == [1, 4, 7, 8]
    assert np.flatnonzero(seeds[:, 1]).tolist() == [5]
    assert np.flatnonzero(seeds[:, 2]).tolist() == [0, 3, 6, 9, 11]
    assert not (seeds & registered).any()
    assert np.array_equal(round_seeds(registered, 1), ~registered)


@pytest.mark.slow
def test_track_after_rounds_fills_the_frames_the_rounds_left(studio, walk):  # noqa: F811
    """Frames 6–9 left unregistered (no features) between registered frames are tracked from them on the
    registration's points, and their states become "tracked" with the tracked measurements."""
    import types

    from bcmocap.frontend.relative import CameraFrameRegistration, CaptureRegistration
    from bcmocap.frontend.tracking import track_after_rounds

    frames, poses = walk
    track = track_camera(frames[:16], to_pycolmap(studio.fisheye), studio.index)
    assert track.registered.all()
    first = 2  # the registration covers processed frames 2 … 15
    states = []
    for t in range(first, 16):
        if 6 <= t <= 9:
            states.append([CameraFrameRegistration(np.zeros((0, 2)), np.zeros((0, 128), np.uint8),
                                                   np.zeros(0, np.int64), np.full(7, np.nan))])
        else:
            states.append([CameraFrameRegistration(track.pixels[t], np.zeros((0, 128), np.uint8),
                                                   track.point_ids[t].copy(), track.poses[t], "relative", 1)])
    points = {int(i): x for i, x in zip(studio.index.point3D_ids, studio.index.xyz)} | track.points
    result = CaptureRegistration(np.arange(first, 16), states, points, set(), [], None)
    capture = types.SimpleNamespace(
        camera_names=("cam",), cameras=(types.SimpleNamespace(intrinsics=studio.fisheye),),
        frames=lambda trial, name, *, stride, start, stop, gray: ((k, frames[k]) for k in range(start, min(stop, 16))))
    assert track_after_rounds(capture, "capture", result, starts=[0], stride=1, first=first) == 4
    assert result.registered.all()
    for t in range(6, 10):
        s = states[t - first][0]
        assert s.how == "tracked" and len(s.keypoints) == len(s.point_ids) >= 30 and (s.point_ids >= 0).all()
        rot_deg, pos_cm = _errors(studio.align, s.world_from_camera, poses[t])
        assert rot_deg < 0.5 and pos_cm < 2.0, (t, rot_deg, pos_cm)


def test_sift_for_homographies_extracts_the_frames_left_and_their_neighbours_without_descriptors():
    import types

    from bcmocap.frontend.relative import CameraFrameRegistration, CaptureRegistration
    from bcmocap.frontend.tracking import sift_for_homographies

    rng = np.random.default_rng(0)
    images = [np.clip(rng.normal(128, 60, (120, 160)), 0, 255).astype(np.uint8) for _ in range(6)]

    def state(t):
        if t == 3:  # left by the rounds and not tracked: unregistered, no features
            return CameraFrameRegistration(np.zeros((0, 2)), np.zeros((0, 128), np.uint8), np.zeros(0, np.int64),
                                           np.full(7, np.nan))
        desc = np.ones((1, 128), np.uint8) if t == 4 else np.zeros((0, 128), np.uint8)  # frame 4 has SIFT already
        return CameraFrameRegistration(np.array([[5.0, 6.0]]), desc, np.array([7]), np.array([1.0, 0, 0, 0, 0, 0, 0]),
                                       "tracked")

    first = 1
    states = [[state(t)] for t in range(first, 6)]
    result = CaptureRegistration(np.arange(first, 6), states, {}, set(), [], None)
    capture = types.SimpleNamespace(camera_names=("cam",), frames=lambda trial, name, *, stride, start, stop, gray: (
        (k, images[k]) for k in range(start, min(stop, 6))))
    leave = np.zeros((5, 1), bool)
    leave[3 - first] = True
    assert sift_for_homographies(capture, "capture", result, leave, starts=[0], stride=1, first=first) == 2  # 2 and 3
    left, before, after = states[3 - first][0], states[2 - first][0], states[4 - first][0]
    assert len(left.descriptors) == len(left.keypoints) > 20 and (left.point_ids == -1).all() and not left.registered
    # a registered neighbour keeps its measurement after its new SIFT keypoints
    assert len(before.descriptors) > 20 and before.point_ids[-1] == 7 and (before.keypoints[-1] == [5.0, 6.0]).all()
    assert len(after.descriptors) == 1 and len(states[0][0].descriptors) == 0  # not a neighbour of frame 3


@pytest.mark.slow
def test_rounds_for_the_rest_register_a_frame_tracking_could_not_reach(studio, walk):  # noqa: F811
    """Two cameras see the walk; camera 1's frame 5 was left by the rounds and could not be tracked. The
    second pass extracts SIFT for it and its neighbours, triangulates new points between them and registers
    it relative to them; everything else keeps its registration."""
    import types

    from bcmocap.frontend.relative import CameraFrameRegistration, CaptureRegistration
    from bcmocap.frontend.tracking import rounds_for_the_rest

    frames, poses = walk
    cam = to_pycolmap(studio.fisheye)
    track = track_camera(frames[:10], cam, studio.index)
    assert track.registered.all()
    empty = np.zeros((0, 128), np.uint8)
    states = [[CameraFrameRegistration(track.pixels[t], empty, track.point_ids[t].copy(), track.poses[t], "tracked", 0)
               for _ in range(2)] for t in range(10)]
    states[5][1] = CameraFrameRegistration(np.zeros((0, 2)), empty, np.zeros(0, np.int64), np.full(7, np.nan))
    points = {int(i): x for i, x in zip(studio.index.point3D_ids, studio.index.xyz)} | track.points
    result = CaptureRegistration(np.arange(10), states, points, set(), [{"registered": 19, "new_points": 0}], [cam, cam])
    capture = types.SimpleNamespace(
        camera_names=("a", "b"), cameras=[types.SimpleNamespace(intrinsics=studio.fisheye)] * 2,
        frames=lambda trial, name, *, stride, start, stop, gray: ((k, frames[k]) for k in range(start, min(stop, 10))))
    leave = np.zeros((10, 2), bool)
    leave[5, 1] = True
    second = rounds_for_the_rest(capture, "capture", result, leave, [[1], [0]], studio.index, starts=[0, 0], stride=1,
                                 first=0)
    assert second.registered.all() and second.states[5][1].how == "relative"
    assert len(second.rounds) >= 2 and second.new_point_ids
    rot_deg, pos_cm = _errors(studio.align, second.states[5][1].world_from_camera, poses[5])
    assert rot_deg < 0.5 and pos_cm < 2.0, (rot_deg, pos_cm)
    assert rounds_for_the_rest(capture, "capture", second, leave, [[1], [0]], studio.index, starts=[0, 0], stride=1,
                               first=0) is second  # nothing left
