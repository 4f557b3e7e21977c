"""Lens calibration from a board video or images (``bcmocap calibrate``): board detection, well-spread view
selection, the FOV / equidistant models fitted by bcmocap's own cameras and Levenberg–Marquardt, the
Kannala–Brandt model by ``cv2.fisheye``, and reports (per-view errors, sensor coverage picture)."""

from ..io.board import Board, Detection, parse_board
from .fit import MODELS, Calibration, calibrate
from .views import BoardViews, detect_views, select_views

__all__ = ["MODELS", "Board", "BoardViews", "Calibration", "Detection", "calibrate", "detect_views", "parse_board",
           "select_views"]
