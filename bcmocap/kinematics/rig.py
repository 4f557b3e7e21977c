"""Rigs: cameras mounted rigidly on skeleton segments.

Several cameras may share a segment (the paper puts three on the waist). All cameras of a rig use one
camera model class with per-camera parameters stacked on a leading axis, so projection vmaps over them.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..cameras import CameraModel, stack_cameras
from ..geometry import SE3
from .fk import forward_kinematics
from .skeleton import Motion, Skeleton


class Rig(eqx.Module):
    """Cameras on segments.

    Attributes:
        segment_from_camera: ``(C, 7)`` SE3 parameters of each mount (camera frame → segment frame).
        intrinsics: a camera model whose array leaves have a leading axis ``C``.
        names: camera names (unique).
        segments: segment index each camera is mounted on.
    """

    segment_from_camera: jax.Array
    intrinsics: CameraModel
    names: tuple[str, ...] = eqx.field(static=True)
    segments: tuple[int, ...] = eqx.field(static=True)

    def __init__(self, names: Sequence[str], segments: Sequence[int], segment_from_camera, intrinsics: CameraModel):
        names = tuple(str(n) for n in names)
        segments = tuple(int(s) for s in segments)
        n = len(names)
        if len(set(names)) != n:
            raise ValueError(f"Rig: duplicate camera names {sorted({x for x in names if names.count(x) > 1})}")
        if len(segments) != n:
            raise ValueError(f"Rig: {n} camera names but {len(segments)} segment indices")
        mounts = jnp.asarray(segment_from_camera, dtype=jnp.float64)
        if mounts.shape != (n, 7):
            raise ValueError(f"Rig: segment_from_camera must have shape ({n}, 7) (wxyz_xyz), got {mounts.shape}")
        leading = {np.shape(leaf)[0] if np.ndim(leaf) else None for leaf in jax.tree.leaves(intrinsics)}
        if leading != {n}:
            raise ValueError(f"Rig: intrinsics must be stacked over the {n} cameras (leading axis), got leading sizes {leading}")
        self.names = names
        self.segments = segments
        self.segment_from_camera = mounts
        self.intrinsics = intrinsics

    @classmethod
    def from_mounts(
        cls,
        skeleton: Skeleton,
        mounts: Sequence[tuple[str, str, SE3 | np.ndarray, CameraModel]],
    ) -> Rig:
        """Build a rig from ``(camera name, segment name, segment_from_camera, camera model)`` tuples."""
        if not mounts:
            raise ValueError("Rig.from_mounts: no cameras given")
        names, segs, poses, cams = [], [], [], []
        for name, segment, pose, camera in mounts:
            try:
                segs.append(skeleton.index(segment))
            except ValueError as err:
                raise ValueError(f"Rig: camera '{name}': {err}") from None
            names.append(name)
            poses.append(np.asarray(pose.wxyz_xyz if isinstance(pose, SE3) else pose, dtype=np.float64))
            cams.append(camera)
        return cls(names, segs, np.stack(poses), stack_cameras(cams))

    @property
    def num_cameras(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"unknown camera '{name}'; the rig has {list(self.names)}") from None

    def check(self, skeleton: Skeleton) -> None:
        """Raise ValueError if a camera is mounted on a segment the skeleton does not have."""
        for name, s in zip(self.names, self.segments):
            if not 0 <= s < skeleton.num_segments:
                raise ValueError(f"Rig: camera '{name}' is on segment {s}, the skeleton has {skeleton.num_segments}")

    def world_from_camera(self, world_from_segment: SE3) -> SE3:
        """Camera poses from segment poses ``(*S, J)`` → ``(*S, C)``."""
        seg = SE3(world_from_segment.wxyz_xyz[..., np.asarray(self.segments), :])
        return seg @ SE3(self.segment_from_camera)


def camera_poses(skeleton: Skeleton, rig: Rig, motion: Motion) -> SE3:
    """``world_from_camera`` with batch shape ``(*S, C)`` for a motion of batch shape ``S`` (Eq. 5)."""
    return rig.world_from_camera(forward_kinematics(skeleton, motion))
