"""Accuracy metrics against ground truth (§5.1 of the paper)."""

from .metrics import ErrorStats, camera_centre_errors, evaluate_motion, joint_angle_errors, joint_position_errors

__all__ = ["ErrorStats", "camera_centre_errors", "evaluate_motion", "joint_angle_errors", "joint_position_errors"]
