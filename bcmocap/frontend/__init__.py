"""Frontend: from a capture folder to what the solver consumes (issue 5, in progress).

The only package that imports ``cv2`` and ``pycolmap``. Done so far: reading a capture folder
(:mod:`.capture`), audio synchronisation by the claps (:mod:`.sync`), the reference reconstruction
from the reference photos (:mod:`.reference`), absolute registration of body-camera frames to it
(:mod:`.register`), and for a whole trial new points, bundle adjustment with the reference fixed and
rounds of relative registration (:mod:`.relative`), homographies for the frames left
(:mod:`.homography`), and ``bcmocap frontend`` (:mod:`.command`). Not built yet: parallel extraction and
matching, scaling the reference model to metres for the solver.
"""

from .capture import Capture, CaptureCamera, VideoInfo, read_camera_json, read_capture
from .reference import ReferenceModel, build_reference, extract_sift, match_descriptors, verify_matches
from .register import (
    FrameRegistration,
    ReferenceIndex,
    RegistrationOptions,
    TrialRegistration,
    reference_index,
    register_frame,
    register_trial,
    similarity,
)
from .homography import HomographyFill, HomographyOptions, fill_with_homographies, rotation_between_frames
from .relative import CaptureRegistration, FrameState, RelativeOptions, extract_trial_features, register_capture
from .sync import SyncResult, clap_candidates, given_offsets, synchronize, synchronize_tracks

__all__ = [
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
    "VideoInfo",
    "build_reference",
    "clap_candidates",
    "extract_sift",
    "given_offsets",
    "match_descriptors",
    "read_camera_json",
    "read_capture",
    "reference_index",
    "register_frame",
    "register_trial",
    "similarity",
    "synchronize",
    "synchronize_tracks",
    "verify_matches",
]
