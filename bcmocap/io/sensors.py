"""Wearable-sensor files of a capture trial: the IMU in each body camera and foot-contact flags.

Two files per trial folder (``<capture>/trials/<trial>/``), numpy ``.npz`` archives written without pickles:

``imu.npz`` (:class:`ImuRecording`)
    ``time`` ``(N,)`` float64 s on the capture's synchronised clock (0 at the trial's first clap),
    ``rate`` ``()`` float64 Hz, ``cameras`` ``(S,)`` str (the cameras carrying an IMU),
    ``camera_from_imu`` ``(S, 7)`` wxyz_xyz (the IMU's pose in its camera's frame, from calibration),
    ``gyro`` ``(N, S, 3)`` rad/s (angular velocity of the IMU frame, in the IMU frame),
    ``accel`` ``(N, S, 3)`` m/s² (specific force in the IMU frame: ``R_world_imuᵀ (a_world − g_world)``,
    ``g_world = (0, 0, −9.81)``, so an IMU at rest reads +9.81 m/s² along world up).

``contacts.npz`` (:class:`ContactRecording`)
    ``time`` ``(N,)`` float64 s (same clock), ``segments`` ``(F,)`` str (skeleton segments whose joint
    centre, the segment frame's origin, is planted when flagged), ``in_contact`` ``(N, F)`` bool.

Trial frame ``f`` of a capture is at time ``(f − clap_frames[0]) / fps`` (``clap_frames`` from the ground
truth). :func:`integrate_gyro` turns gyro samples into relative IMU rotations between two times; it needs
nothing beyond numpy, so residual terms can use it without :mod:`bcmocap.sim`.
"""

from __future__ import annotations

import dataclasses
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..atomic import write_npz_atomic
from ..geometry import quat_conjugate, quat_exp, quat_multiply

__all__ = [
    "CONTACTS_FILE",
    "IMU_FILE",
    "ContactRecording",
    "ImuRecording",
    "integrate_gyro",
    "read_contacts",
    "read_imu",
    "write_contacts",
    "write_imu",
]

IMU_FILE = "imu.npz"
CONTACTS_FILE = "contacts.npz"


@dataclasses.dataclass(frozen=True)
class ImuRecording:
    """One trial of the IMUs inside the body cameras (``N`` samples, ``S`` sensors).

    Attributes:
        time: ``(N,)`` s, strictly increasing, 0 at the trial's first clap.
        rate: sample rate (Hz).
        cameras: ``(S,)`` names of the cameras carrying the IMUs.
        camera_from_imu: ``(S, 7)`` wxyz_xyz pose of each IMU in its camera's frame (m).
        gyro: ``(N, S, 3)`` angular velocity of the IMU frame relative to the world, in the IMU frame (rad/s).
        accel: ``(N, S, 3)`` specific force in the IMU frame (m/s²).
    """

    time: np.ndarray
    rate: float
    cameras: tuple[str, ...]
    camera_from_imu: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    @property
    def num_samples(self) -> int:
        return len(self.time)

    def index(self, camera: str) -> int:
        """Position of a camera's IMU in ``cameras``."""
        try:
            return self.cameras.index(camera)
        except ValueError:
            raise KeyError(f"no IMU in camera {camera!r}; IMUs are in {list(self.cameras)}") from None


@dataclasses.dataclass(frozen=True)
class ContactRecording:
    """Ground contact of chosen segments over one trial (``N`` samples, ``F`` segments).

    Attributes:
        time: ``(N,)`` s, strictly increasing, 0 at the trial's first clap.
        segments: ``(F,)`` skeleton segment names; a flag means the segment's joint centre is planted.
        in_contact: ``(N, F)`` bool.
    """

    time: np.ndarray
    segments: tuple[str, ...]
    in_contact: np.ndarray

    def at(self, time: np.ndarray) -> np.ndarray:
        """Flags ``(*time.shape, F)`` at the nearest sample to each time (s)."""
        t = np.asarray(time, np.float64)
        k = np.clip(np.searchsorted(self.time, t), 1, len(self.time) - 1)
        k = np.where(np.abs(self.time[k - 1] - t) <= np.abs(self.time[k] - t), k - 1, k)
        return self.in_contact[k]


# ---------------------------------------------------------------------------------------------
# Validation, reading and writing.


def _field(data, name: str, where: str, kind: str) -> np.ndarray:
    """Array ``name`` of ``data`` as float64 ("float"), str ("str") or bool ("bool"), or a ValueError."""
    if name not in data:
        raise ValueError(f"{where}: missing field '{name}'")
    value = np.asarray(data[name])
    if kind == "str" and value.size == 0:
        value = value.astype(str)  # no names: np.asarray(()) is float
    ok = {"float": "fiu", "str": "U", "bool": "b"}[kind]
    if value.dtype.kind not in ok:
        expected = {"float": "a real number type", "str": "unicode strings", "bool": "bool"}[kind]
        raise ValueError(f"{where}: field '{name}' has dtype {value.dtype}, expected {expected}")
    if kind == "float":
        value = value.astype(np.float64)
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{where}: field '{name}' has non-finite values (NaN or inf)")
    return value


def _shape(value: np.ndarray, name: str, where: str, expected: tuple, meaning: str) -> None:
    if value.ndim != len(expected) or any(e is not None and s != e for s, e in zip(value.shape, expected)):
        raise ValueError(f"{where}: field '{name}' has shape {value.shape}, expected {meaning}")


def _time(data, where: str) -> np.ndarray:
    time = _field(data, "time", where, "float")
    _shape(time, "time", where, (None,), "(N,)")
    if len(time) < 2:
        raise ValueError(f"{where}: field 'time' has {len(time)} samples, need at least 2")
    if np.any(np.diff(time) <= 0):
        k = int(np.argmax(np.diff(time) <= 0))
        raise ValueError(f"{where}: field 'time' is not strictly increasing (sample {k + 1}: {time[k + 1]} after {time[k]})")
    return time


def _names(data, name: str, where: str, letter: str) -> tuple[str, ...]:
    value = _field(data, name, where, "str")
    _shape(value, name, where, (None,), f"({letter},) names")
    names = tuple(str(x) for x in value)
    if len(set(names)) != len(names) or any(not n for n in names):
        raise ValueError(f"{where}: field '{name}' has empty or repeated names: {list(names)}")
    return names


def _check_imu(data, where: str) -> ImuRecording:
    time = _time(data, where)
    rate = _field(data, "rate", where, "float")
    _shape(rate, "rate", where, (), "() (a scalar, Hz)")
    if not rate > 0:
        raise ValueError(f"{where}: field 'rate' must be positive, got {float(rate)}")
    cameras = _names(data, "cameras", where, "S")
    n, s = len(time), len(cameras)
    mounts = _field(data, "camera_from_imu", where, "float")
    _shape(mounts, "camera_from_imu", where, (s, 7), f"({s}, 7) wxyz_xyz for {s} cameras")
    if np.any(np.abs(np.linalg.norm(mounts[:, :4], axis=1) - 1.0) > 1e-6):
        raise ValueError(f"{where}: field 'camera_from_imu' has quaternions (first 4 columns) that are not unit length")
    arrays = {}
    for name in ("gyro", "accel"):
        arrays[name] = _field(data, name, where, "float")
        _shape(arrays[name], name, where, (n, s, 3), f"({n}, {s}, 3) for {n} samples and {s} cameras")
    return ImuRecording(time, float(rate), cameras, mounts, arrays["gyro"], arrays["accel"])


def _check_contacts(data, where: str) -> ContactRecording:
    time = _time(data, where)
    segments = _names(data, "segments", where, "F")
    flags = _field(data, "in_contact", where, "bool")
    n, f = len(time), len(segments)
    _shape(flags, "in_contact", where, (n, f), f"({n}, {f}) for {n} samples and {f} segments")
    return ContactRecording(time, segments, flags)


def _load(path: Path) -> dict[str, np.ndarray]:
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError("a single array, not an .npz archive")
        with data:
            return {k: data[k] for k in data.files}
    except FileNotFoundError:
        raise ValueError(f"{path}: missing") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error) as err:
        raise ValueError(f"{path}: not a readable .npz file ({err})") from None


def read_imu(path: str | os.PathLike) -> ImuRecording:
    """Read and validate an ``imu.npz``.

    Raises:
        ValueError: naming the file and the field that is missing, of the wrong dtype or shape, non-finite,
            or (``time``) not strictly increasing.
    """
    path = Path(path)
    return _check_imu(_load(path), str(path))


def read_contacts(path: str | os.PathLike) -> ContactRecording:
    """Read and validate a ``contacts.npz`` (errors as :func:`read_imu`)."""
    path = Path(path)
    return _check_contacts(_load(path), str(path))


def write_imu(path: str | os.PathLike, recording: ImuRecording) -> Path:
    """Validate and write an ``imu.npz`` atomically (ValueError as :func:`read_imu`, nothing written)."""
    path = Path(path)
    r = _check_imu(dataclasses.asdict(recording), str(path))
    write_npz_atomic(path, {"time": r.time, "rate": np.float64(r.rate), "cameras": np.array(r.cameras, dtype=str),
                      "camera_from_imu": r.camera_from_imu, "gyro": r.gyro, "accel": r.accel})
    return path


def write_contacts(path: str | os.PathLike, recording: ContactRecording) -> Path:
    """Validate and write a ``contacts.npz`` atomically (ValueError as :func:`read_contacts`, nothing written)."""
    path = Path(path)
    r = _check_contacts(dataclasses.asdict(recording), str(path))
    write_npz_atomic(path, {"time": r.time, "segments": np.array(r.segments, dtype=str), "in_contact": r.in_contact})
    return path


# ---------------------------------------------------------------------------------------------
# Gyro integration.


def _prefix_products(q: np.ndarray) -> np.ndarray:
    """``P`` ``(M + 1, ...)`` with ``P[k] = q[0] ⊗ … ⊗ q[k-1]`` (``P[0]`` identity), by log-depth doubling."""
    out = np.concatenate([np.broadcast_to([1.0, 0.0, 0.0, 0.0], (1, *q.shape[1:])), q])
    step = 1
    while step < len(out):
        out = np.concatenate([out[:step], quat_multiply(out[:-step], out[step:])])
        out /= np.linalg.norm(out, axis=-1, keepdims=True)
        step *= 2
    return out


def _interpolate(time: np.ndarray, values: np.ndarray, t: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Cubic Lagrange interpolation of samples ``values`` ``(N, S, 3)`` at ``t`` ``(K,)`` in steps ``step``
    ``(K,)`` (``time[step] <= t <= time[step + 1]``), through the 4 samples around the step."""
    n = len(time)
    if n < 4:  # linear
        w = (t - time[step]) / (time[step + 1] - time[step])
        return values[step] * (1 - w)[:, None, None] + values[step + 1] * w[:, None, None]
    first = np.clip(step - 1, 0, n - 4)
    idx = first[:, None] + np.arange(4)  # (K, 4)
    tk = time[idx]
    weights = np.ones((len(t), 4))
    for j in range(4):
        for m in range(4):
            if m != j:
                weights[:, j] *= (t - tk[:, m]) / (tk[:, j] - tk[:, m])
    return np.einsum("kj,kjsd->ksd", weights, values[idx])


def _magnus(time: np.ndarray, gyro: np.ndarray, a: np.ndarray, b: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Rotation vectors ``(K, S, 3)`` of the IMU frame from ``a`` to ``b`` (within sample step ``step``):
    fourth-order Magnus expansion, the angular velocity at the two Gauss points."""
    h = b - a
    mid, off = 0.5 * (a + b), h / (2.0 * np.sqrt(3.0))
    w1 = _interpolate(time, gyro, mid - off, step)
    w2 = _interpolate(time, gyro, mid + off, step)
    return 0.5 * h[:, None, None] * (w1 + w2) + (np.sqrt(3.0) / 12.0) * (h**2)[:, None, None] * np.cross(w1, w2)


def integrate_gyro(time: np.ndarray, gyro: np.ndarray, t0, t1) -> np.ndarray:
    """Rotation of the IMU frame from ``t0`` to ``t1``, ``R_imu(t0)ᵀ R_imu(t1)``, from gyro samples.

    The angular velocity between samples is the cubic through the 4 nearest samples, integrated over each
    sample step by the fourth-order Magnus expansion (two Gauss points): about 1e-9 rad over 1/60 s of a
    smooth few-rad/s rotation sampled at 200 Hz. The studio's gyro (:mod:`bcmocap.sim.sensors`) is made for
    this scheme: its noiseless samples integrate to the true rotation between video frames to 1e-12 rad.
    ``t0`` and ``t1`` need not fall on samples; ``t1 < t0`` gives the inverse rotation. Subtract a bias
    estimate from ``gyro`` first. Cost: O(N S log N) per call, vectorised over the ``K`` intervals.

    Args:
        time: ``(N,)`` sample times (s), strictly increasing.
        gyro: ``(N, S, 3)`` angular velocity in the IMU frame (rad/s).
        t0, t1: times (s) within ``[time[0], time[-1]]``: scalars or arrays of one shape ``K``.

    Returns:
        ``(*K, S, 4)`` wxyz unit quaternions.
    """
    time = np.asarray(time, np.float64)
    gyro = np.asarray(gyro, np.float64)
    if time.ndim != 1 or len(time) < 2 or gyro.ndim != 3 or gyro.shape[0] != len(time) or gyro.shape[2] != 3:
        raise ValueError(f"integrate_gyro: expected time (N,) with N >= 2 and gyro (N, S, 3), got {time.shape} and {gyro.shape}")
    t0, t1 = np.broadcast_arrays(np.asarray(t0, np.float64), np.asarray(t1, np.float64))
    shape = t0.shape
    t0, t1 = t0.ravel(), t1.ravel()
    outside = (np.minimum(t0, t1) < time[0]) | (np.maximum(t0, t1) > time[-1]) | ~np.isfinite(t0 + t1)
    if np.any(outside):
        k = int(np.argmax(outside))
        raise ValueError(f"integrate_gyro: times must lie within [{time[0]}, {time[-1]}] s, got {t0[k]} to {t1[k]}")
    n = len(time)
    full = np.arange(n - 1)
    steps = quat_exp(_magnus(time, gyro, time[:-1], time[1:], full))  # (N-1, S, 4)
    prefix = _prefix_products(steps)  # (N, S, 4): rotation from time[0] to time[k]

    def from_start(t):  # rotation from time[0] to t: prefix up to the step, then the part of the step
        k = np.clip(np.searchsorted(time, t, side="right") - 1, 0, n - 2)
        return quat_multiply(prefix[k], quat_exp(_magnus(time, gyro, time[k], t, k)))

    rel = quat_multiply(quat_conjugate(from_start(t0)), from_start(t1))
    rel /= np.linalg.norm(rel, axis=-1, keepdims=True)
    rel = np.where(rel[..., :1] < 0, -rel, rel)
    return rel.reshape(*shape, gyro.shape[1], 4)
