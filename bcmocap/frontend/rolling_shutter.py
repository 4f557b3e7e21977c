"""Rolling-shutter correction of body-camera frames by the cameras' gyros (issue 20; beyond the paper).

A rolling shutter exposes row ``y`` of an ``H``-row frame at ``τ(y) = (y / (H − 1) − ½) · readout`` after the
frame's time (the convention of :mod:`bcmocap.sim.render` and :mod:`bcmocap.residuals.rolling_shutter`). A body
camera turns at up to hundreds of degrees per second, so its view turns by degrees across a 15 ms readout: the
frame is sheared, and registration (PnP), triangulation and tracking, which take all rows as exposed at once,
place the camera centimetres off (about 6 cm at 120–240°/s on the realism captures). The camera's translation
across the readout matters far less (2 m/s × 7.5 ms = 1.5 cm, against scene points metres away).

Action cameras carry a gyro, and so do the studio's (``trials/<trial>/imu.npz``, :mod:`bcmocap.io.sensors`).
With the camera's mean angular velocity ``ω`` over the frame's readout (integrated from the gyro and turned into
the camera frame by the IMU's mount), the row exposed ``τ`` after the frame time saw the world through
``R(t + τ) = R(t) · exp(τ [ω]×)``: a direction with bearing ``b`` in the camera at the frame time appears at bearing
``exp(−τ [ω]×) b``. :class:`GyroUnwarp` resamples each frame into the image a global shutter would have taken
at the frame time, under the rotation alone: every output pixel is unprojected through the camera's lens,
turned to the time of the row it falls in (a fixed point: that row depends on where it falls; 3 iterations),
projected, and the frame is sampled there (``cv2.remap``, bicubic, edges replicated). The map is computed on a
grid every ``grid_px`` pixels and interpolated bilinearly in between (the displacement is smooth).

Frame times: video frame ``i`` of camera ``c`` shows the synchronised time ``(i − offsets[c]) / fps + time_shifts[c]``
(``offsets``: each camera's video frame of the first clap, :mod:`~.sync`), on the clock of ``imu.npz`` (0 at the first
clap). The shifts are 0 when the clocks are trusted, or what :mod:`~.gyro_timing` found in the frames (a sub-frame
start, the IMU clock's offset). Frames outside the gyro's time span take the nearest span's angular velocity.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..geometry import matrix_from_quat, quat_log
from ..io.sensors import IMU_FILE, ImuRecording, integrate_gyro, read_imu
from .capture import lens_fingerprint

__all__ = ["GyroUnwarp", "check_readout", "gyro_file", "gyro_fingerprint", "gyro_unwarp", "imu_indices"]

#: Fixed-point iterations for the row an output pixel falls in (the row moves by the displacement's
#: vertical part, a few pixels: 3 iterations leave it to well below 0.01 px).
ROW_ITERATIONS = 3
#: How the map is made (saved with the settings, so frames corrected by an older map are not taken for these): 2, a
#: grid covering the image (its last row and column at or past the image's) interpolated by ``cv2.warpAffine``; 1
#: (unmarked), a grid ending on the last pixel, interpolated in numpy (at the default 8 px grid, maps within 1e-4 px of
#: these, 0.003 px in the last grid cell of rows and columns).
MAP_VERSION = 2
#: Frames whose mean angular velocity is kept (a few hundred bytes each; the oldest dropped first).
OMEGA_CACHE = 20000


def _turned(rotvec, vector):
    """``vector (..., 3)`` turned by the rotation vectors ``rotvec (..., 3)`` (rad; Rodrigues, series near 0)."""
    theta2 = jnp.sum(rotvec * rotvec, axis=-1, keepdims=True)
    small = theta2 < 1e-12
    theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
    sin_over = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    cos_term = jnp.where(small, 0.5 - theta2 / 24.0, 2.0 * jnp.sin(0.5 * theta) ** 2 / jnp.where(small, 1.0, theta2))
    return vector + sin_over * jnp.cross(rotvec, vector) + cos_term * jnp.cross(rotvec, jnp.cross(rotvec, vector))


@eqx.filter_jit
def _grid_shift(lens, bearing, grid, omega, readout_s, last_row):
    """``(gh, gw, 2)`` where each grid pixel ``grid`` (bearings ``bearing``) lies in the rolling-shutter frame, less
    the grid pixel: the fixed point of the row it falls in (module docstring)."""
    source = grid
    for _ in range(ROW_ITERATIONS):
        tau = (source[..., 1:2] / last_row - 0.5) * readout_s
        projected, valid = lens.project(_turned(-tau * omega, bearing))
        source = jnp.where(valid[..., None], projected, grid)
    return source - grid


@dataclasses.dataclass(frozen=True, eq=False)
class GyroUnwarp:
    """The rolling-shutter correction of one trial's frames (module docstring).

    Attributes:
        lenses: per capture camera, its :class:`~bcmocap.cameras.CameraModel` (the image size is the frame's).
        imu: the trial's gyro recording.
        imu_index: ``(C,)`` each capture camera's sensor in ``imu`` (every camera must carry one).
        offsets: ``(C,)`` each camera's video frame of the first clap.
        fps: video frame rate (Hz).
        readout_s: time from the first row to the last (s), in ``(0, 1 / fps]``.
        grid_px: spacing of the grid the map is computed on (px).
        time_shifts: ``(C,)`` s added to each camera's frame times (None: zeros).
    """

    lenses: tuple
    imu: ImuRecording
    imu_index: tuple[int, ...]
    offsets: tuple[int, ...]
    fps: float
    readout_s: float
    grid_px: int = 8
    time_shifts: tuple[float, ...] | None = None

    def __post_init__(self):
        if self.time_shifts is None:
            object.__setattr__(self, "time_shifts", (0.0,) * len(self.offsets))
        object.__setattr__(self, "time_shifts", tuple(float(t) for t in np.asarray(self.time_shifts).ravel()))
        if len(self.time_shifts) != len(self.offsets) or not np.all(np.isfinite(self.time_shifts)):
            raise ValueError(f"GyroUnwarp: time_shifts must be {len(self.offsets)} finite values (s), got {self.time_shifts}")
        if not 0.0 < self.readout_s <= 1.0 / self.fps:
            raise ValueError(f"rolling-shutter readout {self.readout_s} s must lie in (0, {1.0 / self.fps:.6g}] s "
                             f"(one frame period at {self.fps:g} fps)")
        if not len(self.lenses) == len(self.imu_index) == len(self.offsets):
            raise ValueError(f"GyroUnwarp: {len(self.lenses)} lenses, {len(self.imu_index)} IMU indices and "
                             f"{len(self.offsets)} offsets; expected one of each per camera")
        if self.grid_px < 2:
            raise ValueError(f"GyroUnwarp: grid_px must be at least 2, got {self.grid_px}")

    @functools.cached_property
    def settings(self) -> dict:
        """What the corrected frames depend on besides the videos (for caches and saved registrations): the readout,
        the map's grid, and hashes of the lenses and of the gyro recording."""
        gyro = hashlib.sha256()
        for array in (self.imu.time, self.imu.gyro, self.imu.camera_from_imu, np.asarray(self.imu_index),
                      np.asarray(self.offsets), *([np.asarray(self.time_shifts)] if any(self.time_shifts) else [])):
            gyro.update(np.ascontiguousarray(array, np.float64).tobytes())
        return {"gyro_unwarp": {"readout_s": float(self.readout_s), "grid_px": int(self.grid_px),
                                "iterations": ROW_ITERATIONS, "map": MAP_VERSION, "lenses": lens_fingerprint(self.lenses),
                                "gyro": gyro.hexdigest()[:16]}}

    def frame_time(self, camera: int, index: int) -> float:
        """Synchronised time (s) of video frame ``index`` of camera ``camera``."""
        return (int(index) - int(self.offsets[camera])) / self.fps + self.time_shifts[camera]

    def angular_velocity(self, camera: int, index: int) -> np.ndarray:
        """``(3,)`` mean angular velocity of the camera over the frame's readout, in the camera frame (rad/s); kept
        per frame (the frontend reads a frame more than once)."""
        key = (int(camera), int(index))
        found = self._omegas.get(key)
        if found is None:
            found = self._angular_velocity(*key)
            found.setflags(write=False)
            with self._omega_lock:
                self._omegas[key] = found
                while len(self._omegas) > OMEGA_CACHE:  # the oldest first (frames are read roughly in order)
                    self._omegas.pop(next(iter(self._omegas)))
        return found

    def _angular_velocity(self, camera: int, index: int) -> np.ndarray:
        time = self.imu.time
        half = 0.5 * self.readout_s
        t = float(np.clip(self.frame_time(camera, index), time[0] + half, time[-1] - half))
        s = self.imu_index[camera]
        # the samples around the readout only (the integration reads the 4 nearest to each instant): the cost of a
        # frame does not grow with the recording's length
        # (t ± half within the span: clipped to it, t − half can land an ulp before the first sample)
        start, stop = max(t - half, float(time[0])), min(t + half, float(time[-1]))
        lo = max(int(np.searchsorted(time, start)) - 4, 0)
        hi = min(int(np.searchsorted(time, stop)) + 4, len(time))
        q = integrate_gyro(time[lo:hi], self.imu.gyro[lo:hi, s:s + 1], start, stop)[0]  # (4,) IMU frame
        camera_from_imu = matrix_from_quat(self.imu.camera_from_imu[s, :4])
        return np.asarray(camera_from_imu @ quat_log(q) / self.readout_s, np.float64)

    @functools.cached_property
    def _omegas(self) -> dict:
        return {}  # (camera, video frame) -> (3,) rad/s, at most OMEGA_CACHE of them

    @functools.cached_property
    def _omega_lock(self):
        import threading

        return threading.Lock()

    def __getstate__(self) -> dict:
        """Pickled without what is kept per camera and frame (a cluster task builds its own)."""
        return {k: v for k, v in self.__dict__.items() if k not in ("_tables", "_omegas", "_omega_lock")}

    @functools.cached_property
    def _tables(self) -> list:
        """Per camera what does not change from frame to frame: the grid ``(gh, gw, 2)``, every ``grid_px``-th pixel
        from the first to one at or past the last, its bearings ``(gh, gw, 3)``, and ``(H, W, 2)`` float32 every
        pixel's own position."""
        tables = []
        for lens in self.lenses:
            width, height = int(lens.width), int(lens.height)
            xs = self.grid_px * np.arange(-(-(width - 1) // self.grid_px) + 1, dtype=np.float64)
            ys = self.grid_px * np.arange(-(-(height - 1) // self.grid_px) + 1, dtype=np.float64)
            grid = np.stack(np.meshgrid(xs, ys), axis=-1)
            pixels = np.stack(np.meshgrid(np.arange(width), np.arange(height)), axis=-1).astype(np.float32)
            tables.append((grid, np.asarray(lens.unproject(grid), np.float64), pixels))
        return tables

    def source_pixels(self, camera: int, index: int) -> np.ndarray:
        """``(H, W, 2)`` float32: where output pixel ``(x, y)`` of video frame ``index`` of ``camera`` lies in the
        rolling-shutter frame (OpenCV pixels), for ``cv2.remap``. The displacement is computed on the grid and
        interpolated bilinearly in between (``cv2.warpAffine`` at ``1 / grid_px``: its sample positions, multiples
        of ``1 / grid_px``, are exact in its 1/32 grid-cell steps for a grid of 2, 4, 8, 16 or 32 px; for other
        spacings a position is rounded to 1/32 of a cell, about 1e-3 px of a smooth map)."""
        import cv2

        grid, bearing, pixels = self._tables[camera]
        lens = self.lenses[camera]
        shift = np.asarray(_grid_shift(lens, bearing, grid, self.angular_velocity(camera, index),  # arrays: traced,
                                       np.float64(self.readout_s), np.float64(max(int(lens.height) - 1, 1))),  # not static
                           np.float32)
        scale = 1.0 / self.grid_px
        full = cv2.warpAffine(shift, np.array([[scale, 0.0, 0.0], [0.0, scale, 0.0]]), (pixels.shape[1], pixels.shape[0]),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
        return cv2.add(full, pixels)

    def __call__(self, camera: int, index: int, image: np.ndarray) -> np.ndarray:
        """Video frame ``index`` of ``camera`` (``(H, W)`` or ``(H, W, 3)`` uint8) as a global shutter at the frame
        time would have taken it (rotation only)."""
        import cv2

        lens = self.lenses[camera]
        if image.shape[:2] != (int(lens.height), int(lens.width)):
            raise ValueError(f"GyroUnwarp: camera {camera}'s frame is {image.shape[1]}x{image.shape[0]} px, its "
                             f"intrinsics say {int(lens.width)}x{int(lens.height)}")
        return cv2.remap(image, self.source_pixels(camera, index), None, cv2.INTER_CUBIC,
                         borderMode=cv2.BORDER_REPLICATE)


def check_readout(readout_s: float, fps: float) -> None:
    """ValueError naming ``frontend.rolling_shutter_readout`` unless ``0 < readout_s ≤ 1 / fps`` (a frame period)."""
    if not 0.0 < readout_s <= 1.0 / fps:
        raise ValueError(f"frontend.rolling_shutter_readout (--rolling-shutter-readout) {readout_s:g} s must lie in "
                         f"(0, {1.0 / fps:.6g}] s: at most one frame period at {fps:g} fps")


def gyro_file(capture, trial: str) -> Path:
    """``trials/<trial>/imu.npz`` of a capture, which must exist (ValueError naming it otherwise)."""
    path = Path(capture.path) / "trials" / trial / IMU_FILE
    if not path.is_file():
        raise ValueError(f"{path}: missing; frontend.rolling_shutter_readout corrects the rolling shutter with the "
                         f"cameras' gyros (set it to 0 for a capture without them)")
    return path


def gyro_fingerprint(capture, trial: str) -> str:
    """A hash of the trial's gyro file (saved registrations made with the correction record it)."""
    return hashlib.sha256(gyro_file(capture, trial).read_bytes()).hexdigest()[:16]


def imu_indices(capture, path: Path, imu: ImuRecording) -> tuple[int, ...]:
    """Each capture camera's sensor in ``imu`` (read from ``path``; ValueError naming it for a camera without one)."""
    index = []
    for camera in capture.cameras:
        if camera.name not in imu.cameras:
            raise ValueError(f"{path}: no IMU for camera {camera.name!r} (IMUs: {list(imu.cameras)}); "
                             f"frontend.rolling_shutter_readout needs one in every camera")
        index.append(imu.cameras.index(camera.name))
    return tuple(index)


def gyro_unwarp(capture, trial: str, offsets, readout_s: float, *, grid_px: int = 8, time_shifts=None) -> GyroUnwarp:
    """The :class:`GyroUnwarp` of a capture's trial, from ``trials/<trial>/imu.npz`` and the cameras' intrinsics
    (``time_shifts``: ``(C,)`` s added to the frame times, e.g. from :mod:`~.gyro_timing`; None: zeros).

    Raises:
        ValueError: naming the file when the trial has no gyro recording, or the camera that carries no IMU.
    """
    check_readout(readout_s, capture.fps)
    path = gyro_file(capture, trial)
    imu = read_imu(path)
    if imu.time[-1] - imu.time[0] < readout_s:
        raise ValueError(f"{path}: the gyro recording lasts {imu.time[-1] - imu.time[0]:.4g} s, less than one "
                         f"{readout_s:g} s readout")
    index = imu_indices(capture, path, imu)
    offsets = tuple(int(o) for o in np.asarray(offsets).ravel())
    return GyroUnwarp(tuple(c.intrinsics for c in capture.cameras), imu, index, offsets, float(capture.fps),
                      float(readout_s), grid_px, None if time_shifts is None else tuple(np.asarray(time_shifts, float)))
