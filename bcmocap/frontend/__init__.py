"""Frontend: from a capture folder to what the solver consumes (issue 5).

The only package that imports ``cv2`` and ``pycolmap``: reading a capture folder (:mod:`.capture`),
audio synchronisation by the claps (:mod:`.sync`), the reference reconstruction from the reference
photos (:mod:`.reference`), absolute registration of body-camera frames to it (:mod:`.register`), tracking
registration of each camera's video with keyframes, relocalisation and re-tracking (:mod:`.tracking`, the
default), at most N measurements per camera-frame (:mod:`.selection`), SIFT
features of a trial streamed to disk and read back memory-mapped (:mod:`.features`), for a whole trial
new points, bundle adjustment with the reference fixed and rounds of relative registration
(:mod:`.relative`; cameras and frame pairs in threads), homographies for the frames left
(:mod:`.homography`), and ``bcmocap frontend`` (:mod:`.command`); ``bcmocap init`` assembles a capture folder
from a shoot's camera files and its rig file (:mod:`.assemble`, :mod:`.rig_file`, :mod:`.init_command`). Scaling the reference model to metres
is the pipeline's world stage (:mod:`bcmocap.pipeline.world`)."""

from .capture import Capture, CaptureCamera, TrialVideo, VideoInfo, read_camera_json, read_capture
from .reference import ReferenceModel, build_reference, extract_sift, match_descriptors, verify_matches
from .register import (
    FrameRegistration,
    ReferenceIndex,
    RegistrationOptions,
    TrialRegistration,
    reference_index,
    register_frame,
    register_trial,
)
from .homography import HomographyFill, HomographyOptions, fill_with_homographies, rotation_between_frames
from .relative import CaptureRegistration, FrameState, RelativeOptions, extract_trial_features, register_capture
from .selection import measurement_score, select_measurements
from .sync import SyncResult, clap_candidates, common_claps, given_offsets, synchronize, synchronize_tracks
from .tracking import CameraTrack, TrackingOptions, relocalise, retrack, track_camera, track_trial

__all__ = [
    "CameraTrack",
    "TrackingOptions",
    "measurement_score",
    "relocalise",
    "retrack",
    "select_measurements",
    "track_camera",
    "track_trial",
    "Capture",
    "CaptureCamera",
    "CaptureRegistration",
    "FrameState",
    "HomographyFill",
    "HomographyOptions",
    "fill_with_homographies",
    "rotation_between_frames",
    "RelativeOptions",
    "extract_trial_features",
    "register_capture",
    "FrameRegistration",
    "ReferenceIndex",
    "ReferenceModel",
    "RegistrationOptions",
    "SyncResult",
    "TrialRegistration",
    "TrialVideo",
    "VideoInfo",
    "build_reference",
    "clap_candidates",
    "common_claps",
    "extract_sift",
    "given_offsets",
    "match_descriptors",
    "read_camera_json",
    "read_capture",
    "reference_index",
    "register_frame",
    "register_trial",
    "synchronize",
    "synchronize_tracks",
    "verify_matches",
]
