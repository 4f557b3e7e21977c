"""Residual terms of Eq. (1) and the API for adding new ones."""

from .base import CameraPairTerm, CameraTerm, FrameState, FrameTerm, MultiFrameTerm, PairTerm, Term, camera_slot_count, camera_slots, slot_cameras
from .homography import HomographyTransfer
from .losses import CauchyLoss, HuberLoss, RobustLoss, TrivialLoss, loss_from_name
from .reprojection import Reprojection
from .smoothness import JointSmoothness, RootSmoothness, pair_mask
from .variables import CAMERA_OFFSETS, Euclidean, PerCamera, Rotation, Variable

__all__ = [
    "CAMERA_OFFSETS",
    "CameraPairTerm",
    "CameraTerm",
    "CauchyLoss",
    "Euclidean",
    "FrameState",
    "FrameTerm",
    "HomographyTransfer",
    "HuberLoss",
    "JointSmoothness",
    "MultiFrameTerm",
    "PairTerm",
    "PerCamera",
    "Reprojection",
    "RobustLoss",
    "RootSmoothness",
    "Rotation",
    "Term",
    "TrivialLoss",
    "Variable",
    "camera_slot_count",
    "camera_slots",
    "loss_from_name",
    "pair_mask",
    "slot_cameras",
]
