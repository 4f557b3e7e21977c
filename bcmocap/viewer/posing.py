"""A motion posed on an editable model in numpy, so that the viewer redraws an edit at once.

Joint angles fix every segment's world orientation; the model (joint offsets, camera mounts) only
places the segments. :class:`Posing` therefore computes the world rotations of all frames once (the
kinematic chain of :mod:`bcmocap.kinematics.fk`, Eqs. 3–5) and re-places joints and cameras from any
offsets and mounts with a few array operations: a dragged joint centre or camera mount redraws the
whole trial in milliseconds, where a JAX call outside ``jit`` would take a second. Tests check it
against :func:`bcmocap.kinematics.fk.forward_kinematics` and :func:`bcmocap.kinematics.rig.camera_poses`.
"""

from __future__ import annotations

import numpy as np

from ..geometry import matrix_from_quat, quat_multiply


class Posing:
    """World rotations of a motion's segments, and joints and cameras placed from a model.

    Args:
        parents: ``(J,)`` parent index per segment (−1 for the root, parents before children).
        root_position: ``(T, 3)`` m.
        rotations: ``(T, J, 4)`` local joint rotations (wxyz).

    Attributes:
        world_rotations: ``(T, J, 4)`` wxyz; world_matrices ``(T, J, 3, 3)``.
    """

    def __init__(self, parents, root_position, rotations):
        self.parents = tuple(int(p) for p in parents)
        self.root_position = np.asarray(root_position, np.float64)
        local = np.asarray(rotations, np.float64)
        world = np.empty_like(local)
        world[:, 0] = local[:, 0]
        for j in range(1, len(self.parents)):
            world[:, j] = quat_multiply(world[:, self.parents[j]], local[:, j])
        self.world_rotations = world
        self.world_matrices = matrix_from_quat(world)

    @property
    def num_frames(self) -> int:
        return len(self.root_position)

    def joint_positions(self, offsets) -> np.ndarray:
        """``(T, J, 3)`` joint centres (segment origins, m) for ``offsets`` ``(J, 3)`` (row 0 unused)."""
        offsets = np.asarray(offsets, np.float64)
        out = np.empty((self.num_frames, len(self.parents), 3))
        out[:, 0] = self.root_position
        for j in range(1, len(self.parents)):
            p = self.parents[j]
            out[:, j] = out[:, p] + self.world_matrices[:, p] @ offsets[j]
        return out

    def camera_poses(self, joints: np.ndarray, segments, segment_from_camera) -> np.ndarray:
        """``(T, C, 7)`` world_from_camera (wxyz_xyz) of cameras on ``segments`` ``(C,)`` with mounts
        ``segment_from_camera`` ``(C, 7)``, given this posing's ``joints`` ``(T, J, 3)``."""
        seg = np.asarray(segments, int)
        mounts = np.asarray(segment_from_camera, np.float64)
        rotation = quat_multiply(self.world_rotations[:, seg], mounts[None, :, :4])
        centre = joints[:, seg] + np.einsum("tcij,cj->tci", self.world_matrices[:, seg], mounts[:, 4:])
        return np.concatenate([rotation, centre], axis=-1)
