"""Simulated views of a hand-held calibration board in front of a lens (ground truth for calibration).

Each view puts the board's centre on the ray of a random pixel of the image (so that views reach the
whole sensor, corners included), at a random distance, facing the camera and tilted by up to
``max_tilt_deg`` about a random axis in its plane, turned at random in its plane. A point counts as
seen when it projects inside the image and the board faces the camera there; detected pixels get
Gaussian noise.
"""

from __future__ import annotations

import numpy as np

from ..cameras import CameraModel
from ..geometry import SO3

__all__ = ["simulate_board_views"]


def _frame_facing(direction: np.ndarray) -> np.ndarray:
    """Rotation whose third column is ``-direction`` (the board normal looks back at the camera)."""
    z = -direction / np.linalg.norm(direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def simulate_board_views(camera: CameraModel, points: np.ndarray, count: int, rng: np.random.Generator, *,
                         noise_px: float = 0.1, distance_m: tuple[float, float] = (0.25, 0.6),
                         max_tilt_deg: float = 45.0, min_points: int = 12, margin_px: float = 2.0,
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` views of a planar board through ``camera``.

    Args:
        camera: a single camera.
        points: ``(N, 3)`` board points in the board frame (m, z = 0).
        count: views to return (views showing fewer than ``min_points`` points are redrawn).
        noise_px: standard deviation of the detection noise (px).
        margin_px: points closer than this to the image border are not seen (a detector needs a window).

    Returns:
        ``(pixels (V, N, 2), seen (V, N) bool, camera_from_board (V, 4, 4))``.
    """
    points = np.asarray(points, np.float64)
    centre = points.mean(axis=0)
    pixels, seen, poses = [], [], []
    attempts = 0
    while len(pixels) < count:
        attempts += 1
        if attempts > 100 * count:
            raise ValueError("simulate_board_views: could not place the board in view (board too large for the lens?)")
        target = rng.uniform([0.0, 0.0], [camera.width - 1.0, camera.height - 1.0])
        direction = np.asarray(camera.unproject(target))
        tilt_axis = rng.normal(size=2)
        tilt_axis = np.array([*tilt_axis / np.linalg.norm(tilt_axis), 0.0])
        tilt = np.radians(rng.uniform(0.0, max_tilt_deg))
        spin = rng.uniform(-np.pi, np.pi)
        board_rot = (_frame_facing(direction) @ np.asarray(SO3.exp(tilt * tilt_axis).as_matrix())
                     @ np.asarray(SO3.exp(np.array([0.0, 0.0, spin])).as_matrix()))
        translation = rng.uniform(*distance_m) * direction - board_rot @ centre
        cam_points = points @ board_rot.T + translation
        projected, valid = camera.project(cam_points)
        projected, valid = np.asarray(projected), np.asarray(valid)
        normal = board_rot[:, 2]
        facing = (cam_points @ normal) < -0.05 * np.linalg.norm(cam_points, axis=1)  # front side towards the lens
        inside = ((projected[:, 0] >= margin_px) & (projected[:, 0] <= camera.width - 1 - margin_px)
                  & (projected[:, 1] >= margin_px) & (projected[:, 1] <= camera.height - 1 - margin_px))
        mask = valid & facing & inside
        if mask.sum() < min_points:
            continue
        noisy = projected + rng.normal(scale=noise_px, size=projected.shape)
        pixels.append(np.where(mask[:, None], noisy, 0.0))
        seen.append(mask)
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = board_rot, translation
        poses.append(pose)
    return np.stack(pixels), np.stack(seen), np.stack(poses)
