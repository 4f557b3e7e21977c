"""Frontend: from a capture folder to what the solver consumes (issue 5, in progress).

The only package that imports ``cv2`` and ``pycolmap``. Done so far: reading a capture folder
(:mod:`.capture`), audio synchronisation by the claps (:mod:`.sync`) and the reference reconstruction
from the reference photos (:mod:`.reference`).
"""

from .capture import Capture, CaptureCamera, VideoInfo, read_camera_json, read_capture
from .reference import ReferenceModel, build_reference, extract_sift, match_descriptors, verify_matches
from .sync import SyncResult, clap_candidates, given_offsets, synchronize, synchronize_tracks

__all__ = [
    "Capture",
    "CaptureCamera",
    "ReferenceModel",
    "SyncResult",
    "VideoInfo",
    "build_reference",
    "clap_candidates",
    "extract_sift",
    "given_offsets",
    "match_descriptors",
    "read_camera_json",
    "read_capture",
    "synchronize",
    "synchronize_tracks",
    "verify_matches",
]
