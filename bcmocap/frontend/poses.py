"""Camera pose helpers shared by the registration modules (:mod:`.register`, :mod:`.relative`, :mod:`.tracking`).

- :func:`estimate_pose`: a camera's pose from 2D–3D correspondences (pycolmap's LO-RANSAC P3P and refinement),
  accepted by the thresholds of :class:`~.register.RegistrationOptions`;
- :func:`world_from_camera_wxyz_xyz`: a pycolmap ``cam_from_world`` as bcmocap's ``world_from_camera``
  ``wxyz_xyz``;
- :func:`nearest_point`: the point nearest (least squares) to a set of rays, from their normal equations.

Pixels are in OpenCV's convention (COLMAP's +0.5 px is applied only at the pycolmap calls).
"""

from __future__ import annotations

import numpy as np

from ..native_crashes import load_pycolmap

__all__ = ["estimate_pose", "nearest_point", "world_from_camera_wxyz_xyz"]


def estimate_pose(xy: np.ndarray, xyz: np.ndarray, cam, options):
    """Absolute pose of a camera from 2D–3D correspondences: pycolmap LO-RANSAC (seeded) + refinement.

    Args:
        xy: ``(K, 2)`` pixels (OpenCV convention) of the correspondences.
        xyz: ``(K, 3)`` their 3D points in the world (reference model) frame.
        cam: the ``pycolmap.Camera``.
        options: a :class:`~.register.RegistrationOptions` (not imported here: :mod:`.register` imports this
            module): ``ransac_max_error_px`` is RANSAC's inlier threshold (px); the pose is accepted with more
            than ``min_inliers`` inliers and a mean inlier reprojection error below ``max_mean_error_px`` (px).

    Returns:
        ``(cam_from_world, inlier mask (K,) bool, mean inlier reprojection error in px)``, with
        ``cam_from_world`` a ``pycolmap.Rigid3d``; None with fewer than 4 correspondences, when RANSAC fails
        or when the thresholds reject the pose.
    """
    pycolmap = load_pycolmap()

    if len(xy) < 4:
        return None
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = options.ransac_max_error_px
    est.ransac.random_seed = 0  # the same matches give the same pose (COLMAP's default, -1, seeds at random)
    result = pycolmap.estimate_and_refine_absolute_pose(xy + 0.5, xyz, cam, est)
    if result is None:
        return None
    inl = np.asarray(result["inlier_mask"], bool).reshape(-1)
    pose = result["cam_from_world"]
    proj = np.asarray(cam.img_from_cam(np.asarray(pose * xyz[inl])), np.float64) - 0.5
    err = float(np.nanmean(np.linalg.norm(proj - xy[inl], axis=1))) if inl.any() else np.inf
    if not (int(inl.sum()) > options.min_inliers and err < options.max_mean_error_px):
        return None
    return pose, inl, err


def world_from_camera_wxyz_xyz(cam_from_world) -> np.ndarray:
    """A pycolmap ``cam_from_world`` (``pycolmap.Rigid3d``) inverted to bcmocap's convention.

    Returns:
        ``(7,)`` float64 ``world_from_camera``: unit quaternion ``wxyz``, then the camera centre ``xyz`` in the
        world frame (the units of the world, e.g. the reference model's).
    """
    world_from_cam = cam_from_world.inverse()
    x, y, z, w = np.asarray(world_from_cam.rotation.quat, np.float64)  # Eigen order xyzw
    return np.concatenate([[w, x, y, z], np.asarray(world_from_cam.translation, np.float64)])


def nearest_point(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The point nearest (least squares) to a set of rays, from their normal equations ``a x = b``.

    Args:
        a: ``(..., 3, 3)`` the sum over the rays of their orthogonal projectors ``I − d dᵀ`` (unit world
            directions ``d``).
        b: ``(..., 3)`` the sum over the rays of ``(I − d dᵀ) c`` (world centres ``c``).

    Returns:
        ``(..., 3)`` world points; NaN where the rays are parallel (``det a ≤ 1e-12``; two rays at angle θ:
        ``det a = 2 sin²θ``).
    """
    ok = np.linalg.det(a) > 1e-12
    x = np.linalg.solve(np.where(ok[..., None, None], a, np.eye(3)), b[..., None])[..., 0]
    return np.where(ok[..., None], x, np.nan)
