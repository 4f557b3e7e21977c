"""Homography transfer for frames a camera could not register (Eq. 8, second term; Eq. 2).

Between consecutive frames of one camera the paper neglects the camera's translation, so a feature
seen at ``x_t`` is seen at ``x_{t-1} = H x_t`` with ``H = K R_{t-1←t} K⁻¹``. For wide fisheye lenses
the same transfer is done on rays: unproject ``x_t``, rotate by ``R_{t-1←t}`` (from the two camera
orientations, hence from the joint angles), project, compare with ``x_{t-1}`` in pixels.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..geometry import rotate_vectors
from .base import CameraPairTerm, slot_cameras


class HomographyTransfer(CameraPairTerm):
    """Rotation-only transfer of 2D–2D matches between frames ``t-1`` and ``t`` of one camera.

    Data ``(T, C, M, ...)`` indexed by the later frame ``t``: ``pixels`` ``(T, C, M, 2)`` in frame t,
    ``pixels_prev`` ``(T, C, M, 2)`` the matched pixels in frame t-1, ``weights`` ``(T, C, M)`` in
    px⁻² (0 for padding). Row ``t = 0`` of a sequence has no previous frame and is ignored. Matches
    exist only where a camera could not register, so the data may use camera slots (``"camera"``
    ``(T, K)``, see :func:`bcmocap.residuals.camera_slots`): axis 1 then has K ≪ C entries.
    """

    rotation_only = True  # camera translation is neglected between consecutive frames (Eq. 2)

    def check(self, num_frames: int, num_cameras: int) -> None:
        for key in ("pixels", "pixels_prev", "weights"):
            if key not in self.data:
                raise ValueError(f"{self.label}: data has no '{key}'")
        weights = np.asarray(self.data["weights"])
        slots = slot_cameras(self.data)
        lead = self.leading_axes(num_frames, num_cameras)
        if weights.ndim != 3 or weights.shape[:2] != lead:
            across = "cameras" if slots is None else "camera slots"
            raise ValueError(f"{self.label}: data['weights'] has shape {weights.shape}, expected ({lead[0]}, {lead[1]}, M) (frames, {across}, matches)")
        if not np.all(np.isfinite(weights)) or (weights < 0).any():
            raise ValueError(f"{self.label}: weights must be finite and non-negative")
        for key in ("pixels", "pixels_prev"):
            pixels = np.asarray(self.data[key])
            if pixels.shape != (*weights.shape, 2):
                raise ValueError(f"{self.label}: data['{key}'] has shape {pixels.shape}, expected {(*weights.shape, 2)}")
            bad = (weights > 0) & ~np.all(np.isfinite(pixels), axis=-1)
            if bad.any():
                t, c, i = np.argwhere(bad)[0]
                if slots is not None:
                    c = int(np.asarray(slots)[t, c])
                raise ValueError(f"{self.label}: {key} has NaN/inf at frame {t}, camera {c}, match {i}")

    def residual(self, x, data, variables):
        camera = x.camera
        rays = camera.unproject(data["pixels"])
        prev_from_curr = x[0].cam_from_world.rotation() @ x[1].cam_from_world.rotation().inverse()
        predicted, valid = camera.project(rotate_vectors(prev_from_curr, rays))
        r = (predicted - data["pixels_prev"]) * jnp.sqrt(data["weights"])[:, None]
        return r, valid & (data["weights"] > 0)
