"""When each camera's frames were exposed on its gyro's clock, and the rolling-shutter readout, from a trial's own
frames (issue 42; the method of Karpenko et al. 2011, "Digital video stabilization and rolling shutter correction
using gyroscopes", §4, beyond the paper).

:class:`~.rolling_shutter.GyroUnwarp` reads the gyro at each frame's time, ``(i − offsets[c]) / fps`` on the clock of
``imu.npz``. On a real shoot that time is off: the clap sync finds whole frames (a camera starts at any sub-frame
time), the IMU's clock runs apart from the video's (an offset of tens of milliseconds), and the readout on a data
sheet is not the camera's. A gyro read 10 ms off at 5 rad/s turns the correction by 3° the wrong way.

Both are found in the frames: a feature tracked from frame ``i`` to ``i + 1`` (KLT, checked backwards) is, up to the
camera's small translation, one direction seen at two times, so with the right time shift ``δ`` and readout ``r``
its two bearings turned into the world by the gyro's orientation agree:

    R(t_i(y_a)) b_a ≈ R(t_{i+1}(y_b)) b_b,   t_i(y) = (i − offsets[c]) / fps + δ + (y / (H − 1) − ½) r,

with ``R(t)`` the IMU's orientation integrated from the gyro (:func:`~bcmocap.io.sensors.integrate_gyro`) turned
into the camera by the IMU's mount. :func:`estimate_gyro_timing` minimises the robust (Cauchy, scale
:data:`ANGLE_SCALE`) sum of the pairs' angles: per camera over ``δ`` on a grid (:data:`SEARCH_S` either side, steps
of :data:`COARSE_STEP_S`, then finer around the best), the readout, one per capture (the cameras are one model),
over :data:`READOUT_GRID` fractions of a frame period shared by all cameras, each parabola-refined. The camera's
translation between two frames (2 cm at 1.3 m/s) and the scene's parallax are what the robust loss absorbs; the
rotations they are weighed against are degrees.

A camera that barely turned in the frames used (its cost does not rise by :data:`MIN_CONTRAST` away from its
minimum), or whose least cost lies at the edge of the search, gets the median shift of the others, with a note.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..geometry import quat_conjugate, quat_multiply, rotate_by_quat
from ..io.sensors import ImuRecording, integrate_gyro
from .threads import default_threads

__all__ = ["ANGLE_SCALE", "GyroTiming", "RotationPairs", "alignment_cost", "estimate_gyro_timing", "gyro_orientation",
           "rotation_pairs", "timing_of_trials", "trial_pairs", "turning_windows"]

#: Scale of the Cauchy loss on a pair's angle (rad): about one pixel of a 640-pixel-wide fisheye.
ANGLE_SCALE = 0.004
#: How far either side of the clock's own frame time the shift is searched (s).
SEARCH_S = 0.1
COARSE_STEP_S = 0.002
FINE_STEP_S = 0.00025
#: Readouts tried, as fractions of a frame period (0 to 1: a global shutter to a readout of the whole period).
READOUT_GRID = np.linspace(0.0, 1.0, 21)
#: A camera's cost must rise by this fraction of its minimum within the search for its shift to count.
MIN_CONTRAST = 0.05
#: Spacing of the orientation table the gyro is integrated into (s).
TABLE_STEP_S = 0.0005
#: At most this many pairs per camera are weighed (an even subsample of the rest): the search's cost is linear in
#: them, and past a few thousand the shift's error is the scene's parallax, not their number.
MAX_PAIRS = 6000
#: Fewest rows a batch of pixels is unprojected in (padded to a power of two at or above it, :func:`_bearings`).
_BEARING_BUCKET = 1024


@dataclasses.dataclass(frozen=True)
class RotationPairs:
    """Features tracked from one video frame to the next of one camera.

    Attributes:
        frame: ``(K,)`` int, the trial's video frame of the first of each pair (the second is the next one).
        bearing_a, bearing_b: ``(K, 3)`` unit bearings in the camera (through its lens) in the two frames.
        row_a, row_b: ``(K,)`` image rows (px) of the feature in the two frames.
        height: the image height (px).
    """

    frame: np.ndarray
    bearing_a: np.ndarray
    bearing_b: np.ndarray
    row_a: np.ndarray
    row_b: np.ndarray
    height: int

    def __len__(self) -> int:
        return len(self.frame)

    def take(self, keep: np.ndarray) -> RotationPairs:
        """The pairs at indices (or a mask) ``keep``."""
        return RotationPairs(self.frame[keep], self.bearing_a[keep], self.bearing_b[keep], self.row_a[keep],
                             self.row_b[keep], self.height)

    @staticmethod
    def joined(parts: list[RotationPairs], height: int) -> RotationPairs:
        """All of ``parts``' pairs, in order (none for no parts), of an image ``height`` px high."""
        if not parts:
            empty = np.zeros((0, 3))
            return RotationPairs(np.zeros(0, np.int64), empty, empty, np.zeros(0), np.zeros(0), height)
        return RotationPairs(*(np.concatenate([getattr(p, name) for p in parts])
                               for name in ("frame", "bearing_a", "bearing_b", "row_a", "row_b")), height)


def rotation_pairs(frames, lens, *, max_corners: int = 150, quality: float = 0.01, min_distance: int = 12,
                   max_error_px: float = 0.5) -> RotationPairs:
    """KLT pairs between consecutive frames of one camera.

    Args:
        frames: ``(index, gray (H, W) uint8)`` in order (consecutive indices; a gap starts again).
        lens: the camera's :class:`~bcmocap.cameras.CameraModel` (bearings through it).
        max_corners, quality, min_distance: ``cv2.goodFeaturesToTrack`` in each first frame.
        max_error_px: a pair is kept when tracking it back lands within this of where it started.
    """
    import cv2

    chunks: list[tuple] = []
    previous = None
    for index, image in frames:
        if previous is not None and previous[0] == index - 1:
            corners = cv2.goodFeaturesToTrack(previous[1], max_corners, quality, min_distance)
            if corners is not None and len(corners) >= 8:
                forward, ok1, _ = cv2.calcOpticalFlowPyrLK(previous[1], image, corners, None)
                back, ok2, _ = cv2.calcOpticalFlowPyrLK(image, previous[1], forward, None)
                good = (ok1.ravel() == 1) & (ok2.ravel() == 1) & (np.linalg.norm((back - corners)[:, 0], axis=1) < max_error_px)
                if good.sum() >= 8:
                    chunks.append((np.full(int(good.sum()), previous[0]), corners[good, 0], forward[good, 0]))
        previous = (index, image)
    height = int(lens.height)
    if not chunks:
        return RotationPairs.joined([], height)
    frame = np.concatenate([c[0] for c in chunks]).astype(np.int64)
    a = np.concatenate([c[1] for c in chunks]).astype(np.float64)
    b = np.concatenate([c[2] for c in chunks]).astype(np.float64)
    bearings = _bearings(lens, np.concatenate([a, b]))
    return RotationPairs(frame, bearings[:len(a)], bearings[len(a):], a[:, 1], b[:, 1], height)


def _bearings(lens, pixels: np.ndarray) -> np.ndarray:
    """``(N, 3)`` unit bearings of ``(N, 2)`` pixels (OpenCV convention) through ``lens``. They are unprojected padded
    with the image centre to a power of two rows (at least :data:`_BEARING_BUCKET`), the padding dropped after, so that
    the jitted unprojection compiles once per bucket, not once per count of pairs (a window's pairs vary: each new
    count traced and compiled it again, half of the gyro timing's time)."""
    size = max(_BEARING_BUCKET, 1 << (len(pixels) - 1).bit_length())
    padded = np.concatenate([pixels, np.broadcast_to(np.asarray([[float(lens.width) / 2, float(lens.height) / 2]]),
                                                     (size - len(pixels), 2))])
    bearings = np.array(lens.unproject(padded), np.float64)[:len(pixels)]
    return bearings / np.linalg.norm(bearings, axis=1, keepdims=True)


def gyro_orientation(imu: ImuRecording, sensor: int, step_s: float = TABLE_STEP_S) -> Callable[[np.ndarray], np.ndarray]:
    """``orientation(t)``: ``(K, 4)`` wxyz rotation of sensor ``sensor``'s IMU frame at times ``t`` ``(K,)`` (s, on
    the IMU's clock, clipped to its span) relative to its first sample, from the gyro integrated into a table every
    ``step_s`` and normalised-linear interpolation between its entries."""
    start, stop = float(imu.time[0]), float(imu.time[-1])
    grid = np.linspace(start, stop, max(int(np.ceil((stop - start) / step_s)) + 1, 2))
    table = integrate_gyro(imu.time, imu.gyro[:, sensor:sensor + 1], np.full_like(grid, start), grid)[:, 0]
    # one hemisphere along the table, so neighbours interpolate the short way
    sign = np.cumprod(np.r_[1.0, np.sign(np.sum(table[1:] * table[:-1], axis=1) + 1e-300)])
    table = table * sign[:, None]

    def orientation(t: np.ndarray) -> np.ndarray:
        u = (np.clip(np.asarray(t, np.float64), start, stop) - start) / (grid[1] - grid[0])
        k = np.clip(np.floor(u).astype(np.int64), 0, len(grid) - 2)
        w = (u - k)[:, None]
        q = (1.0 - w) * table[k] + w * table[k + 1]
        return q / np.linalg.norm(q, axis=1, keepdims=True)

    return orientation


def alignment_cost(pairs: RotationPairs, orientation, imu_from_camera: np.ndarray, frame_zero: float, fps: float,
                   shift_s: float, readout_s: float, scale: float = ANGLE_SCALE) -> float:
    """The Cauchy cost ``Σ log(1 + (angle / scale)²)`` of the pairs' world directions disagreeing (module docstring)
    for a time shift ``shift_s`` and readout ``readout_s``; ``frame_zero``: the video frame at time 0 of the IMU's
    clock (the first clap's); ``imu_from_camera`` ``(4,)`` wxyz."""
    h = max(pairs.height - 1, 1)
    times = []
    for frame, row in ((pairs.frame, pairs.row_a), (pairs.frame + 1, pairs.row_b)):
        times.append((frame - frame_zero) / fps + shift_s + (row / h - 0.5) * readout_s)
    world_a = rotate_by_quat(quat_multiply(orientation(times[0]), imu_from_camera), pairs.bearing_a)
    world_b = rotate_by_quat(quat_multiply(orientation(times[1]), imu_from_camera), pairs.bearing_b)
    angle = np.linalg.norm(np.cross(world_a, world_b), axis=1)
    return float(np.sum(np.log1p((angle / scale) ** 2)))


@dataclasses.dataclass(frozen=True)
class GyroTiming:
    """What :func:`estimate_gyro_timing` found for one trial.

    Attributes:
        time_shift_s: ``(C,)`` add to each camera's frame time ``(i − offsets[c]) / fps`` to read its gyro (s).
        readout_s: the rolling shutter's time from the first row to the last (s).
        pairs: ``(C,)`` feature pairs found per camera (at most :data:`MAX_PAIRS` of them weighed).
        determined: ``(C,)`` bool: the camera's cost determined its shift (else it got the others' median).
        readout_estimated: whether the readout was estimated (else the one given).
    """

    time_shift_s: np.ndarray
    readout_s: float
    pairs: np.ndarray
    determined: np.ndarray
    readout_estimated: bool

    def as_dict(self) -> dict:
        return {"time_shift_ms": np.round(1e3 * self.time_shift_s, 4).tolist(), "readout_ms": round(1e3 * self.readout_s, 4),
                "readout_estimated": self.readout_estimated, "pairs": self.pairs.tolist(),
                "determined": self.determined.tolist()}


def _subsample(pairs: RotationPairs, count: int) -> RotationPairs:
    """At most ``count`` of the pairs, evenly spaced in their order (all when there are fewer)."""
    if len(pairs) <= count:
        return pairs
    return pairs.take(np.linspace(0, len(pairs) - 1, count).round().astype(np.int64))


def _parabola_minimum(x: np.ndarray, y: np.ndarray) -> float:
    """The minimum of the parabola through the grid's lowest point and its neighbours (the point itself at an end)."""
    k = int(np.argmin(y))
    if k == 0 or k == len(y) - 1:
        return float(x[k])
    y0, y1, y2 = y[k - 1], y[k], y[k + 1]
    denominator = y0 - 2 * y1 + y2
    if denominator <= 0:
        return float(x[k])
    return float(x[k] + 0.5 * (x[k + 1] - x[k]) * (y0 - y2) / denominator)


def _best_shift(cost: Callable[[float], float], centre: float, search_s: float) -> tuple[float, float, float]:
    """``(shift, cost there, contrast)``: coarse grid over ``centre ± search_s``, then a fine one around the best
    (contrast 0 when the coarse grid's least cost is at its edge: the shift lies beyond the search)."""
    coarse = centre + np.arange(-search_s, search_s + 1e-12, COARSE_STEP_S)
    values = np.array([cost(s) for s in coarse])
    k = int(np.argmin(values))
    best = coarse[k]
    fine = best + np.arange(-2 * COARSE_STEP_S, 2 * COARSE_STEP_S + 1e-12, FINE_STEP_S)
    fine_values = np.array([cost(s) for s in fine])
    shift = _parabola_minimum(fine, fine_values)
    low = min(float(fine_values.min()), float(values.min()))
    if k in (0, len(coarse) - 1):  # the least cost at the search's edge: the shift lies beyond it, not found
        return shift, cost(shift), 0.0
    return shift, cost(shift), (float(np.median(values)) - low) / max(low, 1e-300)


def estimate_gyro_timing(pairs: list[RotationPairs], imu, imu_index, offsets, fps: float,
                         readout_s: float, *, estimate_readout: bool = True, search_s: float = SEARCH_S,
                         groups=None, log: Callable[[str], None] | None = None) -> GyroTiming:
    """Each camera's gyro time shift and (optionally) the shared readout (module docstring).

    Args:
        pairs: per camera, its :func:`rotation_pairs` (frames counted as ``offsets`` are).
        imu: the trial's gyro recording, or one per camera (cameras of several trials, which share the readout);
            imu_index: ``(C,)`` each camera's sensor in its recording.
        groups: ``(C,)`` labels (e.g. the trial): a camera whose shift is undetermined gets the median of its
            group's (None: one group).
        offsets: ``(C,)`` each camera's video frame of the first clap (time 0 of the IMU's clock, up to the shift).
        fps: video frame rate (Hz); readout_s: the readout given (a data sheet's), kept unless ``estimate_readout``.

    Raises:
        ValueError: no camera has pairs that determine its shift.
    """
    count = len(pairs)
    if not count == len(imu_index) == len(offsets):
        raise ValueError(f"estimate_gyro_timing: {count} cameras' pairs, {len(imu_index)} IMU indices, {len(offsets)} offsets")
    found = np.array([len(p) for p in pairs])
    pairs = [_subsample(p, MAX_PAIRS) for p in pairs]
    recordings = [imu] * count if isinstance(imu, ImuRecording) else list(imu)
    if len(recordings) != count:
        raise ValueError(f"estimate_gyro_timing: {count} cameras' pairs, {len(recordings)} gyro recordings")
    costs = []
    for c in range(count):
        orientation = gyro_orientation(recordings[c], int(imu_index[c]))
        imu_from_camera = quat_conjugate(np.asarray(recordings[c].camera_from_imu[int(imu_index[c]), :4], np.float64))

        def cost(shift, readout, p=pairs[c], o=orientation, m=imu_from_camera, zero=float(offsets[c])):
            return alignment_cost(p, o, m, zero, fps, shift, readout) / max(len(p), 1)

        costs.append(cost)
    shifts = np.zeros(count)
    contrast = np.zeros(count)
    searched = [c for c in range(count) if len(pairs[c]) >= 30]
    # cameras in threads (numpy releases the GIL for part of a cost over thousands of pairs); each camera's search is
    # its own, and the results are taken in camera order
    with ThreadPoolExecutor(max_workers=default_threads()) as pool:
        for c, (shift, _, rise) in zip(searched, pool.map(
                lambda c: _best_shift(lambda s: costs[c](s, readout_s), 0.0, search_s), searched)):
            shifts[c], contrast[c] = shift, rise
    determined = contrast >= MIN_CONTRAST
    if not determined.any():
        raise ValueError("estimate_gyro_timing: no camera turned enough in the frames used to time its gyro "
                         f"(cost contrasts {np.round(contrast, 3).tolist()})")
    readout = float(readout_s)
    if estimate_readout:
        period = 1.0 / fps
        grid = READOUT_GRID * period
        local = np.arange(-3 * FINE_STEP_S * 2, 3 * FINE_STEP_S * 2 + 1e-12, 2 * FINE_STEP_S)

        def per_readout(c: int) -> np.ndarray:  # the best shift near this camera's for each readout
            return np.array([min(costs[c](s, r) for s in shifts[c] + local) for r in grid])

        timed = np.flatnonzero(determined)
        with ThreadPoolExecutor(max_workers=default_threads()) as pool:
            total = np.zeros(len(grid))
            for row in pool.map(per_readout, timed):  # summed in camera order, as one thread would
                total += row
            readout = min(max(_parabola_minimum(grid, total), 0.0), period)
            for c, (shift, _, _) in zip(timed, pool.map(
                    lambda c: _best_shift(lambda s: costs[c](s, readout), shifts[c], 4 * COARSE_STEP_S), timed)):
                shifts[c] = shift
    groups = np.zeros(count, np.int64) if groups is None else np.asarray(groups)
    for group in np.unique(groups[~determined]):
        mine = groups == group
        if not (mine & determined).any():
            raise ValueError(f"estimate_gyro_timing: no camera of {str(group)!r} turned enough in the frames used to time its "
                             f"gyro (cost contrasts {np.round(contrast[mine], 3).tolist()})")
        median = float(np.median(shifts[mine & determined]))
        if log is not None:
            log(f"gyro timing: camera(s) {np.flatnonzero(mine & ~determined).tolist()} turned too little to time their "
                f"gyro; given the others' median shift {1e3 * median:.2f} ms")
        shifts[mine & ~determined] = median
    return GyroTiming(shifts, readout, found, determined, bool(estimate_readout))


def turning_windows(imu: ImuRecording, sensor: int, span: int, fps: float, count: int, length: int) -> np.ndarray:
    """Start frames (from the first clap) of ``count`` non-overlapping stretches of ``length`` frames within ``span``
    where the gyro of ``sensor`` turns fastest (mean ``|ω|`` at the frames' clock times): the turns that show the
    readout and the shift best. Fewer when the span holds fewer."""
    frames = np.arange(max(int(span), 1))
    speed = np.linalg.norm(imu.gyro[:, sensor], axis=1)
    at_frame = np.interp(frames / fps, imu.time, speed)
    if len(frames) <= length:
        return np.zeros(1, np.int64)
    score = np.convolve(at_frame, np.ones(length) / length, mode="valid")  # window starting at each frame
    chosen: list[int] = []
    for start in np.argsort(-score, kind="stable"):
        if all(abs(int(start) - c) >= length for c in chosen):
            chosen.append(int(start))
            if len(chosen) == count:
                break
    return np.sort(np.asarray(chosen, np.int64))


def trial_pairs(capture, trial: str, offsets, span: int, *, windows: int = 8, window_frames: int = 20):
    """The trial's gyro recording, each camera's sensor in it, and each camera's :func:`rotation_pairs` from
    ``windows`` stretches of ``window_frames`` consecutive frames of its first ``span`` frames from its first clap
    (:func:`~.command.trial_frames`) where its gyro turns fastest (:func:`turning_windows`).

    Raises:
        ValueError: naming the file when the trial has no gyro recording or a camera none.
    """
    from ..io.sensors import read_imu
    from .rolling_shutter import gyro_file, imu_indices

    path = gyro_file(capture, trial)
    imu = read_imu(path)
    index = imu_indices(capture, path, imu)
    offsets = np.asarray(offsets, np.int64).ravel()

    def one_camera(c: int) -> RotationPairs:
        camera = capture.cameras[c]
        starts = offsets[c] + turning_windows(imu, index[c], span, float(capture.fps), windows, window_frames)
        found = [rotation_pairs(frames, camera.intrinsics)
                 for frames in _windows(capture.frames(trial, c, start=int(starts[0]), stop=int(starts[-1] + window_frames),
                                                       gray=True), starts, window_frames)]
        return RotationPairs.joined(found, int(camera.intrinsics.height))

    # Cameras in threads (decoding and KLT release the GIL), each video read once from its first window to its last
    with ThreadPoolExecutor(max_workers=default_threads()) as pool:
        pairs = list(pool.map(one_camera, range(len(capture.cameras))))
    return imu, index, pairs


def _windows(frames, starts: np.ndarray, length: int):
    """The ``(index, image)`` of ``frames`` (in order) within each window ``starts[k] … starts[k] + length − 1``
    (``starts`` increasing, windows apart), one list per window, each yielded once the stream has passed it (one
    window's frames held at a time)."""
    current: list = []
    k_current = -1
    for index, image in frames:
        k = int(np.searchsorted(starts, index, side="right")) - 1
        if k < 0 or index >= starts[k] + length:
            continue
        if k != k_current and k_current >= 0:
            yield current
            current = []
        k_current = k
        current.append((index, image))
    if k_current >= 0:
        yield current


def timing_of_trials(capture, offsets: dict, readout_s: float, *, spans: dict,
                     estimate_readout: bool = True, log: Callable[[str], None] | None = None) -> dict[str, GyroTiming]:
    """:func:`estimate_gyro_timing` of a capture's trials together (``offsets``: trial → each camera's video frame of
    its first clap; ``spans``: trial → frames used from there, :func:`~.command.trial_frames`): each camera's shift per
    trial (each trial is its own gyro recording), one readout for all (the same cameras), pairs from
    :func:`trial_pairs`. Trial → its :class:`GyroTiming`.

    Raises:
        ValueError: naming the file when a trial has no gyro recording or a camera none; a trial where no camera
            turned enough.
    """
    recordings, indices, pairs, zero, groups = [], [], [], [], []
    for trial, trial_offsets in offsets.items():
        imu, index, found = trial_pairs(capture, trial, trial_offsets, spans[trial])
        recordings += [imu] * len(found)
        indices += list(index)
        pairs += found
        zero += list(np.asarray(trial_offsets).ravel())
        groups += [trial] * len(found)
    joint = estimate_gyro_timing(pairs, recordings, indices, zero, float(capture.fps), readout_s,
                                 estimate_readout=estimate_readout, groups=groups, log=log)
    out, at = {}, 0
    for trial in offsets:
        mine = slice(at, at + len(capture.cameras))
        out[trial] = GyroTiming(joint.time_shift_s[mine], joint.readout_s, joint.pairs[mine], joint.determined[mine],
                                joint.readout_estimated)
        at += len(capture.cameras)
    return out
