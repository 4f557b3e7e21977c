"""Reprojection of fixed 3D scene points (Eq. 8, first term, with the projection of Eq. 9)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..cameras import CameraModel
from ..geometry import transform_points
from .base import CameraTerm


class Reprojection(CameraTerm):
    """‖π_c(cam_from_world · X_p) − x‖² per observation, in pixels.

    Sequence-level data (numpy or JAX arrays; padded slots have weight 0):
        ``point_ids`` ``(T, C, N)`` int indices into ``points``; ``pixels`` ``(T, C, N, 2)`` measured
        pixel coordinates (OpenCV convention); ``weights`` ``(T, C, N)`` ≥ 0, the inverse variance of
        each measurement in px⁻² (1 for σ = 1 px).
    ``points`` ``(P, 3)``: world coordinates of the scene points (m), held fixed.

    A window gathers the points, so the residual function sees ``data["points"]`` ``(N, 3)``.
    Observations behind the camera or outside the lens model give a zero, masked residual.
    """

    points: jax.Array = None

    def window(self, start: int, stop: int) -> Reprojection:
        return Reprojection(window_data(self.data, self.points, start, stop), points=jnp.zeros((0, 3)), weight=self.weight,
                            loss=self.loss, name=self.name)

    def check(self, num_frames: int, num_cameras: int) -> None:
        check_measurements(self.label, self.data, self.points, num_frames, num_cameras)

    def residual(self, x, data, variables):
        return self.residual_in_camera(transform_points(x.cam_from_world, data["points"]), x.camera, data)

    def world_points(self, data):
        return data["points"]

    def residual_in_camera(self, points_cam, camera: CameraModel, data):
        predicted, valid = camera.project(points_cam)
        r = (predicted - data["pixels"]) * jnp.sqrt(data["weights"])[:, None]
        return r, valid & (data["weights"] > 0)


def window_data(data: dict, points, start: int, stop: int) -> dict:
    """A reprojection term's sequence data (``point_ids``, ``pixels``, ``weights``) cut to frames ``[start, stop)``
    with the points gathered: ``points`` ``(W, C, N, 3)``, ``pixels``, ``weights`` (0 where the id is −1)."""
    ids = np.asarray(data["point_ids"][start:stop])
    points = np.asarray(points)[np.clip(ids, 0, len(points) - 1)]
    return {
        "points": jnp.asarray(points),
        "pixels": jnp.asarray(np.asarray(data["pixels"][start:stop], dtype=np.float64)),
        "weights": jnp.asarray(np.asarray(data["weights"][start:stop], dtype=np.float64) * (ids >= 0)),
    }


def check_measurements(label: str, data: dict, points, num_frames: int, num_cameras: int) -> None:
    """Raise ValueError naming ``label`` and the array if reprojection data do not fit ``(T, C, N)`` or hold NaN/inf."""
    ids = np.asarray(data["point_ids"])
    n = ids.shape[2] if ids.ndim == 3 else None
    shapes = {k: np.shape(v) for k, v in data.items() if k != "points"}
    want = {"point_ids": (num_frames, num_cameras, n), "pixels": (num_frames, num_cameras, n, 2),
            "weights": (num_frames, num_cameras, n)}
    for key, shape in want.items():
        if key not in data:
            raise ValueError(f"{label}: data has no '{key}'")
        if shapes[key] != shape:
            raise ValueError(f"{label}: data['{key}'] has shape {shapes[key]}, expected {shape} (frames, cameras, observations)")
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{label}: points must have shape (P, 3), got {points.shape}")
    if ids.max(initial=-1) >= len(points):
        raise ValueError(f"{label}: point_ids reach {ids.max()} but there are only {len(points)} points")
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{label}: points contain NaN/inf")
    used = np.asarray(data["weights"]) > 0
    pixels = np.asarray(data["pixels"])
    bad = used & ~np.all(np.isfinite(pixels), axis=-1)
    if bad.any():
        t, c, i = np.argwhere(bad)[0]
        raise ValueError(f"{label}: pixels has NaN/inf at frame {t}, camera {c}, observation {i}")
    weights = np.asarray(data["weights"])
    if not np.all(np.isfinite(weights)) or (weights < 0).any():
        raise ValueError(f"{label}: weights must be finite and non-negative")
