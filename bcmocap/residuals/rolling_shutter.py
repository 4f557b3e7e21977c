"""Rolling-shutter reprojection (beyond the paper).

A rolling-shutter sensor exposes its rows one after another: row ``r`` of ``H`` at
``(r / (H − 1) − ½) · readout`` frame periods from the frame's timestamp (``readout``: the time from the
first row to the last, in frame periods; the studio's convention, centred on the timestamp). A fast-turning
camera sees the top and the bottom of its image from different poses, and a global-shutter projection
bends the motion to explain it. :class:`RollingShutterReprojection` projects each measurement with the
camera's pose at its row's time, moved from frame ``t`` at the camera's velocity between frames ``t − 1``
and ``t``: ``exp(s · log(T_t T_{t−1}⁻¹)) · T_t`` for ``s`` frame periods (both poses are in the window), so it
is a camera *pair* term; the first frame of a sequence has no previous frame and its measurements drop out.
The readout may be estimated with the motion (the static block :data:`READOUT`, frame periods, added to
the given value), and the intrinsics corrected as by :mod:`.self_calibration`.

Time: a camera's frame ``t`` need not be exposed at the solver's frame time ``t``. Cameras start at
arbitrary sub-frame times and their audio (which synchronises them) lags their video by a latency of their
own, so each camera is off by a constant time offset of its own: the per-camera static block
:data:`TIME_OFFSET` (frame periods, the camera's exposure is that much after the frame's time), estimated
with the motion; the same velocity moves the pose by it (``s · readout + offset`` frame periods).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..cameras import CameraModel
from ..geometry import SE3, transform_points
from .base import CameraPairTerm, CameraView
from .reprojection import check_measurements, window_data
from .self_calibration import INTRINSICS_CORRECTION, corrected_camera, intrinsics_correction
from .variables import Euclidean, PerCamera

#: Static block: the correction to the readout time, in frame periods (one value shared by all cameras).
READOUT = "readout"
#: Static block (per camera): when the camera's frames are exposed after the solver's frame times, frame periods.
TIME_OFFSET = "time_offset"


def time_offsets(num_cameras: int) -> PerCamera:
    """The :data:`TIME_OFFSET` block of a rig of ``num_cameras`` cameras (one value each, frame periods)."""
    return PerCamera(Euclidean(1), num_cameras)


def rolling_shutter_motion(camera: CameraModel, velocity: jax.Array, readout, rows: jax.Array,
                           time_offset=0.0) -> SE3:
    """``(N,)`` how far the camera has moved when its image rows ``rows`` ``(N,)`` (px) are exposed:
    ``exp((s · readout + time_offset) · velocity)`` with ``s = row / (H − 1) − ½`` (``velocity`` ``(6,)``: a left
    increment of ``cam_from_world`` per frame period; ``readout`` and ``time_offset`` in frame periods). The pose at
    a row is this times the frame's ``cam_from_world``: :func:`rolling_shutter_projection`."""
    s = rows / max(camera.height - 1, 1) - 0.5  # (N,) in [-½, ½] over the image
    return SE3.exp((s * readout + time_offset)[:, None] * velocity)


def rolling_shutter_projection(camera: CameraModel, cam_from_world: SE3, velocity: jax.Array, readout,
                               points: jax.Array, rows: jax.Array, time_offset=0.0) -> tuple[jax.Array, jax.Array]:
    """``(N, 2)`` pixels and ``(N,)`` validity of world ``points`` ``(N, 3)``, each seen from the camera's pose at
    the time its image row ``rows`` ``(N,)`` (px) is exposed (:func:`rolling_shutter_motion` ``· cam_from_world``,
    ``time_offset`` frame periods after the frame's time), projected through ``camera``. The one rolling-shutter
    projection of bcmocap: :class:`RollingShutterReprojection` and :mod:`bcmocap.solver.registered_poses` predict
    with it."""
    s = rows / max(camera.height - 1, 1) - 0.5
    return camera.project(moved_points(transform_points(cam_from_world, points), velocity, s * readout + time_offset))


def moved_points(points: jax.Array, velocity: jax.Array, periods: jax.Array) -> jax.Array:
    """``exp(periods[i] · velocity) · points[i]`` ``(N, 3)`` for camera-frame ``points`` ``(N, 3)``, a ``velocity``
    ``(6,)`` (translation, rotation) per frame period and ``periods`` ``(N,)``: the SE(3) exponential in closed form
    (Rodrigues), ``q + A ω×q + B ω×(ω×q) + ε v + B ω×v + C ω×(ω×v)`` with ``θ = |ω|``, ``A = sin(εθ)/θ``,
    ``B = (1 − cos εθ)/θ²`` and ``C = (εθ − sin εθ)/θ³`` (their Taylor series where ``θ < 10⁻³``). Equal to
    :func:`rolling_shutter_motion`'s ``SE3.exp`` applied to the points, about three times cheaper in the solver's
    Jacobians (one sine and cosine per measurement; no quaternions)."""
    v, w = velocity[:3], velocity[3:]
    theta2 = w @ w
    small = theta2 < 1e-6
    safe2 = jnp.where(small, 1.0, theta2)
    theta = jnp.sqrt(safe2)
    e = periods
    sin, cos = jnp.sin(e * theta), jnp.cos(e * theta)
    a = jnp.where(small, e - e**3 * theta2 / 6.0, sin / theta)
    b = jnp.where(small, e**2 / 2.0 - e**4 * theta2 / 24.0, (1.0 - cos) / safe2)
    c = jnp.where(small, e**3 / 6.0 - e**5 * theta2 / 120.0, (e * theta - sin) / (safe2 * theta))
    wq = jnp.cross(w, points)
    wv = jnp.cross(w, v)
    return (points + a[:, None] * wq + b[:, None] * (jnp.cross(w, wq) + wv) + e[:, None] * v
            + c[:, None] * jnp.cross(w, wv))


class RollingShutterReprojection(CameraPairTerm):
    """‖π_c(T_c(t + s_row) · X_p) − x‖² per observation of frame ``t``, in pixels.

    Data as :class:`~.reprojection.Reprojection` (``point_ids``, ``pixels``, ``weights`` ``(T, C, N, …)`` and
    ``points``); row ``t`` holds frame ``t``'s measurements (the pair ``(t − 1, t)`` gives the velocity).

    Attributes:
        points: ``(P, 3)`` world points (m).
        readout: time from the first row to the last, in frame periods of the solver's frames (readout
            seconds × frames per second).
        estimate_readout: also solve for a correction to ``readout`` (static block :data:`READOUT`).
        estimate_time_offsets: also solve for each camera's time offset (static block :data:`TIME_OFFSET`;
            needs ``num_cameras``).
        num_cameras: the rig's camera count, when ``calibrate``.
        calibrate: project through corrected intrinsics (static block ``INTRINSICS_CORRECTION``).
    """

    points: jax.Array = None
    readout: jax.Array = eqx.field(default=0.0, kw_only=True, converter=jnp.asarray)
    estimate_readout: bool = eqx.field(default=False, static=True, kw_only=True)
    estimate_time_offsets: bool = eqx.field(default=False, static=True, kw_only=True)
    calibrate: bool = eqx.field(default=False, static=True, kw_only=True)
    num_cameras: int = eqx.field(default=0, static=True, kw_only=True)

    def static_variables(self):
        blocks = {READOUT: Euclidean(1)} if self.estimate_readout else {}
        if self.calibrate:
            blocks[INTRINSICS_CORRECTION] = intrinsics_correction(self.num_cameras)
        if self.estimate_time_offsets:
            blocks[TIME_OFFSET] = time_offsets(self.num_cameras)
        return blocks

    def window(self, start: int, stop: int) -> RollingShutterReprojection:
        return RollingShutterReprojection(
            window_data(self.data, self.points, start, stop), points=jnp.zeros((0, 3)), readout=self.readout,
            estimate_readout=self.estimate_readout, estimate_time_offsets=self.estimate_time_offsets,
            calibrate=self.calibrate, num_cameras=self.num_cameras, weight=self.weight, loss=self.loss, name=self.name)

    def check(self, num_frames: int, num_cameras: int) -> None:
        check_measurements(self.label, self.data, self.points, num_frames, num_cameras)
        if (self.calibrate or self.estimate_time_offsets) and self.num_cameras != num_cameras:
            raise ValueError(f"{self.label}: num_cameras is {self.num_cameras}, the rig has {num_cameras}")

    def residual(self, x: CameraView, data, variables):
        prev, curr, camera, statics = x[0].cam_from_world, x[1].cam_from_world, x.camera, variables
        readout = self.readout + (statics[READOUT][0] if self.estimate_readout else 0.0)
        if self.calibrate:
            camera = corrected_camera(camera, statics[INTRINSICS_CORRECTION])
        offset = statics[TIME_OFFSET][0] if self.estimate_time_offsets else 0.0
        velocity = (curr @ prev.inverse()).log()  # (6,) left increment per frame period
        predicted, valid = rolling_shutter_projection(camera, curr, velocity, readout, data["points"], data["pixels"][:, 1],
                                                      offset)
        r = (predicted - data["pixels"]) * jnp.sqrt(data["weights"])[:, None]
        return r, valid & (data["weights"] > 0)
