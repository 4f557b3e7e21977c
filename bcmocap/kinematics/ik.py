"""Initial motion from registered camera poses (§4.2, "Forward kinematics from camera poses").

Each segment's world orientation is the average over the cameras mounted on it of
``world_from_camera · camera_from_segment``; joint rotations are relative orientations of parent and
child segments along the chain (projected on hinge axes); the root position comes from the root
segment's cameras only, as in the paper. Frames where a segment has no registered camera are filled
by interpolation in time (slerp for rotations, linear for positions), nearest frame at the ends.
With ``robust=True`` a segment's cameras are averaged like a virtual camera (§4.2): a Tukey-reweighted
mean, so one camera of three that registered badly at a frame is outvoted.
"""

from __future__ import annotations

import numpy as np

from ..geometry import SE3, SO3, average_quaternions, slerp
from .rig import Rig
from .skeleton import Motion, Skeleton
from .virtual import robust_average_poses


def fill_gaps(values: np.ndarray, known: np.ndarray, rotations: bool) -> np.ndarray:
    """Interpolate ``(T, k)`` values over frames where ``known`` ``(T,)`` is False.

    Linear interpolation, or slerp when ``rotations`` (rows are (w, x, y, z) unit quaternions); frames
    before the first or after the last known one hold that value.
    """
    t_known = np.flatnonzero(known)
    out = values.copy()
    if len(t_known) == len(known):
        return out
    for t in np.flatnonzero(~known):
        after = np.searchsorted(t_known, t)
        if after == 0:
            out[t] = values[t_known[0]]
        elif after == len(t_known):
            out[t] = values[t_known[-1]]
        else:
            t0, t1 = t_known[after - 1], t_known[after]
            frac = (t - t0) / (t1 - t0)
            out[t] = slerp(values[t0], values[t1], frac) if rotations else (1 - frac) * values[t0] + frac * values[t1]
    return out


def motion_from_camera_poses(
    skeleton: Skeleton, rig: Rig, world_from_camera: np.ndarray, registered: np.ndarray, *, robust: bool = False
) -> Motion:
    """Root pose and joint rotations from registered camera poses.

    Args:
        skeleton, rig: the model with known camera mounts.
        world_from_camera: ``(T, C, 7)`` camera poses (wxyz_xyz).
        registered: ``(T, C)`` bool, which poses are known.
        robust: average a segment's cameras robustly (matters from three cameras on a segment).

    Returns:
        A ``(T, J)`` motion. Segments without any camera keep the rest rotation.

    Raises:
        ValueError: shapes do not match the rig, or the root segment has no registered camera at all.
    """
    world_from_camera = np.asarray(world_from_camera, dtype=np.float64)
    registered = np.asarray(registered, dtype=bool)
    t, c = registered.shape if registered.ndim == 2 else (world_from_camera.shape[0], rig.num_cameras)
    if registered.ndim != 2:
        c = -1  # force the shape error below
    if world_from_camera.shape != (t, c, 7) or c != rig.num_cameras:
        raise ValueError(
            f"motion_from_camera_poses: expected world_from_camera ({t}, {rig.num_cameras}, 7) and registered "
            f"({t}, {rig.num_cameras}), got {world_from_camera.shape} and {registered.shape}"
        )
    world_from_segment = np.asarray(
        (SE3(world_from_camera) @ SE3(np.asarray(rig.segment_from_camera)[None]).inverse()).wxyz_xyz
    )
    n = skeleton.num_segments
    seg_rot = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (t, n, 1))
    has_camera = np.zeros(n, bool)
    root_position = None
    for j in range(n):
        cams = [k for k, s in enumerate(rig.segments) if s == j]
        if not cams:
            continue
        known = registered[:, cams].any(axis=1)
        if not known.any():
            if j == 0:
                raise ValueError("motion_from_camera_poses: the root segment's cameras are never registered")
            continue
        has_camera[j] = True
        if robust and len(cams) > 2:
            mean, _ = robust_average_poses(world_from_segment[:, cams], registered[:, cams])
            seg_rot[:, j] = fill_gaps(np.where(known[:, None], mean[:, :4], 0.0), known, rotations=True)
            if j == 0:
                root_position = fill_gaps(np.where(known[:, None], mean[:, 4:], 0.0), known, rotations=False)
            continue
        q = np.zeros((t, 4))
        for frame in np.flatnonzero(known):
            use = [k for k in cams if registered[frame, k]]
            q[frame] = average_quaternions(world_from_segment[frame, use, :4])
        seg_rot[:, j] = fill_gaps(q, known, rotations=True)
        if j == 0:
            p = np.zeros((t, 3))
            for frame in np.flatnonzero(known):
                use = [k for k in cams if registered[frame, k]]
                p[frame] = world_from_segment[frame, use, 4:].mean(axis=0)
            root_position = fill_gaps(p, known, rotations=False)
    if root_position is None:
        raise ValueError("motion_from_camera_poses: no camera is mounted on the root segment")
    # segments without cameras inherit their parent's orientation (identity local rotation)
    for j in range(1, n):
        if not has_camera[j]:
            seg_rot[:, j] = seg_rot[:, skeleton.parents[j]]
    parents = np.array([max(p, 0) for p in skeleton.parents])
    local = np.array((SO3(seg_rot[:, parents]).inverse() @ SO3(seg_rot)).wxyz)
    local[:, 0] = seg_rot[:, 0]
    local = np.asarray(skeleton.project_rotations(local))
    return Motion(root_position, local)
