"""The cameras' gyros: each camera's turn between solver frames is what its gyro integrates to (beyond the paper).

Action cameras record a gyro beside the video (``trials/<trial>/imu.npz``, :mod:`bcmocap.io.sensors`). Where a
camera's frames are too blurred to register (a hand flapping at 1800°/s smears 14° over an 8 ms exposure), nothing
in the images says how it turned, and the gyro still does. :class:`GyroTurn` compares the turn of the camera's
orientation between frames ``t − 1`` and ``t``, ``R_wc(t − 1)ᵀ R_wc(t)``, with the gyro's, in radians, one block of
3 per camera-frame; :func:`bcmocap.pipeline.gyro_turns.gyro_turns` integrates the gyro over each pair of frames
(:func:`~bcmocap.io.sensors.integrate_gyro`), on the gyro's clock: camera ``c``'s frame at trial time ``t`` is read
at ``t + time_shifts[c]``, the shift :mod:`bcmocap.frontend.gyro_timing` finds in the trial's own frames (the IMU
clock's offset and the camera's sub-frame start), and turned into the camera by the IMU's mount
(``camera_from_imu``). Its σ covers the shift's error (a turn over a frame read ``δ`` late moves by
``(ω(t) − ω(t − 1)) δ``: 0.3° for 1 ms, the gyro timing's 0.05 frames, where ω changes by 5 rad/s in a frame, as the
realistic hop's flapping hand does) and the gyro's bias; with a few hundred measurements a registered camera-frame is held by its images, an unregistered one by its
gyro. ``bcmocap run``: ``[solver] gyro_turn = σ`` (degrees).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..geometry import SO3
from .base import CameraPairTerm, CameraView


class GyroTurn(CameraPairTerm):
    """``log(turn_gyro⁻¹ · R_wc(t − 1)ᵀ R_wc(t))`` ``(1, 3)`` rad per camera and frame ``t``, scaled by
    ``√weights``.

    Data ``(T, C, 1, …)`` indexed by the later frame ``t``: ``turn`` ``(T, C, 1, 4)`` the gyro's rotation of the
    camera from frame ``t − 1`` to ``t`` (wxyz, in the camera's frame), ``weights`` ``(T, C, 1)`` rad⁻² (0: no gyro
    reading). Row ``t = 0`` of a sequence has no previous frame and is ignored.
    """

    rotation_only = True

    def check(self, num_frames: int, num_cameras: int) -> None:
        for key in ("turn", "weights"):
            if key not in self.data:
                raise ValueError(f"{self.label}: data has no '{key}'")
        weights, turn = np.asarray(self.data["weights"]), np.asarray(self.data["turn"])
        if weights.shape != (num_frames, num_cameras, 1):
            raise ValueError(f"{self.label}: data['weights'] has shape {weights.shape}, expected "
                             f"({num_frames}, {num_cameras}, 1) (frames, cameras, 1)")
        if turn.shape != (*weights.shape, 4):
            raise ValueError(f"{self.label}: data['turn'] has shape {turn.shape}, expected {(*weights.shape, 4)}")
        if not np.all(np.isfinite(weights)) or (weights < 0).any():
            raise ValueError(f"{self.label}: weights must be finite and non-negative")
        bad = (weights > 0) & ~np.all(np.isfinite(turn), axis=-1)
        if bad.any():
            t, c, _ = np.argwhere(bad)[0]
            raise ValueError(f"{self.label}: turn has NaN/inf at frame {t}, camera {c}")

    def residual(self, x: CameraView, data, variables):
        # cam_from_world rotations C: the camera-frame turn R_wc(t-1)^T R_wc(t) is C(t-1) C(t)^T
        turn = x[0].cam_from_world.rotation() @ x[1].cam_from_world.rotation().inverse()
        r = (SO3(data["turn"][0]).inverse() @ turn).log()[None] * jnp.sqrt(data["weights"])[:, None]
        return r, data["weights"] > 0
