"""Vicon-style synthetic ground truth: CMU motions, the paper's rig, a scene and its measurements."""

from .capture import LazyProblem, SyntheticCapture, standard_capture
from .motions import BODY_SEGMENTS, CMU_TRIALS, BodySegment, back_and_forth, load_body_motion, reduce_motion, resample
from .observe import NoiseModel, ObservationSimulator, body_capsules
from .rig import fov_camera_for, standard_rig
from .rom import RangeOfMotionTrial, range_of_motion, range_of_motion_trial, skeleton_errors
from .world import World, make_world

__all__ = [
    "BODY_SEGMENTS",
    "CMU_TRIALS",
    "BodySegment",
    "LazyProblem",
    "NoiseModel",
    "ObservationSimulator",
    "RangeOfMotionTrial",
    "SyntheticCapture",
    "World",
    "back_and_forth",
    "body_capsules",
    "fov_camera_for",
    "load_body_motion",
    "make_world",
    "range_of_motion",
    "range_of_motion_trial",
    "reduce_motion",
    "resample",
    "skeleton_errors",
    "standard_capture",
    "standard_rig",
]
