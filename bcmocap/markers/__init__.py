"""Skeletons from optical marker data (Kirk, O'Brien & Forsyth, CVPR 2005).

From marker trajectories alone (a C3D file or a ``(frames, markers, 3)`` array with NaN gaps): which
markers belong to which segment (§3.1), how the segments connect and where the joints are (§3.2), a rigid
skeleton with marker offsets and per-frame poses by inverse kinematics (§3.3), and — for passive systems —
which labels are the same physical marker (§4). :func:`fit_marker_skeleton` runs it all; the command line
is ``bcmocap markers FILE.c3d --out DIR``.
"""

from .identities import IdentityMerge, concurrent_labels, label_distances, merge_identities
from .ik import IkResult, initial_motion, marker_model_positions, solve_ik
from .joints import JointSolution, informative_frames, joint_cost_matrix, joint_objective, minimum_spanning_tree, solve_joints
from .pipeline import MarkerOptions, MarkerSkeleton, fit_marker_skeleton
from .preprocess import MarkerTrajectories, PreprocessReport, preprocess, visible_runs
from .rigid import RigidSkeleton, build_skeleton, procrustes
from .segmentation import PairStatistics, Segmentation, distance_std, jittered_samples, pair_statistics, segment_markers, within_group_cost
from .spectral import eigengap, kmeans, spectral_clustering, spectral_embedding

__all__ = [
    "IdentityMerge",
    "IkResult",
    "JointSolution",
    "MarkerOptions",
    "MarkerSkeleton",
    "MarkerTrajectories",
    "PairStatistics",
    "PreprocessReport",
    "RigidSkeleton",
    "Segmentation",
    "build_skeleton",
    "concurrent_labels",
    "distance_std",
    "eigengap",
    "fit_marker_skeleton",
    "informative_frames",
    "initial_motion",
    "jittered_samples",
    "joint_cost_matrix",
    "joint_objective",
    "kmeans",
    "label_distances",
    "marker_model_positions",
    "merge_identities",
    "minimum_spanning_tree",
    "pair_statistics",
    "preprocess",
    "procrustes",
    "segment_markers",
    "solve_ik",
    "solve_joints",
    "spectral_clustering",
    "spectral_embedding",
    "visible_runs",
    "within_group_cost",
]
