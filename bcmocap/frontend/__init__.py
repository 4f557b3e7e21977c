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

from ..lazy_exports import lazy_exports

# Imported on first use (PEP 562), so that the command line does not pay for JAX where it is not used.
__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "Capture": "capture",
    "CaptureCamera": "capture",
    "TrialVideo": "capture",
    "VideoInfo": "capture",
    "read_camera_json": "capture",
    "read_capture": "capture",
    "ReferenceModel": "reference",
    "build_reference": "reference",
    "extract_sift": "reference",
    "match_descriptors": "reference",
    "verify_matches": "reference",
    "FrameRegistration": "register",
    "ReferenceIndex": "register",
    "RegistrationOptions": "register",
    "TrialRegistration": "register",
    "reference_index": "register",
    "register_frame": "register",
    "register_trial": "register",
    "HomographyFill": "homography",
    "HomographyOptions": "homography",
    "fill_with_homographies": "homography",
    "rotation_between_frames": "homography",
    "CaptureRegistration": "relative",
    "CameraFrameRegistration": "relative",
    "RelativeOptions": "relative",
    "extract_trial_features": "relative",
    "register_capture": "relative",
    "measurement_score": "selection",
    "select_measurements": "selection",
    "SyncResult": "sync",
    "clap_candidates": "sync",
    "common_claps": "sync",
    "given_offsets": "sync",
    "synchronize": "sync",
    "synchronize_tracks": "sync",
    "CameraTrack": "tracking",
    "TrackingOptions": "tracking",
    "relocalise": "tracking",
    "retrack": "tracking",
    "track_camera": "tracking",
    "track_trial": "tracking",
})
