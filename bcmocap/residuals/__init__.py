"""Residual terms of Eq. (1) and the API for adding new ones.

A new term is a function decorated with :func:`residual_term` (``fn(x, data, variables) -> (r, valid)``), its data
made per window by a term factory that is given a :class:`TermWindow`. The classes of :mod:`.base` (the five kinds)
are what the decorator makes, and what the project's terms with extra methods (:class:`Reprojection`'s
camera-frame points) subclass directly."""

from .base import CameraPairTerm, CameraTerm, CameraView, FrameState, FrameTerm, MultiFrameTerm, PairTerm, StackedFrames, Term, camera_slot_count, camera_slots, slot_cameras
from .function_term import residual_term
from .homography import HomographyTransfer
from .losses import CauchyLoss, HuberLoss, RobustLoss, TrivialLoss, loss_from_name
from .reprojection import Reprojection
from .smoothness import JointSmoothness, RootSmoothness, pair_mask
from .term_window import TermWindow
from .variables import CAMERA_OFFSETS, Euclidean, PerCamera, Rotation, Variable

__all__ = [
    "CAMERA_OFFSETS",
    "CameraPairTerm",
    "CameraTerm",
    "CameraView",
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
    "StackedFrames",
    "Rotation",
    "Term",
    "TermWindow",
    "TrivialLoss",
    "Variable",
    "camera_slot_count",
    "camera_slots",
    "loss_from_name",
    "pair_mask",
    "residual_term",
    "slot_cameras",
]
