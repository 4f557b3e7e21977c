"""Joint position, joint angle and camera-centre errors (§5.1), reported in cm and degrees."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..geometry import rotation_angle
from ..kinematics.fk import joint_positions
from ..kinematics.rig import Rig, camera_poses
from ..kinematics.skeleton import Motion, Skeleton


@dataclasses.dataclass(frozen=True)
class ErrorStats:
    """Mean, median and max of a set of errors (in the unit the field name says)."""

    mean: float
    median: float
    max: float

    @classmethod
    def of(cls, values: np.ndarray) -> ErrorStats:
        values = np.asarray(values, dtype=np.float64).ravel()
        if values.size == 0:
            raise ValueError("ErrorStats: no values")
        return cls(float(values.mean()), float(np.median(values)), float(values.max()))

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


def _check_pair(skeleton: Skeleton, estimate: Motion, truth: Motion) -> None:
    estimate.check(skeleton, "estimate")
    truth.check(skeleton, "truth")
    if estimate.rotations.shape != truth.rotations.shape:
        raise ValueError(f"estimate and truth differ in shape: {estimate.rotations.shape} vs {truth.rotations.shape}")


def joint_position_errors(skeleton: Skeleton, estimate: Motion, truth: Motion) -> np.ndarray:
    """``(T, J)`` distances (m) between estimated and true joint positions."""
    _check_pair(skeleton, estimate, truth)
    diff = np.asarray(joint_positions(skeleton, estimate)) - np.asarray(joint_positions(skeleton, truth))
    return np.linalg.norm(diff, axis=-1)


def joint_angle_errors(skeleton: Skeleton, estimate: Motion, truth: Motion) -> np.ndarray:
    """``(T, J-1)`` geodesic angles (rad) between estimated and true local joint rotations (root excluded)."""
    _check_pair(skeleton, estimate, truth)
    return np.asarray(rotation_angle(estimate.rotations[..., 1:, :], truth.rotations[..., 1:, :]))


def camera_centre_errors(skeleton: Skeleton, rig: Rig, estimate: Motion, truth: Motion) -> np.ndarray:
    """``(T, C)`` distances (m) between estimated and true camera centres."""
    _check_pair(skeleton, estimate, truth)
    est = np.asarray(camera_poses(skeleton, rig, estimate).translation())
    tru = np.asarray(camera_poses(skeleton, rig, truth).translation())
    return np.linalg.norm(est - tru, axis=-1)


def evaluate_motion(skeleton: Skeleton, estimate: Motion, truth: Motion, rig: Rig | None = None) -> dict[str, dict[str, float]]:
    """The paper's metrics as a dict: joint position error (cm), joint angle error (deg), camera centres (cm)."""
    out = {
        "joint_position_error_cm": ErrorStats.of(100.0 * joint_position_errors(skeleton, estimate, truth)).as_dict(),
        "joint_angle_error_deg": ErrorStats.of(np.rad2deg(joint_angle_errors(skeleton, estimate, truth))).as_dict(),
    }
    if rig is not None:
        out["camera_centre_error_cm"] = ErrorStats.of(100.0 * camera_centre_errors(skeleton, rig, estimate, truth)).as_dict()
    return out
