"""Registration of a whole trial: absolute registration, new points, relative registration rounds
(§4.1, issue 5 items 4–5).

:func:`register_capture` (a :class:`CaptureRegistrar`: its state, and a method per step) works on the frames
of all cameras of one trial at once:

1. SIFT features of every frame (:func:`extract_trial_features`);
2. **absolute registration** of each frame to the reference model (:func:`register_features`, as
   :func:`~bcmocap.frontend.register.register_frame`; frames in threads);
3. rounds, until a round registers nothing new (at most ``max_rounds``):

   a. **new points**: registered frames that may see the same scene (same time, the ``max_other_cameras``
      other cameras with the nearest optical axes; same camera, up to ``max_time_gap`` frames apart) are
      matched (FLANN, ratio test, mutual) — by default only pairs next to an unregistered frame, which
      relative registration will use (``new_points_everywhere`` matches all of them); a match of two
      features without a 3D point is triangulated (least squares over the two rays) and kept when both
      reprojection errors are below ``max_reprojection_error_px`` and the rays meet at
      ``min_triangulation_angle_deg`` or more; a match of a feature with a point to one without extends
      that point's track when it reprojects there within the same threshold;
   b. **bundle adjustment with the reference held fixed**, by block coordinate descent on the
      reprojection error: every new point is re-triangulated from all its observations (tracks whose
      error stays above the threshold lose the offending observations), then every pose that observes a
      new point is refined (``pycolmap.refine_absolute_pose``) on its reference and new points;
   c. **relative registration**: each unregistered frame is matched to the registered frames of the same
      time and of nearby times of its camera; features matched to features with a 3D point give 2D–3D
      correspondences, and the pose is estimated and accepted as in absolute registration (more than
      ``min_inliers`` inliers, mean inlier error below ``max_mean_error_px``).

Poses are ``world_from_camera`` ``wxyz_xyz`` in the reference model's frame; pixels are in OpenCV's
convention (COLMAP's +0.5 px is applied only at the pycolmap calls).
"""

from __future__ import annotations

import dataclasses
import json
import threading
import zipfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..cameras import CameraModel
from ..io.colmap import to_pycolmap
from ..native_crashes import load_pycolmap
from .features import read_camera_features, write_camera_features
from .poses import estimate_pose, nearest_point, world_from_camera_wxyz_xyz
from .reference import (
    DescriptorIndex,
    extract_sift,
    match_descriptors,
    uint8_descriptors,
)
from .register import ReferenceIndex, RegistrationOptions, match_to_reference
from .threads import default_threads, give_back_freed_memory

__all__ = ["CameraFrameRegistration", "RelativeOptions", "CaptureRegistration", "CaptureRegistrar",
           "RegistrationCheckpoint", "extract_trial_features", "register_features", "register_capture", "triangulate_rays"]


@dataclasses.dataclass(frozen=True)
class RelativeOptions:
    """Settings of :func:`register_capture`.

    Attributes:
        registration: thresholds of absolute and relative registration (same for both).
        max_time_gap: frames of one camera this far apart (in the frames processed) are matched.
        min_triangulation_angle_deg, max_reprojection_error_px: a new point must pass both.
        max_rounds: at most this many rounds of new points + relative registration.
        min_track_length: new points seen in fewer frames are not used to register frames.
        max_view_angle_deg: frames of other cameras are matched only when their optical axes are this
            close (for an unregistered frame: to the axis its camera had at the nearest registered time;
            all cameras when it has none).
        max_other_cameras: at most this many other registered cameras at the same time (most similar axes
            first; every registered one while the frame's camera has no registered frame yet).
        new_points_everywhere: triangulate new points between every pair of neighbouring registered
            frames. By default only pairs where one frame is a neighbour of an unregistered frame are
            matched: new points serve relative registration, and a trial that registers absolutely
            everywhere then costs no pair matching at all.
        second_order_pairs: a registered neighbour of an unregistered frame is matched with all its own
            registered neighbours (True), or only with the other neighbours of unregistered frames (False:
            the pairs whose new points an unregistered frame can see; far fewer pairs when many frames
            are left, as after tracking).
        enough_correspondences: relative registration stops matching a frame to more registered frames
            (most similar views first) once it has this many 2D–3D correspondences.
        workers: threads matching pairs of frames for new points (default: the CPU count).
        index_memory_mb: the FLANN indexes of frames kept for reuse (:class:`_IndexCache`) take at most about
            this much memory; past it the least recently used go and are built again when needed (the matches
            are the same). At 640×360 most of a trial's working set fits; at 1080p with 8000 features little would.
    """

    registration: RegistrationOptions = RegistrationOptions()
    max_time_gap: int = 3
    min_triangulation_angle_deg: float = 2.0
    max_reprojection_error_px: float = 1.0
    max_rounds: int = 10
    min_track_length: int = 2
    max_view_angle_deg: float = 90.0
    max_other_cameras: int = 4
    new_points_everywhere: bool = False
    second_order_pairs: bool = True
    enough_correspondences: int = 400
    workers: int | None = None
    index_memory_mb: float = 1536.0


@dataclasses.dataclass
class CameraFrameRegistration:
    """One frame of one camera as :func:`register_capture` holds it: its features, the 3D points they observe and
    its pose as registration goes (:class:`~.register.FrameRegistration` is one absolute registration's result).

    Attributes:
        keypoints: ``(N, 2)`` SIFT keypoint pixels (then, after tracking, tracked measurements without a
            descriptor); descriptors: ``(M ≤ N, 128)`` uint8 of the first ``M`` keypoints (a quarter of
            float32's memory; matching converts).
        point_ids: ``(N,)`` the 3D point each keypoint observes (−1: none).
        world_from_camera: ``(7,)`` wxyz_xyz, NaN while unregistered.
        how: "" (unregistered), "absolute", "tracked", "relocalised" (:mod:`~.tracking`) or "relative";
            round: the round that registered it (0 = before the rounds).
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    point_ids: np.ndarray
    world_from_camera: np.ndarray
    how: str = ""
    round: int = -1

    @property
    def registered(self) -> bool:
        return bool(self.how)


@dataclasses.dataclass
class CaptureRegistration:
    """Result of :func:`register_capture` for ``T`` frames of ``C`` cameras.

    Attributes:
        frames: ``(T,)`` frame numbers (per camera: ``frames + start offset`` of that camera).
        states: ``states[t][c]`` :class:`CameraFrameRegistration`.
        points: ``{point id: (3,) position}`` of the reference's and the new points.
        new_point_ids: ids of the points triangulated here.
        rounds: per round ``{"registered": frames registered, "new_points": points added}``.
        cameras: ``(C,)`` the ``pycolmap.Camera`` of each camera (for measurement selection).
        reference_point_ids: ids of the reference model's points (made from the reference photos, so their
            errors do not follow any body camera's pose).
    """

    frames: np.ndarray
    states: list
    points: dict
    new_point_ids: set
    rounds: list
    cameras: list | None = None
    reference_point_ids: frozenset = frozenset()

    @property
    def registered(self) -> np.ndarray:
        """``(T, C)`` bool."""
        return np.array([[s.registered for s in row] for row in self.states], bool).reshape(len(self.states), -1)

    @property
    def world_from_camera(self) -> np.ndarray:
        """``(T, C, 7)`` poses, NaN where unregistered."""
        return np.array([[s.world_from_camera for s in row] for row in self.states]).reshape(len(self.states), -1, 7)

    @property
    def registered_fraction(self) -> float:
        reg = self.registered
        return float(reg.mean()) if reg.size else 0.0

    def _selected(self, per: list, ids: np.ndarray, xyz: np.ndarray, limit: int) -> list:
        """``per[t][c]`` cut to at most ``limit`` keypoints each (:mod:`~.selection`)."""
        from .selection import measurement_score, select_measurements

        if self.cameras is None:
            raise ValueError("correspondences: max_per_frame needs the registration's cameras")
        observed = np.concatenate([s.point_ids[k] for row, krow in zip(self.states, per) for s, k in zip(row, krow)]
                                  + [np.zeros(0, np.int64)])
        seen, count = np.unique(observed, return_counts=True)
        geo = _Geometry(self.cameras)
        out = []
        for row, krow in zip(self.states, per):
            out_row = []
            for c, (s, k) in enumerate(zip(row, krow)):
                if len(k) > limit:
                    pid = s.point_ids[k]
                    uv = geo.reproject(c, s.world_from_camera, xyz[np.searchsorted(ids, pid)])
                    error = np.linalg.norm(uv - s.keypoints[k], axis=1)
                    score = measurement_score(count[np.searchsorted(seen, pid)], error)
                    cam = self.cameras[c]
                    k = k[select_measurements(s.keypoints[k], score, limit, cam.width, cam.height)]
                out_row.append(k)
            out.append(out_row)
        return out

    def correspondences(self, fps: float, *, pixel_sigma: float = 1.0, homographies=None,
                        max_per_frame: int | None = None, points: str = "all"):
        """What the solver consumes: a :class:`~bcmocap.correspondences.Correspondences` with every point
        (reference and new, renumbered ``0 … P−1``), per registered frame and camera the pixels of its
        keypoints that observe one (weight ``1 / pixel_sigma²``; with ``max_per_frame``, at most that many,
        chosen by :func:`~.selection.select_measurements`: spread over the image, long tracks and low
        reprojection error first), the poses and the registered mask, and the homography pairs of
        unregistered frames from ``homographies`` (a :class:`~bcmocap.frontend.homography.HomographyFill`;
        none without it; at most ``max_per_frame`` of them, spread over the image). Points and poses are in the reference model's frame.

        ``points`` "reference" keeps only the measurements of reference-model points: a point triangulated from
        a body camera's own frames (tracking, relative rounds) carries that camera's pose error, so its
        measurements pull the solver back to the registered pose instead of correcting it (on the rendered
        10 s walk with the tracking frontend: 1.54 cm / 0.35° instead of 1.90 cm / 0.55°)."""
        if points not in ("all", "reference"):
            raise ValueError(f"correspondences: points must be 'all' or 'reference', got {points!r}")
        from ..correspondences import Correspondences

        ids = np.array(sorted(self.points), np.int64)
        xyz = np.array([self.points[int(i)] for i in ids], np.float64).reshape(-1, 3)
        t_count, c_count = self.registered.shape
        reference = np.fromiter(self.reference_point_ids, np.int64)
        measured = (lambda ids: ids >= 0) if points == "all" else (lambda ids: np.isin(ids, reference))
        per = [[np.flatnonzero(measured(s.point_ids)) if s.registered else np.zeros(0, np.int64) for s in row]
               for row in self.states]
        if max_per_frame is not None:
            per = self._selected(per, ids, xyz, max_per_frame)
        n = max((len(k) for row in per for k in row), default=0)
        point_ids = np.full((t_count, c_count, n), -1, np.int32)
        pixels = np.zeros((t_count, c_count, n, 2))
        weights = np.zeros((t_count, c_count, n))
        for t, row in enumerate(self.states):
            for c, s in enumerate(row):
                k = per[t][c]
                point_ids[t, c, : len(k)] = np.searchsorted(ids, s.point_ids[k])
                pixels[t, c, : len(k)] = s.keypoints[k]
                weights[t, c, : len(k)] = 1.0 / pixel_sigma**2
        poses = self.world_from_camera.copy()
        poses[~self.registered] = np.array([1.0, 0, 0, 0, 0, 0, 0])
        pairs = {} if homographies is None else homographies.pixels
        keep = {key: np.arange(len(px)) for key, px in pairs.items()}
        if max_per_frame is not None:  # homography pairs spread over the image too (all score alike)
            from .selection import select_measurements

            keep = {(t, c): select_measurements(px, np.zeros(len(px)), max_per_frame, self.cameras[c].width,
                                                self.cameras[c].height) for (t, c), px in pairs.items()}
        m = max((len(v) for v in keep.values()), default=0)
        h_pixels = np.zeros((t_count, c_count, m, 2))
        h_prev = np.zeros((t_count, c_count, m, 2))
        h_weights = np.zeros((t_count, c_count, m))
        for (t, c), k in keep.items():
            h_pixels[t, c, : len(k)] = pairs[(t, c)][k]
            h_prev[t, c, : len(k)] = homographies.pixels_prev[(t, c)][k]
            h_weights[t, c, : len(k)] = 1.0 / pixel_sigma**2
        return Correspondences(xyz, point_ids, pixels, weights, h_pixels, h_prev, h_weights, poses, self.registered,
                               float(fps))


def extract_trial_features(capture, trial: str, *, stride: int = 1, starts=None, num_frames: int | None = None,
                           max_features: int = 8000, cache_dir=None, workers: int | None = None,
                           progress: Callable[[int, int], None] | None = None, map_tasks=None) -> list:
    """SIFT features of every ``stride``-th frame of every camera of a trial.

    Args:
        starts: ``(C,)`` first frame of each camera's video (e.g. the synchronisation offsets; default 0).
        num_frames: frames per camera to read from its start (default: as many as the shortest video has).
        cache_dir: if given, each camera's features are streamed to ``cache_dir/<camera>/``
            (:mod:`~bcmocap.frontend.features`) and returned memory-mapped, so a long capture never has to fit
            in memory; they are read back instead of recomputed when start, stride, frame count and
            ``max_features`` are the same. Without it they are kept in memory.
        workers: cameras processed at once (threads; default: the CPU count).
        map_tasks: ``map_tasks(fn, items, label=, on_done=)`` running independent calls elsewhere (a cluster);
            with ``cache_dir``, each camera's SIFT is one such call filling its cache folder, read back here.

    Returns:
        ``features[t][c] = (keypoints (N, 2), descriptors (N, 128) uint8)``.
    """
    import functools

    names = capture.camera_names
    starts = np.zeros(len(names), np.int64) if starts is None else np.asarray(starts, np.int64)
    if starts.shape != (len(names),):
        raise ValueError(f"extract_trial_features: starts must have shape ({len(names)},), got {starts.shape}")
    if num_frames is None:
        num_frames = min(capture.video_info(trial, n).num_frames - int(s) for n, s in zip(names, starts))
    per_video = max(0, -(-num_frames // stride))
    tick = ProgressCounter(len(names) * per_video, progress)
    one_camera = functools.partial(_camera_features, capture, trial, stride, num_frames, max_features, cache_dir)
    if map_tasks is not None and cache_dir is not None:
        map_tasks(functools.partial(_camera_features_task, one_camera), list(zip(names, starts.tolist())),
                  label=f"sift {trial}", on_done=lambda i, done: tick(done))
        tick = ProgressCounter(0, None)  # every camera is in its cache now: read back without counting again

    # OpenCV releases the GIL while decoding and in SIFT, so threads run the cameras in parallel.
    with ThreadPoolExecutor(max_workers=_workers(workers)) as pool:
        per_camera = list(pool.map(lambda name, start: one_camera(name, start, tick), names, starts.tolist()))
    count = min(len(f) for f in per_camera)
    return [[per_camera[c][t] for c in range(len(names))] for t in range(count)]


def _camera_features_task(one_camera, name_start: tuple[str, int]) -> int:
    """A task of :func:`extract_trial_features` on a cluster: one camera's SIFT into its cache; the frames."""
    return len(one_camera(*name_start, None))


def _camera_features(capture, trial: str, stride: int, num_frames: int, max_features: int, cache_dir,
                     name: str, start: int, tick) -> list:
    """One camera's features (:func:`extract_trial_features`), from its cache folder when it holds them;
    ``tick(n)`` (or None) counts processed frames."""
    from pathlib import Path

    count = tick or (lambda n: None)
    per_video = max(0, -(-num_frames // stride))

    def sift_frames():
        for _, gray in capture.frames(trial, name, stride=stride, start=int(start),
                                      stop=int(start) + num_frames, gray=True):
            kp, desc = extract_sift(gray, max_features=max_features)
            yield kp[:, :2].astype(np.float64), desc
            count(1)

    if cache_dir is None:
        feats = list(sift_frames())
    else:
        settings = {"start": int(start), "stride": int(stride), "num_frames": int(num_frames),
                    "max_features": int(max_features), **capture.correction_settings(trial)}
        folder = Path(cache_dir) / name
        feats = read_camera_features(folder, settings)
        if feats is not None:
            count(per_video)
            return feats
        write_camera_features(folder, settings, sift_frames())
        feats = read_camera_features(folder, settings)
        if feats is None:
            raise OSError(f"{folder}: features written but not readable")
    count(per_video - len(feats))
    return feats


class ProgressCounter:
    """Counts work done by several threads and reports ``progress(done, total)`` after each step."""

    def __init__(self, total: int, progress: Callable[[int, int], None] | None):
        self.total, self.progress, self.done = total, progress, 0
        self.lock = threading.Lock()

    def __call__(self, n: int) -> None:
        with self.lock:
            self.done += n
            if self.progress is not None:
                self.progress(self.done, self.total)


def _workers(workers: int | None) -> int:
    return max(1, int(workers) if workers is not None else default_threads())


def register_features(keypoints: np.ndarray, descriptors: np.ndarray, cam, index: ReferenceIndex,
                      options: RegistrationOptions = RegistrationOptions()):
    """Absolute registration of one frame's features (pycolmap camera ``cam``) to the reference index.

    Returns:
        ``(world_from_camera (7,), point_ids (N,))`` or None when the thresholds reject it.
    """
    if len(descriptors) < 2:
        return None
    query, rows = match_to_reference(descriptors, index, options.ratio, options.checks)
    found = estimate_pose(keypoints[query], index.xyz[rows], cam, options)
    if found is None:
        return None
    pose, inl, _ = found
    ids = np.full(len(keypoints), -1, np.int64)
    ids[query[inl]] = index.point3D_ids[rows[inl]]
    return world_from_camera_wxyz_xyz(pose), ids


def triangulate_rays(centres: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The point nearest (least squares) to ``K`` rays: ``centres (..., K, 3)``, unit ``directions (..., K, 3)``;
    NaN where the rays are parallel (e.g. a camera that did not move between two frames)."""
    proj = np.eye(3) - directions[..., :, None] * directions[..., None, :]  # (..., K, 3, 3)
    return nearest_point(proj.sum(-3), np.einsum("...kij,...kj->...i", proj, centres))


def pixel_rays(cam, pixels: np.ndarray) -> np.ndarray:
    """``(K, 3)`` unit rays in the camera frame of ``(K, 2)`` pixels (OpenCV convention) of a
    ``pycolmap.Camera`` (fields of view below 180°)."""
    xy = np.asarray(cam.cam_from_img(np.asarray(pixels, np.float64) + 0.5), np.float64).reshape(-1, 2)
    d = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


class _Geometry:
    """Per-frame pycolmap camera, rotation and centre, rays and reprojection."""

    def __init__(self, cams):
        self.cams = cams

    @staticmethod
    def rotation_centre(pose: np.ndarray):
        from ..geometry import matrix_from_quat

        return np.asarray(matrix_from_quat(pose[:4]), np.float64), pose[4:]

    def rays(self, c: int, pose: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        rot, _ = self.rotation_centre(pose)
        return pixel_rays(self.cams[c], pixels) @ rot.T

    def reproject(self, c: int, pose: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """``(K, 2)`` pixels of world points (NaN behind the camera)."""
        rot, centre = self.rotation_centre(pose)
        local = (np.asarray(xyz, np.float64).reshape(-1, 3) - centre) @ rot
        uv = np.asarray(self.cams[c].img_from_cam(local), np.float64).reshape(-1, 2) - 0.5
        uv[local[:, 2] <= 1e-9] = np.nan
        return uv


def _axis(pose: np.ndarray) -> np.ndarray:
    """World direction of a camera's optical axis (its z) from a wxyz_xyz pose."""
    w, x, y, z = pose[:4]
    return np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])


def _neighbours(t: int, c: int, num_frames: int, num_cameras: int, gap: int, states=None, max_angle_deg=180.0,
                max_others: int | None = None):
    """Frames that may see what frame ``(t, c)`` sees: other cameras at ``t``, then the same camera up to
    ``gap`` frames away.

    With ``states``, only registered other cameras are offered (an unregistered one has neither a pose nor
    points to lend), those whose axis is within ``max_angle_deg`` of this camera's nearest registered axis,
    at most ``max_others`` of them, most similar first. While this camera has no registered frame its axis
    is unknown, so every registered camera at ``t`` is offered: ranking them by index would leave a camera
    that never registers absolutely (the upper-arm cameras in the demo's range-of-motion trial) to whichever
    cameras come first.
    """
    axis = None
    if states is not None:
        near = sorted((abs(t2 - t), t2) for t2 in range(num_frames) if states[t2][c].registered)
        if near:
            axis = _axis(states[near[0][1]][c].world_from_camera)
    cos_max = np.cos(np.radians(max_angle_deg))
    others = []
    for c2 in range(num_cameras):
        if c2 == c or (states is not None and not states[t][c2].registered):
            continue
        cos = 1.0
        if axis is not None:
            cos = float(axis @ _axis(states[t][c2].world_from_camera))
            if cos < cos_max:
                continue
        others.append((-cos, c2))
    limit = max_others if states is None or axis is not None else None
    for _, c2 in sorted(others)[:limit]:  # most similar view first
        yield t, c2
    for dt in range(1, gap + 1):
        for t2 in (t - dt, t + dt):
            if 0 <= t2 < num_frames:
                yield t2, c


class RegistrationCheckpoint:
    """The progress of one :func:`register_capture` call, saved under ``folder`` as it goes, so a run killed
    during registration continues where it was instead of starting the trial again.

    - ``absolute_NNNNNN.npz``: the absolute registration of ``every`` camera-frames from the ``NNNNNN``-th
      (found or not, pose, the keypoints' point ids);
    - ``round_NN.npz``: the whole state after round ``NN`` (poses, how and round of every frame, point ids,
      points, tracks, the pairs already matched, the rounds' counts); the files it supersedes are removed.

    Every file is written atomically (:mod:`bcmocap.atomic`) and holds ``key`` (the caller's settings) and a
    digest of the call's inputs: a file of other settings or inputs is ignored. Resuming gives the same result
    as an uninterrupted call because registration is deterministic (seeded FLANN trees and RANSACs, results
    of threads used in order). The caller removes the folder once the result is saved.
    """

    def __init__(self, folder, key: dict, every: int = 64):
        from pathlib import Path

        self.folder, self.every = Path(folder), max(1, int(every))
        self.key = json.dumps(key, sort_keys=True)

    def _tag(self, digest: str) -> str:
        return json.dumps([self.key, digest])

    def _read(self, path, digest: str) -> dict | None:
        try:
            with np.load(path, allow_pickle=False) as data:
                if str(data["tag"]) != self._tag(digest):
                    return None
                return {k: data[k] for k in data.files}
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            return None  # damaged (it was written atomically, so not by a kill): redo that part

    def _write(self, name: str, digest: str, **arrays) -> None:
        from ..atomic import write_npz_atomic

        # not deflated: a round's state is megabytes, written after every round (deflating them took a
        # tenth of the frontend's time on the 10 s walk) and removed once the registration is saved
        write_npz_atomic(self.folder / name, {"tag": np.array(self._tag(digest)), **arrays}, compress=False)

    def absolute(self, digest: str, count: int) -> list:
        """The saved absolute registrations of the first camera-frames of the todo list, in order:
        ``[(pose (7,), keypoints (K,), their point ids (K,)) or None]`` (up to the first part missing)."""
        found: list = []
        while len(found) < count:
            part = self._read(self.folder / f"absolute_{len(found):06d}.npz", digest)
            if part is None:
                break
            cut = np.cumsum(part["counts"])[:-1]
            for ok, pose, kp, ids in zip(part["found"], part["poses"], np.split(part["keypoints"], cut),
                                         np.split(part["ids"], cut)):
                found.append((pose, kp, ids) if ok else None)
        return found[:count]

    def save_absolute(self, digest: str, start: int, results: list) -> None:
        ok = [r is not None for r in results]
        sparse = [(np.flatnonzero(r[1] >= 0), r[1][r[1] >= 0]) if r is not None else (np.zeros(0, np.int64),) * 2
                  for r in results]
        self._write(f"absolute_{start:06d}.npz", digest, found=np.array(ok, bool),
                    poses=np.array([r[0] if r is not None else np.full(7, np.nan) for r in results]).reshape(-1, 7),
                    counts=np.array([len(k) for k, _ in sparse], np.int64),
                    keypoints=np.concatenate([k for k, _ in sparse] + [np.zeros(0, np.int64)]).astype(np.int64),
                    ids=np.concatenate([i for _, i in sparse] + [np.zeros(0, np.int64)]).astype(np.int64))

    def last_round(self, digest: str) -> dict | None:
        """The state after the last round saved, or None."""
        for path in sorted(self.folder.glob("round_*.npz"), reverse=True):
            state = self._read(path, digest)
            if state is not None:
                return state
        return None

    def save_round(self, digest: str, round_no: int, **state) -> None:
        self._write(f"round_{round_no:02d}.npz", digest, **state)
        for path in self.folder.glob("*.npz"):  # superseded: earlier rounds and the absolute parts
            if path.name != f"round_{round_no:02d}.npz":
                path.unlink(missing_ok=True)


def _inputs_digest(states: list, initial: list | None, initial_points: dict | None, leave, frames) -> str:
    """A digest of what :func:`register_capture` starts from (keypoints, initial registration, frames left)."""
    import hashlib

    h = hashlib.sha256()
    for row in states:
        for s in row:
            h.update(np.ascontiguousarray(s.keypoints).tobytes())
            h.update(np.int64(len(s.descriptors)).tobytes())
            if initial is not None:
                h.update(s.how.encode() + b"|" + np.ascontiguousarray(s.world_from_camera).tobytes()
                         + np.ascontiguousarray(s.point_ids).tobytes())
    for i in sorted(initial_points or {}):
        h.update(np.int64(i).tobytes() + np.asarray(initial_points[i], np.float64).tobytes())
    h.update(np.ascontiguousarray(leave).tobytes() + np.asarray(frames, np.int64).tobytes())
    return h.hexdigest()[:32]


def register_capture(features: list, cameras, index: ReferenceIndex, options: RelativeOptions = RelativeOptions(),
                     *, frames: np.ndarray | None = None, initial: list | None = None, initial_points: dict | None = None,
                     leave: np.ndarray | None = None, checkpoint: RegistrationCheckpoint | None = None,
                     progress: Callable[[str, int, int], None] | None = None) -> CaptureRegistration:
    """Register every frame of a trial (module docstring): absolute, then rounds of new points and relative
    registration (a :class:`CaptureRegistrar` run once).

    Args:
        features: ``features[t][c] = (keypoints (N, 2), descriptors (N, 128))`` (:func:`extract_trial_features`).
        cameras: ``(C,)`` intrinsics (:class:`~bcmocap.cameras.CameraModel` or ``pycolmap.Camera``).
        index: the reference model's :func:`~bcmocap.frontend.register.reference_index`.
        frames: ``(T,)`` frame numbers to report (default ``0 … T−1``).
        initial: ``initial[t][c] = (world_from_camera (7,), point_ids (N,), how)``, the registration of
            each frame so far (e.g. :func:`~.tracking.tracking_states`; ``how`` "" where unregistered):
            absolute registration is then skipped and the rounds start from it.
        initial_points: ``{id: (3,) position}`` of points ``initial`` observes besides the reference's.
        leave: ``(T, C)`` bool, unregistered frames the rounds neither register nor match around (filled
            afterwards by other means, e.g. :func:`~.tracking.track_after_rounds`).
        checkpoint: a :class:`RegistrationCheckpoint`: progress is saved there as it is made and a call with
            the same inputs continues from it (the result is the same as without it).
        progress: called as ``progress(stage, done, total)``.
    """
    result = CaptureRegistrar(features, cameras, index, options, frames=frames, initial=initial,
                              initial_points=initial_points, leave=leave, checkpoint=checkpoint,
                              progress=progress).run()
    give_back_freed_memory()  # its indexes and matches, so that the next chunk starts from what is live
    return result


class CaptureRegistrar:
    """One :func:`register_capture` call: its state, explicit, and its phases, one method each.

    :meth:`run` runs them in order: :meth:`register_absolute`, :meth:`start_rounds`, then rounds
    (:meth:`run_round`: :meth:`add_points`, :meth:`adjust`, :meth:`register_relative`) until one registers
    nothing new or ``max_rounds`` ran. The phases update the state in place; an instance is run once.

    Attributes:
        num_t, num_c: frames ``T`` and cameras ``C``.
        cams: ``(C,)`` ``pycolmap.Camera``; geo: their :class:`_Geometry`.
        options: the :class:`RelativeOptions`; reg: its ``registration`` thresholds; index: the reference index.
        states: ``states[t][c]`` :class:`CameraFrameRegistration` (poses ``world_from_camera`` wxyz_xyz in the reference
            model's frame, keypoints' point ids).
        points: ``{point id: (3,) position}`` of the reference's and the new points (its order orders later work).
        next_id: the id the next new point gets; new_ids: ids of the points triangulated here.
        tracks: ``{new point id: [(t, c, keypoint)]}``, the observations of each new point.
        leave: ``(T, C)`` bool, unregistered frames the rounds neither register nor match around.
        frames: ``(T,)`` frame numbers to report.
        checkpoint: the :class:`RegistrationCheckpoint` or None; digest: the inputs' digest there ("" without);
            resumed: the state after the last round it saved, or None.
        has_initial: an initial registration was given (absolute registration is skipped).
        matched: frame pairs ``(a, b)``, ``a < b``, already matched for new points.
        pair_matches: ``{(a, b) with a < b: (K, 2) int32}`` mutual matches of whole frames (symmetric; rounds
            reuse them).
        point_matches: ``{(a, b): (rows of b searched (M_b,) bool, their matches (K, 2) int64)}``
            (:meth:`match_to_points`).
        indexes: the frames' FLANN indexes (:class:`_IndexCache`).
        rounds: per round ``{"registered": frames registered, "new_points": points added}`` (round 0: before
            the rounds).
        progress: ``progress(stage, done, total)`` or None.
    """

    def __init__(self, features: list, cameras, index: ReferenceIndex, options: RelativeOptions = RelativeOptions(),
                 *, frames: np.ndarray | None = None, initial: list | None = None,
                 initial_points: dict | None = None, leave: np.ndarray | None = None,
                 checkpoint: RegistrationCheckpoint | None = None,
                 progress: Callable[[str, int, int], None] | None = None):
        """Check the inputs (those of :func:`register_capture`) and set the state up; registers nothing."""
        self.num_t = num_t = len(features)
        self.num_c = num_c = len(cameras)
        if num_t and len(features[0]) != num_c:
            raise ValueError(f"register_capture: features hold {len(features[0])} cameras per frame, cameras {num_c}")
        self.cams = [to_pycolmap(c) if isinstance(c, CameraModel) else c for c in cameras]
        self.geo = _Geometry(self.cams)
        self.options, self.reg, self.index = options, options.registration, index
        self.states = self._frame_states(features, initial, num_c)
        self.points = {int(i): np.asarray(x, np.float64) for i, x in zip(index.point3D_ids, index.xyz)}
        self.points.update({int(i): np.asarray(x, np.float64) for i, x in (initial_points or {}).items()})
        self.next_id = max(self.points, default=-1) + 1
        self.new_ids: set[int] = set()
        self.tracks: dict[int, list[tuple[int, int, int]]] = {}  # new point -> [(t, c, keypoint)]
        leave = np.zeros((num_t, num_c), bool) if leave is None else np.asarray(leave, bool)
        if leave.shape != (num_t, num_c):
            raise ValueError(f"register_capture: leave has shape {leave.shape}, expected {(num_t, num_c)}")
        self.leave = leave
        self.frames = np.arange(num_t) if frames is None else np.asarray(frames)
        self.checkpoint, self.progress = checkpoint, progress
        self.digest = _inputs_digest(self.states, initial, initial_points, leave, self.frames) \
            if checkpoint is not None else ""
        self.resumed = checkpoint.last_round(self.digest) if checkpoint is not None else None
        self.has_initial = initial is not None
        self.matched: set = set()
        self.pair_matches: dict = {}  # (a, b) with a < b -> (K, 2) int32; mutual matching is symmetric, rounds reuse it
        self.point_matches: dict = {}  # (a, b) -> (rows of b searched (M_b,) bool, their matches (K, 2) int64)
        self.indexes = _IndexCache(self.states, self.reg.checks, (2 * options.max_time_gap + 2) * num_c,
                                   memory_bytes=options.index_memory_mb * 1e6)
        self.rounds: list = []

    @staticmethod
    def _frame_states(features: list, initial: list | None, num_c: int) -> list:
        """``states[t][c]`` of the features, unregistered, or registered where ``initial`` says so."""
        num_t = len(features)
        states = [[CameraFrameRegistration(np.asarray(kp, np.float64).reshape(-1, 2),
                                           uint8_descriptors(d),
                                           np.full(len(kp), -1, np.int64), np.full(7, np.nan)) for kp, d in row]
                  for row in features]
        if initial is not None:
            if len(initial) != num_t or any(len(row) != num_c for row in initial):
                raise ValueError(f"register_capture: initial must hold {num_t} frames of {num_c} cameras")
            for row, init_row in zip(states, initial):
                for s, (pose, point_ids, how) in zip(row, init_row):
                    if len(point_ids) != len(s.keypoints):
                        raise ValueError(f"register_capture: initial point ids ({len(point_ids)}) and keypoints "
                                         f"({len(s.keypoints)}) differ")
                    if how:
                        s.world_from_camera, s.point_ids, s.how, s.round = np.asarray(pose, np.float64), \
                            np.asarray(point_ids, np.int64).copy(), how, 0
        return states

    def run(self) -> CaptureRegistration:
        """Every phase in order (the class docstring); returns the result."""
        self.register_absolute()
        first_round = self.start_rounds()
        finished = self.resumed is not None and (self.rounds[-1]["registered"] == 0
                                                 or first_round > self.options.max_rounds)
        for round_no in range(first_round, self.options.max_rounds + 1):
            if finished:
                break
            if self.run_round(round_no) == 0:
                break
        return self.result()

    # ---- absolute registration ----------------------------------------------------------------------------

    def register_absolute(self) -> None:
        """Absolute registration of every frame to the reference, frames in threads (FLANN searches release
        the GIL), their results applied in frame order; the parts the checkpoint saved are read back instead,
        and the parts done are saved there. Skipped with an initial registration or a saved round."""
        checkpoint, progress = self.checkpoint, self.progress
        todo = [(t, c) for t in range(self.num_t) for c in range(self.num_c)] \
            if not self.has_initial and self.resumed is None else []
        saved = []
        if checkpoint is not None and todo:
            for tc, found in zip(todo, checkpoint.absolute(self.digest, len(todo))):
                if found is not None:
                    ids = np.full(len(self.states[tc[0]][tc[1]].keypoints), -1, np.int64)
                    ids[found[1]] = found[2]
                    found = (np.asarray(found[0], np.float64), ids)
                self._keep_absolute(tc, found)
                saved.append(tc)
        with ThreadPoolExecutor(max_workers=_workers(self.options.workers)) as pool:
            rest, batch = todo[len(saved):], []
            for k, (tc, found) in enumerate(zip(rest, pool.map(self._absolute_pose, rest)), start=len(saved)):
                self._keep_absolute(tc, found)
                batch.append(found)
                if checkpoint is not None and (len(batch) == checkpoint.every or k + 1 == len(todo)):
                    checkpoint.save_absolute(self.digest, k + 1 - len(batch), batch)
                    batch = []
                if progress is not None:
                    progress("absolute", k + 1, len(todo))

    def _absolute_pose(self, tc: tuple):
        """:func:`register_features` of frame ``tc = (t, c)`` (reads states only; called from threads)."""
        s = self.states[tc[0]][tc[1]]
        return register_features(s.keypoints, s.descriptors, self.cams[tc[1]], self.index, self.reg)

    def _keep_absolute(self, tc: tuple, found) -> None:
        """Apply an absolute registration ``(world_from_camera (7,), point_ids (N,))`` (None: not found)."""
        s = self.states[tc[0]][tc[1]]
        if found is not None:
            s.world_from_camera, s.point_ids = found
            s.how, s.round = "absolute", 0

    def start_rounds(self) -> int:
        """Round 0's count (the frames registered so far), or, when resuming, the state after the last round
        the checkpoint saved put back; returns the first round to run."""
        self.rounds = [{"registered": int(sum(s.registered for row in self.states for s in row)), "new_points": 0}]
        if self.resumed is None:
            return 1
        self.next_id, first_round, self.rounds = _restore_round(self.resumed, self.states, self.points, self.new_ids,
                                                                self.tracks, self.matched)
        return first_round

    # ---- a round ------------------------------------------------------------------------------------------

    def run_round(self, round_no: int) -> int:
        """New points, bundle adjustment, relative registration; the state saved in the checkpoint after it.
        Returns the frames it registered."""
        added = self.add_points(round_no)
        self.adjust()
        count = self.register_relative(round_no)
        self.rounds.append({"registered": count, "new_points": added})
        if self.checkpoint is not None:
            self.checkpoint.save_round(self.digest, round_no, **_round_state(self.states, self.points, self.new_ids,
                                                                             self.tracks, self.matched, self.next_id,
                                                                             self.rounds))
        return count

    def match(self, a: tuple, b: tuple) -> np.ndarray:
        """``(K, 2)`` int64 mutual matches (keypoint of ``a``, keypoint of ``b``) of frames ``a = (t, c)`` and
        ``b``, matched once per pair (:attr:`pair_matches`)."""
        reg, states = self.reg, self.states
        key = (min(a, b), max(a, b))
        m = self.pair_matches.get(key)
        if m is None:
            sa, sb = states[key[0][0]][key[0][1]], states[key[1][0]][key[1][1]]
            m = self.pair_matches[key] = match_descriptors(sa.descriptors, sb.descriptors, ratio=reg.ratio,
                                                           checks=reg.checks, index_a=self.indexes(key[0]),
                                                           index_b=self.indexes(key[1])).astype(np.int32)
        return (m if key[0] == a else m[:, ::-1]).astype(np.int64)

    def match_to_points(self, a: tuple, b: tuple) -> np.ndarray:
        """The rows of ``match(a, b)`` whose keypoint of ``b`` observes a 3D point now, in the same order (what
        relative registration of ``a`` uses; the order decides RANSAC's samples). Unless the pair is matched
        already, they are found from those keypoints alone: the matches of a set of rows are those of the whole
        matching on them, so each round searches only the keypoints that gained a point since the last (none,
        mostly). Called from threads, each pair by one of them."""
        reg, states = self.reg, self.states
        sb = states[b[0]][b[1]]
        if (min(a, b), max(a, b)) in self.pair_matches:
            m = self.match(a, b)
            return m[sb.point_ids[m[:, 1]] >= 0]
        has = sb.point_ids[: len(sb.descriptors)] >= 0
        done, m = self.point_matches.get((a, b), (np.zeros(len(has), bool), np.zeros((0, 2), np.int64)))
        rows = np.flatnonzero(has & ~done)
        if len(rows):
            sa = states[a[0]][a[1]]
            more = match_descriptors(sa.descriptors, sb.descriptors, ratio=reg.ratio, checks=reg.checks,
                                     index_a=self.indexes(a), index_b=self.indexes(b), rows_b=rows).astype(np.int64)
            m = np.concatenate([m, more])  # in the order of match(a, b): by the keypoints of the earlier frame
            m = m[np.argsort(m[:, 0 if a < b else 1], kind="stable")]
            self.point_matches[(a, b)] = (done | has, m)
        return m[sb.point_ids[m[:, 1]] >= 0]

    def neighbours(self, t: int, c: int):
        """The frames :func:`_neighbours` offers frame ``(t, c)`` now (registered other cameras by view)."""
        o = self.options
        return _neighbours(t, c, self.num_t, self.num_c, o.max_time_gap, self.states, o.max_view_angle_deg,
                           o.max_other_cameras)

    # ---- new points ---------------------------------------------------------------------------------------

    def add_points(self, round_no: int) -> int:
        """New points: the pairs of registered frames not matched yet (:meth:`pairs_for_new_points`) are matched
        (in threads, their matches used in order) to extend tracks and triangulate new points. Returns the
        points added."""
        pairs = self.pairs_for_new_points()
        added = 0
        # FLANN releases the GIL: pairs are matched in threads while their matches are used in order.
        pool = ThreadPoolExecutor(max_workers=_workers(self.options.workers))
        try:
            for k, ((a, b), m) in enumerate(zip(pairs, pool.map(lambda ab: self.match(*ab), pairs))):
                if self.progress is not None:
                    self.progress(f"new points round {round_no}", k + 1, len(pairs))
                self.matched.add((a, b))
                if not len(m):
                    continue
                self._extend_tracks(a, b, m)
                added += self._triangulate_new_points(a, b, m)
        finally:
            pool.shutdown(cancel_futures=True)
        return added

    def pairs_for_new_points(self) -> list:
        """Sorted pairs ``(a, b)``, ``a < b``, of registered neighbouring frames not matched yet: around every
        frame with ``new_points_everywhere``, else around the registered frames that relative registration
        of some unregistered frame (not left) will match."""
        o, states, num_t, num_c = self.options, self.states, self.num_t, self.num_c
        if o.new_points_everywhere:
            near = {(t, c) for t in range(num_t) for c in range(num_c)}
        else:  # registered frames that relative registration of some unregistered frame will match
            near = {n for t in range(num_t) for c in range(num_c)
                    if not states[t][c].registered and not self.leave[t, c] for n in self.neighbours(t, c)}
        found = set()
        for a in near:
            if states[a[0]][a[1]].registered:
                for n in self.neighbours(*a):
                    if states[n[0]][n[1]].registered and (o.second_order_pairs or n in near):
                        pair = (min(a, n), max(a, n))
                        if pair not in self.matched:
                            found.add(pair)
        return sorted(found)

    def _extend_tracks(self, a: tuple, b: tuple, m: np.ndarray) -> None:
        """Track extension: a match ``m`` (K, 2) of a keypoint with a point to one without gives it that point
        when the point reprojects there within ``max_reprojection_error_px``."""
        sa, sb = self.states[a[0]][a[1]], self.states[b[0]][b[1]]
        pa, pb = sa.point_ids[m[:, 0]], sb.point_ids[m[:, 1]]
        # Track extension: one side has a point, the other none.
        for src, dst, i_src, i_dst, s_dst, cd in ((pa, pb, m[:, 0], m[:, 1], sb, b[1]),
                                                   (pb, pa, m[:, 1], m[:, 0], sa, a[1])):
            sel = (src >= 0) & (dst < 0)
            if sel.any():
                xyz = np.array([self.points[int(p)] for p in src[sel]])
                err = np.linalg.norm(self.geo.reproject(cd, s_dst.world_from_camera, xyz) - s_dst.keypoints[i_dst[sel]],
                                     axis=1)
                ok = err < self.options.max_reprojection_error_px
                for p, i in zip(src[sel][ok], i_dst[sel][ok]):
                    if s_dst.point_ids[i] < 0:
                        s_dst.point_ids[i] = p
                        if int(p) in self.tracks:
                            self.tracks[int(p)].append((*(b if s_dst is sb else a), int(i)))

    def _triangulate_new_points(self, a: tuple, b: tuple, m: np.ndarray) -> int:
        """New points: matches ``m`` (K, 2) of two keypoints without a point are triangulated (two rays) and kept
        when both reproject within ``max_reprojection_error_px`` and the rays meet at
        ``min_triangulation_angle_deg`` or more. Returns the points added."""
        o, geo = self.options, self.geo
        sa, sb = self.states[a[0]][a[1]], self.states[b[0]][b[1]]
        # New points: neither side has one.
        sel = (sa.point_ids[m[:, 0]] < 0) & (sb.point_ids[m[:, 1]] < 0)
        if not sel.any():
            return 0
        ia, ib = m[sel, 0], m[sel, 1]
        ra = geo.rays(a[1], sa.world_from_camera, sa.keypoints[ia])
        rb = geo.rays(b[1], sb.world_from_camera, sb.keypoints[ib])
        ca, cb = sa.world_from_camera[4:], sb.world_from_camera[4:]
        centres = np.stack([np.broadcast_to(ca, ra.shape), np.broadcast_to(cb, rb.shape)], 1)
        xyz = triangulate_rays(centres, np.stack([ra, rb], 1))
        angle = np.degrees(np.arccos(np.clip(np.sum(ra * rb, 1), -1, 1)))
        ea = np.linalg.norm(geo.reproject(a[1], sa.world_from_camera, xyz) - sa.keypoints[ia], axis=1)
        eb = np.linalg.norm(geo.reproject(b[1], sb.world_from_camera, xyz) - sb.keypoints[ib], axis=1)
        ok = (angle >= o.min_triangulation_angle_deg) & (ea < o.max_reprojection_error_px) \
            & (eb < o.max_reprojection_error_px)
        added = 0
        for x, i, j in zip(xyz[ok], ia[ok], ib[ok]):
            self.points[self.next_id] = x
            self.new_ids.add(self.next_id)
            self.tracks[self.next_id] = [(a[0], a[1], int(i)), (b[0], b[1], int(j))]
            sa.point_ids[i] = sb.point_ids[j] = self.next_id
            self.next_id += 1
            added += 1
        return added

    # ---- bundle adjustment with the reference fixed -------------------------------------------------------

    def adjust(self) -> None:
        """Block coordinate descent on the reprojection error, reference points fixed: new points
        re-triangulated (:meth:`retriangulate`), then the poses of the frames that observe new points refined
        (:meth:`refine_poses`)."""
        if not self.tracks:
            return
        self.refine_poses(self.retriangulate())

    def retriangulate(self) -> list:
        """Every new point re-triangulated from all its observations (least squares over their rays); the
        observations reprojecting ``max_reprojection_error_px`` or more away are dropped, and the points left
        with fewer than two. Returns the frames ``(t, c)`` observing new points (whose points moved), in
        order."""
        states, tracks, points, geo, num_c = self.states, self.tracks, self.points, self.geo, self.num_c
        ids = np.array(list(tracks), np.int64)
        count = np.array([len(tracks[int(p)]) for p in ids])
        owner = np.repeat(np.arange(len(ids)), count)
        obs = np.array([o for p in ids for o in tracks[int(p)]], np.int64).reshape(-1, 3)
        frame_key = obs[:, 0] * num_c + obs[:, 1]
        order = np.argsort(frame_key, kind="stable")
        keys, starts = np.unique(frame_key[order], return_index=True)
        groups = [(divmod(int(k), num_c), g) for k, g in zip(keys, np.split(order, starts[1:]))]
        rays = np.zeros((len(obs), 3))
        centres = np.zeros((len(obs), 3))
        for (t, c), sel in groups:
            pose = states[t][c].world_from_camera
            rays[sel] = geo.rays(c, pose, states[t][c].keypoints[obs[sel, 2]])
            centres[sel] = pose[4:]
        proj = np.eye(3) - rays[:, :, None] * rays[:, None, :]
        a_sum = np.zeros((len(ids), 3, 3))
        b_sum = np.zeros((len(ids), 3))
        np.add.at(a_sum, owner, proj)
        np.add.at(b_sum, owner, np.einsum("kij,kj->ki", proj, centres))
        xyz = nearest_point(a_sum, b_sum)  # NaN for parallel rays: the point is dropped below
        err = np.full(len(obs), np.inf)
        for (t, c), sel in groups:
            uv = geo.reproject(c, states[t][c].world_from_camera, xyz[owner[sel]])
            err[sel] = np.linalg.norm(uv - states[t][c].keypoints[obs[sel, 2]], axis=1)
        keep = err < self.options.max_reprojection_error_px  # NaN (behind the camera, no point) is dropped too
        kept = np.bincount(owner[keep], minlength=len(ids))
        drop = ~keep | (kept[owner] < 2)
        for (t, c), sel in groups:
            states[t][c].point_ids[obs[sel[drop[sel]], 2]] = -1
        rows = np.split(np.arange(len(obs)), np.cumsum(count)[:-1])  # obs are grouped by owner
        for k, pid in enumerate(ids.tolist()):
            if kept[k] < 2:
                del tracks[pid], points[pid]
                self.new_ids.discard(pid)
            else:
                if kept[k] < count[k]:  # some observations dropped (a whole track stays as it is)
                    tracks[pid] = [tuple(o) for o in obs[rows[k][keep[rows[k]]]].tolist()]
                points[pid] = xyz[k]
        return [tc for tc, _ in groups]  # only these frames' points moved

    def refine_poses(self, frames_moved: list) -> None:
        """The pose of each registered frame of ``frames_moved`` with 4 points or more refined on its reference
        and new points (``pycolmap.refine_absolute_pose``; frames in threads, results applied in order)."""
        points = self.points
        point_ids = np.fromiter(points, np.int64, len(points))
        by_id = np.argsort(point_ids)
        point_ids, point_xyz = point_ids[by_id], np.array(list(points.values()), np.float64).reshape(-1, 3)[by_id]
        with ThreadPoolExecutor(max_workers=_workers(self.options.workers)) as pool:
            for (t, c), out in zip(frames_moved,
                                   pool.map(lambda tc: self._refined_pose(tc, point_ids, point_xyz), frames_moved)):
                if out is not None:
                    self.states[t][c].world_from_camera = world_from_camera_wxyz_xyz(out["cam_from_world"])

    def _refined_pose(self, tc: tuple, point_ids: np.ndarray, point_xyz: np.ndarray):
        """The frame's pose refined on its points (``point_ids`` sorted, ``point_xyz`` their positions); the
        ``pycolmap.refine_absolute_pose`` output or None. Reads only (pycolmap releases the GIL)."""
        pycolmap = load_pycolmap()

        t, c = tc
        s = self.states[t][c]
        has = np.flatnonzero(s.point_ids >= 0)
        if not s.registered or len(has) < 4:
            return None
        xyz_frame = point_xyz[np.searchsorted(point_ids, s.point_ids[has])]
        rot, centre = self.geo.rotation_centre(s.world_from_camera)
        cfw = pycolmap.Rigid3d(pycolmap.Rotation3d(rot.T), -rot.T @ centre)
        return pycolmap.refine_absolute_pose(cfw, s.keypoints[has] + 0.5, xyz_frame, np.ones(len(has), bool),
                                             self.cams[c])

    # ---- relative registration ----------------------------------------------------------------------------

    def register_relative(self, round_no: int) -> int:
        """Every frame unregistered (and not left) at the start of the round is tried against the frames
        registered then (in threads; the results are applied afterwards in frame order, so they do not depend
        on timing). Returns the frames registered."""
        states, tracks, progress = self.states, self.tracks, self.progress
        todo = [(t, c) for t in range(self.num_t) for c in range(self.num_c)
                if not states[t][c].registered and not self.leave[t, c]]
        with ThreadPoolExecutor(max_workers=_workers(self.options.workers)) as pool:
            found = []
            for k, result in enumerate(pool.map(lambda tc: self.relative_pose(*tc), todo)):
                found.append(result)
                if progress is not None:
                    progress(f"relative round {round_no}", k + 1, len(todo))
        count = 0
        for (t, c), result in zip(todo, found):
            if result is None:
                continue
            pose, kp_idx, pid = result
            s = states[t][c]
            s.world_from_camera = pose
            s.point_ids[kp_idx] = pid
            for i, p in zip(kp_idx, pid):
                if int(p) in tracks:
                    tracks[int(p)].append((t, c, int(i)))
            s.how, s.round = "relative", round_no
            count += 1
        return count

    def relative_pose(self, t: int, c: int):
        """Match frame ``(t, c)`` to its registered neighbours and estimate its pose (reads states only).

        Returns:
            ``(world_from_camera (7,), keypoint indices (K,), their point ids (K,))`` of the inliers, or None.
        """
        o, states, tracks = self.options, self.states, self.tracks
        s = states[t][c]
        xy, pid, kp_idx = [], [], []
        for n in self.neighbours(t, c):
            sn = states[n[0]][n[1]]
            if not sn.registered:
                continue
            m = self.match_to_points((t, c), n)
            if not len(m):
                continue
            p = sn.point_ids[m[:, 1]]
            sel = p >= 0
            if o.min_track_length > 2:
                sel &= np.array([int(q) not in tracks or len(tracks[int(q)]) >= o.min_track_length for q in p])
            xy.append(s.keypoints[m[sel, 0]])
            pid.append(p[sel])
            kp_idx.append(m[sel, 0])
            if sum(len(q) for q in pid) >= o.enough_correspondences:
                break
        if not xy:
            return None
        xy, pid, kp_idx = np.concatenate(xy), np.concatenate(pid), np.concatenate(kp_idx)
        _, first = np.unique(pid, return_index=True)
        xy, pid, kp_idx = xy[first], pid[first], kp_idx[first]
        _, first = np.unique(kp_idx, return_index=True)
        xy, pid, kp_idx = xy[first], pid[first], kp_idx[first]
        found = estimate_pose(xy, np.array([self.points[int(p)] for p in pid]).reshape(-1, 3), self.cams[c], self.reg)
        if found is None:
            return None
        pose, inl, _ = found
        return world_from_camera_wxyz_xyz(pose), kp_idx[inl], pid[inl]

    def result(self) -> CaptureRegistration:
        """The registration as it stands."""
        return CaptureRegistration(self.frames, self.states, self.points, self.new_ids, self.rounds, self.cams,
                                   frozenset(int(i) for i in self.index.point3D_ids))


class _IndexCache:
    """The FLANN index (:class:`~.reference.DescriptorIndex`) of each frame's descriptors, built once and shared
    by every pair the frame is matched in (a frame is in about ten pairs per round), for the frames used last:
    at most ``size`` of them and about ``memory_bytes`` (pairs are matched in time order, so a few times' frames
    are in use at once). Each index holds its descriptors as float32 (0.5 kB per feature) and, per thread that
    searched it, OpenCV's copy of them with its k-d trees (about 1.6 times as much, measured): an index counts
    ``(1 + 1.6 · copies)`` × its float32 size. Thread-safe. The trees are seeded (:data:`~.reference.FLANN_SEED`),
    so the matches are those of indexes built per pair, whatever was dropped."""

    #: OpenCV's copy of the descriptors and 4 k-d trees per thread, as a multiple of the float32 descriptors.
    TREES_PER_THREAD = 1.6

    def __init__(self, states: list, checks: int, size: int, *, memory_bytes: float = float("inf")):
        from collections import OrderedDict

        self.states, self.checks, self.size = states, int(checks), max(2, int(size))
        self.memory_bytes = float(memory_bytes)
        self.cache: OrderedDict = OrderedDict()
        self.lock = threading.Lock()

    @property
    def held(self) -> float:
        """The estimated bytes of the indexes in the cache."""
        return sum(i.descriptors.nbytes * (1.0 + self.TREES_PER_THREAD * i.copies) for i in list(self.cache.values()))

    def __call__(self, tc: tuple) -> DescriptorIndex:
        with self.lock:
            found = self.cache.get(tc)
            if found is None:
                found = self.cache[tc] = DescriptorIndex(self.states[tc[0]][tc[1]].descriptors, checks=self.checks)
                while len(self.cache) > 2 and (len(self.cache) > self.size or self.held > self.memory_bytes):
                    self.cache.popitem(last=False)
            else:
                self.cache.move_to_end(tc)
            return found


def _round_state(states, points: dict, new_ids: set, tracks: dict, matched: set, next_id: int, rounds: list) -> dict:
    """Arrays of :func:`register_capture`'s state after a round (dict orders kept: they order later work)."""
    flat = [s for row in states for s in row]
    has = [np.flatnonzero(s.point_ids >= 0) for s in flat]
    track_ids = np.fromiter(tracks, np.int64, len(tracks))
    return {"poses": np.array([s.world_from_camera for s in flat]).reshape(-1, 7),
            "how": np.array([s.how for s in flat], dtype="U16"), "round": np.array([s.round for s in flat], np.int64),
            "counts": np.array([len(h) for h in has], np.int64),
            "keypoints": np.concatenate(has + [np.zeros(0, np.int64)]).astype(np.int64),
            "ids": np.concatenate([s.point_ids[h] for s, h in zip(flat, has)] + [np.zeros(0, np.int64)]),
            "point_ids": np.fromiter(points, np.int64, len(points)),
            "point_xyz": np.array(list(points.values()), np.float64).reshape(-1, 3),
            "new_ids": np.array(sorted(new_ids), np.int64), "track_ids": track_ids,
            "track_counts": np.array([len(tracks[int(p)]) for p in track_ids], np.int64),
            "track_obs": np.array([o for p in track_ids for o in tracks[int(p)]], np.int64).reshape(-1, 3),
            "matched": np.array([[*a, *b] for a, b in sorted(matched)], np.int64).reshape(-1, 4),
            "next_id": np.int64(next_id), "rounds": np.array(json.dumps(rounds))}


def _restore_round(state: dict, states, points: dict, new_ids: set, tracks: dict, matched: set) -> tuple:
    """Put a :func:`_round_state` back (in place); returns ``(next_id, next round, rounds)``."""
    flat = [s for row in states for s in row]
    cut = np.cumsum(state["counts"])[:-1]
    for s, pose, how, rnd, kp, ids in zip(flat, state["poses"], state["how"], state["round"],
                                          np.split(state["keypoints"], cut), np.split(state["ids"], cut)):
        s.world_from_camera, s.how, s.round = np.array(pose, np.float64), str(how), int(rnd)
        s.point_ids = np.full(len(s.keypoints), -1, np.int64)
        s.point_ids[kp] = ids
    points.clear()
    points.update({int(i): x for i, x in zip(state["point_ids"].tolist(), np.array(state["point_xyz"], np.float64))})
    new_ids.clear()
    new_ids.update(state["new_ids"].tolist())
    tracks.clear()
    cut = np.cumsum(state["track_counts"])[:-1]
    tracks.update({int(p): [tuple(o) for o in obs.tolist()]
                   for p, obs in zip(state["track_ids"].tolist(), np.split(state["track_obs"], cut))})
    matched.clear()
    matched.update(((a, b), (c, d)) for a, b, c, d in state["matched"].tolist())
    rounds = json.loads(str(state["rounds"]))
    return int(state["next_id"]), len(rounds), rounds
