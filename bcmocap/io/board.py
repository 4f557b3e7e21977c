"""Calibration boards: the ``--board`` text, the board's points (m) and their detection in an image (OpenCV).

``--board`` is one of::

    chessboard:COLSxROWS:SQUARE_M                  inner corners per row x per column, square side (m)
    circles:COLSxROWS:SPACING_M[:asymmetric]       circle centres per row x rows; asymmetric: OpenCV's
                                                   staggered grid (spacing = half the distance along a row)
    charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]     squares per row x per column, square and marker sides (m),
                                                   ArUco dictionary (default DICT_5X5_100)

A ChArUco board is found from its markers, so a view that shows only part of it still gives its corners
(each with its id): this is what a wide lens needs near the edge of the image, where a whole
chessboard rarely fits. A chessboard or circle grid is found whole or not at all.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np

__all__ = ["Board", "Detection", "parse_board"]

_SIZE = re.compile(r"(\d+)[xX](\d+)")
_MAX_POINTS = 10_000


@dataclasses.dataclass(frozen=True)
class Detection:
    """Board points found in one image.

    Attributes:
        ids: ``(K,)`` int, indices into :attr:`Board.points` (all of them, in order, for a whole board).
        pixels: ``(K, 2)`` float64 pixel positions (OpenCV convention: top-left pixel centre at (0, 0)).
    """

    ids: np.ndarray
    pixels: np.ndarray


@dataclasses.dataclass(frozen=True)
class Board:
    """A planar calibration target.

    Attributes:
        kind: ``"chessboard"``, ``"circles"`` or ``"charuco"``.
        cols, rows: pattern size (inner corners, circles, or ChArUco squares; see the module docstring).
        spacing: square side or circle spacing (m).
        marker: ChArUco marker side (m; 0 otherwise).
        asymmetric: staggered circle grid.
        dictionary: ArUco dictionary name (ChArUco only).
    """

    kind: str
    cols: int
    rows: int
    spacing: float
    marker: float = 0.0
    asymmetric: bool = False
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self):
        if self.kind not in ("chessboard", "circles", "charuco"):
            raise ValueError(f"board kind must be chessboard, circles or charuco, got {self.kind!r}")
        if not (3 <= self.cols and 3 <= self.rows and self.cols * self.rows <= _MAX_POINTS):
            raise ValueError(f"board size {self.cols}x{self.rows} must be at least 3x3 and hold at most "
                             f"{_MAX_POINTS} points")
        if not (np.isfinite(self.spacing) and self.spacing > 0):
            raise ValueError(f"board spacing must be a positive length in metres, got {self.spacing!r}")
        if self.kind == "charuco":
            if not (0 < self.marker < self.spacing):
                raise ValueError(f"ChArUco marker side ({self.marker} m) must be positive and smaller than the square "
                                 f"({self.spacing} m)")
            import cv2

            if not self.dictionary.startswith("DICT_") or not hasattr(cv2.aruco, self.dictionary):
                raise ValueError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_4X4_50, DICT_5X5_100, "
                                 "DICT_6X6_250)")

    @property
    def points(self) -> np.ndarray:
        """``(N, 3)`` float64 board points in the board frame (m, z = 0), in detection id order."""
        if self.kind == "charuco":
            return np.asarray(self.charuco().getChessboardCorners(), np.float64).reshape(-1, 3)
        i, j = np.mgrid[0 : self.rows, 0 : self.cols]
        x = (2 * j + i % 2) if self.asymmetric else j
        pts = np.stack([x.ravel() * self.spacing, i.ravel() * self.spacing, np.zeros(i.size)], axis=-1)
        return pts.astype(np.float64)

    @property
    def describe(self) -> str:
        if self.kind == "charuco":
            return (f"ChArUco {self.cols}x{self.rows} squares of {self.spacing * 1000:g} mm, markers "
                    f"{self.marker * 1000:g} mm ({self.dictionary})")
        what = "asymmetric circle grid" if self.asymmetric else ("circle grid" if self.kind == "circles" else "chessboard")
        return f"{what} {self.cols}x{self.rows}, spacing {self.spacing * 1000:g} mm"

    def charuco(self):
        """The OpenCV ``CharucoBoard`` of a ChArUco board (its drawing, ``generateImage``, and detection)."""
        import cv2

        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.spacing, self.marker, dictionary)

    def detect(self, gray: np.ndarray) -> Detection | None:
        """The board in a ``(H, W)`` uint8 image, or None when it is not found."""
        import cv2

        if self.kind == "chessboard":
            size = (self.cols, self.rows)
            flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
            ok, corners = cv2.findChessboardCornersSB(gray, size, flags)
            if not ok:
                ok, corners = cv2.findChessboardCorners(gray, size, cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
                if ok:
                    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
                    corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria)
            return self._whole(corners) if ok else None
        if self.kind == "circles":
            flags = cv2.CALIB_CB_ASYMMETRIC_GRID if self.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
            # A light blur merges what breaks a blob in two (print texture, marks drawn over the dots)
            # without moving its centre; tried after the plain image.
            for image in (gray, cv2.GaussianBlur(gray, (0, 0), 2.0)):
                ok, centres = cv2.findCirclesGrid(image, (self.cols, self.rows), flags=flags)
                if ok:
                    return self._whole(centres)
            return None
        detector = cv2.aruco.CharucoDetector(self.charuco())
        corners, ids, _, _ = detector.detectBoard(gray)
        if ids is None or len(ids) == 0:
            return None
        return Detection(np.asarray(ids, np.int64).reshape(-1), np.asarray(corners, np.float64).reshape(-1, 2))

    def _whole(self, found: np.ndarray) -> Detection:
        pixels = np.asarray(found, np.float64).reshape(-1, 2)
        return Detection(np.arange(len(pixels)), pixels)


def parse_board(text: str) -> Board:
    """``--board`` text (see the module docstring) as a :class:`Board`; ValueError with the expected form."""
    forms = ("chessboard:COLSxROWS:SQUARE_M, circles:COLSxROWS:SPACING_M[:asymmetric] or "
             "charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]")
    parts = str(text).split(":")
    kind = parts[0].strip().lower()
    try:
        size = _SIZE.fullmatch(parts[1].strip()) if len(parts) > 1 else None
        if size is None:
            raise ValueError
        cols, rows = int(size.group(1)), int(size.group(2))
        if kind == "chessboard" and len(parts) == 3:
            return Board("chessboard", cols, rows, float(parts[2]))
        if kind == "circles" and len(parts) in (3, 4):
            shape = parts[3].strip().lower() if len(parts) == 4 else "symmetric"
            if shape not in ("symmetric", "asymmetric"):
                raise ValueError
            return Board("circles", cols, rows, float(parts[2]), asymmetric=shape == "asymmetric")
        if kind == "charuco" and len(parts) in (4, 5):
            dictionary = parts[4].strip().upper() if len(parts) == 5 else "DICT_5X5_100"
            return Board("charuco", cols, rows, float(parts[2]), float(parts[3]), dictionary=dictionary)
    except ValueError as err:
        if str(err):
            raise ValueError(f"--board {text!r}: {err}") from None
    raise ValueError(f"--board {text!r} is not {forms}")
