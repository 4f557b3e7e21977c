"""Skeletons from optical marker data (Kirk, O'Brien & Forsyth, CVPR 2005).

From marker trajectories alone (a C3D file or a ``(frames, markers, 3)`` array with NaN gaps): which
markers belong to which segment (§3.1), how the segments connect and where the joints are (§3.2), a rigid
skeleton with marker offsets and per-frame poses by inverse kinematics (§3.3), and — for passive systems —
which labels are the same physical marker (§4); then which part of a human body each segment is
(:mod:`~bcmocap.markers.anatomy`). :func:`fit_marker_skeleton` runs it all; the command line
is ``bcmocap markers FILE.c3d --out DIR``.
"""

from ..lazy_exports import lazy_exports
from .preprocess import preprocess  # noqa: F401  (now: the function shares its module's name, which an import of
#                                      the module would otherwise put here; numpy only, no JAX)

# Imported on first use (PEP 562), so that the command line does not pay for JAX where it is not used.
__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "Anatomy": "anatomy",
    "label_anatomy": "anatomy",
    "IdentityMerge": "identities",
    "concurrent_labels": "identities",
    "label_distances": "identities",
    "merge_identities": "identities",
    "IkResult": "ik",
    "initial_motion": "ik",
    "marker_model_positions": "ik",
    "solve_ik": "ik",
    "JointSolution": "joints",
    "informative_frames": "joints",
    "joint_cost_matrix": "joints",
    "joint_objective": "joints",
    "minimum_spanning_tree": "joints",
    "solve_joints": "joints",
    "MarkerOptions": "pipeline",
    "MarkerSkeleton": "pipeline",
    "fit_marker_skeleton": "pipeline",
    "MarkerTrajectories": "preprocess",
    "PreprocessReport": "preprocess",
    "preprocess": "preprocess",
    "visible_runs": "preprocess",
    "RigidSkeleton": "rigid",
    "build_skeleton": "rigid",
    "procrustes": "rigid",
    "PairStatistics": "segmentation",
    "Segmentation": "segmentation",
    "distance_std": "segmentation",
    "jittered_samples": "segmentation",
    "pair_statistics": "segmentation",
    "segment_markers": "segmentation",
    "within_group_cost": "segmentation",
    "eigengap": "spectral",
    "kmeans": "spectral",
    "spectral_clustering": "spectral",
    "spectral_embedding": "spectral",
})
