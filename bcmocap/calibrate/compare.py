"""How far apart two calibrations of one lens are, in pixels, across the image.

Each pixel of a grid is unprojected by the reference camera and projected by the other: the distance
between the pixel and where the other camera puts that ray is what using the other calibration instead
costs at that pixel. Pixels the reference cannot invert (beyond the angle where its distortion
polynomial stops increasing) are left out and counted.

A difference that a small turn of the camera undoes (a principal point shifted by a decentred lens, a tilted
sensor's first-order shift) costs nothing on the body: the skeleton stage estimates each camera's rotation on
its mount, which takes the turn up. :func:`turned_difference` gives the difference after the turn that best
undoes it, with the turn.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cameras import CameraModel

__all__ = ["CameraDifference", "camera_difference", "pixel_grid", "turned_difference"]


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

    @property
    def rms_px(self) -> float:
        """Root mean square distance (px)."""
        return float(np.sqrt(np.mean(self.distance**2)))


def pixel_grid(width: int, height: int, step: int = 8) -> np.ndarray:
    """``(P, 2)`` pixel centres every ``step`` px, the image's last row and column included."""
    us = np.unique(np.append(np.arange(0, width, step), width - 1))
    vs = np.unique(np.append(np.arange(0, height, step), height - 1))
    u, v = np.meshgrid(us, vs)
    return np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)


def _check_sizes(camera: CameraModel, reference: CameraModel, caller: str) -> None:
    if (camera.width, camera.height) != (reference.width, reference.height):
        raise ValueError(f"{caller}: image sizes differ ({camera.width}x{camera.height} vs "
                         f"{reference.width}x{reference.height})")


def _compared_rays(reference: CameraModel, step: int, mask, max_angle_deg: float) -> tuple[np.ndarray, np.ndarray, int]:
    """``(grid pixels (P, 2), their rays (P, 3), grid size)``: the pixels of the grid (where ``mask`` is true) that
    ``reference`` inverts, within ``max_angle_deg`` of its axis."""
    grid = pixel_grid(reference.width, reference.height, step)
    if mask is not None:
        grid = grid[np.asarray(mask)[grid[:, 1].astype(int), grid[:, 0].astype(int)]]
    rays = np.asarray(reference.unproject(grid))
    back, ok_ref = reference.project(rays)
    keep = (np.asarray(ok_ref) & (np.linalg.norm(np.asarray(back) - grid, axis=1) < 1e-3)
            & (np.degrees(np.arccos(np.clip(rays[:, 2], -1.0, 1.0))) <= max_angle_deg))
    return grid[keep], rays[keep], len(grid)


def _difference(camera: CameraModel, grid: np.ndarray, rays: np.ndarray, size: int, caller: str) -> CameraDifference:
    projected, ok = camera.project(rays)
    ok = np.asarray(ok)
    distance = np.linalg.norm(np.asarray(projected)[ok] - grid[ok], axis=1)
    if not len(distance):
        raise ValueError(f"{caller}: no pixel of the grid could be compared")
    return CameraDifference(grid[ok], distance, float(distance.max()), float(distance.mean()),
                            float(ok.sum() / max(size, 1)))


def camera_difference(camera: CameraModel, reference: CameraModel, *, step: int = 8,
                      mask: np.ndarray | None = None, max_angle_deg: float = 180.0) -> CameraDifference:
    """Distance (px) between ``reference``'s pixels and ``camera``'s projections of their rays.

    Args:
        camera, reference: single cameras of the same image size.
        step: grid spacing (px).
        mask: optional ``(height, width)`` bool: compare only the grid pixels where it is true
            (e.g. where the board was seen).
        max_angle_deg: compare only the pixels whose rays lie within this angle of ``reference``'s axis.
    """
    _check_sizes(camera, reference, "camera_difference")
    return _difference(camera, *_compared_rays(reference, step, mask, max_angle_deg), "camera_difference")


def turned_difference(camera: CameraModel, reference: CameraModel, *, step: int = 4,
                      max_angle_deg: float = 180.0) -> tuple[CameraDifference, float]:
    """:func:`camera_difference` after the rotation of ``camera`` that best aligns the two over the compared pixels
    (least squares), and that rotation's angle (degrees)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    _check_sizes(camera, reference, "turned_difference")
    grid, rays, size = _compared_rays(reference, step, None, max_angle_deg)

    def turned(rotvec):
        moved, ok = camera.project(rays @ Rotation.from_rotvec(rotvec).as_matrix().T)
        return np.where(np.asarray(ok)[:, None], np.asarray(moved) - grid, 0.0).ravel()

    fit = least_squares(turned, np.zeros(3))
    turned_rays = rays @ Rotation.from_rotvec(fit.x).as_matrix().T
    return (_difference(camera, grid, turned_rays, size, "turned_difference"),
            float(np.degrees(np.linalg.norm(fit.x))))
