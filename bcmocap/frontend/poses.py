"""Camera pose helpers shared by the registration modules (:mod:`.register`, :mod:`.relative`, :mod:`.tracking`).

- :func:`estimate_pose`: a camera's pose from 2D–3D correspondences (pycolmap's LO-RANSAC P3P and refinement),
  accepted by the thresholds of :class:`~.register.RegistrationOptions` and refused where they support a
  :func:`second_pose` (a repeated pattern);
- :func:`world_from_camera_wxyz_xyz`: a pycolmap ``cam_from_world`` as bcmocap's ``world_from_camera``
  ``wxyz_xyz``;
- :func:`nearest_point`: the point nearest (least squares) to a set of rays, from their normal equations.

Pixels are in OpenCV's convention (COLMAP's +0.5 px is applied only at the pycolmap calls).
"""

from __future__ import annotations

import numpy as np

from ..native_crashes import load_pycolmap

__all__ = ["estimate_pose", "nearest_point", "second_pose", "world_from_camera_wxyz_xyz"]


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
        ``cam_from_world`` a ``pycolmap.Rigid3d``; None with fewer than 4 correspondences, when RANSAC fails,
        when the thresholds reject the pose, or when the correspondences support a :func:`second_pose`.
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
    if second_pose(xy, xyz, inl, pose, cam, options) is not None:
        return None
    return pose, inl, err


def second_pose(xy: np.ndarray, xyz: np.ndarray, inliers: np.ndarray, cam_from_world, cam, options):
    """A second pose, elsewhere, that the correspondences the first leaves out support with a good share of its
    inliers (a quarter by default): the sign of a repeated pattern.

    A floor of identical tiles or a wall of identical bricks matches each feature to one copy of its pattern
    chosen by chance, and the pose with most inliers is then often a copy's: the right rotation, the centre
    moved by a period of the pattern (the repeated room's limb cameras, standing over its floor, registered
    0.6–3 m off in every frame; the pose from the matches the first pose leaves had 33–95 % of its inliers; a
    right pose's second had up to 83 % in that room and at most 8 % in the sparse one). RANSAC is run again on the
    correspondences the first pose leaves out.

    Args:
        xy, xyz: ``(K, 2)`` pixels (OpenCV convention) and ``(K, 3)`` points of the correspondences.
        inliers: ``(K,)`` the first pose's inliers; cam_from_world: that pose (``pycolmap.Rigid3d``).
        cam: the ``pycolmap.Camera``; options: :class:`~.register.RegistrationOptions` (its
            ``ambiguity_ratio``: 0 turns the check off).

    Returns:
        ``(cam_from_world, inliers)`` of a second pose with at least ``ambiguity_ratio`` of the first's inliers
        whose centre lies more than ``ambiguity_shift`` of the first inliers' median depth away from the first's
        (its ``inliers`` a mask over the correspondences the first left out, ``(K − first's inliers,)``), or None
        (also without first inliers or with a ratio that is not positive).
    """
    pycolmap = load_pycolmap()

    ratio = float(getattr(options, "ambiguity_ratio", 0.0))
    inliers = np.asarray(inliers, bool).reshape(-1)
    if not (np.isfinite(ratio) and ratio > 0) or not inliers.any():
        return None
    need = int(np.ceil(ratio * int(inliers.sum())))
    rest = ~inliers
    if rest.sum() < max(need, 4):
        return None
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = options.ransac_max_error_px
    est.ransac.random_seed = 0
    # A second pose only counts with ``need`` inliers among the rest: RANSAC stops once that share is ruled out
    # (without this it searched the outliers of every right pose to its cap: 10× the first search's time).
    est.ransac.min_inlier_ratio = 0.9 * need / int(rest.sum())
    result = pycolmap.estimate_and_refine_absolute_pose(xy[rest] + 0.5, xyz[rest], cam, est)
    if result is None:
        return None
    inl = np.asarray(result["inlier_mask"], bool).reshape(-1)
    if int(inl.sum()) < need:
        return None
    depth = float(np.median(np.asarray(cam_from_world * xyz[inliers], np.float64)[:, 2]))
    if not np.isfinite(depth):
        return None
    first = np.asarray(cam_from_world.inverse().translation, np.float64)
    second = np.asarray(result["cam_from_world"].inverse().translation, np.float64)
    if np.linalg.norm(second - first) <= options.ambiguity_shift * abs(depth):
        return None
    return result["cam_from_world"], inl


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
