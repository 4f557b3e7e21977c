"""Homographies for unregistered frames (bcmocap.frontend.homography): a camera turning in a far scene."""

import numpy as np
import pytest

from bcmocap.frontend.homography import fill_with_homographies, rotation_between_frames
from bcmocap.frontend.relative import CameraFrameRegistration, CaptureRegistration
from bcmocap.geometry import matrix_from_quat, quat_from_matrix
from bcmocap.sim import fov_camera_for

CAMERA = fov_camera_for(640, 480)


def _yaw(angle):
    c, s = np.cos(angle), np.sin(angle)
    # Camera z (optical axis) horizontal along (cos, sin, 0), y down.
    return np.array([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])


def _scene(rng, count=600):
    d = rng.normal(size=(count, 3))
    d[:, 2] *= 0.4
    return 10.0 * d / np.linalg.norm(d, axis=1, keepdims=True)


def _observe(points, descriptors, rot, centre, rng, noise_px=0.2):
    local = (points - centre) @ rot
    uv, valid = CAMERA.project(local)
    uv, valid = np.asarray(uv), np.asarray(valid) & (local[:, 2] > 0.2)
    keep = np.flatnonzero(valid & (uv[:, 0] > 0) & (uv[:, 0] < 639) & (uv[:, 1] > 0) & (uv[:, 1] < 479))
    return uv[keep] + rng.normal(scale=noise_px, size=(len(keep), 2)), descriptors[keep]


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1)))


def test_rotation_between_frames_recovers_a_turn():
    rng = np.random.default_rng(0)
    points = _scene(rng)
    desc = rng.random((len(points), 128)).astype(np.float32)
    r0, r1 = _yaw(0.2), _yaw(0.26)
    uv0, d0 = _observe(points, desc, r0, np.zeros(3), rng)
    uv1, d1 = _observe(points, desc, r1, np.array([0.01, 0.0, 0.0]), rng)
    ids0 = {tuple(v): i for i, v in enumerate(d0[:, :4])}
    pairs = np.array([(ids0[tuple(v)], j) for j, v in enumerate(d1[:, :4]) if tuple(v) in ids0])
    # Every tenth match is wrong: RANSAC must reject them.
    wrong = pairs[::10, 0].copy()
    pairs[::10, 0] = np.roll(wrong, 1)
    rot, inliers = rotation_between_frames(uv0[pairs[:, 0]], uv1[pairs[:, 1]], CAMERA)
    assert _angle_deg(rot, r0.T @ r1) < 0.05  # R_{0<-1} maps frame-1 rays to frame-0 rays
    assert not inliers[::10].any() and inliers.mean() > 0.85
    assert rotation_between_frames(uv0[:10], uv1[:10], CAMERA) is None


def test_fill_with_homographies_chains_orientations_and_interpolates_positions():
    rng = np.random.default_rng(1)
    points = _scene(rng)
    desc = rng.random((len(points), 128)).astype(np.float32)
    yaws = 0.1 + 0.05 * np.arange(6)
    centres = np.stack([0.01 * np.arange(6), np.zeros(6), np.zeros(6)], 1)
    registered = [True, False, False, False, True, False]
    states = []
    for t in range(6):
        uv, d = _observe(points, desc, _yaw(yaws[t]), centres[t], rng)
        pose = np.concatenate([np.asarray(quat_from_matrix(_yaw(yaws[t]))), centres[t]])
        states.append([CameraFrameRegistration(uv, d, np.full(len(uv), -1),
                                               pose if registered[t] else np.full(7, np.nan),
                                               "absolute" if registered[t] else "")])
    reg = CaptureRegistration(np.arange(6), states, {}, set(), [])
    fill = fill_with_homographies(reg, [CAMERA])
    assert fill.filled[:, 0].tolist() == [False, True, True, True, False, True]
    for t in (1, 2, 3, 5):
        assert _angle_deg(matrix_from_quat(fill.world_from_camera[t, 0, :4]), _yaw(yaws[t])) < 0.1, t
        assert (t, 0) in fill.pixels and len(fill.pixels[(t, 0)]) == len(fill.pixels_prev[(t, 0)]) > 30
    assert np.allclose(fill.world_from_camera[2, 0, 4:], centres[2])  # halfway between frames 0 and 4
    assert np.allclose(fill.world_from_camera[5, 0, 4:], centres[4])  # held after the last registered frame
    assert (4, 0) in fill.relative and (4, 0) not in fill.pixels  # frame 4 is registered: no homography data
    assert np.allclose(fill.world_from_camera[[0, 4], 0], [s[0].world_from_camera for s in (states[0], states[4])])

    corr = reg.correspondences(fps=30.0, homographies=fill)
    assert corr.homography_weights.shape[:2] == (6, 1) and (corr.homography_weights[[0, 4]] == 0).all()
    k = corr.homography_weights[2, 0] > 0
    assert k.sum() == len(fill.pixels[(2, 0)]) and np.allclose(corr.homography_pixels_prev[2, 0, k], fill.pixels_prev[(2, 0)])
