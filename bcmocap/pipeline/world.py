"""From the reference model's frame to a metric, Z-up world, and from there to a ground truth's world.

Structure from motion gives the scene and the cameras up to a similarity. The solver's defaults (the
smoothness weights λ_O, λ_A; the range-of-motion thresholds) are in metres, and BVH viewers expect an up
axis, so ``bcmocap run`` moves everything into a world fixed by the subject:

* **scale** from tape measurements between joint centres (``capture.json`` → ``subject.measurements``,
  e.g. hip to ankle): the range-of-motion skeleton is estimated once at a provisional scale, its
  rest-pose distances compared with the measurements;
* **up** (+Z) from the rest pose, the direction from the feet's joint centres to the head's;
* **origin** on the floor under the rest pose's root, at the height of the ankles' joint centres.

:class:`Similarity` acts on points and camera poses; :func:`transform_model` moves a skeleton, its rig
and a motion into another world while keeping bcmocap's rest-pose convention (segment frames parallel to
the world at rest), which is what comparing with a ground truth after the §5.1 similarity needs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..geometry import matrix_from_quat, quat_from_matrix, rotation_onto
from ..io.run_folder import SIMILARITY, read_json
from ..kinematics.fk import forward_kinematics
from ..kinematics.rig import Rig
from ..kinematics.skeleton import Motion, Skeleton


@dataclasses.dataclass(frozen=True)
class Similarity:
    """``x ↦ s R x + t`` (``rotation`` (3, 3), ``translation`` (3,), ``scale`` > 0)."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    @classmethod
    def identity(cls) -> Similarity:
        return cls(1.0, np.eye(3), np.zeros(3))

    def points(self, x: np.ndarray) -> np.ndarray:
        """``(..., 3)`` points (NaN stays NaN)."""
        return self.scale * np.asarray(x, np.float64) @ self.rotation.T + self.translation

    def poses(self, world_from_camera: np.ndarray) -> np.ndarray:
        """``(..., 7)`` wxyz_xyz poses of cameras (or of anything whose frame is rigid) in the new world."""
        p = np.asarray(world_from_camera, np.float64)
        out = np.full_like(p, np.nan)
        ok = np.all(np.isfinite(p), axis=-1)
        if ok.any():
            rot = self.rotation @ matrix_from_quat(p[ok][:, :4])
            out[ok] = np.concatenate([quat_from_matrix(rot), self.points(p[ok][:, 4:])], axis=-1)
        return out

    def then(self, other: Similarity) -> Similarity:
        """``other ∘ self``: first this, then ``other``."""
        return Similarity(other.scale * self.scale, other.rotation @ self.rotation,
                          other.scale * other.rotation @ self.translation + other.translation)

    def inverse(self) -> Similarity:
        rt = self.rotation.T
        return Similarity(1.0 / self.scale, rt, -rt @ self.translation / self.scale)

    def to_dict(self) -> dict:
        return {"scale": self.scale, "rotation": self.rotation.tolist(), "translation": self.translation.tolist()}

    @classmethod
    def from_dict(cls, data: dict, where: str = "similarity") -> Similarity:
        try:
            rot = np.asarray(data["rotation"], np.float64)
            t = np.asarray(data["translation"], np.float64)
            s = float(data["scale"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: not a similarity ({exc})") from None
        if rot.shape != (3, 3) or t.shape != (3,) or not s > 0:
            raise ValueError(f"{where}: expected rotation (3, 3), translation (3,), scale > 0")
        return cls(s, rot, t)



def load_similarity(run_dir: str | Path) -> Similarity:
    """The run's reference-model frame → metric world map (``DIR/world/similarity.json``, the world stage's)."""
    path = Path(run_dir) / SIMILARITY
    return Similarity.from_dict(read_json(path), str(path))

def rest_joint_positions(skeleton: Skeleton) -> np.ndarray:
    """``(J, 3)`` joint centres in the rest pose, root at the origin, in world axes (m)."""
    return np.asarray(forward_kinematics(skeleton, skeleton.rest_motion()).translation())


def scale_from_measurements(skeleton: Skeleton, measurements: Sequence[dict], where: str = "measurements") -> float:
    """Mean ratio of measured to estimated rest-pose distances between joint centres.

    Args:
        measurements: ``{"from": segment, "to": segment, "metres": d}`` each.

    Raises:
        ValueError: no measurement, an unknown segment (named), a non-positive distance.
    """
    if not measurements:
        raise ValueError(f"{where}: no measurement between joint centres to fix the scale")
    rest = rest_joint_positions(skeleton)
    ratios = []
    for i, m in enumerate(measurements):
        try:
            a, b, d = m["from"], m["to"], float(m["metres"])
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"{where}[{i}]: expected {{'from', 'to', 'metres'}}, got {m!r}") from None
        for seg in (a, b):
            if seg not in skeleton.names:
                raise ValueError(f"{where}[{i}]: unknown segment {seg!r} (segments: {', '.join(skeleton.names)})")
        est = float(np.linalg.norm(rest[skeleton.index(a)] - rest[skeleton.index(b)]))
        if not d > 0 or not est > 0:
            raise ValueError(f"{where}[{i}]: {a}→{b} must be a positive distance (measured {d}, estimated {est})")
        ratios.append(d / est)
    return float(np.mean(ratios))


def upright_frame(skeleton: Skeleton, rest_motion: Motion, up_from: Sequence[str], up_to: str,
                  scale: float) -> Similarity:
    """The similarity that scales by ``scale``, turns the rest pose upright (feet → head along +Z, the
    smallest rotation doing so) and puts the origin on the floor below the root at the ankles' height.

    Args:
        skeleton: the (provisional) skeleton; rest_motion: its motion over the rest frames (``(R, J)``).
        up_from: segments whose joint centres are the feet; up_to: the segment at the top (the head).
    """
    for seg in (*up_from, up_to):
        if seg not in skeleton.names:
            raise ValueError(f"skeleton.up: unknown segment {seg!r} (segments: {', '.join(skeleton.names)})")
    joints = np.asarray(forward_kinematics(skeleton, rest_motion).translation()).reshape(-1, skeleton.num_segments, 3)
    feet = joints[:, [skeleton.index(s) for s in up_from]].mean(axis=1)
    up = (joints[:, skeleton.index(up_to)] - feet).mean(axis=0)
    if not np.linalg.norm(up) > 0:
        raise ValueError("skeleton.up: the head and the feet coincide in the rest pose")
    rot = rotation_onto(up / np.linalg.norm(up), np.array([0.0, 0.0, 1.0]))
    root = scale * rot @ joints[:, 0].mean(axis=0)
    floor = scale * rot @ feet.mean(axis=0)
    return Similarity(scale, rot, -np.array([root[0], root[1], floor[2]]))


def transform_model(skeleton: Skeleton, rig: Rig | None, motion: Motion, sim: Similarity
                    ) -> tuple[Skeleton, Rig | None, Motion]:
    """The same body in the world ``sim`` maps to, with segment frames re-chosen parallel to that world at rest.

    With ``R`` the similarity's rotation: offsets ``s R o``, hinge axes ``R a``, local rotations and the
    root rotation ``R q Rᵀ``, root positions ``s R p + t``, mounts ``(R q_m, s R t_m)``. Joint positions
    map by ``sim`` and joint angles (rotations relative to the rest pose) keep their magnitude.
    """
    rot, s = sim.rotation, sim.scale
    offsets = s * np.asarray(skeleton.offsets, np.float64) @ rot.T
    axes = np.asarray(skeleton.hinge_axes, np.float64) @ rot.T
    new_skeleton = Skeleton(skeleton.names, skeleton.parents, offsets, skeleton.joint_types, hinge_axes=axes)
    r = np.asarray(motion.rotations, np.float64)
    mats = matrix_from_quat(r.reshape(-1, 4)).reshape(*r.shape[:-1], 3, 3)
    conj = rot @ mats @ rot.T
    new_motion = Motion(sim.points(np.asarray(motion.root_position)), quat_from_matrix(conj))
    new_rig = None
    if rig is not None:
        mounts = np.asarray(rig.segment_from_camera, np.float64)
        mq = rot @ matrix_from_quat(mounts[:, :4])
        new_mounts = np.concatenate([quat_from_matrix(mq), s * mounts[:, 4:] @ rot.T], axis=1)
        new_rig = Rig(rig.names, rig.segments, new_mounts, rig.intrinsics)
    return new_skeleton, new_rig, new_motion
