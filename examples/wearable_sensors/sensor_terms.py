"""Residual terms for wearable sensors, written as a user would: outside bcmocap, named in a run config.

Three term factories read the capture trial's own sensor files (``trials/capture/imu.npz`` and
``contacts.npz``, formats in :mod:`bcmocap.io.sensors`; the synthetic studio writes them):

- :func:`gyroscope`: every body camera's rotation from one solver frame to the next equals what its IMU's
  gyro integrates to over that interval (a pair term on the camera poses; the gyro needs no world
  alignment and no mount beyond the camera-IMU calibration).
- :func:`foot_contact`: a flagged foot's joint centre does not move between consecutive frames (a pair
  term through forward kinematics).
- :func:`accelerometer`: the second difference of every IMU's position over three frames equals its
  accelerometer reading rotated into the world plus gravity (a three-frame term: the solver's matrix
  becomes block banded with bandwidth 2). The run's world has +Z up from the rest pose (``[skeleton]
  up_from`` / ``up_to``), so gravity is only as vertical as that estimate.

Use them from ``bcmocap run`` with this folder on ``PYTHONPATH``::

    PYTHONPATH=examples/wearable_sensors bcmocap run CAPTURE --out OUT --config examples/wearable_sensors/config.toml

Weights are in the units of the reprojection term's squared pixels per squared residual unit: about
``1 / σ²`` of each measurement's error σ (rad, m, m/s²), as the reprojection residuals are about 1 px.
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from bcmocap.geometry import SE3, SO3
from bcmocap.io.sensors import CONTACTS_FILE, IMU_FILE, ContactRecording, ImuRecording, integrate_gyro, read_contacts, read_imu
from bcmocap.residuals import TermWindow, loss_from_name, residual_term

GRAVITY = 9.81  # m/s², along world −Z


@functools.lru_cache(maxsize=4)
def _imu(path: Path) -> ImuRecording:
    return read_imu(path)


@functools.lru_cache(maxsize=4)
def _contacts(path: Path) -> ContactRecording:
    return read_contacts(path)


def _rig_slots(window: TermWindow, imu: ImuRecording) -> tuple[np.ndarray, np.ndarray]:
    """For every rig camera: the index of its IMU (0 if none) and whether it has one."""
    names = window.rig.names
    index = np.array([imu.cameras.index(n) if n in imu.cameras else 0 for n in names])
    return index, np.array([n in imu.cameras for n in names])


# ---- gyroscope ----------------------------------------------------------------------------------


@residual_term(frames=2)
def camera_rotation_change(states, data, variables):
    """Each camera's rotation from frame t−1 to t, ``R_wc(t−1)ᵀ R_wc(t)``, equals ``data["rotation"][t]``
    (wxyz ``(C, 4)``); residual: its rotation vector error (rad), 3 per camera."""
    predicted = states[0].world_from_camera.rotation().inverse() @ states[1].world_from_camera.rotation()
    return (SO3(data["rotation"]).inverse() @ predicted).log(), data["valid"]


def gyroscope(window: TermWindow, weight: float = 1e6, loss: str = "none", loss_scale: float = 1.0):
    """:func:`camera_rotation_change` from ``imu.npz``: each camera's gyro integrated between consecutive solver
    frames, turned into the camera frame by the IMU's mount (``R_c ΔR_imu R_cᵀ``)."""
    imu = _imu(window.trial_file(IMU_FILE))
    t1 = window.times
    t0 = t1 - 1.0 / window.fps
    inside = (t0 >= imu.time[0]) & (t1 <= imu.time[-1])
    change = integrate_gyro(imu.time, imu.gyro, np.where(inside, t0, imu.time[0]), np.where(inside, t1, imu.time[0]))
    mount = SO3(jnp.asarray(imu.camera_from_imu[:, :4]))
    in_camera = np.asarray((mount @ SO3(jnp.asarray(change)) @ mount.inverse()).wxyz)  # (W, S, 4)
    index, has = _rig_slots(window, imu)
    data = {"rotation": in_camera[:, index], "valid": inside[:, None] & has[None, :]}
    return camera_rotation_change(data, weight=weight, loss=loss_from_name(loss, loss_scale), name="gyroscope")


# ---- foot contact -------------------------------------------------------------------------------


@residual_term(frames=2)
def planted_joints(states, data, variables):
    """Joint centres (segment origins ``data["segment"]``) flagged in contact at t−1 and t do not move (m)."""
    centres = states.world_from_segment.translation()[:, data["segment"]]  # (2, S, 3)
    return centres[1] - centres[0], data["planted"]


def foot_contact(window: TermWindow, weight: float = 1e4, loss: str = "huber", loss_scale: float = 0.01):
    """:func:`planted_joints` from ``contacts.npz``: the flagged segments' joint centres stay put while flagged
    at both frames of a pair."""
    contacts = _contacts(window.trial_file(CONTACTS_FILE))
    names = list(window.skeleton.names)
    missing = [s for s in contacts.segments if s not in names]
    if missing:
        raise ValueError(f"{window.trial_folder / CONTACTS_FILE}: segments {missing} are not in the skeleton {names}")
    t1 = window.times
    t0 = t1 - 1.0 / window.fps
    inside = (t0 >= contacts.time[0]) & (t1 <= contacts.time[-1])
    flags = contacts.at(t1) & contacts.at(np.maximum(t0, contacts.time[0])) & inside[:, None]
    segments = np.broadcast_to([names.index(s) for s in contacts.segments], flags.shape)
    return planted_joints({"planted": flags, "segment": segments}, weight=weight, loss=loss_from_name(loss, loss_scale),
                          name="foot contact")


# ---- accelerometer ------------------------------------------------------------------------------


@residual_term(frames=3)
def imu_acceleration(states, data, variables):
    """Three frames t−2, t−1, t: the IMU position's second difference over ``dt²`` (``data["dt"]``, s) equals
    ``R_wi(t−1) f̄ + g``, where ``f̄`` (``data["force"]``, m/s² in the IMU frame at t−1) is the specific force
    averaged over ``[t−2, t]`` with the triangle weights a second difference applies to acceleration (3
    residuals per camera, m/s²; ``data["camera_from_imu"]`` ``(C, 7)``: each camera's IMU mount)."""
    world_from_imu = states.world_from_camera @ SE3(data["camera_from_imu"])  # batch (3, C)
    p = world_from_imu.translation()
    acceleration = (p[2] - 2.0 * p[1] + p[0]) / data["dt"] ** 2
    measured = SO3(world_from_imu.rotation().wxyz[1]) @ data["force"] - jnp.array([0.0, 0.0, GRAVITY])
    return acceleration - measured, data["valid"]


def _second_difference_force(imu: ImuRecording, middle: np.ndarray, dt: float) -> np.ndarray:
    """``(W, S, 3)``: the specific force over ``[m − dt, m + dt]`` around each middle time ``m``, each sample
    turned into the IMU frame at ``m`` by the integrated gyro and weighted by the triangle ``(dt − |τ − m|)/dt²``
    (trapezoid rule at the IMU rate), so that ``R_wi(m) f̄ + g = (p(m+dt) − 2 p(m) + p(m−dt)) / dt²`` exactly
    for the true motion up to the quadrature error."""
    per_side = max(1, int(np.ceil(dt * imu.rate)))
    offsets = np.linspace(-dt, dt, 2 * per_side + 1)  # (K,)
    weights = np.maximum(dt - np.abs(offsets), 0.0) / dt**2
    weights *= (offsets[1] - offsets[0])
    weights[[0, -1]] *= 0.5
    middle = np.clip(middle, imu.time[0], imu.time[-1])  # frames outside the recording are marked invalid
    times = np.clip(middle[:, None] + offsets[None, :], imu.time[0], imu.time[-1])  # (W, K)
    rotation = integrate_gyro(imu.time, imu.gyro, np.broadcast_to(middle[:, None], times.shape), times)  # (W, K, S, 4)
    force = _interpolate(imu.time, imu.accel, times)  # (W, K, S, 3)
    turned = np.asarray(SO3(jnp.asarray(rotation)) @ jnp.asarray(force))
    return np.einsum("k,wksd->wsd", weights, turned)


def _interpolate(time: np.ndarray, samples: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Samples ``(N, ...)`` linearly interpolated at times ``at`` (within ``time``), shape ``(*at.shape, ...)``."""
    k = np.clip(np.searchsorted(time, at, side="right") - 1, 0, len(time) - 2)
    w = ((at - time[k]) / (time[k + 1] - time[k])).reshape(*at.shape, *([1] * (samples.ndim - 1)))
    return (1.0 - w) * samples[k] + w * samples[k + 1]


def accelerometer(window: TermWindow, weight: float = 1.0, loss: str = "huber", loss_scale: float = 3.0):
    """:func:`imu_acceleration` from ``imu.npz`` (bias not removed: it enters as a constant error)."""
    imu = _imu(window.trial_file(IMU_FILE))
    dt = 1.0 / window.fps
    middle = window.times - dt
    inside = (middle - dt >= imu.time[0]) & (middle + dt <= imu.time[-1])
    index, has = _rig_slots(window, imu)
    force = _second_difference_force(imu, middle, dt)[:, index]  # (W, C, 3)
    mounts = np.where(has[:, None], imu.camera_from_imu[index], np.array([1.0, 0, 0, 0, 0, 0, 0]))
    data = {"force": force, "valid": inside[:, None] & has[None, :], "dt": np.full(len(middle), dt),
            "camera_from_imu": np.broadcast_to(mounts, (len(middle), *mounts.shape))}
    return imu_acceleration(data, weight=weight, loss=loss_from_name(loss, loss_scale), name="accelerometer")
