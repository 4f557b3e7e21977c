"""Synthetic wearable sensors for the capture studio: an IMU in each body camera, and foot contacts.

The ground truth defines poses at trial frames only; the sensors need them in continuous time. Between
frames every pose follows a local C² quintic Hermite interpolant through the frame poses, its velocity
and acceleration at each frame from central differences of the neighbouring frames:

* positions (IMU origins, joint centres) componentwise, so at a frame time the IMU's true world
  acceleration is exactly the central second difference ``(p[f+1] − 2 p[f] + p[f−1]) fps²`` of its
  positions at the frames;
* rotations in the tangent space of the interval's first frame, ``R(t) = R_f Exp(φ(s))``, with ``φ``
  matching the angular velocity and acceleration at both ends (through the right Jacobian of SO(3)); at
  a frame time the angular velocity is ``(Log(R[f−1]ᵀ R[f]) + Log(R[f]ᵀ R[f+1])) fps / 2``.

A few samples per frame cannot carry all of that interpolant (integrating them misses the rotation
between frames by about 1e-4 rad on the CMU walk at 240 Hz), and the truth between frames is a choice:
inside each frame interval the angular velocity gets a smooth bump ``c sin²(π s)``, zero at the frames,
with ``c`` such that :func:`bcmocap.io.sensors.integrate_gyro` reproduces the rotation between every two
frames to 1e-12 rad (the bump is 0.2 °/s at the median, 1.2 °/s RMS, 40 °/s at the walk's one-frame 35°
foot glitch). The accelerometer uses the interpolant's rotation.

Before trial frame 0 and after the last one the subject holds the first / last pose (as the videos
show); a motion that is moving at frame 0 (the CMU walk) starts and stops abruptly, and the IMU reads
the large accelerations of that over the first and last frame interval (up to 200 m/s² on the walk,
also where ``back_and_forth`` reverses it). Mocap jitter is in the truth too: the walk's root has a
median acceleration of 5 m/s² by second differences at 60 fps, and so does its IMU.

Sampling: time 0 is the trial's first clap (trial frame ``clap_frames[0]``), the last sample is at or
just after the second clap; the default rate (:func:`default_imu_rate`) is the smallest whole multiple
of the frame rate of at least 200 Hz and 4 samples per frame (240 Hz at 60 fps), so that every video
frame falls on a sample. Contacts use the same times.

Sensor errors (MEMS-like, e.g. the Bosch BMI260 of action cameras; all settable, 0 gives exact data):
white noise per sample at the chosen rate, σ = 0.2 °/s (gyro) and 0.02 m/s² (accelerometer), and a
constant bias per sensor, axis and trial drawn uniformly within ±0.5 °/s and ±0.05 m/s² (a turn-on
bias: each trial is a new recording). The IMU's mount in its camera (``camera_from_imu``, known from
calibration, the same for every trial) is a rotation of up to 2° about a random axis and an offset
within ±5 mm per axis, drawn from the seed.

Contacts (:func:`simulate_contacts`): a segment's joint centre (the feet: the ankle) is planted while it
moves slower than 0.1 m/s and is within 5 cm of the lowest height at which it is that slow in the trial,
contacts and gaps shorter than 50 ms removed: on the CMU walk that flags the foot-flat part of each stance
(about 30 % of the time per foot; the ankle still slides by up to 2 cm over a contact), never the swing.
"""

from __future__ import annotations

import dataclasses

import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..geometry import matrix_from_quat, quat_conjugate, quat_exp, quat_log, quat_multiply
from ..io.capture_folder import read_npz, read_truth_model, trial_dir, trial_truth_path
from ..io.sensors import (
    CONTACTS_FILE,
    IMU_FILE,
    ContactRecording,
    ImuRecording,
    integrate_gyro,
    write_contacts,
    write_imu,
)
from ..kinematics.fk import forward_kinematics
from ..kinematics.rig import Rig
from ..kinematics.skeleton import Motion, Skeleton
from ..precision import require_float64

__all__ = [
    "ACCEL_BIAS",
    "ACCEL_NOISE",
    "CONTACT_HEIGHT_TOLERANCE",
    "CONTACT_SPEED",
    "FOOT_SEGMENTS",
    "GRAVITY",
    "GYRO_BIAS",
    "GYRO_NOISE",
    "default_imu_rate",
    "imu_mounts",
    "simulate_contacts",
    "simulate_imu",
    "write_sensor_data",
    "write_trial_sensors",
]

GRAVITY = 9.81  # m/s², along world -Z
GYRO_NOISE = math.radians(0.2)  # rad/s, σ per sample
GYRO_BIAS = math.radians(0.5)  # rad/s, largest bias per axis
ACCEL_NOISE = 0.02  # m/s², σ per sample
ACCEL_BIAS = 0.05  # m/s², largest bias per axis
MOUNT_ROTATION_DEG = 2.0  # largest rotation of an IMU in its camera
MOUNT_OFFSET_M = 0.005  # largest offset per axis of an IMU in its camera
FOOT_SEGMENTS = ("left_foot", "right_foot")  # their origin is the ankle joint centre
CONTACT_SPEED = 0.1  # m/s: a planted joint centre moves slower
CONTACT_HEIGHT_TOLERANCE = 0.05  # m above the lowest height at which the joint centre is that slow
CONTACT_MIN_SECONDS = 0.05  # shorter contacts or gaps between contacts are dropped / filled

# Quintic Hermite on [0, 1]: coefficients (of 1, s, ..., s^5) from (p0, v0, a0, p1, v1, a1).
_POWERS = np.arange(6)


def _quintic_matrix() -> np.ndarray:
    rows = []
    for s in (0.0, 1.0):
        rows.append(s ** _POWERS)
        rows.append(np.where(_POWERS >= 1, _POWERS * s ** np.maximum(_POWERS - 1, 0), 0.0))
        rows.append(np.where(_POWERS >= 2, _POWERS * (_POWERS - 1) * s ** np.maximum(_POWERS - 2, 0), 0.0))
    # rows: p(0), p'(0), p''(0), p(1), p'(1), p''(1)
    return np.linalg.inv(np.array(rows))


_QUINTIC = _quintic_matrix()  # coefficients = _QUINTIC @ [p0, v0, a0, p1, v1, a1]


def _quintic_eval(ends: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Value, first and second derivative in ``s`` of quintic Hermites.

    Args:
        ends: ``(K, 6, ...)`` end conditions (p0, v0, a0, p1, v1, a1) per sample (s-units).
        s: ``(K,)`` positions in the interval, in [0, 1].
    """
    coef = np.einsum("ij,kj...->ki...", _QUINTIC, ends)  # (K, 6, ...)
    shape = (len(s),) + (1,) * (coef.ndim - 2)
    sp = s.reshape(shape)
    value = sum(coef[:, i] * sp**i for i in range(6))
    first = sum(i * coef[:, i] * sp ** (i - 1) for i in range(1, 6))
    second = sum(i * (i - 1) * coef[:, i] * sp ** (i - 2) for i in range(2, 6))
    return value, first, second


def default_imu_rate(fps: float) -> float:
    """Smallest whole multiple of ``fps`` of at least 200 Hz and 4 samples per frame (240 Hz at 60 fps, 210 Hz
    at 30 fps): video frames fall on samples, and each frame interval has samples inside it."""
    return float(fps) * max(4, math.ceil(200.0 / float(fps) - 1e-9))


def _knot_frames(num_frames: int, clap_frames) -> np.ndarray:
    """Trial frame shown at each knot from one frame before the first clap to one after the second
    (the subject holds the first / last pose outside the trial)."""
    first, last = int(clap_frames[0]), int(clap_frames[1])
    if last <= first:
        raise ValueError(f"clap_frames must be increasing, got {list(clap_frames)}")
    return np.clip(np.arange(first - 1, last + 2), 0, num_frames - 1)


def _sample_times(num_knots: int, fps: float, rate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample times (s) from the first clap to the second, the knot interval of each and the position in it."""
    span = (num_knots - 1) / fps
    count = int(math.ceil(span * rate - 1e-6)) + 1  # the last sample at or just after the second clap
    time = np.arange(count) / rate
    u = np.arange(count) * (fps / rate)
    interval = np.clip(np.floor(u + 1e-9).astype(np.int64), 0, num_knots - 2)
    return time, interval, np.clip(u - interval, 0.0, 1.0)


def _position_ends(points: np.ndarray, interval: np.ndarray) -> np.ndarray:
    """Hermite end conditions ``(K, 6, ...)`` of points ``(M + 2, ...)`` at knots (one padding knot each
    side), derivatives from central differences (per knot interval)."""
    v = 0.5 * (points[2:] - points[:-2])
    a = points[2:] - 2.0 * points[1:-1] + points[:-2]
    p = points[1:-1]
    return np.stack([p[interval], v[interval], a[interval], p[interval + 1], v[interval + 1], a[interval + 1]], axis=1)


def _series(theta: np.ndarray, exact, taylor) -> np.ndarray:
    small = theta < 0.05
    safe = np.where(small, 0.1, theta)
    return np.where(small, taylor(theta), exact(safe))


def _jr_coefficients(phi: np.ndarray):
    """Scalars of the right Jacobian ``J_r(φ) = I − a [φ]× + b [φ]×²`` and of their derivatives ``a'/θ, b'/θ``."""
    t = np.linalg.norm(phi, axis=-1, keepdims=True)
    a = _series(t, lambda x: (1 - np.cos(x)) / x**2, lambda x: 0.5 - x**2 / 24 + x**4 / 720)
    b = _series(t, lambda x: (x - np.sin(x)) / x**3, lambda x: 1 / 6 - x**2 / 120 + x**4 / 5040)
    da = _series(t, lambda x: (x * np.sin(x) - 2 * (1 - np.cos(x))) / x**4, lambda x: -1 / 12 + x**2 / 180 - x**4 / 6720)
    db = _series(t, lambda x: ((1 - np.cos(x)) * x - 3 * (x - np.sin(x))) / x**5,
                 lambda x: -1 / 60 + x**2 / 1260 - x**4 / 60480)
    return a, b, da, db


def _jr_apply(phi: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``J_r(φ) u``: body angular velocity (per unit of the parameter) of ``Exp(φ)`` moving at ``φ' = u``."""
    a, b, _, _ = _jr_coefficients(phi)
    pu = np.cross(phi, u)
    return u - a * pu + b * np.cross(phi, pu)


def _jr_solve(phi: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``J_r(φ)⁻¹ w`` ``(..., 3)``."""
    a, b, _, _ = _jr_coefficients(phi)
    k = np.zeros((*phi.shape[:-1], 3, 3))
    x, y, z = np.moveaxis(phi, -1, 0)
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -z, y, -x
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = z, -y, x
    jr = np.eye(3) - a[..., None] * k + b[..., None] * (k @ k)
    return np.linalg.solve(jr, w[..., None])[..., 0]


def _jr_curvature(phi: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``(d/dφ J_r(φ) · u) u``: the angular acceleration of ``Exp(φ)`` moving at constant ``φ' = u``."""
    _, b, da, db = _jr_coefficients(phi)
    pu = np.cross(phi, u)
    rate = np.sum(phi * u, axis=-1, keepdims=True)  # θ θ'
    return rate * (-da * pu + db * np.cross(phi, pu)) + b * np.cross(u, pu)


def _rotation_trajectory(quats: np.ndarray, interval: np.ndarray, s: np.ndarray, fps: float):
    """World rotations and body angular velocities at samples.

    Args:
        quats: ``(M + 2, S, 4)`` wxyz rotations at the knots (one padding knot each side).
        interval, s: ``(K,)`` knot interval and position in it of each sample.

    Returns:
        ``(K, S, 4)`` rotations and ``(K, S, 3)`` angular velocities in the rotating frame (rad/s).
    """
    q = quats / np.linalg.norm(quats, axis=-1, keepdims=True)
    step = quat_log(quat_multiply(quat_conjugate(q[:-1]), q[1:]))  # (M + 1, S, 3): from knot i to i + 1, same in both frames
    omega = 0.5 * (step[:-1] + step[1:])  # (M, S, 3) per knot, s-units
    alpha = step[1:] - step[:-1]
    d = step[1:-1]  # (M - 1, S, 3) per interval
    w1 = _jr_solve(d, omega[1:])
    a1 = _jr_solve(d, alpha[1:] - _jr_curvature(d, w1))
    zero = np.zeros_like(d)
    ends = np.stack([zero, omega[:-1], alpha[:-1], d, w1, a1], axis=1)  # (M - 1, 6, S, 3)
    phi, dphi, _ = _quintic_eval(ends[interval], s)
    rotation = quat_multiply(q[1:-1][interval], quat_exp(phi))
    return rotation, _jr_apply(phi, dphi) * fps


def _consistent_gyro(time: np.ndarray, gyro: np.ndarray, interval: np.ndarray, s: np.ndarray, knots: np.ndarray,
                     fps: float, tolerance: float = 1e-12, max_rounds: int = 50) -> np.ndarray:
    """Gyro samples ``(N, S, 3)`` nudged so that :func:`~bcmocap.io.sensors.integrate_gyro` reproduces the rotation
    between every two knots ``(M, S, 4)`` (module docstring): a bump ``c sin²(π s)`` per frame interval, ``c``
    by fixed-point rounds (a handful; stops early if a round does not help, e.g. without samples inside the
    intervals)."""
    q = knots / np.linalg.norm(knots, axis=-1, keepdims=True)
    target = quat_multiply(quat_conjugate(q[:-1]), q[1:])  # (M - 1, S, 4)
    bump = (np.sin(np.pi * s) ** 2)[:, None, None]
    frame_time = np.arange(len(q)) / fps
    correction = np.zeros((len(q) - 1, *gyro.shape[1:]))
    best, best_error = gyro, np.inf
    for _ in range(max_rounds):
        out = gyro + bump * correction[interval]
        rel = integrate_gyro(time, out, frame_time[:-1], frame_time[1:])
        residual = quat_log(quat_multiply(quat_conjugate(rel), target))
        error = float(np.max(np.abs(residual), initial=0.0))
        if error >= 0.5 * best_error:
            break
        best, best_error = out, error
        if error < tolerance:
            break
        correction += residual * (2.0 * fps)  # ∫ sin²(π s) dt over a frame is 1 / (2 fps)
    return best


def imu_mounts(num_cameras: int, seed: int = 0, *, max_rotation_deg: float = MOUNT_ROTATION_DEG,
               max_offset_m: float = MOUNT_OFFSET_M) -> np.ndarray:
    """``camera_from_imu`` ``(S, 7)`` wxyz_xyz: a rotation of up to ``max_rotation_deg`` about a random axis
    and an offset within ±``max_offset_m`` per axis, the same for a seed whatever the trial."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 20]))
    axis = rng.normal(size=(num_cameras, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.deg2rad(max_rotation_deg) * rng.uniform(0.0, 1.0, (num_cameras, 1))
    offset = rng.uniform(-max_offset_m, max_offset_m, (num_cameras, 3))
    return np.concatenate([quat_exp(axis * angle), offset], axis=1)


def simulate_imu(skeleton: Skeleton, rig: Rig, motion: Motion, fps: float, clap_frames, *, rate: float | None = None,
                 seed: int = 0, trial_index: int = 0, camera_from_imu: np.ndarray | None = None,
                 gyro_noise: float = GYRO_NOISE, gyro_bias: float = GYRO_BIAS, accel_noise: float = ACCEL_NOISE,
                 accel_bias: float = ACCEL_BIAS, gravity: float = GRAVITY,
                 world_from_camera: np.ndarray | None = None) -> ImuRecording:
    """The IMU in every camera of a rig over one trial, from the first clap to the second.

    Args:
        skeleton, rig, motion: the true model and the trial's motion (``T`` frames at ``fps``).
        fps: frame rate of ``motion`` (Hz).
        clap_frames: ``(2,)`` trial frames of the claps (the first is time 0; the subject holds the first
            pose before frame 0 and the last one after frame ``T − 1``).
        rate: sample rate (Hz); None: :func:`default_imu_rate`.
        seed: seeds the mounts (:func:`imu_mounts`) and, with ``trial_index``, the biases and noise.
        camera_from_imu: ``(C, 7)`` IMU mounts instead of the seed's.
        gyro_noise, accel_noise: white-noise σ per sample (rad/s, m/s²); gyro_bias, accel_bias: largest
            constant bias per axis (rad/s, m/s², uniform within ±). 0 gives exact data.
        gravity: m/s² along world −Z.
        world_from_camera: ``(T, C, 7)`` the cameras' true poses when they move on their mounts (the IMU is
            in the camera); None: rigidly mounted, from the motion and the rig.

    Returns:
        ``ImuRecording`` with ``N`` samples and ``S = C`` sensors, named by the rig's cameras.
    """
    require_float64("bcmocap.sim.sensors.simulate_imu")
    if not fps > 0:
        raise ValueError(f"simulate_imu: fps must be positive, got {fps}")
    rate = default_imu_rate(fps) if rate is None else float(rate)
    if not rate > 0:
        raise ValueError(f"simulate_imu: rate must be positive, got {rate}")
    mounts = imu_mounts(rig.num_cameras, seed) if camera_from_imu is None else np.asarray(camera_from_imu, np.float64)
    if mounts.shape != (rig.num_cameras, 7):
        raise ValueError(f"simulate_imu: camera_from_imu must have shape ({rig.num_cameras}, 7), got {mounts.shape}")
    if world_from_camera is None:
        cams = np.asarray(rig.world_from_camera(forward_kinematics(skeleton, motion)).wxyz_xyz, np.float64)  # (T, C, 7)
    else:
        cams = np.asarray(world_from_camera, np.float64)
        if cams.shape != (motion.num_frames, rig.num_cameras, 7):
            raise ValueError(f"simulate_imu: world_from_camera must have shape ({motion.num_frames}, {rig.num_cameras}, 7), "
                             f"got {cams.shape}")
    knots = cams[_knot_frames(len(cams), clap_frames)]
    cam_rot = knots[..., :4]
    imu_rot = quat_multiply(cam_rot, mounts[:, :4])
    imu_pos = knots[..., 4:] + np.einsum("kcij,cj->kci", matrix_from_quat(cam_rot), mounts[:, 4:])
    time, interval, s = _sample_times(len(knots) - 2, fps, rate)
    rotation, gyro = _rotation_trajectory(imu_rot, interval, s, fps)
    gyro = _consistent_gyro(time, gyro, interval, s, imu_rot[1:-1], fps)
    _, _, acc = _quintic_eval(_position_ends(imu_pos, interval), s)
    world_accel = acc * fps**2 + np.array([0.0, 0.0, gravity])  # a − g with g = (0, 0, −gravity)
    accel = np.einsum("kcji,kcj->kci", matrix_from_quat(rotation), world_accel)  # Rᵀ (a − g)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 21, int(trial_index)]))
    shape = gyro.shape
    gyro = gyro + rng.uniform(-1.0, 1.0, shape[1:]) * gyro_bias + rng.normal(size=shape) * gyro_noise
    accel = accel + rng.uniform(-1.0, 1.0, shape[1:]) * accel_bias + rng.normal(size=shape) * accel_noise
    return ImuRecording(time, rate, tuple(rig.names), mounts, gyro, accel)


def _clean_runs(flags: np.ndarray, min_length: int) -> np.ndarray:
    """Fill gaps shorter than ``min_length`` samples between contacts, then drop shorter contacts (``(N, F)``)."""
    out = flags.copy()
    if min_length <= 1:
        return out
    for value in (False, True):  # first fill short gaps, then remove short contacts
        for f in range(out.shape[1]):
            col = out[:, f]
            edges = np.flatnonzero(np.diff(np.r_[-1, col.astype(np.int8), -1]) != 0)
            for start, stop in zip(edges[:-1], edges[1:]):
                inner = start > 0 and stop < len(col)  # gaps at the ends are not between contacts
                if col[start] == value and stop - start < min_length and (value or inner):
                    col[start:stop] = not value
    return out


def simulate_contacts(skeleton: Skeleton, motion: Motion, fps: float, clap_frames, *, rate: float | None = None,
                      segments: Sequence[str] = FOOT_SEGMENTS, speed_threshold: float = CONTACT_SPEED,
                      height_tolerance: float = CONTACT_HEIGHT_TOLERANCE,
                      min_seconds: float = CONTACT_MIN_SECONDS) -> ContactRecording:
    """Ground-truth contact flags of joint centres (what a pressure insole gives), same clock as the IMU.

    A segment is in contact while its joint centre (the segment frame's origin; for the feet the ankle)
    moves slower than ``speed_threshold`` (m/s) and is within ``height_tolerance`` (m) of the lowest height
    at which it moves that slowly in the trial (its height on the floor: in the range-of-motion trial, whose
    root is held in place, a swinging leg dips below the standing height); contacts and gaps shorter than
    ``min_seconds`` are removed.

    Args:
        skeleton, motion, fps, clap_frames, rate: as :func:`simulate_imu`.
        segments: segment names (default the feet).

    Returns:
        ``ContactRecording`` with ``N`` samples and ``F = len(segments)``.
    """
    require_float64("bcmocap.sim.sensors.simulate_contacts")
    if not fps > 0:
        raise ValueError(f"simulate_contacts: fps must be positive, got {fps}")
    unknown = [name for name in segments if name not in skeleton.names]
    if unknown:
        raise ValueError(f"simulate_contacts: no segment {unknown} in the skeleton; segments are {list(skeleton.names)}")
    rate = default_imu_rate(fps) if rate is None else float(rate)
    index = np.array([skeleton.index(name) for name in segments], np.int64)
    joints = np.asarray(forward_kinematics(skeleton, motion).translation(), np.float64)[:, index]  # (T, F, 3)
    knots = joints[_knot_frames(len(joints), clap_frames)]
    time, interval, s = _sample_times(len(knots) - 2, fps, rate)
    position, velocity, _ = _quintic_eval(_position_ends(knots, interval), s)
    speed = np.linalg.norm(velocity, axis=-1) * fps
    slow = speed < speed_threshold
    # the floor: the lowest height at which the joint centre is ever still (a leg swung through the floor, as in
    # the range-of-motion trial whose root is held in place, does not count)
    low = np.where(slow, position[..., 2], np.inf).min(axis=0)
    flags = slow & (position[..., 2] < low + height_tolerance)
    return ContactRecording(time, tuple(segments), _clean_runs(flags, int(round(min_seconds * rate))))


def write_sensor_data(capture_path: str | os.PathLike, *, seed: int | None = None, rate: float | None = None,
                      gyro_noise: float = GYRO_NOISE, gyro_bias: float = GYRO_BIAS, accel_noise: float = ACCEL_NOISE,
                      accel_bias: float = ACCEL_BIAS, contact_segments: Sequence[str] = FOOT_SEGMENTS,
                      ) -> dict[str, tuple[Path, Path]]:
    """Add ``imu.npz`` and ``contacts.npz`` to every trial of a capture from its ground truth (no rendering).

    Reads ``capture.json`` (seed, trials), ``ground_truth/skeleton.json``, ``ground_truth/rig.json`` and
    ``ground_truth/<trial>.npz`` (motion, fps, clap frames) and writes ``trials/<trial>/imu.npz`` and
    ``contacts.npz`` atomically; with the defaults these are the bytes :func:`bcmocap.sim.studio.write_capture`
    writes.

    Args:
        capture_path: a capture folder written by the studio.
        seed: None: the capture's seed.
        rate, gyro_noise, gyro_bias, accel_noise, accel_bias: as :func:`simulate_imu`.
        contact_segments: as :func:`simulate_contacts` (those the skeleton has).

    Returns:
        ``{trial: (imu path, contacts path)}``.

    Raises:
        ValueError: naming a missing or malformed file of the capture.
    """
    folder = Path(capture_path)
    # the manifest's trial names are checked plain names (they become path components)
    manifest, skeleton, rig = read_truth_model(folder)
    if seed is None:
        seed = manifest.settings.get("seed", 0)  # the studio's default seed when its settings do not give one
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ValueError(f"{manifest.path}: field 'settings.seed' must be a whole number, got {seed!r}")
    written = {}
    for trial_index, name in enumerate(manifest.trials):
        where = trial_truth_path(folder, name)
        data = read_npz(where)
        try:
            motion = Motion(data["root_position"], data["rotations"])
            fps, clap_frames = float(data["fps"]), np.asarray(data["clap_frames"])
            # cameras that move on their mounts (studio mount wobble): the IMU follows the true camera poses
            moving = "camera_offsets" in data and np.any(data["camera_offsets"] != 0)
            cameras = np.asarray(data["world_from_camera"]) if moving else None
        except KeyError as err:
            raise ValueError(f"{where}: missing array {err}") from None
        if not (np.isfinite(fps) and fps > 0):
            raise ValueError(f"{where}: fps must be positive, got {fps}")
        if clap_frames.shape != (2,) or clap_frames.dtype.kind not in "iu" or clap_frames[1] <= clap_frames[0]:
            raise ValueError(f"{where}: clap_frames must be 2 increasing whole frames, got {clap_frames!r}")
        written[name] = write_trial_sensors(
            trial_dir(folder, name), skeleton, rig, motion, fps, clap_frames, seed=seed, trial_index=trial_index,
            rate=rate, gyro_noise=gyro_noise, gyro_bias=gyro_bias, accel_noise=accel_noise, accel_bias=accel_bias,
            contact_segments=contact_segments, world_from_camera=cameras)
    return written


def write_trial_sensors(folder: str | os.PathLike, skeleton: Skeleton, rig: Rig, motion: Motion, fps: float, clap_frames,
                        *, seed: int, trial_index: int, rate: float | None = None, contact_segments=FOOT_SEGMENTS,
                        world_from_camera: np.ndarray | None = None, clock_offset_s: float = 0.0,
                        **noise) -> tuple[Path, Path]:
    """Simulate and write one trial's ``imu.npz`` and ``contacts.npz`` into ``folder`` (returns their paths);
    ``world_from_camera`` as :func:`simulate_imu`; ``clock_offset_s``: added to the IMU's timestamps (its clock
    is that much ahead of the video's; the contacts keep true time)."""
    folder = Path(folder)
    imu = simulate_imu(skeleton, rig, motion, fps, clap_frames, rate=rate, seed=seed, trial_index=trial_index,
                       world_from_camera=world_from_camera, **noise)
    if clock_offset_s:
        imu = dataclasses.replace(imu, time=imu.time + float(clock_offset_s))
    segments = [name for name in contact_segments if name in skeleton.names]
    contacts = simulate_contacts(skeleton, motion, fps, clap_frames, rate=imu.rate, segments=segments)
    return write_imu(folder / IMU_FILE, imu), write_contacts(folder / CONTACTS_FILE, contacts)
