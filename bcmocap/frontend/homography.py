"""Homographies for the frames registration leaves (§4.1, Eq. 2; issue 5 item 6).

Between consecutive frames of one camera the translation is neglected next to the scene's depth, so the
two frames are related by a rotation: a ray ``r_t`` of frame ``t`` is seen along ``r_{t-1} = R r_t`` in
frame ``t-1`` (``R = R_{t-1←t}``; for a pinhole lens the homography ``H = K R K⁻¹`` of Eq. 2). Fisheye
pixels are first unprojected to rays (the residual, :class:`~bcmocap.residuals.HomographyTransfer`, works
on rays too), and the homography is fitted by ``cv2.findHomography`` (RANSAC) on the rays' normalised
plane coordinates; the rotation nearest to it, refined on the inlier rays (Kabsch), is ``R``.

:func:`fill_with_homographies` does this for every pair of consecutive frames of a camera that touches an
unregistered frame: orientations of unregistered frames are chained forward from the last registered
frame and backward from the next one and averaged (slerp, weighted by the distance to each; one side
only at the ends), positions interpolated linearly between registered frames; the inlier pixel pairs
become the homography term's data.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cameras import CameraModel
from ..geometry import matrix_from_quat, quat_from_matrix, rotation_from_covariance, slerp
from ..io.colmap import to_pycolmap
from .reference import match_descriptors
from .relative import pixel_rays

__all__ = ["HomographyOptions", "HomographyFill", "rotation_between_frames", "fill_with_homographies"]


@dataclasses.dataclass(frozen=True)
class HomographyOptions:
    """Settings of the homography stage.

    Attributes:
        ratio: Lowe's ratio for frame-to-frame matches; ransac_px: RANSAC threshold (pixels, converted with
            the camera's focal length); min_inliers: fewest inliers for a pair to count.
    """

    ratio: float = 0.8
    ransac_px: float = 2.0
    min_inliers: int = 30


@dataclasses.dataclass
class HomographyFill:
    """What :func:`fill_with_homographies` found for ``T`` frames of ``C`` cameras.

    Attributes:
        world_from_camera: ``(T, C, 7)`` registered poses, and for unregistered frames the chained
            orientations with interpolated positions (NaN where a camera has no registered frame or a
            chain breaks on both sides).
        filled: ``(T, C)`` frames whose pose came from homographies.
        pixels, pixels_prev: ``{(t, c): (M, 2)}`` inlier pixels of frame ``t`` and ``t-1`` for unregistered ``t``.
        relative: ``{(t, c): (3, 3)}`` ``R_{t-1←t}`` of every pair estimated.
    """

    world_from_camera: np.ndarray
    filled: np.ndarray
    pixels: dict
    pixels_prev: dict
    relative: dict


def rotation_between_frames(pixels_prev: np.ndarray, pixels: np.ndarray, camera,
                            options: HomographyOptions = HomographyOptions()):
    """``R_{t-1←t}`` from matched pixels of frames ``t-1`` and ``t`` of one camera (module docstring).

    Args:
        pixels_prev, pixels: ``(K, 2)`` matched pixels (OpenCV convention).
        camera: :class:`~bcmocap.cameras.CameraModel` or ``pycolmap.Camera``.

    Returns:
        ``(R (3, 3), inlier mask (K,))`` or None with fewer than ``min_inliers`` inliers.
    """
    import cv2

    cam = to_pycolmap(camera) if isinstance(camera, CameraModel) else camera
    if len(pixels) < max(4, options.min_inliers):
        return None
    prev, cur = pixel_rays(cam, pixels_prev), pixel_rays(cam, pixels)
    focal = float(cam.mean_focal_length())
    h, mask = cv2.findHomography(cur[:, :2] / cur[:, 2:], prev[:, :2] / prev[:, 2:], cv2.RANSAC,
                                 options.ransac_px / focal, maxIters=2000, confidence=0.999)
    if h is None or mask is None:
        return None
    inl = mask.ravel().astype(bool)
    if inl.sum() < options.min_inliers:
        return None
    rot = rotation_from_covariance(prev[inl].T @ cur[inl])
    # Keep the rays the rotation transfers within the threshold (angle ≈ pixels / focal).
    inl = np.linalg.norm(prev - cur @ rot.T, axis=1) < options.ransac_px / focal
    if inl.sum() < options.min_inliers:
        return None
    return rotation_from_covariance(prev[inl].T @ cur[inl]), inl


def fill_with_homographies(registration, cameras, options: HomographyOptions = HomographyOptions()) -> HomographyFill:
    """Orientations, positions and homography data for the frames a
    :class:`~bcmocap.frontend.relative.CaptureRegistration` left unregistered (module docstring)."""
    states = registration.states
    num_t = len(states)
    num_c = len(cameras)
    cams = [to_pycolmap(c) if isinstance(c, CameraModel) else c for c in cameras]
    poses = np.array(registration.world_from_camera, np.float64).reshape(num_t, num_c, 7)
    registered = registration.registered.reshape(num_t, num_c)
    pixels, pixels_prev, relative = {}, {}, {}
    filled = np.zeros((num_t, num_c), bool)
    for c in range(num_c):
        for t in range(1, num_t):
            if registered[t, c] and registered[t - 1, c]:
                continue
            a, b = states[t - 1][c], states[t][c]
            m = match_descriptors(a.descriptors, b.descriptors, ratio=options.ratio).astype(np.int64)
            found = rotation_between_frames(a.keypoints[m[:, 0]], b.keypoints[m[:, 1]], cams[c], options) \
                if len(m) else None
            if found is None:
                continue
            rot, inl = found
            relative[(t, c)] = rot
            if not registered[t, c]:
                pixels[(t, c)] = b.keypoints[m[inl, 1]]
                pixels_prev[(t, c)] = a.keypoints[m[inl, 0]]
        known = np.flatnonzero(registered[:, c])
        if not len(known):
            continue
        rotations = matrix_from_quat(np.where(registered[:, c, None], poses[:, c, :4], [1.0, 0, 0, 0]))
        forward, backward = [None] * num_t, [None] * num_t
        for t in range(num_t):
            if registered[t, c]:
                forward[t] = (rotations[t], 0)
            elif t > 0 and forward[t - 1] is not None and (t, c) in relative:
                forward[t] = (forward[t - 1][0] @ relative[(t, c)], forward[t - 1][1] + 1)
        for t in range(num_t - 1, -1, -1):
            if registered[t, c]:
                backward[t] = (rotations[t], 0)
            elif t + 1 < num_t and backward[t + 1] is not None and (t + 1, c) in relative:
                backward[t] = (backward[t + 1][0] @ relative[(t + 1, c)].T, backward[t + 1][1] + 1)
        for t in np.flatnonzero(~registered[:, c]):
            f, b = forward[t], backward[t]
            if f is None and b is None:
                continue
            if f is not None and b is not None:
                q = slerp(np.asarray(quat_from_matrix(f[0])), np.asarray(quat_from_matrix(b[0])), f[1] / (f[1] + b[1]))
            else:
                q = quat_from_matrix((f or b)[0])
            before, after = known[known < t], known[known > t]
            if len(before) and len(after):
                t0, t1 = before[-1], after[0]
                pos = poses[t0, c, 4:] + (t - t0) / (t1 - t0) * (poses[t1, c, 4:] - poses[t0, c, 4:])
            else:
                pos = poses[(before[-1] if len(before) else after[0]), c, 4:]
            poses[t, c] = np.concatenate([np.asarray(q, np.float64), pos])
            filled[t, c] = True
    return HomographyFill(poses, filled, pixels, pixels_prev, relative)
