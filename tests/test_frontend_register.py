"""Tests for absolute registration (bcmocap.frontend.register): a rendered textured room, 8 pinhole
reference photos → reference model; FOV fisheye (170°) frames from known poses are registered and
compared with the truth after aligning the model to the world by a similarity (photo centres)."""

import types

import cv2
import numpy as np
import pycolmap
import pytest

from bcmocap.cameras import PinholeCamera
from bcmocap.frontend.reference import build_reference
from bcmocap.frontend.register import RegistrationOptions, reference_index, register_frame, register_trial
from bcmocap.geometry import similarity

pytestmark = pytest.mark.slow  # rendered frames through SIFT and registration


TEST_OPTIONS = RegistrationOptions()
from bcmocap.geometry import matrix_from_quat, quat_from_matrix
from bcmocap.sim import Renderer, fov_camera_for, make_textured_scene

W, H = 640, 480


def _look(position, yaw, pitch=-0.2):
    f = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    return np.concatenate([quat_from_matrix(np.stack([r, np.cross(f, r), f], axis=1)), position])


def _render(scene, camera, poses):
    poses = np.asarray(poses)
    rot = np.asarray(matrix_from_quat(poses[:, :4]))[:, None, None]
    return Renderer(scene, camera).render(rot, poses[:, None, None, 4:])


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    pycolmap.logging.minloglevel = 2
    folder = tmp_path_factory.mktemp("register")
    scene = make_textured_scene(np.array([[0.0, 0.0], [1.0, 0.0]]), seed=3, num_pillars=4, num_boxes=4)
    camera = PinholeCamera(width=W, height=H, focal=[400.0, 400.0], principal_point=[(W - 1) / 2, (H - 1) / 2])
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    poses = np.array([_look(np.array([0.5 + 0.4 * np.cos(a), 0.4 * np.sin(a), 1.6]), 0.3 * np.sin(a)) for a in angles])
    for i, image in enumerate(_render(scene, camera, poses)):
        cv2.imwrite(str(folder / f"p{i}.png"), np.ascontiguousarray(image[..., ::-1]))
    model = build_reference(folder, camera=camera, workdir=folder / "work", max_features=2000,
                            refine_intrinsics=False)
    assert model.num_registered == 8
    rec = model.reconstruction
    images = [rec.image(i) for i in rec.reg_image_ids()]
    est = np.array([im.projection_center() for im in images])
    true = np.array([poses[int(im.name[1:-4])][4:] for im in images])
    s, r, t = align = similarity(est, true)
    # A model from a wrong homography decomposition (seen before build_reference verified pairs at its
    # own RANSAC threshold) misplaces photos by tens of cm; a good one by a few mm.
    assert np.max(np.linalg.norm(s * est @ r.T + t - true, axis=1)) < 0.02
    fisheye = fov_camera_for(W, H)
    queries = np.array([_look(np.array([0.55, 0.1, 1.55]), 0.1, -0.1), _look(np.array([0.3, -0.2, 1.4]), -0.2, -0.25)])
    frames = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in _render(scene, fisheye, queries)]
    return types.SimpleNamespace(model=model, index=reference_index(model), align=align,
                                 fisheye=fisheye, queries=queries, frames=frames)


def _errors(align, estimate, truth):
    s, rot, shift = align
    centre = s * rot @ estimate[4:] + shift
    rel = np.asarray(matrix_from_quat(truth[:4])).T @ rot @ np.asarray(matrix_from_quat(estimate[:4]))
    angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
    return angle, 100 * np.linalg.norm(centre - truth[4:])


def test_reference_index_holds_observations_of_3d_points(studio):
    idx, rec = studio.index, studio.model.reconstruction
    assert idx.descriptors.shape == (len(idx.point3D_ids), 128) and idx.descriptors.dtype == np.float32
    assert len(set(idx.point3D_ids.tolist())) == rec.num_points3D()
    k = len(idx.point3D_ids) // 2
    assert np.allclose(idx.xyz[k], rec.point3D(int(idx.point3D_ids[k])).xyz)


def test_reference_index_is_the_same_for_a_model_read_back(studio, tmp_path):
    """A resumed run reads the reference model from disk, where its images are listed by id; the one just
    reconstructed lists them in registration order. The index's rows (FLANN's trees) must not differ."""
    import dataclasses

    studio.model.reconstruction.write(str(tmp_path))
    again = reference_index(dataclasses.replace(studio.model, reconstruction=pycolmap.Reconstruction(str(tmp_path))))
    assert np.array_equal(again.point3D_ids, studio.index.point3D_ids)
    assert np.array_equal(again.descriptors, studio.index.descriptors) and np.array_equal(again.xyz, studio.index.xyz)


def test_register_fisheye_frames_to_true_pose(studio):
    for frame, truth in zip(studio.frames, studio.queries):
        result = register_frame(frame, studio.fisheye, studio.index, TEST_OPTIONS)
        assert result.registered and result.num_inliers > 50 and result.mean_error_px < 2.0
        assert result.points2D.shape == (result.num_inliers, 2) and len(result.point3D_ids) == result.num_inliers
        assert np.isclose(np.linalg.norm(result.world_from_camera[:4]), 1.0)
        rot_deg, pos_cm = _errors(studio.align, result.world_from_camera, truth)
        assert rot_deg < 0.5 and pos_cm < 2.0, (rot_deg, pos_cm)
        # Inliers reproject through the model: the 3D points project near their 2D pixels.
        cam = studio.fisheye
        p = result.world_from_camera
        r = np.asarray(matrix_from_quat(p[:4]))
        xyz = np.array([studio.model.reconstruction.point3D(int(i)).xyz for i in result.point3D_ids])
        uv = np.asarray(cam.project((xyz - p[4:]) @ r)[0])
        assert np.median(np.linalg.norm(uv - result.points2D, axis=1)) < 1.0


def test_thresholds_reject(studio):
    strict = register_frame(studio.frames[0], studio.fisheye, studio.index, RegistrationOptions(min_inliers=100000))
    assert not strict.registered and np.isfinite(strict.world_from_camera).all()
    blank = register_frame(np.zeros((H, W), np.uint8), studio.fisheye, studio.index)
    assert not blank.registered and np.isnan(blank.world_from_camera).all() and blank.num_inliers == 0


def test_register_trial_with_stride_and_progress(studio):
    frames = [studio.frames[0], np.zeros((H, W), np.uint8), studio.frames[1]]
    camera = types.SimpleNamespace(name="cam0", intrinsics=studio.fisheye)

    class FakeCapture:  # the Capture methods register_trial uses
        cameras = (camera,)

        def camera_index(self, name):
            return 0

        def video_info(self, trial, name):
            return types.SimpleNamespace(num_frames=2 * len(frames))

        def frames(self, trial, name, *, stride, start, stop, gray):
            assert gray and stride == 2
            for k, image in enumerate(frames):
                yield start + stride * k, image

    calls = []
    out = register_trial(FakeCapture(), "capture", "cam0", studio.index, stride=2, options=TEST_OPTIONS,
                         progress=lambda done, total: calls.append((done, total)))
    assert out.frames.tolist() == [0, 2, 4] and out.poses.shape == (3, 7)
    assert out.registered.tolist() == [True, False, True] and out.registered_fraction == pytest.approx(2 / 3)
    assert np.isnan(out.poses[1]).all() and np.isfinite(out.poses[[0, 2]]).all()
    assert calls == [(1, 3), (2, 3), (3, 3)]


def test_neighbours_offer_registered_cameras_nearest_in_view_first():
    from bcmocap.frontend.relative import CameraFrameRegistration, _neighbours

    def state(yaw_deg=None):
        if yaw_deg is None:  # unregistered
            return CameraFrameRegistration(np.zeros((0, 2)), np.zeros((0, 128), np.uint8), np.zeros(0, np.int64),
                                           np.full(7, np.nan))
        half = np.radians(yaw_deg) / 2  # about the camera's y axis: the optical axis turns in the x-z plane
        return CameraFrameRegistration(np.zeros((0, 2)), np.zeros((0, 128), np.uint8), np.zeros(0, np.int64),
                                       np.array([np.cos(half), 0, np.sin(half), 0, 0, 0, 0]), how="absolute", round=0)

    # Frame 1 of camera 0 is unregistered; camera 0 looked along yaw 0 at frame 0. At frame 1, cameras
    # 1 and 2 are unregistered and must not take the slots; 3 (yaw 100) is beyond 90 degrees.
    yaws = [[0, 60, 40, 100, 10, 30], [None, None, None, 100, 10, 30]]
    states = [[state(y) for y in row] for row in yaws]
    got = list(_neighbours(1, 0, 2, 6, 1, states, 90.0, 2))
    assert got == [(1, 4), (1, 5), (0, 0)]
    # A camera with no registered frame at all: every registered camera at that time, in camera order.
    states[0][0] = state(None)
    assert list(_neighbours(1, 0, 2, 6, 1, states, 90.0, 2)) == [(1, 3), (1, 4), (1, 5), (0, 0)]
    # Without states (no poses known yet): the first max_others other cameras.
    assert list(_neighbours(1, 0, 2, 6, 0, None, 90.0, 2)) == [(1, 1), (1, 2)]


def test_triangulate_rays_meets_the_point():
    from bcmocap.frontend.relative import triangulate_rays

    point = np.array([1.0, 2.0, 3.0])
    centres = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]])
    rays = (point - centres) / np.linalg.norm(point - centres, axis=1, keepdims=True)
    assert np.allclose(triangulate_rays(centres, rays), point)
    assert triangulate_rays(np.stack([centres, centres + 1]), np.stack([rays, rays])).shape == (2, 3)
    # A camera that stood still: identical rays meet nowhere in particular (NaN, not an exception).
    same = triangulate_rays(np.stack([centres[:2], centres[[0, 0]]]), np.stack([rays[:2], rays[[0, 0]]]))
    assert np.allclose(same[0], point) and np.isnan(same[1]).all()


@pytest.fixture(scope="module")
def turned_rig(studio):
    """Two frames of three body cameras, the third turned away from the reference photos' views (yaw 1.6
    rad): ``(features[t][c] = (keypoints, descriptors), true poses (2, 3, 7))``."""
    from bcmocap.frontend.reference import extract_sift

    scene = make_textured_scene(np.array([[0.0, 0.0], [1.0, 0.0]]), seed=3, num_pillars=4, num_boxes=4)
    yaws = [0.1, 0.8, 1.6]
    # Cameras 0.25 m from the body's centre, as on a person: baselines between cameras at one time.
    poses = np.array([[_look(np.array([0.4 + 0.1 * k + 0.25 * np.cos(y), 0.05 * k + 0.25 * np.sin(y), 1.5]), y, -0.1)
                       for y in yaws] for k in range(2)])
    features = []
    for row in poses:
        images = _render(scene, studio.fisheye, row)
        features.append([(kp[:, :2], desc) for kp, desc in
                         (extract_sift(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)) for im in images)])
    return features, poses


def test_relative_registration_reaches_frames_the_reference_does_not_see(studio, turned_rig):
    """Body frames turned away from the reference photos' views (yaw 1.6 rad) fail absolute registration;
    new points triangulated between the registered frames register them relatively, accurately."""
    from bcmocap.frontend.relative import register_capture

    features, poses = turned_rig
    calls = []
    out = register_capture(features, [studio.fisheye] * 3, studio.index,
                           progress=lambda stage, done, total: calls.append(stage))
    how = [[s.how for s in row] for row in out.states]
    assert how == [["absolute", "absolute", "relative"]] * 2, how
    assert out.registered_fraction == 1.0 and out.rounds[1]["registered"] == 2 and out.rounds[1]["new_points"] > 500
    assert out.registered.shape == (2, 3) and out.world_from_camera.shape == (2, 3, 7)
    for k in range(2):
        for c in range(3):
            rot_deg, pos_cm = _errors(studio.align, out.states[k][c].world_from_camera, poses[k, c])
            assert rot_deg < 0.5 and pos_cm < 2.0, (k, c, rot_deg, pos_cm)
    # New points sit where the frames see them: each observation reprojects within the threshold.
    s = out.states[1][2]
    has = np.flatnonzero(s.point_ids >= 0)
    xyz = np.array([out.points[int(p)] for p in s.point_ids[has]])
    p = s.world_from_camera
    uv = np.asarray(studio.fisheye.project((xyz - p[4:]) @ np.asarray(matrix_from_quat(p[:4])))[0])
    assert np.median(np.linalg.norm(uv - s.keypoints[has], axis=1)) < 1.0
    assert calls[0] == "absolute" and "relative round 1" in calls
    corr = out.correspondences(fps=60.0)
    assert corr.point_ids.shape[:2] == (2, 3) and corr.registered.all() and corr.fps == 60.0
    k = corr.point_ids[1, 2] >= 0
    assert k.sum() == len(has) and np.allclose(corr.points[corr.point_ids[1, 2, k]], xyz)
    assert np.allclose(corr.pixels[1, 2, k], s.keypoints[has]) and np.all(corr.weights[1, 2, k] == 1.0)
    # points="reference": only the reference model's points are measured (the turned camera, registered through
    # new points, keeps far fewer)
    assert out.reference_point_ids == frozenset(int(i) for i in studio.index.point3D_ids)
    ref = out.correspondences(fps=60.0, points="reference")
    measured = ref.weights > 0
    reference_xyz = {tuple(x) for x in np.round(studio.index.xyz, 9)}
    assert all(tuple(x) in reference_xyz for x in np.round(ref.points[ref.point_ids[measured]], 9))
    for t in range(2):
        for c in range(3):
            assert measured[t, c].sum() == int(np.isin(out.states[t][c].point_ids, studio.index.point3D_ids).sum())
    assert measured[1, 2].sum() < 0.5 * (corr.weights[1, 2] > 0).sum()
    with pytest.raises(ValueError, match="points must be 'all' or 'reference'"):
        out.correspondences(fps=60.0, points="some")
    with pytest.raises(ValueError, match="features hold 3 cameras per frame, cameras 2"):
        register_capture(features, [studio.fisheye] * 2, studio.index)


def test_extract_trial_features_reads_every_camera_from_its_start(studio, tmp_path):
    from bcmocap.frontend.relative import extract_trial_features

    reads = []

    class FakeCapture:
        camera_names = ("a", "b")

        def correction_settings(self, trial):  # no correction of the frames
            return {}

        def video_info(self, trial, name):
            return types.SimpleNamespace(num_frames={"a": 5, "b": 7}[name])

        def frames(self, trial, name, *, stride, start, stop, gray):
            reads.append((name, start, stop, stride))
            for k in range(start, stop, stride):
                yield k, studio.frames[k % 2]

    calls = []
    out = extract_trial_features(FakeCapture(), "capture", starts=[1, 2], stride=2,
                                 progress=lambda done, total: calls.append((done, total)))
    assert sorted(reads) == [("a", 1, 5, 2), ("b", 2, 6, 2)]  # 4 frames from each start: the shorter video's count
    assert len(out) == 2 and len(out[0]) == 2 and out[0][0][0].shape[1] == 2 and out[0][0][1].shape[1] == 128
    assert calls[-1] == (4, 4)
    with pytest.raises(ValueError, match=r"starts must have shape \(2,\)"):
        extract_trial_features(FakeCapture(), "capture", starts=[0])
    # Cached: the second call decodes nothing and returns the same features; other settings recompute.
    first = extract_trial_features(FakeCapture(), "capture", starts=[1, 2], stride=2, cache_dir=tmp_path)
    reads.clear()
    again = extract_trial_features(FakeCapture(), "capture", starts=[1, 2], stride=2, cache_dir=tmp_path)
    assert reads == [] and sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]
    assert isinstance(again[0][0][1].base, np.memmap) or isinstance(again[0][0][1], np.memmap)
    assert all(np.array_equal(x[0], y[0]) and np.array_equal(x[1], y[1])
               for rx, ry in zip(first, again) for x, y in zip(rx, ry))
    extract_trial_features(FakeCapture(), "capture", starts=[1, 2], stride=1, cache_dir=tmp_path)
    assert [r[3] for r in reads] == [1, 1]


def test_chunks_are_equal_and_no_longer_than_asked():
    from bcmocap.frontend.command import chunk_bounds

    assert chunk_bounds(315, 400) == chunk_bounds(315, 0) == [(0, 315)]
    assert chunk_bounds(401, 400) == [(0, 200), (200, 401)]
    assert chunk_bounds(10, 3) == [(0, 2), (2, 5), (5, 8), (8, 10)]
    assert chunk_bounds(2, 1) == [(0, 1), (1, 2)]


def test_a_trial_registered_in_chunks_is_saved_chunk_by_chunk_and_resumed(studio, turned_rig, tmp_path, monkeypatch):
    """process_trial with chunk_frames: each chunk registered on its own and written as it is done, the
    trial's correspondences the chunks end to end; a rerun reuses the chunks instead of registering."""
    import json

    import bcmocap.frontend.relative as relative
    from bcmocap.correspondence_store import CorrespondenceStore
    from bcmocap.correspondences import Correspondences
    from bcmocap.frontend.command import TrialOptions, process_trial

    features, poses = turned_rig
    names = ("a", "b", "c")
    capture = types.SimpleNamespace(
        camera_names=names, fps=60.0, cameras=[types.SimpleNamespace(name=n, intrinsics=studio.fisheye) for n in names],
        video_info=lambda trial, name: types.SimpleNamespace(num_frames=2), correction_settings=lambda trial: {},
        lens_fingerprint=lambda: "lenses")
    monkeypatch.setattr(relative, "extract_trial_features", lambda *args, **kwargs: features)
    quiet = dict(offsets=[0, 0, 0], log=lambda line: None)
    whole_trial = TrialOptions(homographies=False, registration="global")
    by_frame = TrialOptions(homographies=False, registration="global", chunk_frames=1)
    whole = process_trial(capture, studio.index, "capture", tmp_path / "whole", whole_trial, **quiet)
    chunked = process_trial(capture, studio.index, "capture", tmp_path / "chunked", by_frame, **quiet)
    a = CorrespondenceStore.open(tmp_path / "whole" / "capture" / "correspondences").load()
    b = CorrespondenceStore.open(tmp_path / "chunked" / "capture" / "correspondences").load()
    assert whole["registered_fraction"] == chunked["registered_fraction"] == 1.0
    assert b.point_ids.shape[:2] == (2, 3) and b.fps == 60.0 and chunked["chunk_frames"] == 1
    assert len(chunked["rounds"]) == 2 and chunked["registered_absolute"] == 4 and chunked["registered_relative"] == 2
    for t in range(2):
        part = Correspondences.load(tmp_path / "chunked" / "capture" / "chunks" / f"{t:04d}.npz")
        assert json.loads((tmp_path / "chunked" / "capture" / "chunks" / f"{t:04d}.json").read_text())["frames"] == [t, t + 1]
        assert np.array_equal(part.registered[0], b.registered[t])
        for c in range(3):
            rot_deg, pos_cm = _errors(studio.align, b.world_from_camera[t, c], poses[t, c])
            # 2.15 cm at worst (a frame registered relative to one other, on ~100 points); which of FLANN's
            # approximate matches it gets depends on the reference index's row order
            assert rot_deg < 0.5 and pos_cm < 2.5, (t, c, rot_deg, pos_cm)
            has = b.point_ids[t, c] >= 0
            assert has.sum() == (part.point_ids[0, c] >= 0).sum() > 50
            # Each chunk's points follow the previous chunks' in the merged trial.
            assert np.allclose(b.points[b.point_ids[t, c, has]], part.points[part.point_ids[0, c, part.point_ids[0, c] >= 0]])
        assert a.world_from_camera.shape == b.world_from_camera.shape

    def no_registration(*args, **kwargs):
        raise AssertionError("a saved chunk was registered again")

    monkeypatch.setattr(relative, "register_capture", no_registration)
    again = process_trial(capture, studio.index, "capture", tmp_path / "chunked", by_frame, **quiet)
    assert again["registered_fraction"] == 1.0 and again["rounds"] == chunked["rounds"]
