"""The gyro turns of a solver window (``[solver] gyro_turn``): each camera's gyro integrated over each pair of frames,
read at the camera's shift on the gyro's clock, as a :class:`~bcmocap.residuals.gyro.GyroTurn`."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..geometry import quat_conjugate, quat_multiply
from ..io.sensors import integrate_gyro, read_imu
from ..residuals.gyro import GyroTurn
from ..residuals.term_window import TermWindow


def gyro_turns(window: TermWindow, sigma_deg: float, time_shifts_s: Sequence[float] | None = None,
               file: str = "imu.npz") -> GyroTurn:
    """The :class:`GyroTurn` of a window from the trial's gyro file (``window.trial_file(file)``), σ
    ``sigma_deg`` per axis; ``time_shifts_s`` ``(C,)`` where each camera's frames lie on the gyro's clock after the
    trial's times (None: on them). A camera the file does not hold, and frames whose interval the recording does not
    cover, get no reading.

    Raises:
        ValueError: σ not positive, or a shift per camera missing (one line).
    """
    if not sigma_deg > 0:
        raise ValueError(f"gyro turns: σ must be > 0 degrees, got {sigma_deg}")
    names = list(window.rig.names)
    shifts = np.zeros(len(names)) if time_shifts_s is None else np.asarray(time_shifts_s, np.float64)
    if shifts.shape != (len(names),):
        raise ValueError(f"gyro turns: {shifts.size} time shifts for {len(names)} cameras")
    imu = read_imu(window.trial_file(file))
    if not set(names) & set(imu.cameras):
        raise ValueError(f"{window.trial_file(file)}: holds none of the rig's cameras (it has {', '.join(imu.cameras)})")
    turn = np.zeros((window.num_frames, len(names), 1, 4))
    turn[..., 0] = 1.0
    weights = np.zeros((window.num_frames, len(names), 1))
    for c, name in enumerate(names):
        if name not in imu.cameras:
            continue
        s = imu.cameras.index(name)
        t1 = window.times + shifts[c]
        t0 = t1 - 1.0 / window.fps
        ok = (t0 >= imu.time[0]) & (t1 <= imu.time[-1])
        if not ok.any():
            continue
        q = integrate_gyro(imu.time, imu.gyro[:, s : s + 1], np.where(ok, t0, imu.time[0]), np.where(ok, t1, imu.time[0]))
        mount = np.asarray(imu.camera_from_imu[s, :4], np.float64)  # the turn in the camera: mount · q · mount⁻¹
        turn[:, c, 0] = quat_multiply(quat_multiply(mount, q[:, 0]), quat_conjugate(mount))
        weights[:, c, 0] = np.where(ok, 1.0 / np.radians(sigma_deg) ** 2, 0.0)
    return GyroTurn({"turn": turn, "weights": weights}, name="gyro turns")
