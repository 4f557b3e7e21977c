"""What the cameras' gyros say of their turns: over each pair of a solver window's frames (``[solver] gyro_turn``,
read at the camera's shift on the gyro's clock, as a :class:`~bcmocap.residuals.gyro.GyroTurn`), from the frames
a camera registered in to the rest pose of a range-of-motion trial where it registered in none of the rest frames,
through the frames of a trial it did not register in (the initial motion's), and, for a camera that registered
nowhere, how it sits relative to another camera of its segment."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..cameras import camera_at
from ..geometry import (matrix_from_quat, quat_conjugate, quat_from_matrix, quat_log, quat_multiply,
                        rotation_from_covariance, slerp)
from ..io.sensors import ImuRecording, integrate_gyro, read_imu
from ..kinematics.virtual import robust_average_poses
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
        turn[:, c, 0] = _in_camera(imu, s, q[:, 0])
        weights[:, c, 0] = np.where(ok, 1.0 / np.radians(sigma_deg) ** 2, 0.0)
    return GyroTurn({"turn": turn, "weights": weights}, name="gyro turns")


def homography_weights_gyros_agree_with(window: TermWindow, tolerance_deg: float,
                                        time_shifts_s: Sequence[float] | None = None, *, min_matches: int = 30,
                                        file: str = "imu.npz") -> np.ndarray:
    """``(W, C, M)`` the window's homography weights with the matches its cameras' gyros contradict set to 0.

    A homography match pairs a pixel of frame ``t`` with one of frame ``t−1``; the camera's gyro turn over that
    interval (read at the camera's shift on the gyro's clock, :func:`gyro_turns`) carries the ray of the first onto
    where the second should lie. A match further than ``tolerance_deg`` from it is on something that moved: most
    often the wearer's own body, which fills a limb camera's view where the room has little texture, and whose
    matches then pull the camera's turn towards the body's. A frame pair where fewer than half of the matches agree,
    or fewer than ``min_matches`` (or all of them, when it had fewer), loses them all: its agreeing few are as likely
    on the moving thing. Cameras and frames without a gyro reading keep theirs.
    """
    corr = window.correspondences
    weights = np.array(corr.homography_weights, np.float64)
    if not weights.size or not (weights > 0).any():
        return weights
    turns = gyro_turns(window, 1.0, time_shifts_s, file)
    read = turns.data["weights"][:, :, 0] > 0  # (W, C)
    cos_tolerance = np.cos(np.radians(tolerance_deg))
    for c in range(weights.shape[1]):
        rows = read[:, c] & (weights[:, c] > 0).any(axis=1)
        if not rows.any():
            continue
        camera = camera_at(window.rig.intrinsics, c)
        # the whole window's (W, M) pixels at once: the same shapes in every window, so JAX compiles them once
        rays = np.asarray(camera.unproject(corr.homography_pixels[:, c]))[rows]  # (K, M, 3) frame t
        rays_prev = np.asarray(camera.unproject(corr.homography_pixels_prev[:, c]))[rows]  # frame t - 1
        prev_from_curr = matrix_from_quat(turns.data["turn"][rows, c, 0])  # (K, 3, 3)
        carried = np.einsum("kab,kmb->kma", prev_from_curr, rays)
        agree = np.sum(carried * rays_prev, axis=-1) >= cos_tolerance * np.linalg.norm(carried, axis=-1) * \
            np.linalg.norm(rays_prev, axis=-1)
        kept = np.where(agree, weights[rows, c], 0.0)
        had, agreed = (weights[rows, c] > 0).sum(axis=1), (kept > 0).sum(axis=1)
        kept[(agreed < np.minimum(min_matches, had)) | (2 * agreed < had)] = 0.0
        weights[rows, c] = kept
    return weights


def _in_camera(imu: ImuRecording, sensor: int, turn: np.ndarray) -> np.ndarray:
    """``(K, 4)`` turns of ``sensor``'s IMU frame (wxyz) as turns of its camera: mount · q · mount⁻¹."""
    mount = np.asarray(imu.camera_from_imu[sensor, :4], np.float64)
    return quat_multiply(quat_multiply(mount, turn), quat_conjugate(mount))


def _shifts_and_cameras(what: str, c: int, time_shifts_s, cameras) -> tuple[np.ndarray, np.ndarray]:
    """``(C,)`` time shifts (None: 0) and ``(C,)`` chosen cameras (None: all), checked (one-line ValueError)."""
    shifts = np.zeros(c) if time_shifts_s is None else np.asarray(time_shifts_s, np.float64)
    if shifts.shape != (c,):
        raise ValueError(f"{what}: {shifts.size} time shifts for {c} cameras")
    chosen = np.ones(c, bool) if cameras is None else np.asarray(cameras, bool)
    if chosen.shape != (c,):
        raise ValueError(f"{what}: cameras has shape {chosen.shape}, expected ({c},)")
    return shifts, chosen


def rest_orientations_from_gyros(world_from_camera: np.ndarray, registered: np.ndarray, rest: np.ndarray, fps: float,
                                 imu: ImuRecording, names: Sequence[str],
                                 time_shifts_s: Sequence[float] | None = None, *,
                                 cameras: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Each camera's orientation in the rest pose of a range-of-motion trial, where no rest frame registered it,
    carried by its gyro from the frames that did.

    Each registered frame's orientation is turned by the gyro's integral from that frame to the middle of the rest
    frames (on the gyro's clock: the frame times plus the camera's shift), and the turned orientations are averaged
    robustly. The gyro's bias is not taken off: its mean over the rest frames is not a bias where the cameras wobble
    on their straps while the body holds still (on the studio's realistic sparse walk it read up to 2.1°/s where the
    turn-on bias is at most 0.9°/s, and carried the cameras 0.4–3.8° off the truth against 0.6–2.1° without it), so a
    bias ``b`` leaves up to ``|b| · t`` over the ``t`` seconds carried.

    Args:
        world_from_camera: ``(T, C, 7)`` registered poses (wxyz_xyz); only registered rows are read.
        registered: ``(T, C)`` bool. rest: ``(T,)`` bool, the rest frames. fps: frame rate (frame ``k`` at ``k/fps`` s).
        imu: the trial's recording. names: ``(C,)`` camera names, matched to ``imu.cameras``.
        time_shifts_s: ``(C,)`` where each camera's frames lie on the gyro's clock after the frame times (None: 0).
        cameras: ``(C,)`` bool, the cameras to carry (None: every camera registered in no rest frame; a camera
            registered in a rest frame is never carried).

    Returns:
        ``(C, 4)`` wxyz orientations (NaN for cameras registered in a rest frame, without a gyro, or registered in no
        frame the recording covers) and, per carried camera name, ``{"frames", "nearest_s", "spread_deg"}``: the
        frames carried from, the nearest one's distance from the rest frames, and the turned orientations' median
        angle from their mean.
    """
    world_from_camera = np.asarray(world_from_camera, np.float64)
    registered = np.asarray(registered, bool)
    rest = np.asarray(rest, bool)
    c = len(names)
    if world_from_camera.shape != (len(rest), c, 7) or registered.shape != (len(rest), c):
        raise ValueError(f"rest orientations from gyros: expected poses ({len(rest)}, {c}, 7) and registered "
                         f"({len(rest)}, {c}), got {world_from_camera.shape} and {registered.shape}")
    shifts, chosen = _shifts_and_cameras("rest orientations from gyros", c, time_shifts_s, cameras)
    out = np.full((c, 4), np.nan)
    report = {}
    if not rest.any():
        return out, report
    times = np.arange(len(rest)) / fps
    rest_mid = float(np.mean(times[rest]))
    for i, name in enumerate(names):
        if not chosen[i] or registered[rest, i].any() or name not in imu.cameras:
            continue
        s = imu.cameras.index(name)
        t_mid = rest_mid + shifts[i]
        frames = np.flatnonzero(registered[:, i] & (times + shifts[i] >= imu.time[0]) & (times + shifts[i] <= imu.time[-1]))
        if not frames.size or not imu.time[0] <= t_mid <= imu.time[-1]:
            continue
        q = integrate_gyro(imu.time, imu.gyro[:, s : s + 1], times[frames] + shifts[i], np.full(frames.size, t_mid))
        carried = quat_multiply(world_from_camera[frames, i, :4], _in_camera(imu, s, q[:, 0]))  # turned frame → rest
        mean = robust_average_poses(np.concatenate([carried, np.zeros((frames.size, 3))], axis=1))[0][:4]
        angles = 2.0 * np.arccos(np.clip(np.abs(carried @ mean), 0.0, 1.0))
        out[i] = mean
        report[name] = {"frames": int(frames.size), "nearest_s": float(np.min(np.abs(times[frames] - rest_mid))),
                        "spread_deg": float(np.degrees(np.median(angles)))}
    return out, report


def fill_orientations_from_gyros(world_from_camera: np.ndarray, registered: np.ndarray, fps: float,
                                 imu: ImuRecording, names: Sequence[str],
                                 time_shifts_s: Sequence[float] | None = None, *,
                                 cameras: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each camera's orientation in the frames it did not register, carried by its gyro from the registered frames on
    either side.

    In a gap between registered frames ``a`` and ``b``, the orientation carried forward from ``a`` and the one carried
    back from ``b`` are blended by slerp at ``(t − a) / (b − a)``, so what the gyro's bias adds over the gap ends where
    the registrations are; before the first and after the last registered frame, one side carries. A hand that turns
    180° in a few unregistered frames is then turned the way it turned, where interpolating between the registered
    orientations takes the shorter way round.

    Args:
        world_from_camera: ``(T, C, 7)`` registered poses (wxyz_xyz); only registered rows are read.
        registered: ``(T, C)`` bool. fps: frame rate (frame ``k`` at ``k/fps`` s).
        imu: the trial's recording. names: ``(C,)`` camera names, matched to ``imu.cameras``.
        time_shifts_s: ``(C,)`` where each camera's frames lie on the gyro's clock after the frame times (None: 0).
        cameras: ``(C,)`` bool, the cameras to fill (None: all).

    Returns:
        ``(T, C, 7)`` poses, their orientations filled where carried (positions as given), and ``(T, C)`` bool, the
        camera-frames filled (never a registered one; none for a camera without a gyro or registered nowhere the
        recording covers).
    """
    world_from_camera = np.array(world_from_camera, np.float64)
    registered = np.asarray(registered, bool)
    num_frames, c = registered.shape
    if world_from_camera.shape != (num_frames, c, 7) or len(names) != c:
        raise ValueError(f"orientations from gyros: expected poses ({num_frames}, {c}, 7) and {c} names, got "
                         f"{world_from_camera.shape} and {len(names)}")
    shifts, chosen = _shifts_and_cameras("orientations from gyros", c, time_shifts_s, cameras)
    filled = np.zeros((num_frames, c), bool)
    times = np.arange(num_frames) / fps
    for i, name in enumerate(names):
        if not chosen[i] or name not in imu.cameras:
            continue
        s = imu.cameras.index(name)
        on_clock = times + shifts[i]
        covered = (on_clock >= imu.time[0]) & (on_clock <= imu.time[-1])
        known = np.flatnonzero(registered[:, i] & covered)
        gaps = np.flatnonzero(~registered[:, i] & covered)
        if not known.size or not gaps.size:
            continue
        after = np.searchsorted(known, gaps)
        before = known[np.maximum(after - 1, 0)]
        nxt = known[np.minimum(after, known.size - 1)]

        def carried(frm):
            turn = _in_camera(imu, s, integrate_gyro(imu.time, imu.gyro[:, s : s + 1], on_clock[frm], on_clock[gaps])[:, 0])
            return quat_multiply(world_from_camera[frm, i, :4], turn)

        forward, backward = carried(before), carried(nxt)
        frac = np.where(after == 0, 1.0, np.where(after == known.size, 0.0,
                                                   (gaps - before) / np.maximum(nxt - before, 1)))
        world_from_camera[gaps, i, :4] = slerp(forward, backward, frac)
        filled[gaps, i] = True
    return world_from_camera, filled


def rotations_from_siblings_by_gyro(trials: Sequence[tuple[np.ndarray, np.ndarray, float, ImuRecording, np.ndarray]],
                                    names: Sequence[str], segments: Sequence[str], cameras: np.ndarray, *,
                                    stride_s: float = 0.2, min_turn_deg: float = 3.0,
                                    min_spread: float = 0.1) -> tuple[dict, dict]:
    """Where a camera registered in no frame of any trial, its orientation relative to another camera of its segment
    that registered (its *sibling*: the one registered most), from its gyro: both are rigid on the segment, so over
    any interval the sibling's turn, read from its registered poses, is the camera's turn, read from its gyro, seen
    through the rotation ``Q`` = sibling_from_camera: ``log(ΔR_sibling) = Q · log(ΔR_camera)``. ``Q`` is the
    least-squares (Wahba) rotation over pairs of the sibling's registered frames ``stride_s`` apart (at most 1.5 times
    that: none across a gap), read on the gyro's clock at the sibling's shift, fitted again without the pairs whose
    residual is over 3 times the median (a wrong registration).

    Args:
        trials: per trial ``(world_from_camera (T, C, 7), registered (T, C), fps, imu, time_shifts_s (C,))``: the
            registered poses (only registered rows are read; any world frame, a turn does not depend on it), the
            trial's recording, and where each camera's frames lie on the gyro's clock after the frame times.
        names, segments: ``(C,)`` camera names and their segments' names.
        cameras: ``(C,)`` bool, the cameras to place this way.
        stride_s: the frame pairs' spacing (s); min_turn_deg: pairs whose turns are smaller are left out (noise).
        min_spread: the turns' axes must span more than a line: the second singular value of their cross-covariance
            over the first at least this, or the rotation about their common axis is not determined.

    Returns:
        name → ``(sibling name, (4,) wxyz Q)`` for each camera placed, and name → ``{"sibling", "pairs",
        "residual_deg", "spread"}`` for each chosen camera with a gyro and a registered sibling (``"placed"``: whether
        its rotation was determined): the pairs used, the median angle between the sibling's turns and the camera's
        turned by ``Q``, and the axes' spread.
    """
    c = len(names)
    chosen = np.asarray(cameras, bool)
    if chosen.shape != (c,) or len(segments) != c:
        raise ValueError(f"rotations from siblings: {c} names, {len(segments)} segments, cameras of shape {chosen.shape}")
    counts = sum((np.asarray(r, bool).sum(axis=0) for _, r, *_ in trials), np.zeros(c, int))
    placed, report = {}, {}
    for i in np.flatnonzero(chosen):
        siblings = [k for k in range(c) if segments[k] == segments[i] and k != i and counts[k] > 0]
        if not siblings:
            continue
        k = max(siblings, key=lambda m: counts[m])
        sibling_turns, own_turns = [], []
        for poses, registered, fps, imu, shifts in trials:
            if names[i] not in imu.cameras:
                continue
            s = imu.cameras.index(names[i])
            known = np.flatnonzero(np.asarray(registered, bool)[:, k])
            step = max(1, round(stride_s * fps))
            later = np.searchsorted(known, known + step)
            pairs = np.stack([known[later < known.size], known[later[later < known.size]]], axis=1)
            pairs = pairs[pairs[:, 1] - pairs[:, 0] <= 1.5 * step]  # no pair across a gap: the gyro drifts over it
            on_clock = pairs / fps + shifts[k]  # the sibling's frames, where its exposures lie on the gyro's clock
            pairs = pairs[((on_clock >= imu.time[0]) & (on_clock <= imu.time[-1])).all(axis=1)]
            if not pairs.size:
                continue
            q = np.asarray(poses, np.float64)[:, k, :4]
            sibling_turns.append(quat_multiply(quat_conjugate(q[pairs[:, 0]]), q[pairs[:, 1]]))
            t0, t1 = (pairs[:, j] / fps + shifts[k] for j in (0, 1))
            own_turns.append(_in_camera(imu, s, integrate_gyro(imu.time, imu.gyro[:, s : s + 1], t0, t1)[:, 0]))
        if not sibling_turns:
            continue
        a_sibling, a_own = quat_log(np.concatenate(sibling_turns)), quat_log(np.concatenate(own_turns))
        big = np.linalg.norm(a_own, axis=1) > np.radians(min_turn_deg)
        a_sibling, a_own = a_sibling[big], a_own[big]

        def wahba(target, source):
            """The rotation with ``target ≈ R source`` (from ``Σ target sourceᵀ``), each row's residual and the
            cross-covariance's singular values."""
            cov = target.T @ source
            rot = rotation_from_covariance(cov)
            return rot, np.linalg.norm(target - source @ rot.T, axis=1), np.linalg.svd(cov, compute_uv=False)

        rot, residual, _ = wahba(a_sibling, a_own)
        if residual.size:  # once more without the turns a wrong registration gave (over 3 times the median residual)
            keep = residual <= 3.0 * np.median(residual)
            a_sibling, a_own = a_sibling[keep], a_own[keep]
        rot, residual, sv = wahba(a_sibling, a_own)
        spread = float(sv[1] / sv[0]) if sv[0] > 0 else 0.0
        report[names[i]] = {"sibling": names[k], "pairs": len(residual), "spread": spread,
                            "residual_deg": float(np.degrees(np.median(residual))) if residual.size else float("nan"),
                            "placed": bool(residual.size >= 3 and spread >= min_spread)}
        if report[names[i]]["placed"]:
            placed[names[i]] = (names[k], quat_from_matrix(rot))
    return placed, report
