"""Vicon-style synthetic ground truth: CMU motions, the paper's rig, a scene and its measurements."""

from .capture import LazyProblem, SyntheticCapture, standard_capture
from .motions import BODY_SEGMENTS, CMU_TRIALS, BodySegment, back_and_forth, load_body_motion, reduce_motion, resample
from .observe import NoiseModel, ObservationSimulator, body_capsules
from .rig import fov_camera_for, standard_rig
from .world import World, make_world

__all__ = [
    "BODY_SEGMENTS",
    "CMU_TRIALS",
    "BodySegment",
    "LazyProblem",
    "NoiseModel",
    "ObservationSimulator",
    "SyntheticCapture",
    "World",
    "back_and_forth",
    "body_capsules",
    "fov_camera_for",
    "load_body_motion",
    "make_world",
    "reduce_motion",
    "resample",
    "standard_capture",
    "standard_rig",
]
