"""Lens calibration from a board video or images (``bcmocap calibrate``): board detection, well-spread view
selection, the FOV / equidistant models fitted by bcmocap's own cameras and Levenberg–Marquardt, the
Kannala–Brandt model by ``cv2.fisheye``, and reports (per-view errors, sensor coverage picture)."""

from ..lazy_exports import lazy_exports

# Imported on first use (PEP 562), so that the command line does not pay for JAX where it is not used.
__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "Board": "..io.board", "Detection": "..io.board", "parse_board": "..io.board", "MODELS": "fit",
    "Calibration": "fit", "calibrate": "fit", "BoardViews": "views", "detect_views": "views",
    "select_views": "views"})
