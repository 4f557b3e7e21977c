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
* :func:`pool_mean_pose` — the mean pose of a pool of motions, kept in a file keyed by the pool;
* :func:`motion_from_joints` — a :class:`~bcmocap.kinematics.Skeleton` and
  :class:`~bcmocap.kinematics.Motion` (for :func:`~bcmocap.io.write_bvh`) from reconstructed joints;
* :func:`aligned_joint_errors` (3DPE; per joint :func:`aligned_joint_distances`) and :func:`joint_errors` (MPJPE).
"""

from ..lazy_exports import lazy_exports

# Imported on first use (PEP 562), so that the command line does not pay for JAX where it is not used.
__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "Anatomy": "anatomy",
    "Hinge": "anatomy",
    "human_anatomy": "anatomy",
    "WeakPerspectiveCameras": "cameras",
    "fit_cameras": "cameras",
    "initial_cameras": "cameras",
    "reprojection_rms": "cameras",
    "CMU_JOINTS": "chain_space",
    "KinematicChainSpace": "chain_space",
    "mean_pose": "chain_space",
    "motion_from_joints": "export",
    "aligned_joint_distances": "metrics",
    "aligned_joint_errors": "metrics",
    "joint_errors": "metrics",
    "pool_mean_pose": "prior",
    "KCSOptions": "solve",
    "KCSResult": "solve",
    "limb_signs": "solve",
    "reconstruct": "solve",
    "singular_value_threshold": "solve",
    "solve_bones": "solve",
})
