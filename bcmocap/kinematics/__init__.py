"""Kinematic trees, forward kinematics and camera rigs."""

from .fk import forward_kinematics, joint_positions, world_rotations
from .ik import motion_from_camera_poses
from .rig import Rig, camera_poses
from .skeleton import DOFS, JointType, Motion, Skeleton

__all__ = [
    "DOFS",
    "JointType",
    "Motion",
    "Rig",
    "Skeleton",
    "camera_poses",
    "motion_from_camera_poses",
    "forward_kinematics",
    "joint_positions",
    "world_rotations",
]
