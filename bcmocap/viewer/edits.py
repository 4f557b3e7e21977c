"""Hand edits of a model, as in the paper's GUI (000 §4.2): a joint centre or a camera mount moved, and checked.

A model is the skeleton's joint offsets and the rig's camera mounts. Moving a **joint centre** by Δ
(world, at the frame shown) moves that joint in its parent's frame and, at that frame, leaves everything
else where it was: the children's joints and the segment's cameras keep their world positions there, so
only the estimate of the joint's location changes (in other frames they follow the segment's rotation
about the new centre). Moving a **camera mount** gives the camera a new pose relative to its segment.
The root's position belongs to the motion, not to the model, so it cannot be moved here.

An edit is refused (with a message for the panel) when it shortens a bone below :data:`MIN_BONE_M`, or
leaves a camera on the wrong side of the body: within :data:`MIN_CAMERA_DISTANCE_M` of
its segment's bone (inside the limb) or looking into it (its optical axis pointing towards the bone).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..geometry import matrix_from_quat, quat_conjugate, quat_multiply

#: Shortest bone an edit may leave (m).
MIN_BONE_M = 0.01
#: Closest a camera centre may be to its segment's bone (m).
MIN_CAMERA_DISTANCE_M = 0.01


@dataclasses.dataclass(frozen=True)
class EditableModel:
    """Offsets and mounts of a skeleton and rig, as numpy arrays.

    Attributes:
        names: segment names; parents ``(J,)``; offsets ``(J, 3)`` m in the parent frame (row 0 unused).
        camera_names; camera_segments ``(C,)``; mounts ``(C, 7)`` segment_from_camera (wxyz_xyz, m).
    """

    names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets: np.ndarray
    camera_names: tuple[str, ...]
    camera_segments: tuple[int, ...]
    mounts: np.ndarray

    @classmethod
    def of(cls, skeleton, rig=None) -> EditableModel:
        """From a :class:`~bcmocap.kinematics.Skeleton` and an optional :class:`~bcmocap.kinematics.rig.Rig`."""
        return cls(tuple(skeleton.names), tuple(skeleton.parents), np.array(skeleton.offsets, np.float64),
                   tuple(rig.names) if rig is not None else (), tuple(rig.segments) if rig is not None else (),
                   np.array(rig.segment_from_camera, np.float64) if rig is not None else np.zeros((0, 7)))

    def applied_to(self, skeleton, rig=None):
        """``(skeleton, rig)`` with this model's offsets and mounts (topology, joint types, hinge axes and
        intrinsics from the given ones)."""
        from ..kinematics.rig import Rig
        from ..kinematics.skeleton import Skeleton

        edited = Skeleton(skeleton.names, skeleton.parents, self.offsets, skeleton.joint_types, skeleton.hinge_axes)
        if rig is None:
            return edited, None
        return edited, Rig(rig.names, rig.segments, self.mounts, rig.intrinsics)

    def children(self, j: int) -> tuple[int, ...]:
        return tuple(k for k, p in enumerate(self.parents) if p == j)

    def with_joint_moved(self, j: int, delta_world, parent_rotation, segment_rotation) -> EditableModel:
        """Joint ``j`` moved by ``delta_world`` ``(3,)`` m, given the world rotation matrices ``(3, 3)`` of its
        parent and of its own segment at the frame where the move was made. ValueError for the root."""
        if j == 0:
            raise ValueError(f"'{self.names[0]}' is the root: its position is part of the motion, not of the model")
        delta = np.asarray(delta_world, np.float64)
        in_parent = np.asarray(parent_rotation).T @ delta
        in_segment = np.asarray(segment_rotation).T @ delta
        offsets = self.offsets.copy()
        offsets[j] += in_parent
        for k in self.children(j):
            offsets[k] -= in_segment
        mounts = self.mounts.copy()
        on_segment = np.asarray(self.camera_segments, int) == j
        mounts[on_segment, 4:] -= in_segment
        return dataclasses.replace(self, offsets=offsets, mounts=mounts)

    def with_camera_moved(self, c: int, world_from_camera, world_from_segment) -> EditableModel:
        """Camera ``c`` given the world pose ``world_from_camera`` ``(7,)`` while its segment is at
        ``world_from_segment`` ``(7,)`` (both wxyz_xyz)."""
        camera, segment = np.asarray(world_from_camera, np.float64), np.asarray(world_from_segment, np.float64)
        inverse = quat_conjugate(segment[:4])
        rotation = quat_multiply(inverse, camera[:4])
        rotation = rotation / np.linalg.norm(rotation)
        translation = matrix_from_quat(inverse) @ (camera[4:] - segment[4:])
        mounts = self.mounts.copy()
        mounts[c] = np.concatenate([rotation, translation])
        return dataclasses.replace(self, mounts=mounts)

    # ---- checks -----------------------------------------------------------------------------------
    def bone_problems(self, joints=None, before: EditableModel | None = None) -> list[str]:
        """One message per bone (of ``joints``, default all) shorter than :data:`MIN_BONE_M`; with ``before``,
        only bones an edit shortened (a skeleton may have a zero-length bone of its own, e.g. a torso joint
        at the root)."""
        out = []
        for k in range(1, len(self.names)) if joints is None else joints:
            length = float(np.linalg.norm(self.offsets[k]))
            if not k or length >= MIN_BONE_M:
                continue
            if before is not None and length >= float(np.linalg.norm(before.offsets[k])) - 1e-9:
                continue
            out.append(f"bone {self.names[self.parents[k]]} → {self.names[k]} would be {100 * length:.2f} cm long "
                       f"(at least {100 * MIN_BONE_M:g} cm)")
        return out

    def camera_problems(self, cameras=None) -> list[str]:
        """One message per camera (of ``cameras``, default all) inside its segment or looking into it."""
        out = []
        for c in range(len(self.camera_names)) if cameras is None else cameras:
            s = self.camera_segments[c]
            centre, axis = self.mounts[c, 4:], matrix_from_quat(self.mounts[c, :4])[:, 2]
            outward = _from_bone(centre, [self.offsets[k] for k in self.children(s)])
            distance = float(np.linalg.norm(outward))
            name, segment = self.camera_names[c], self.names[s]
            if distance < MIN_CAMERA_DISTANCE_M:
                out.append(f"camera {name} would be {100 * distance:.2f} cm from the bone of {segment}: inside the "
                           f"body (at least {100 * MIN_CAMERA_DISTANCE_M:g} cm)")
            elif float(axis @ outward) < 0:
                out.append(f"camera {name} would be on the wrong side of the body: it would look into {segment}")
        return out

    def problems_after_editing(self, joint: int | None = None, camera: int | None = None,
                               before: EditableModel | None = None) -> list[str]:
        """The checks an edit of ``joint`` (its bone, its children's bones, its cameras) or of ``camera`` can
        fail (everything when neither is given); bones are compared with the model ``before`` the edit."""
        if joint is not None:
            cams = [c for c, s in enumerate(self.camera_segments) if s == joint]
            return self.bone_problems([joint, *self.children(joint)], before) + self.camera_problems(cams)
        if camera is not None:
            return self.camera_problems([camera])
        return self.bone_problems(before=before) + self.camera_problems()


def _from_bone(point: np.ndarray, ends: list[np.ndarray]) -> np.ndarray:
    """``point`` minus its nearest point on the segments from the origin to each of ``ends`` (the origin
    alone when there are none): the outward direction from a segment's bone, in the segment frame."""
    best = point
    for end in ends:
        length2 = float(end @ end)
        u = 0.0 if length2 < 1e-12 else float(np.clip(point @ end / length2, 0.0, 1.0))
        r = point - u * end
        if np.linalg.norm(r) < np.linalg.norm(best):
            best = r
    return best
