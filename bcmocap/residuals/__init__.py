"""Residual terms of Eq. (1) and the API for adding new ones."""

from .base import CameraPairTerm, CameraTerm, FrameState, FrameTerm, MultiFrameTerm, PairTerm, Term, camera_slot_count, camera_slots, slot_cameras
from .homography import HomographyTransfer
from .losses import CauchyLoss, HuberLoss, RobustLoss, TrivialLoss, loss_from_name
from .reprojection import Reprojection
from .smoothness import JointSmoothness, RootSmoothness, pair_mask

__all__ = [
    "CameraPairTerm",
    "CameraTerm",
    "CauchyLoss",
    "FrameState",
    "FrameTerm",
    "HomographyTransfer",
    "HuberLoss",
    "JointSmoothness",
    "MultiFrameTerm",
    "PairTerm",
    "Reprojection",
    "RobustLoss",
    "RootSmoothness",
    "Term",
    "TrivialLoss",
    "camera_slot_count",
    "camera_slots",
    "loss_from_name",
    "pair_mask",
    "slot_cameras",
]
