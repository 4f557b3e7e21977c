"""Monocular motion capture in the kinematic chain space (Wandt, Ackermann & Rosenhahn).

Training-free 3-D reconstruction of a kinematic chain (a human skeleton, a robot arm, an animal) from
its 2-D joints seen by one uncalibrated camera with little or no motion:

* :class:`KinematicChainSpace` — the matrices C (joints → bones) and D (bones → joints) of any bcmocap
  kinematic tree, plus extra rigid links (§3.1);
* :func:`initial_cameras`, :func:`fit_cameras` — per-frame weak-perspective cameras (§3.3, Eqs. 22–25);
* :func:`reconstruct` — Algorithm 1: cameras alternating with the nuclear-norm shape step (Eq. 21) by
  singular value thresholding, jitted and vmapped over sequences or camera paths;
* :func:`human_anatomy`, :func:`limb_signs` — beyond the paper: depth signs of whole limbs chosen over
  time with anatomical hinges (knees, ankles, elbows) and the rigid pelvis and thorax;
* :func:`motion_from_joints` — a :class:`~bcmocap.kinematics.Skeleton` and
  :class:`~bcmocap.kinematics.Motion` (for :func:`~bcmocap.io.write_bvh`) from reconstructed joints;
* :func:`aligned_joint_errors` (3DPE; per joint :func:`aligned_joint_distances`) and :func:`joint_errors` (MPJPE).
"""

from .anatomy import Anatomy, Hinge, human_anatomy
from .cameras import WeakPerspectiveCameras, fit_cameras, initial_cameras, reprojection_rms
from .chain_space import CMU_JOINTS, KinematicChainSpace, mean_pose
from .export import motion_from_joints
from .metrics import aligned_joint_distances, aligned_joint_errors, joint_errors
from .solve import KCSOptions, KCSResult, limb_signs, reconstruct, singular_value_threshold, solve_bones

__all__ = [
    "Anatomy",
    "CMU_JOINTS",
    "Hinge",
    "KCSOptions",
    "KCSResult",
    "KinematicChainSpace",
    "WeakPerspectiveCameras",
    "aligned_joint_distances",
    "aligned_joint_errors",
    "fit_cameras",
    "human_anatomy",
    "initial_cameras",
    "joint_errors",
    "limb_signs",
    "mean_pose",
    "motion_from_joints",
    "reconstruct",
    "reprojection_rms",
    "singular_value_threshold",
    "solve_bones",
]
