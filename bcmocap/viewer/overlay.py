"""A camera's video frame with its measurements and their reprojections drawn on it (residual lines).

Each measured pixel is a green dot; the scene point it measures, projected through the camera's own lens
model at the pose being viewed, is a red dot; a yellow line joins them. A bad registration or a wrong
mount shows as long, parallel lines.
"""

from __future__ import annotations

import numpy as np

from ..geometry import matrix_from_quat
from .inputs import CameraFrame

GREEN, RED, YELLOW = (60, 220, 60), (235, 50, 50), (250, 220, 40)


def reprojections(camera, world_from_camera, points) -> tuple[np.ndarray, np.ndarray]:
    """``(N, 2)`` pixels of ``points`` ``(N, 3)`` (m) through ``camera`` (a single
    :class:`~bcmocap.cameras.CameraModel`) at ``world_from_camera`` ``(7,)``, and an ``(N,)`` mask of those in
    front of the lens and in the image."""
    pose = np.asarray(world_from_camera, np.float64)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if not len(points) or not np.isfinite(pose).all():
        return np.zeros((len(points), 2)), np.zeros(len(points), bool)
    in_camera = (points - pose[4:]) @ matrix_from_quat(pose[:4])
    pixels, valid = camera.project(in_camera)
    pixels, valid = np.asarray(pixels), np.asarray(valid) & np.asarray(camera.in_image(pixels))
    return pixels, valid


def residual_image(frame: CameraFrame, camera, world_from_camera, width: int = 640) -> tuple[np.ndarray, dict]:
    """The frame scaled to ``width`` px with measurements, reprojections and residual lines.

    Returns:
        ``(image, stats)``: RGB uint8, and ``{"measurements", "reprojected", "median_px", "max_px"}``
        (residuals in the frame's full-resolution pixels; NaN when nothing reprojects).
    """
    import cv2

    image = np.ascontiguousarray(frame.image)
    scale = width / image.shape[1] if image.shape[1] > width else 1.0
    if scale != 1.0:
        image = cv2.resize(image, (width, round(image.shape[0] * scale)), interpolation=cv2.INTER_AREA)
    image = image.copy()
    projected, valid = reprojections(camera, world_from_camera, frame.points)
    measured = np.asarray(frame.pixels, np.float64).reshape(-1, 2)
    residual = np.linalg.norm(projected - measured, axis=-1)[valid]

    def at(p):
        return int(round((p[0] + 0.5) * scale - 0.5)), int(round((p[1] + 0.5) * scale - 0.5))

    for m, p, ok in zip(measured, projected, valid):
        if ok:
            cv2.line(image, at(m), at(p), YELLOW, 1, cv2.LINE_AA)
    for m, p, ok in zip(measured, projected, valid):
        cv2.circle(image, at(m), 2, GREEN, -1, cv2.LINE_AA)
        if ok:
            cv2.circle(image, at(p), 2, RED, -1, cv2.LINE_AA)
    stats = {"measurements": len(measured), "reprojected": int(valid.sum()),
             "median_px": float(np.median(residual)) if residual.size else float("nan"),
             "max_px": float(residual.max()) if residual.size else float("nan")}
    return image, stats
