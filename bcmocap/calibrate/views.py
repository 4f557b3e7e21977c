"""Views of a calibration board: images or a video in, board detections out, and a well-spread subset.

A calibration video holds hundreds of near-identical frames; fitting all of them costs time and weights
the lens towards wherever the board lingered. :func:`select_views` keeps a subset that covers the sensor
(a grid of cells, every cell a view's points touched) and differs in position, size and tilt.

Input names are untrusted: an image folder is listed without descending into subfolders, and a file that
resolves outside the folder (a symlink) is skipped, so nothing outside the given folder is read.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from ..io.board import Board, Detection

__all__ = ["BoardViews", "IMAGE_SUFFIXES", "detect_views", "image_files", "select_views", "view_descriptor"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
MIN_POINTS = 6  # a view with fewer board points (ChArUco) constrains too little to keep


@dataclasses.dataclass(frozen=True)
class BoardViews:
    """Board detections of several views, padded to the board's N points.

    Attributes:
        board: the board; its ``points`` are ``(N, 3)`` (m).
        pixels: ``(V, N, 2)`` float64 detected pixels (0 where not seen).
        seen: ``(V, N)`` bool.
        names: ``V`` labels (image file name or ``frame NNNN``).
        width, height: image size (px).
        examined: images or frames looked at; found: of those, views with a usable board.
    """

    board: Board
    pixels: np.ndarray
    seen: np.ndarray
    names: tuple[str, ...]
    width: int
    height: int
    examined: int = 0
    found: int = 0

    @property
    def num_views(self) -> int:
        return len(self.names)

    def subset(self, keep) -> BoardViews:
        keep = np.asarray(keep)
        return dataclasses.replace(self, pixels=self.pixels[keep], seen=self.seen[keep],
                                   names=tuple(np.asarray(self.names, dtype=object)[keep]))


def image_files(folder: str | os.PathLike) -> list[Path]:
    """Image files directly in ``folder`` (sorted by name, numbers in natural order), none outside it."""
    folder = Path(folder)
    root = folder.resolve()
    files = []
    for entry in folder.iterdir():
        if entry.suffix.lower() not in IMAGE_SUFFIXES or not entry.is_file():
            continue
        if root not in entry.resolve().parents:  # a symlink leading out of the folder
            continue
        files.append(entry)

    def natural(p: Path):
        import re

        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]

    return sorted(files, key=natural)


def _usable(board: Board, found: Detection | None) -> bool:
    """At least MIN_POINTS points not all on one line of the board."""
    if found is None or len(found.ids) < MIN_POINTS:
        return False
    xy = board.points[found.ids, :2]
    s = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
    return bool(s[-1] > 0.5 * board.spacing)


def _frames(source: Path, stride: int | None, max_frames: int) -> Iterator[tuple[str, np.ndarray, int]]:
    """``(name, gray image, total)`` of the images in a folder, or of every ``stride``-th video frame."""
    import cv2

    if source.is_dir():
        files = image_files(source)
        for f in files:
            gray = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise ValueError(f"{f}: not a readable image")
            yield f.name, gray, len(files)
        return
    if source.suffix.lower() in IMAGE_SUFFIXES:
        gray = cv2.imread(str(source), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise ValueError(f"{source}: not a readable image")
        yield source.name, gray, 1
        return
    video = cv2.VideoCapture(str(source))
    if not video.isOpened():
        raise ValueError(f"{source}: neither an image folder nor a video OpenCV can open")
    try:
        total = int(video.get(cv2.CAP_PROP_FRAME_COUNT))
        if stride is None:
            stride = max(1, -(-total // max_frames)) if total > 0 else 1
        index = 0
        while video.grab():
            if index % stride == 0:
                ok, image = video.retrieve()
                if not ok:
                    raise ValueError(f"{source}: frame {index} could not be decoded")
                yield f"frame {index}", cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), max(total, index + 1)
            index += 1
        if index == 0:
            raise ValueError(f"{source}: no frame could be decoded")
    finally:
        video.release()


def detect_views(source: str | os.PathLike, board: Board, *, stride: int | None = None, max_frames: int = 300,
                 progress: Callable[[int, int, int], None] | None = None) -> BoardViews:
    """Detect ``board`` in an image folder, one image, or a video (every ``stride``-th frame; by default
    spread so that at most ``max_frames`` are examined).

    Raises:
        ValueError: the source is missing or unreadable, the images differ in size, or no view shows the board.
    """
    source = Path(source)
    if not source.exists():
        raise ValueError(f"{source}: no such file or folder")
    points = len(board.points)
    pixels, seen, names = [], [], []
    size = None
    examined = 0
    for name, gray, total in _frames(source, stride, max_frames):
        if size is None:
            size = gray.shape
        elif gray.shape != size:
            raise ValueError(f"{source}: {name} is {gray.shape[1]}x{gray.shape[0]} px, the first image "
                             f"{size[1]}x{size[0]}: one calibration is for one image size")
        examined += 1
        found = board.detect(gray)
        if _usable(board, found):
            px = np.zeros((points, 2))
            mask = np.zeros(points, bool)
            px[found.ids] = found.pixels
            mask[found.ids] = True
            pixels.append(px)
            seen.append(mask)
            names.append(name)
        if progress is not None:
            progress(examined, total, len(names))
    if examined == 0:
        raise ValueError(f"{source}: no images (expected {', '.join(IMAGE_SUFFIXES)} files or a video)")
    if not names:
        raise ValueError(f"no board found: the {board.describe} was not detected in any of the {examined} "
                         f"{'images' if source.is_dir() else 'frames'} of {source} (check --board: "
                         "chessboard sizes count inner corners)")
    return BoardViews(board, np.stack(pixels), np.stack(seen), tuple(names), int(size[1]), int(size[0]),
                      examined, len(names))


def view_descriptor(views: BoardViews) -> np.ndarray:
    """``(V, 6)`` what tells views apart: centroid (fraction of width and height), size (sqrt of the area
    its points span, fraction of the image), and tilt (an affine fit board → image: anisotropy and its
    direction as a doubled angle)."""
    out = np.zeros((views.num_views, 6))
    scale = np.array([views.width, views.height], np.float64)
    board_xy = views.board.points[:, :2]
    for v in range(views.num_views):
        m = views.seen[v]
        px, xy = views.pixels[v, m], board_xy[m]
        centre = px.mean(axis=0)
        design = np.concatenate([xy - xy.mean(axis=0), np.ones((len(xy), 1))], axis=1)
        affine, *_ = np.linalg.lstsq(design, px - centre, rcond=None)
        u, s, _ = np.linalg.svd(affine[:2].T)
        tilt = 1.0 - s[1] / max(s[0], 1e-12)
        angle = 2.0 * np.arctan2(u[1, 0], u[0, 0])
        cov = np.cov((px / scale).T)
        area = np.sqrt(max(np.linalg.det(cov), 0.0)) ** 0.5
        out[v] = [*(centre / scale), 2.0 * area, tilt * np.cos(angle), tilt * np.sin(angle), tilt]
    return out


def select_views(views: BoardViews, count: int, *, grid: tuple[int, int] = (8, 6)) -> np.ndarray:
    """Indices of at most ``count`` views, chosen greedily: each adds the most sensor cells not yet covered
    (an ``grid`` = (columns, rows) division of the image), ties and later picks going to the view least like
    those already kept (:func:`view_descriptor` distance)."""
    if views.num_views <= count:
        return np.arange(views.num_views)
    cols, rows = grid
    cells = []
    for v in range(views.num_views):
        px = views.pixels[v, views.seen[v]]
        cu = np.clip((px[:, 0] / views.width * cols).astype(int), 0, cols - 1)
        cv = np.clip((px[:, 1] / views.height * rows).astype(int), 0, rows - 1)
        cells.append(set((cv * cols + cu).tolist()))
    desc = view_descriptor(views)
    covered: set[int] = set()
    chosen: list[int] = []
    nearest = np.full(views.num_views, np.inf)
    for _ in range(count):
        gain = np.array([len(c - covered) for c in cells], np.float64)
        novelty = np.where(np.isfinite(nearest), nearest, 10.0)
        score = gain + 4.0 * novelty
        score[chosen] = -np.inf
        best = int(np.argmax(score))
        chosen.append(best)
        covered |= cells[best]
        nearest = np.minimum(nearest, np.linalg.norm(desc - desc[best], axis=1))
    return np.array(sorted(chosen))
