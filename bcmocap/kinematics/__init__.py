"""Kinematic trees, forward kinematics and camera rigs."""

from .fk import forward_kinematics, joint_positions, world_rotations
from .ik import motion_from_camera_poses
from .rig import Rig, camera_poses
from .rom import JointEstimate, RomEstimate, RomOptions, Topology, skeleton_from_range_of_motion
from .skeleton import DOFS, JointType, Motion, Skeleton
from .virtual import VirtualCamera, estimate_virtual_camera, reparameterise_rig, robust_average_poses, segment_from_virtual

__all__ = [
    "DOFS",
    "JointEstimate",
    "JointType",
    "Motion",
    "Rig",
    "RomEstimate",
    "RomOptions",
    "Skeleton",
    "Topology",
    "VirtualCamera",
    "camera_poses",
    "motion_from_camera_poses",
    "forward_kinematics",
    "joint_positions",
    "world_rotations",
    "estimate_virtual_camera",
    "reparameterise_rig",
    "robust_average_poses",
    "segment_from_virtual",
    "skeleton_from_range_of_motion",
]
