"""Vicon-style synthetic ground truth: CMU motions, the paper's rig, a scene and its measurements."""

from .capture import LazyProblem, SyntheticCapture, standard_capture
from .markers import MarkerNoise, MarkerSpec, SimulatedMarkers, calibration_motion, full_body_markers, simulate_markers  # noqa: F401
from .motions import (BODY_SEGMENTS, CMU_TRIALS, BodySegment, back_and_forth, load_body_motion, load_motion_file,
                      reduce_motion, resample)
from .observe import NoiseModel, ObservationSimulator, body_capsules
from .rig import fov_camera_for, standard_rig
from .render import RenderOptions, Renderer, camera_rays
from .rom import RangeOfMotionTrial, range_of_motion, range_of_motion_trial, skeleton_errors
from .scene import TexturedScene, TextureParams, make_textured_scene
from .studio import GroundTruth, StudioSettings, load_ground_truth, preset_settings, write_capture
from .world import World, make_world

__all__ = [
    "BODY_SEGMENTS",
    "CMU_TRIALS",
    "BodySegment",
    "LazyProblem",
    "NoiseModel",
    "ObservationSimulator",
    "GroundTruth",
    "RangeOfMotionTrial",
    "RenderOptions",
    "Renderer",
    "StudioSettings",
    "SyntheticCapture",
    "TextureParams",
    "TexturedScene",
    "World",
    "back_and_forth",
    "body_capsules",
    "camera_rays",
    "fov_camera_for",
    "load_body_motion",
    "load_ground_truth",
    "load_motion_file",
    "make_textured_scene",
    "make_world",
    "preset_settings",
    "range_of_motion",
    "range_of_motion_trial",
    "reduce_motion",
    "resample",
    "skeleton_errors",
    "standard_capture",
    "standard_rig",
    "write_capture",
]
