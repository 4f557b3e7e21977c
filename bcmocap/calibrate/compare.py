"""How far apart two calibrations of one lens are, in pixels, across the image.

Each pixel of a grid is unprojected by the reference camera and projected by the other: the distance
between the pixel and where the other camera puts that ray is what using the other calibration instead
costs at that pixel. Pixels the reference cannot invert (beyond the angle where its distortion
polynomial stops increasing) are left out and counted.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cameras import CameraModel

__all__ = ["CameraDifference", "camera_difference", "pixel_grid"]


@dataclasses.dataclass(frozen=True)
class CameraDifference:
    """Pixel distance between two calibrations over a grid.

    Attributes:
        pixels: ``(P, 2)`` grid pixels compared; distance: ``(P,)`` px.
        max_px, mean_px: largest and mean distance; compared: fraction of the grid the reference inverts.
    """

    pixels: np.ndarray
    distance: np.ndarray
    max_px: float
    mean_px: float
    compared: float


def pixel_grid(width: int, height: int, step: int = 8) -> np.ndarray:
    """``(P, 2)`` pixel centres every ``step`` px, the image's last row and column included."""
    us = np.unique(np.append(np.arange(0, width, step), width - 1))
    vs = np.unique(np.append(np.arange(0, height, step), height - 1))
    u, v = np.meshgrid(us, vs)
    return np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)


def camera_difference(camera: CameraModel, reference: CameraModel, *, step: int = 8,
                      mask: np.ndarray | None = None) -> CameraDifference:
    """Distance (px) between ``reference``'s pixels and ``camera``'s projections of their rays.

    Args:
        camera, reference: single cameras of the same image size.
        step: grid spacing (px).
        mask: optional ``(height, width)`` bool: compare only the grid pixels where it is true
            (e.g. where the board was seen).
    """
    if (camera.width, camera.height) != (reference.width, reference.height):
        raise ValueError(f"camera_difference: image sizes differ ({camera.width}x{camera.height} vs "
                         f"{reference.width}x{reference.height})")
    grid = pixel_grid(reference.width, reference.height, step)
    if mask is not None:
        grid = grid[np.asarray(mask)[grid[:, 1].astype(int), grid[:, 0].astype(int)]]
    rays = np.asarray(reference.unproject(grid))
    back, ok_ref = reference.project(rays)
    inverted = np.asarray(ok_ref) & (np.linalg.norm(np.asarray(back) - grid, axis=1) < 1e-3)
    projected, ok = camera.project(rays)
    keep = inverted & np.asarray(ok)
    distance = np.linalg.norm(np.asarray(projected)[keep] - grid[keep], axis=1)
    if not len(distance):
        raise ValueError("camera_difference: no pixel of the grid could be compared")
    return CameraDifference(grid[keep], distance, float(distance.max()), float(distance.mean()),
                            float(keep.sum() / max(len(grid), 1)))
