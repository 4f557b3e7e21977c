"""The cameras' own IMUs on a trial's clock: the ``imu.npz`` that ``bcmocap init`` writes from camera files.

Action cameras record a gyroscope and an accelerometer in their files (GoPro: the GPMF track,
:mod:`bcmocap.io.gopro`), each camera on its own clock: sample times in seconds after the file's first video frame.
A trial's ``imu.npz`` (:mod:`bcmocap.io.sensors`) holds every camera's samples on one grid of the trial's clock,
0 at the first clap, the clock the frontend gives video frames: frame ``i`` of camera ``c``'s stretch of the trial is
at ``(i − offsets[c]) / fps`` (``offsets``: the claps' frames, :mod:`~.sync`). :func:`trial_imu` puts a sample at
``τ`` s of its file at ``τ − (first_frame + offsets[c]) / fps``, the time of the frame the file shows at ``τ``, and
interpolates each camera's samples (linearly) onto one grid at the cameras' median gyro rate, over the span every
camera with telemetry covers. What this leaves off (the telemetry's time base, tens of milliseconds; the claps'
sub-frame part) the frontend's gyro timing finds in the frames (:mod:`~.gyro_timing`).

A camera without telemetry is left out of the file (its gyro terms are then off); a trial where no camera has any
gets no ``imu.npz``; a camera whose telemetry has a gyroscope but no accelerometer stops ``init``, named.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..io.gopro import GoProImu
from ..io.sensors import ImuRecording

__all__ = ["CameraTelemetry", "trial_imu"]


@dataclasses.dataclass(frozen=True)
class CameraTelemetry:
    """One camera's telemetry and where its trial sits in its file.

    Attributes:
        camera: its name. imu: what its file holds (None: no telemetry).
        first_frame, num_frames: the trial's stretch of the file (frames). offset: the stretch's frame of the first
            clap. fps: the file's frame rate (Hz).
    """

    camera: str
    imu: GoProImu | None
    first_frame: int
    num_frames: int
    offset: int
    fps: float


def trial_imu(cameras: list[CameraTelemetry], *, where: str = "trial") -> ImuRecording | None:
    """The trial's ``imu.npz`` content from its cameras' telemetry (module docstring), or None where no camera has
    any. ValueError naming ``where`` and the cameras where their telemetry does not overlap in time."""
    found = [c for c in cameras if c.imu is not None]
    if not found:
        return None
    shifted = []
    for c in found:
        zero = (c.first_frame + c.offset) / c.fps  # the first clap, in s after the file's first frame
        shifted.append((c.imu.gyro.time_s - zero, c.imu.accel.time_s - zero if c.imu.accel is not None else None))
    start = max(max(g[0], -c.offset / c.fps) for (g, _), c in zip(shifted, found))  # within the trial's stretch
    stop = min(min(g[-1], (c.num_frames - 1 - c.offset) / c.fps) for (g, _), c in zip(shifted, found))
    for _, a in shifted:
        if a is not None:
            start, stop = max(start, a[0]), min(stop, a[-1])
    if not stop > start:
        raise ValueError(f"{where}: the telemetry of cameras {[c.camera for c in found]} does not overlap in time "
                         f"(the trial's clock: {start:.3f} to {stop:.3f} s)")
    rate = float(np.median([c.imu.gyro.rate_hz for c in found]))
    time = start + np.arange(int(np.floor((stop - start) * rate)) + 1) / rate
    gyro = np.stack([_interpolate(t, c.imu.gyro.values, time) for (t, _), c in zip(shifted, found)], axis=1)
    accel = np.stack([_interpolate(a, c.imu.accel.values, time) if a is not None else np.full((len(time), 3), np.nan)
                      for (_, a), c in zip(shifted, found)], axis=1)
    if np.isnan(accel).any():  # a camera without an accelerometer: its accel terms cannot be used
        raise ValueError(f"{where}: cameras {[c.camera for c in found if c.imu.accel is None]} have a gyroscope but "
                         "no accelerometer in their telemetry")
    mounts = np.array([np.concatenate([c.imu.camera_from_imu, np.zeros(3)]) for c in found])
    return ImuRecording(time, rate, tuple(c.camera for c in found), mounts, gyro, accel)


def _interpolate(times: np.ndarray, values: np.ndarray, at: np.ndarray) -> np.ndarray:
    """``(len(at), 3)``: ``values`` ``(N, 3)`` sampled at ``times`` ``(N,)``, linearly interpolated at ``at``."""
    return np.stack([np.interp(at, times, values[:, k]) for k in range(values.shape[1])], axis=1)
