"""Tracking registration of one camera's video, the way visual SLAM systems track (issue 18, item 1).

Global matching of every frame against the whole reference (:func:`~.relative.register_features`) costs a
full SIFT extraction and a FLANN search of thousands of descriptors per image. Consecutive frames of one
camera see almost the same scene, so :func:`track_camera` registers most frames from the previous one:

1. **prediction**: the pose is extrapolated from the camera's two previous registered frames (constant
   velocity on SE(3)); the 3D points of the previous frame's inliers are projected with it and serve as
   the starting positions of
2. **KLT optical flow** (``cv2.calcOpticalFlowPyrLK``) of the previous frame's inlier pixels, checked
   forward–backward (a point that does not flow back to where it started within
   ``max_flow_error_px`` is dropped); the 3D points carry over;
3. **PnP-RANSAC and refinement** with the camera's own fisheye model
   (``pycolmap.estimate_and_refine_absolute_pose``, inlier threshold ``tracking_max_error_px``), accepted
   with the thresholds of absolute registration (more than ``min_inliers`` inliers, mean inlier error
   below ``max_mean_error_px``).

A **keyframe** gets SIFT and global matching against the reference (today's absolute registration) plus
guided matching of the camera's local map: the first frame, a frame where tracking failed, a frame whose
tracked inliers fell below ``max(min_tracked_inliers, keyframe_inlier_ratio × the last keyframe's)`` (the
tracked points its pose agrees with are kept), every ``keyframe_interval``-th frame, and every
``lost_keyframe_interval``-th frame while the camera is lost. A registered keyframe's keypoints without a
3D point are followed by KLT as candidates and **triangulated into new points** once their rays span
``min_triangulation_angle_deg``, so tracking goes on where the reference photos do not reach.

:func:`track_trial` tracks every camera of a trial (threads; keyframe SIFT and tracks cached on disk).
For the frames it leaves, chunk by chunk: :func:`relocalise` matches them against the reference plus every
camera's view of the map (:func:`map_index`), :func:`retrack` tracks into each gap from the registered
frames around it, and :func:`tracking_states` hands the rest, with SIFT of them and their neighbours
(:func:`frames_for_rounds`, :func:`sift_at`), to the rounds of :func:`~.relative.register_capture`.

Poses are ``world_from_camera`` ``wxyz_xyz`` in the reference model's frame; pixels in OpenCV's convention.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable

import numpy as np

from ..geometry import matrix_from_quat
from .poses import estimate_pose, nearest_point, world_from_camera_wxyz_xyz
from .reference import extract_sift
from .register import ReferenceIndex, RegistrationOptions, match_to_reference
from .threads import default_threads

__all__ = ["CameraTrack", "TrackingOptions", "frames_for_rounds", "map_index", "predict_pose", "relocalise", "retrack",
           "sift_at", "states_for_rounds", "track_camera", "track_trial", "tracking_states"]


#: The rounds of relative registration after tracking match each frame they need with at most this many other
#: cameras at the same time (the most similar views). On the rendered 10 s walk, against 4: the rounds 31 % faster
#: (294 → 203 s), registered 99.4 / 99.1 % instead of 99.0 / 99.2 % (ROM / capture); 1 gave 98.2 % of the capture.
ROUND_PARTNERS = 2


def round_options():
    """The :class:`~.relative.RelativeOptions` of the rounds after tracking: only the pairs their new points come
    from (no second-order pairs), each frame with at most :data:`ROUND_PARTNERS` other cameras."""
    from .relative import RelativeOptions

    return RelativeOptions(second_order_pairs=False, max_other_cameras=ROUND_PARTNERS)


@dataclasses.dataclass(frozen=True)
class TrackingOptions:
    """Settings of :func:`track_camera`.

    Attributes:
        registration: thresholds of pose acceptance and of the keyframes' global matching (shared with
            absolute registration).
        min_tracked_inliers, keyframe_inlier_ratio: a frame tracked with fewer inliers than
            ``max(min_tracked_inliers, keyframe_inlier_ratio × the last keyframe's)`` becomes a keyframe
            (re-acquisition by global matching).
        keyframe_interval: at most this many processed frames between keyframes.
        lost_keyframe_interval: while a camera is lost (two keyframes in a row failed), only every
            this-many-th frame is a keyframe: a camera the reference does not see
            would otherwise cost SIFT and global matching at every frame; :func:`relocalise`,
            :func:`retrack` and the rounds of relative registration work on the frames in between.
        window_px, levels: KLT search window (px) and pyramid levels (level 3 follows ~80 px of motion).
        max_flow_error_px: forward–backward KLT check.
        local_frames, guided_radius_px, max_descriptor_distance: guided matching at a keyframe: points
            measured in the last ``local_frames`` frames, projected with the tracked or predicted pose, are
            matched to keypoints within ``guided_radius_px`` (SIFT distance below
            ``max_descriptor_distance``, of 512).
        tracking_max_error_px: RANSAC inlier threshold of a tracked frame's pose (tighter than the
            keyframes': KLT drifts slowly, and a drifted point is dropped rather than kept as an inlier).
        max_candidates, candidate_spacing_px: keypoints of a registered keyframe without a 3D point tracked
            as candidates for new points (at most this many, this far from tracked points and each other).
        min_triangulation_angle_deg, max_reprojection_error_px: a candidate becomes a new 3D point once its
            rays span this angle, if it reprojects within this error in its first and current frame.
    """

    registration: RegistrationOptions = RegistrationOptions()
    min_tracked_inliers: int = 80
    keyframe_inlier_ratio: float = 0.6
    keyframe_interval: int = 15
    lost_keyframe_interval: int = 4
    window_px: int = 21
    levels: int = 3
    max_flow_error_px: float = 0.5
    max_candidates: int = 300
    candidate_spacing_px: float = 4.0
    min_triangulation_angle_deg: float = 5.0
    max_reprojection_error_px: float = 0.5
    tracking_max_error_px: float = 2.0
    local_frames: int = 30
    guided_radius_px: float = 8.0
    max_descriptor_distance: float = 300.0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass
class CameraTrack:
    """What :func:`track_camera` found for ``T`` processed frames of one camera.

    Attributes:
        poses: ``(T, 7)`` world_from_camera wxyz_xyz, NaN where unregistered.
        how: ``(T,)`` ``"keyframe"`` (registered by global matching), ``"tracked"`` or ``""``.
        keyframe: ``(T,)`` bool, SIFT was extracted (registered or not).
        pixels, point_ids: per frame the inlier measurements, ``(K, 2)`` float64 pixels and ``(K,)`` ids of
            reference 3D points.
        keypoint_index: per frame ``(K,)`` the keypoint of each measurement in the frame's SIFT features
            (keyframes registered by global matching), else −1.
        new_points: ``(P, 3)`` points triangulated while tracking, ids ``id_base … id_base + P − 1``.
        map_ids, map_descriptors: ``(L,)`` every 3D point the camera measured at a keypoint (reference and
            new) with ``(L, 128)`` uint8 the descriptor of its last such keypoint: the camera's view of the
            map, which :func:`relocalise` matches frames against.
    """

    poses: np.ndarray
    how: np.ndarray
    keyframe: np.ndarray
    pixels: list
    point_ids: list
    keypoint_index: list
    new_points: np.ndarray
    id_base: int
    map_ids: np.ndarray
    map_descriptors: np.ndarray

    @property
    def points(self) -> dict:
        """``{id: (3,) position}`` of the new points."""
        return {self.id_base + k: x for k, x in enumerate(self.new_points)}

    @property
    def registered(self) -> np.ndarray:
        return self.how != ""

    def save(self, path) -> None:
        """Write as an ``.npz`` (ragged measurements concatenated with per-frame counts)."""
        counts = np.array([len(p) for p in self.point_ids], np.int64)
        np.savez(path, poses=self.poses, how=self.how.astype("U8"), keyframe=self.keyframe, counts=counts,
                 pixels=np.concatenate(self.pixels).reshape(-1, 2) if len(counts) else np.zeros((0, 2)),
                 point_ids=np.concatenate(self.point_ids) if len(counts) else np.zeros(0, np.int64),
                 keypoint_index=np.concatenate(self.keypoint_index) if len(counts) else np.zeros(0, np.int64),
                 new_points=self.new_points, id_base=self.id_base, map_ids=self.map_ids,
                 map_descriptors=self.map_descriptors)

    @classmethod
    def load(cls, path) -> "CameraTrack":
        with np.load(path) as data:
            cut = np.cumsum(data["counts"])[:-1]
            return cls(data["poses"], data["how"].astype(str), data["keyframe"].astype(bool),
                       list(np.split(data["pixels"], cut)), list(np.split(data["point_ids"], cut)),
                       list(np.split(data["keypoint_index"], cut)), data["new_points"], int(data["id_base"]),
                       data["map_ids"], data["map_descriptors"])


def _matrix(pose: np.ndarray) -> np.ndarray:
    """``(4, 4)`` matrix of a wxyz_xyz pose."""
    m = np.eye(4)
    m[:3, :3] = matrix_from_quat(pose[:4])
    m[:3, 3] = pose[4:]
    return m


def predict_pose(before: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Constant-velocity prediction on SE(3): ``(4, 4)`` world_from_camera of the next frame, the motion
    from ``before`` to ``last`` (``(7,)`` wxyz_xyz world_from_camera of two consecutive processed frames)
    applied once more after ``last``."""
    a, b = _matrix(before), _matrix(last)
    return b @ (np.linalg.inv(a) @ b)  # world_from_next = world_from_last · before_from_last


def _project(cam, world_from_camera: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """``(K, 2)`` OpenCV pixels of world points seen by a pycolmap camera (NaN behind it); the pose is a
    ``(4, 4)`` matrix or a ``(7,)`` wxyz_xyz."""
    m = _matrix(world_from_camera) if world_from_camera.shape == (7,) else world_from_camera
    local = (xyz - m[:3, 3]) @ m[:3, :3]
    uv = np.asarray(cam.img_from_cam(local), np.float64).reshape(-1, 2) - 0.5
    uv[local[:, 2] <= 1e-9] = np.nan
    return uv


def _flow(prev, cur, pts: np.ndarray, guess: np.ndarray | None, options: TrackingOptions) -> tuple[np.ndarray, np.ndarray]:
    """KLT of ``pts (K, 2)`` from image ``prev`` to ``cur`` (optionally from initial positions ``guess``),
    checked forward–backward: ``(new positions (K, 2), ok (K,))``."""
    import cv2

    win = (options.window_px, options.window_px)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    p0 = np.ascontiguousarray(pts, np.float32).reshape(-1, 1, 2)
    flags = 0
    p1 = None
    if guess is not None:
        p1 = np.ascontiguousarray(np.where(np.isfinite(guess), guess, pts), np.float32).reshape(-1, 1, 2)
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, p1, winSize=win, maxLevel=options.levels,
                                          criteria=criteria, flags=flags)
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, p0.copy(), winSize=win, maxLevel=options.levels,
                                           criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) \
        & (np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1) < options.max_flow_error_px)
    return p1.reshape(-1, 2).astype(np.float64), ok


class _Tracker:
    """The state of :func:`track_camera` between frames; :meth:`step` registers the next frame.

    Besides the tracked measurements of 3D points it keeps **candidates**: a registered keyframe's SIFT
    keypoints without a 3D point, followed by KLT too, each with the normal equations of its rays so far
    (``Σ (I − d dᵀ)`` and ``Σ (I − d dᵀ) c`` over rays ``d`` from centres ``c``). Once its rays span
    ``min_triangulation_angle_deg`` the candidate is triangulated (least squares over all its rays), kept
    if it reprojects within ``max_reprojection_error_px`` in its first and current frame, and becomes a
    new 3D point (id ``id_base + k``) measured in both, so tracking goes on where the reference is not seen.
    """

    def __init__(self, cam, index: ReferenceIndex, options: TrackingOptions, id_base: int = 1 << 40):
        self.cam, self.index, self.options, self.id_base = cam, index, options, int(id_base)
        self.poses, self.how, self.keyframe = [], [], []
        self.pixels, self.point_ids, self.keypoint_index = [], [], []
        self.new_xyz = np.zeros((0, 3))
        self.prev_gray = None
        self.since_key = 0
        self.key_count = 0  # inliers at the last registered keyframe
        self.track_only = False  # no keyframes (re-tracking from a seed, :func:`retrack`)
        self.lost = 0  # frames since the last registered one
        self.local: dict[int, np.ndarray] = {}  # point id -> (128,) uint8 descriptor of its last keyframe
        self.last_seen: dict[int, int] = {}  # point id -> last frame measuring it
        self._clear_candidates()

    def _clear_candidates(self) -> None:
        self.cand_px = np.zeros((0, 2))
        self.cand_a = np.zeros((0, 3, 3))
        self.cand_b = np.zeros((0, 3))
        self.cand_ray0 = np.zeros((0, 3))
        self.cand_t0 = np.zeros(0, np.int64)
        self.cand_px0 = np.zeros((0, 2))
        self.cand_desc = np.zeros((0, 128), np.uint8)

    def _keep_candidates(self, keep: np.ndarray) -> None:
        for name in ("cand_px", "cand_a", "cand_b", "cand_ray0", "cand_t0", "cand_px0", "cand_desc"):
            setattr(self, name, getattr(self, name)[keep])

    def xyz_of(self, ids: np.ndarray) -> np.ndarray:
        """``(K, 3)`` positions of reference and new points by id."""
        ids = np.asarray(ids, np.int64)
        out = np.zeros((len(ids), 3))
        new = (ids >= self.id_base) & (ids - self.id_base < len(self.new_xyz))
        if (~new).any():
            out[~new] = self.index.xyz_of(ids[~new])
        if new.any():
            out[new] = self.new_xyz[ids[new] - self.id_base]
        return out

    def _track(self, gray: np.ndarray):
        """KLT of the previous frame's inliers and candidates, and PnP: ``(pose, pixels, ids)`` or None (the
        candidates are moved along, or dropped when the frame is lost)."""
        if self.prev_gray is None or not self.how or not self.how[-1] or len(self.point_ids[-1]) < 4:
            self._clear_candidates()
            return None
        px, ids = self.pixels[-1], self.point_ids[-1]
        xyz = self.xyz_of(ids)
        guess = None
        if len(self.how) >= 2 and self.how[-2]:
            predicted = predict_pose(self.poses[-2], self.poses[-1])
            guess = np.concatenate([_project(self.cam, predicted, xyz), np.full((len(self.cand_px), 2), np.nan)])
        moved, ok = _flow(self.prev_gray, gray, np.concatenate([px, self.cand_px]), guess, self.options)
        h, w = gray.shape[:2]
        ok &= (moved[:, 0] >= 0) & (moved[:, 1] >= 0) & (moved[:, 0] <= w - 1) & (moved[:, 1] <= h - 1)
        k = len(px)
        self.cand_px = moved[k:]
        self._keep_candidates(ok[k:])
        moved, ok = moved[:k], ok[:k]
        reg = dataclasses.replace(self.options.registration, ransac_max_error_px=self.options.tracking_max_error_px)
        found = estimate_pose(moved[ok], xyz[ok], self.cam, reg) if ok.sum() >= 4 else None
        if found is None:
            self._clear_candidates()
            return None
        cfw, inl, _ = found
        return world_from_camera_wxyz_xyz(cfw), moved[ok][inl], ids[ok][inl]

    def _needs_keyframe(self, tracked) -> bool:
        o = self.options
        if tracked is None and self.lost >= 2:  # lost: global matching every lost_keyframe_interval-th frame
            return self.lost % o.lost_keyframe_interval == 0
        return (tracked is None or self.since_key + 1 >= o.keyframe_interval
                or len(tracked[2]) < max(o.min_tracked_inliers, o.keyframe_inlier_ratio * self.key_count))

    def _rays(self, pose: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        from .relative import pixel_rays

        return pixel_rays(self.cam, pixels) @ matrix_from_quat(pose[:4]).T

    def _map(self, t: int, pose: np.ndarray) -> None:
        """Add frame ``t``'s rays to the candidates and triangulate those whose rays span enough angle."""
        o = self.options
        if not len(self.cand_px):
            return
        rays = self._rays(pose, self.cand_px)
        proj = np.eye(3) - rays[:, :, None] * rays[:, None, :]
        self.cand_a = self.cand_a + proj
        self.cand_b = self.cand_b + proj @ pose[4:]
        angle = np.degrees(np.arccos(np.clip(np.sum(rays * self.cand_ray0, 1), -1, 1)))
        ready = np.flatnonzero(angle >= o.min_triangulation_angle_deg)
        if not len(ready):
            return
        xyz = nearest_point(self.cand_a[ready], self.cand_b[ready])
        err_now = np.linalg.norm(_project(self.cam, pose, xyz) - self.cand_px[ready], axis=1)
        err_first = np.full(len(ready), np.inf)
        for t0 in np.unique(self.cand_t0[ready]):
            sel = self.cand_t0[ready] == t0
            err_first[sel] = np.linalg.norm(_project(self.cam, self.poses[t0], xyz[sel]) - self.cand_px0[ready][sel],
                                            axis=1)
        good = (err_now < o.max_reprojection_error_px) & (err_first < o.max_reprojection_error_px)
        new_ids = self.id_base + len(self.new_xyz) + np.arange(int(good.sum()))
        self.new_xyz = np.concatenate([self.new_xyz, xyz[good]])
        self.local.update(zip(new_ids.tolist(), self.cand_desc[ready][good]))
        for t0 in np.unique(self.cand_t0[ready][good]):  # the first observation joins its frame's measurements
            sel = self.cand_t0[ready][good] == t0
            self.pixels[t0] = np.concatenate([self.pixels[t0], self.cand_px0[ready][good][sel]])
            self.point_ids[t0] = np.concatenate([self.point_ids[t0], new_ids[sel]])
            self.keypoint_index[t0] = np.concatenate([self.keypoint_index[t0], np.full(int(sel.sum()), -1)])
        self.pixels[t] = np.concatenate([self.pixels[t], self.cand_px[ready][good]])
        self.point_ids[t] = np.concatenate([self.point_ids[t], new_ids])
        self.keypoint_index[t] = np.concatenate([self.keypoint_index[t], np.full(len(new_ids), -1)])
        keep = np.ones(len(self.cand_px), bool)
        keep[ready] = False
        self._keep_candidates(keep)

    def _add_candidates(self, t: int, pose: np.ndarray, keypoints: np.ndarray, desc: np.ndarray,
                        used: np.ndarray) -> None:
        """A registered keyframe's keypoints without a 3D point (``used`` marks those with one) that lie away
        from every tracked point and candidate become candidates, spread over the image."""
        from scipy.spatial import cKDTree

        from .selection import select_measurements

        o = self.options
        room = o.max_candidates - len(self.cand_px)
        free = np.flatnonzero(~used)
        if room <= 0 or not len(free):
            return
        taken = np.concatenate([self.pixels[t], self.cand_px])
        if len(taken):
            dist, _ = cKDTree(taken).query(keypoints[free], distance_upper_bound=o.candidate_spacing_px)
            free = free[~np.isfinite(dist)]
        h, w = self.prev_shape
        free = free[select_measurements(keypoints[free], np.zeros(len(free)), room, w, h)]
        px = keypoints[free]
        rays = self._rays(pose, px)
        proj = np.eye(3) - rays[:, :, None] * rays[:, None, :]
        self.cand_px = np.concatenate([self.cand_px, px])
        self.cand_a = np.concatenate([self.cand_a, proj])
        self.cand_b = np.concatenate([self.cand_b, proj @ pose[4:]])
        self.cand_ray0 = np.concatenate([self.cand_ray0, rays])
        self.cand_t0 = np.concatenate([self.cand_t0, np.full(len(px), t)])
        self.cand_px0 = np.concatenate([self.cand_px0, px])
        self.cand_desc = np.concatenate([self.cand_desc, desc[free]])

    def _guess(self):
        """A pose for an untracked frame from the previous ones (constant velocity, or the last pose), or None."""
        if not self.how or not self.how[-1]:
            return None
        if len(self.how) >= 2 and self.how[-2]:
            return predict_pose(self.poses[-2], self.poses[-1])
        return self.poses[-1]

    def _guided(self, t: int, guess: np.ndarray, keypoints: np.ndarray, desc: np.ndarray):
        """Guided matching: the local map's points (seen in the last ``local_frames`` frames, with the
        descriptor of their last keyframe) projected with the ``guess`` pose, each matched to the keyframe's
        keypoints within ``guided_radius_px`` by descriptor (Lowe's ratio among them; one keypoint per point).
        Returns ``(keypoint rows (K,), point ids (K,))``."""
        from scipy.spatial import cKDTree

        o = self.options
        recent = [i for i, seen in self.last_seen.items() if t - seen <= o.local_frames and i in self.local]
        if not recent or not len(keypoints):
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        ids = np.array(recent, np.int64)
        uv = _project(self.cam, guess, self.xyz_of(ids))
        h, w = self.prev_shape
        inside = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < w) & (uv[:, 1] < h)
        ids, uv = ids[inside], uv[inside]
        near = cKDTree(keypoints).query_ball_point(uv, o.guided_radius_px)
        rows = np.repeat(np.arange(len(ids)), [len(n) for n in near])
        if not len(rows):
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        cols = np.concatenate([np.asarray(n, np.int64) for n in near])
        point_desc = np.stack([self.local[int(i)] for i in ids]).astype(np.float32)
        dist = np.linalg.norm(point_desc[rows] - desc[cols].astype(np.float32), axis=1)
        order = np.lexsort((dist, rows))
        rows, cols, dist = rows[order], cols[order], dist[order]
        first = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
        second = np.full(len(first), np.inf)
        has_second = np.r_[first[1:], len(rows)] - first > 1
        second[has_second] = dist[first[has_second] + 1]
        good = first[(dist[first] < o.registration.ratio * second) & (dist[first] < o.max_descriptor_distance)]
        good = good[np.argsort(dist[good], kind="stable")]
        _, unique = np.unique(cols[good], return_index=True)  # one point per keypoint, the closest
        good = good[unique]
        return cols[good], ids[rows[good]]

    def step(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Register the next frame (gray uint8); returns its SIFT ``(keypoints (N, 2), descriptors (N, 128))``,
        empty unless it is a keyframe."""
        reg = self.options.registration
        t = len(self.poses)
        self.prev_shape = gray.shape[:2]
        tracked = self._track(gray)
        pose, px, ids, kpi, kind = np.full(7, np.nan), np.zeros((0, 2)), np.zeros(0, np.int64), None, ""
        if tracked is not None:
            pose, px, ids = tracked
            kind = "tracked"
        keypoints, desc = np.zeros((0, 2)), np.zeros((0, 128), np.uint8)
        is_key = self._needs_keyframe(tracked) and not self.track_only
        used = None
        if is_key:
            keypoints, desc = extract_sift(gray, max_features=reg.max_features)
            keypoints = keypoints[:, :2].astype(np.float64)
            self.since_key = 0
            found = None
            if len(desc) >= 2:
                query, rows = match_to_reference(desc, self.index, reg.ratio, reg.checks)
                kp_rows, kp_ids = query, self.index.point3D_ids[rows]
                guess = pose if kind else self._guess()
                if guess is not None:  # guided matching of the local map adds what global matching missed
                    g_rows, g_ids = self._guided(t, guess, keypoints, desc)
                    kp_rows, kp_ids = np.concatenate([kp_rows, g_rows]), np.concatenate([kp_ids, g_ids])
                    _, first = np.unique(kp_ids, return_index=True)
                    kp_rows, kp_ids = kp_rows[first], kp_ids[first]
                    _, first = np.unique(kp_rows, return_index=True)
                    kp_rows, kp_ids = kp_rows[first], kp_ids[first]
                found = estimate_pose(keypoints[kp_rows], self.xyz_of(kp_ids), self.cam, reg)
            if found is not None:
                cfw, inl, _ = found
                key_pose = world_from_camera_wxyz_xyz(cfw)
                new_ids, new_px, new_kpi = kp_ids[inl], keypoints[kp_rows[inl]], kp_rows[inl]
                if kind:  # tracked points the keyframe did not find again, if its pose agrees with them
                    extra = np.flatnonzero(~np.isin(ids, new_ids))
                    err = np.linalg.norm(_project(self.cam, key_pose, self.xyz_of(ids[extra])) - px[extra], axis=1)
                    keep = extra[err < self.options.tracking_max_error_px]
                    new_ids = np.concatenate([new_ids, ids[keep]])
                    new_px = np.concatenate([new_px, px[keep]])
                    new_kpi = np.concatenate([new_kpi, np.full(len(keep), -1)])
                pose, px, ids, kpi, kind = key_pose, new_px, new_ids, new_kpi.astype(np.int64), "keyframe"
                self.key_count = len(ids)
                used = np.zeros(len(keypoints), bool)
                used[kp_rows] = True
                for i, row in zip(new_ids[new_kpi >= 0].tolist(), new_kpi[new_kpi >= 0].tolist()):
                    self.local[i] = desc[row]
        else:
            self.since_key += 1
        self.lost = 0 if kind else self.lost + 1
        self.poses.append(pose)
        self.how.append(kind)
        self.keyframe.append(is_key)
        self.pixels.append(np.asarray(px, np.float64).reshape(-1, 2))
        self.point_ids.append(np.asarray(ids, np.int64))
        self.keypoint_index.append(kpi if kpi is not None else np.full(len(ids), -1, np.int64))
        if kind:
            self._map(t, pose)
            self.last_seen.update(dict.fromkeys(self.point_ids[t].tolist(), t))
            if used is not None:
                self._add_candidates(t, pose, keypoints, desc, used)
        else:
            self._clear_candidates()
        self.prev_gray = gray
        return keypoints, desc

    def seed(self, gray: np.ndarray, pose: np.ndarray, pixels: np.ndarray, point_ids: np.ndarray) -> None:
        """Start from a frame registered elsewhere (its image, pose and measurements), as if just tracked."""
        self.poses.append(np.asarray(pose, np.float64))
        self.how.append("seed")
        self.keyframe.append(False)
        self.pixels.append(np.asarray(pixels, np.float64).reshape(-1, 2))
        self.point_ids.append(np.asarray(point_ids, np.int64))
        self.keypoint_index.append(np.full(len(point_ids), -1, np.int64))
        self.prev_gray = gray
        self.prev_shape = gray.shape[:2]

    def result(self) -> CameraTrack:
        return CameraTrack(np.array(self.poses, np.float64).reshape(-1, 7), np.array(self.how, dtype="U8"),
                           np.array(self.keyframe, bool), self.pixels, self.point_ids, self.keypoint_index,
                           self.new_xyz, self.id_base, np.array(list(self.local), np.int64),
                           np.array(list(self.local.values()), np.uint8).reshape(-1, 128))


def track_camera(frames: Iterable[np.ndarray], cam, index: ReferenceIndex,
                 options: TrackingOptions = TrackingOptions()) -> CameraTrack:
    """Register one camera's processed frames in order by tracking, with keyframes matched globally (module
    docstring).

    Args:
        frames: gray ``uint8 (H, W)`` images, the camera's processed frames in time order.
        cam: its ``pycolmap.Camera`` (COLMAP pixel convention).
        index: the reference model's :func:`~.register.reference_index`.
    """
    tracker = _Tracker(cam, index, options)
    for gray in frames:
        tracker.step(gray)
    return tracker.result()


def track_trial(capture, trial: str, index: ReferenceIndex, *, starts, num_frames: int, stride: int = 1,
                options: TrackingOptions = TrackingOptions(), cache_dir=None, workers: int | None = None,
                progress: Callable[[int, int], None] | None = None, map_tasks=None) -> tuple[list, list]:
    """Track every camera of a trial (:func:`track_camera`), cameras in parallel.

    Args:
        capture: a :class:`~bcmocap.frontend.capture.Capture`; trial: its name.
        starts: ``(C,)`` first video frame of each camera (the synchronisation offsets);
        num_frames: video frames per camera from its start; stride: every ``stride``-th is processed.
        cache_dir: each camera's keyframe SIFT (:mod:`~.features`, empty for the other frames) and its
            :class:`CameraTrack` (``track.npz``) go to ``cache_dir/<camera>/`` and are read back instead of
            recomputed when the settings match.
        workers: cameras tracked at once (threads; OpenCV and pycolmap release the GIL).
        progress: ``progress(done, total)`` over all processed images.
        map_tasks: ``map_tasks(fn, items, label=, on_done=)`` running independent calls elsewhere (a cluster,
            :class:`bcmocap.pipeline.cluster.Executor`); with ``cache_dir``, each camera is tracked as one
            such call that fills its cache folder, and the tracks are then read from the caches here.

    Returns:
        ``(tracks, features)``: per camera its :class:`CameraTrack` and its per-frame keyframe SIFT
        ``[(keypoints (N, 2), descriptors (N, 128) uint8)]`` (memory-mapped with ``cache_dir``).
    """
    import functools
    from concurrent.futures import ThreadPoolExecutor

    from .relative import ProgressCounter

    names = capture.camera_names
    starts = np.asarray(starts, np.int64)
    per_video = max(0, -(-num_frames // stride))
    tick = ProgressCounter(len(names) * per_video, progress)
    one_camera = functools.partial(_track_one_camera, capture, trial, index, starts, num_frames, stride, options,
                                   cache_dir)
    if map_tasks is not None and cache_dir is not None:
        map_tasks(functools.partial(_track_camera_task, one_camera), range(len(names)), label=f"track {trial}",
                  on_done=lambda i, done: tick(done))
        tick = ProgressCounter(0, None)  # every camera is in its cache now: read back without counting again
    count = workers if workers is not None else default_threads()
    with ThreadPoolExecutor(max_workers=max(1, count)) as pool:
        done = list(pool.map(lambda c: one_camera(c, tick), range(len(names))))
    return [d[0] for d in done], [d[1] for d in done]


def _track_camera_task(one_camera, c: int) -> int:
    """A task of :func:`track_trial` on a cluster: track camera ``c`` into its cache; the images processed."""
    track, _ = one_camera(c, None)
    return len(track.how)


def _track_one_camera(capture, trial: str, index: ReferenceIndex, starts: np.ndarray, num_frames: int, stride: int,
                      options: TrackingOptions, cache_dir, c: int, tick) -> tuple:
    """``(CameraTrack, keyframe features)`` of camera ``c`` (:func:`track_trial`), from its cache folder when
    it holds them for these settings; ``tick(n)`` (or None) counts processed images."""
    import os
    from pathlib import Path

    from ..io.colmap import to_pycolmap
    from .features import read_camera_features, write_camera_features

    name, start = capture.camera_names[c], int(starts[c])
    cam = to_pycolmap(capture.cameras[c].intrinsics)
    tracker = _Tracker(cam, index, options, id_base=(c + 1) << 40)
    count = tick or (lambda n: None)

    def steps():
        for _, gray in capture.frames(trial, name, stride=stride, start=start, stop=start + num_frames, gray=True):
            yield tracker.step(gray)
            count(1)

    if cache_dir is None:
        feats = list(steps())
        return tracker.result(), feats
    settings = {"start": start, "stride": int(stride), "num_frames": int(num_frames), "tracking": options.to_dict(),
                "lenses": capture.lens_fingerprint(), **capture.correction_settings(trial)}
    folder = Path(cache_dir) / name
    feats = read_camera_features(folder, settings)
    if feats is not None and (folder / "track.npz").is_file():
        try:
            track = CameraTrack.load(folder / "track.npz")
        except (OSError, ValueError, KeyError):
            track = None
        if track is not None and len(track.how) == len(feats):
            count(len(feats))
            return track, feats
    write_camera_features(folder, settings, steps())
    track = tracker.result()
    tmp = folder / ".track.npz"
    track.save(tmp)
    os.replace(tmp, folder / "track.npz")
    feats = read_camera_features(folder, settings)
    if feats is None:
        raise OSError(f"{folder}: features written but not readable")
    return track, feats


def frames_for_rounds(registered: np.ndarray, gap: int, partners: list | None = None) -> np.ndarray:
    """``(T, C)`` bool: frames whose SIFT the rounds of relative registration and the homographies need —
    every frame left unregistered (``registered (T, C)`` False), the same camera's frames up to ``gap``
    away, and at the same time the frames of its ``partners[c]`` (camera indices; default every camera)."""
    need = ~np.asarray(registered, bool)
    out = need.copy()
    for c in range(need.shape[1]):
        others = slice(None) if partners is None else np.asarray(partners[c], np.int64)
        out[np.ix_(need[:, c], np.arange(need.shape[1])[others])] = True
    for dt in range(1, gap + 1):
        out[dt:] |= need[:-dt]
        out[:-dt] |= need[dt:]
    return out


def tracking_states(tracks: list, keyframe_features: list, extra_features: dict, first: int, stop: int,
                    relocalised: dict | None = None, match_px: float = 1.0) -> tuple[list, list, dict]:
    """Features and initial registration of the processed frames ``first … stop − 1`` for
    :func:`~.relative.register_capture`.

    A frame's keypoints are its SIFT keypoints (a keyframe's, or ``extra_features[(t, c)]``, extracted
    for the rounds) followed by its tracked measurements that no SIFT keypoint lies within ``match_px``
    of; only the SIFT keypoints have descriptors. Tracked measurements give their point ids to the
    keypoints they fall on (a registered keyframe's inliers by index). Frames in ``relocalised``
    (:func:`relocalise`) take its pose and point ids.

    Returns:
        ``(features, initial, points)``: ``features[t][c] = (keypoints (N, 2), descriptors (M ≤ N, 128))``,
        ``initial[t][c] = (world_from_camera (7,), point_ids (N,), how)`` with ``how`` ``"absolute"``
        (a keyframe registered by global matching), ``"tracked"``, ``"relocalised"`` or ``""``, and
        ``{id: (3,) position}`` of
        the points the trackers triangulated.
    """
    from scipy.spatial import cKDTree

    features, initial = [], []
    for t in range(first, stop):
        row_f, row_i = [], []
        for c, track in enumerate(tracks):
            kp, desc = keyframe_features[c][t] if track.keyframe[t] else extra_features.get(
                (t, c), (np.zeros((0, 2)), np.zeros((0, 128), np.uint8)))
            kp = np.asarray(kp, np.float64).reshape(-1, 2)
            px, ids, kpi = track.pixels[t], track.point_ids[t], track.keypoint_index[t]
            point_ids = np.full(len(kp), -1, np.int64)
            on_kp = kpi >= 0
            point_ids[kpi[on_kp]] = ids[on_kp]
            rest = np.flatnonzero(~on_kp)
            if len(rest) and len(kp):
                dist, nearest = cKDTree(kp).query(px[rest], distance_upper_bound=match_px)
                hit = np.isfinite(dist)
                # one measurement per keypoint: the first claim wins
                _, first_hit = np.unique(nearest[hit], return_index=True)
                chosen = rest[hit][first_hit]
                free = point_ids[nearest[hit][first_hit]] < 0
                point_ids[nearest[hit][first_hit][free]] = ids[chosen[free]]
                rest = np.setdiff1d(rest, chosen[free])
            keypoints = np.concatenate([kp, px[rest]])
            point_ids = np.concatenate([point_ids, ids[rest]])
            how = {"keyframe": "absolute", "tracked": "tracked"}.get(str(track.how[t]), "")
            pose = track.poses[t]
            if (t, c) in (relocalised or {}):
                pose, found_ids = relocalised[(t, c)]
                point_ids = np.concatenate([found_ids, np.full(len(keypoints) - len(found_ids), -1)])
                how = "relocalised"
            row_f.append((keypoints, desc))
            row_i.append((pose, point_ids, how))
        features.append(row_f)
        initial.append(row_i)
    points = {k: x for track in tracks for k, x in track.points.items()}
    return features, initial, points


def sift_at(capture, trial: str, wanted: np.ndarray, *, starts, stride: int, first: int = 0,
            max_features: int = 8000, workers: int | None = None) -> dict:
    """SIFT of the processed frames ``wanted (T, C)`` (bool, rows are processed frames ``first …
    first + T − 1``): ``{(t, c): (keypoints (N, 2), descriptors (N, 128) uint8)}`` with ``t`` counted
    from 0 like the processed frames. Each camera's video is decoded once, up to its last wanted frame."""
    from concurrent.futures import ThreadPoolExecutor

    names = capture.camera_names
    starts = np.asarray(starts, np.int64)

    def one_camera(c: int) -> dict:
        rows = np.flatnonzero(wanted[:, c])
        if not len(rows):
            return {}
        todo = set((first + rows).tolist())
        start = int(starts[c]) + first * stride
        out = {}
        for k, (_, gray) in enumerate(capture.frames(trial, names[c], stride=stride, start=start,
                                                     stop=int(starts[c]) + (first + int(rows[-1])) * stride + 1,
                                                     gray=True)):
            if first + k in todo:
                kp, desc = extract_sift(gray, max_features=max_features)
                out[(first + k, c)] = (kp[:, :2].astype(np.float64), desc)
        return out

    count = workers if workers is not None else default_threads()
    found = {}
    with ThreadPoolExecutor(max_workers=max(1, count)) as pool:
        for part in pool.map(one_camera, range(len(names))):
            found.update(part)
    return found


def map_index(tracks: list, index: ReferenceIndex) -> tuple[ReferenceIndex, np.ndarray]:
    """The reference index extended by every camera's view of the map (:attr:`CameraTrack.map_ids`): the
    reference points' descriptors as the body cameras saw them and the points tracking triangulated.
    Returns it with ``(M,)`` the camera each row comes from (−1: the reference photos)."""
    descriptors, ids, xyz = [index.descriptors], [index.point3D_ids], [index.xyz]
    owners = [np.full(len(index.point3D_ids), -1)]
    for c, track in enumerate(tracks):
        if not len(track.map_ids):
            continue
        new = track.map_ids >= track.id_base
        pos = np.zeros((len(track.map_ids), 3))
        pos[~new] = index.xyz_of(track.map_ids[~new])
        pos[new] = track.new_points[track.map_ids[new] - track.id_base]
        descriptors.append(np.asarray(track.map_descriptors, np.float32))
        ids.append(track.map_ids)
        xyz.append(pos)
        owners.append(np.full(len(track.map_ids), c))
    extended = ReferenceIndex(np.ascontiguousarray(np.concatenate(descriptors)), np.concatenate(ids),
                              np.concatenate(xyz))
    return extended, np.concatenate(owners)


def relocalise(tracks: list, keyframe_features: list, cams: list, index: ReferenceIndex, first: int, stop: int,
               registration: RegistrationOptions = RegistrationOptions(), workers: int | None = None) -> dict:
    """Register the frames ``first … stop − 1`` tracking left (each a keyframe that global matching could not
    register) against :func:`map_index`: the map the other cameras built while tracking covers what the
    reference photos do not.

    Returns:
        ``({(t, c): (world_from_camera (7,), point_ids per keypoint (N,))}, affinity (C, C))``: per camera,
        how many of its frames' matches fell on each other camera's map (which cameras see what it sees).
    """
    from concurrent.futures import ThreadPoolExecutor

    num_c = len(tracks)
    affinity = np.zeros((num_c, num_c), np.int64)
    todo = [(t, c) for t in range(first, stop) for c, track in enumerate(tracks)
            if not track.registered[t] and track.keyframe[t]]
    if not todo:
        return {}, affinity
    extended, owners = map_index(tracks, index)

    def one(tc):
        t, c = tc
        kp, desc = keyframe_features[c][t]
        if len(desc) < 2:
            return None, np.zeros(num_c, np.int64)
        query, rows = match_to_reference(desc, extended, registration.ratio, registration.checks)
        votes = np.bincount(owners[rows][owners[rows] >= 0], minlength=num_c)
        found = estimate_pose(np.asarray(kp, np.float64)[query], extended.xyz[rows], cams[c], registration)
        if found is None:
            return None, votes
        cfw, inl, _ = found
        ids = np.full(len(kp), -1, np.int64)
        ids[query[inl]] = extended.point3D_ids[rows[inl]]
        return (world_from_camera_wxyz_xyz(cfw), ids), votes

    count = workers if workers is not None else default_threads()
    registered = {}
    with ThreadPoolExecutor(max_workers=max(1, count)) as pool:
        for (t, c), (found, votes) in zip(todo, pool.map(one, todo)):
            affinity[c] += votes
            if found is not None:
                registered[(t, c)] = found
    return registered, affinity


def _track_into_gaps(capture, trial: str, lookup: ReferenceIndex, registered: Callable[[int, int], bool],
                     measurements: Callable[[int, int], tuple], store: Callable[[int, int, "_Tracker"], None], *,
                     starts, stride: int, first: int, stop: int, options: TrackingOptions,
                     workers: int | None = None) -> int:
    """Track each camera into its runs of unregistered frames among ``first … stop − 1``: forward from the
    registered frame before a run and backward from the one after it, without keyframes, until tracking
    fails.

    Args:
        lookup: positions of every point a seed frame may observe (``xyz_of``).
        registered: ``registered(c, t)``, whether frame ``t`` of camera ``c`` is registered (seeds and stops).
        measurements: ``measurements(c, t) → (world_from_camera (7,), pixels (K, 2), point ids (K,))`` of a
            registered frame, to start from.
        store: ``store(c, t, tracker)`` records a frame the tracker registered (its pose and measurements
            are the tracker's last); it must make ``registered(c, t)`` true.

    Returns how many frames were registered.
    """
    from concurrent.futures import ThreadPoolExecutor

    from ..io.colmap import to_pycolmap

    names = capture.camera_names
    starts = np.asarray(starts, np.int64)

    def one_camera(c: int) -> int:
        unreg = [t for t in range(first, stop) if not registered(c, t)]
        if not unreg:
            return 0
        runs = np.split(np.array(unreg), np.flatnonzero(np.diff(unreg) > 1) + 1)
        runs = [(int(r[0]), int(r[-1]) + 1) for r in runs]
        runs = [(a, b) for a, b in runs if (a > first and registered(c, a - 1)) or (b < stop and registered(c, b))]
        if not runs:
            return 0
        wanted = set()
        for a, b in runs:
            wanted.update(range(max(first, a - 1), min(stop, b + 1)))
        lo, hi = min(wanted), max(wanted)
        images = {}
        for k, (_, gray) in enumerate(capture.frames(trial, names[c], stride=stride, start=int(starts[c]) + lo * stride,
                                                     stop=int(starts[c]) + hi * stride + 1, gray=True)):
            if lo + k in wanted:
                images[lo + k] = gray
        cam = to_pycolmap(capture.cameras[c].intrinsics)
        count = 0
        for r, (a, b) in enumerate(runs):
            for seed_t, order in ((a - 1, range(a, b)), (b, range(b - 1, a - 1, -1))):
                if not (first <= seed_t < stop) or not registered(c, seed_t) or seed_t not in images:
                    continue
                tracker = _Tracker(cam, lookup, options, id_base=((c + 1) << 40) + ((r + 1) << 28))
                tracker.track_only = True
                tracker.seed(images[seed_t], *measurements(c, seed_t))
                for t in order:
                    if registered(c, t) or t not in images:
                        break
                    tracker.step(images[t])
                    if not tracker.how[-1]:
                        break
                    store(c, t, tracker)
                    count += 1
        return count

    count = workers if workers is not None else default_threads()
    with ThreadPoolExecutor(max_workers=max(1, count)) as pool:
        return sum(pool.map(one_camera, range(len(names))))


def retrack(capture, trial: str, tracks: list, relocalised: dict, keyframe_features: list, index: ReferenceIndex,
            *, starts, stride: int, first: int, stop: int, options: TrackingOptions = TrackingOptions(),
            workers: int | None = None) -> int:
    """Track into the runs of frames ``first … stop − 1`` that tracking left, from the registered frames
    around them (tracked, or registered by :func:`relocalise`; :func:`_track_into_gaps`). ``tracks`` are
    updated in place (the frames become ``"tracked"``). Returns how many frames were registered."""
    lookup, _ = map_index(tracks, index)

    def registered(c: int, t: int) -> bool:
        return bool(tracks[c].registered[t]) or (t, c) in relocalised

    def measurements(c: int, t: int):
        if (t, c) in relocalised:
            pose, ids = relocalised[(t, c)]
            kp = np.asarray(keyframe_features[c][t][0], np.float64)
            has = ids >= 0
            return pose, kp[has], ids[has]
        return tracks[c].poses[t], tracks[c].pixels[t], tracks[c].point_ids[t]

    def store(c: int, t: int, tracker: _Tracker) -> None:
        track = tracks[c]
        track.poses[t] = tracker.poses[-1]
        track.how[t] = "tracked"
        track.pixels[t], track.point_ids[t] = tracker.pixels[-1], tracker.point_ids[-1]
        track.keypoint_index[t] = np.full(len(tracker.point_ids[-1]), -1, np.int64)

    return _track_into_gaps(capture, trial, lookup, registered, measurements, store, starts=starts, stride=stride,
                            first=first, stop=stop, options=options, workers=workers)


def track_after_rounds(capture, trial: str, result, *, starts, stride: int, first: int,
                       options: TrackingOptions = TrackingOptions(), workers: int | None = None) -> int:
    """Fill what the rounds of relative registration left (``result``, a
    :class:`~.relative.CaptureRegistration` of the processed frames ``first … first + T − 1``) by tracking
    from its registered frames (:func:`_track_into_gaps`), on the reference's and the rounds' points.

    The rounds then need SIFT for only some of the frames tracking left (``states_for_rounds`` with
    ``round_stride``): the rest are tracked from them here. Frames registered here become ``"tracked"``
    states whose keypoints are the tracked measurements (no descriptors). Returns how many."""
    states = result.states
    ids = np.array(sorted(result.points), np.int64)
    xyz = np.array([result.points[int(i)] for i in ids], np.float64).reshape(-1, 3)
    lookup = ReferenceIndex(np.zeros((0, 128), np.float32), ids, xyz)

    def registered(c: int, t: int) -> bool:
        return states[t - first][c].registered

    def measurements(c: int, t: int):
        s = states[t - first][c]
        has = s.point_ids >= 0
        return s.world_from_camera, s.keypoints[has], s.point_ids[has]

    def store(c: int, t: int, tracker: _Tracker) -> None:
        s = states[t - first][c]
        s.keypoints, s.point_ids = tracker.pixels[-1], tracker.point_ids[-1].copy()
        s.descriptors = np.zeros((0, 128), np.uint8)
        s.world_from_camera, s.how, s.round = tracker.poses[-1], "tracked", -1

    return _track_into_gaps(capture, trial, lookup, registered, measurements, store, starts=starts, stride=stride,
                            first=first, stop=first + len(states), options=options, workers=workers)


def _attach_sift(capture, trial: str, result, want: np.ndarray, *, starts, stride: int, first: int,
                 max_features: int) -> int:
    """Extract SIFT for the frames ``want (T, C)`` of ``result`` that have no descriptors and attach it to
    their states: an unregistered frame's keypoints become the SIFT keypoints, a registered frame keeps its
    measurements after them. Returns how many frames were extracted."""
    states = result.states
    want = want & np.array([[not len(st.descriptors) for st in row] for row in states], bool).reshape(want.shape)
    found = sift_at(capture, trial, want, starts=starts, stride=stride, first=first, max_features=max_features)
    for (t, c), (kp, desc) in found.items():
        st = states[t - first][c]
        if st.registered:
            st.keypoints = np.concatenate([kp, st.keypoints])
            st.point_ids = np.concatenate([np.full(len(kp), -1, np.int64), st.point_ids])
        else:
            st.keypoints, st.point_ids = kp, np.full(len(kp), -1, np.int64)
        st.descriptors = desc
    return len(found)


def sift_for_homographies(capture, trial: str, result, leave: np.ndarray, *, starts, stride: int, first: int,
                          max_features: int = 8000) -> int:
    """SIFT for the frames in ``leave`` that are still unregistered in ``result`` (a
    :class:`~.relative.CaptureRegistration` of the processed frames ``first …``) and for their neighbours in
    time that have no descriptors, so that :func:`~.homography.fill_with_homographies` can match each such
    frame with the one before it. Returns how many frames were extracted."""
    left = np.asarray(leave, bool) & ~result.registered
    want = frames_for_rounds(~left, 1, [()] * left.shape[1])  # each such frame and the ones beside it in time
    return _attach_sift(capture, trial, result, want, starts=starts, stride=stride, first=first,
                        max_features=max_features)


def rounds_for_the_rest(capture, trial: str, result, leave: np.ndarray, partners: list, index: ReferenceIndex, *,
                        starts, stride: int, first: int, max_features: int = 8000, progress=None, checkpoint=None):
    """A second pass of the rounds of relative registration for the frames in ``leave`` that neither the
    first pass (on the seeds) nor :func:`track_after_rounds` registered: SIFT for them and their neighbours
    (:func:`frames_for_rounds` with the ``partners`` of :func:`states_for_rounds`), then
    :func:`~.relative.register_capture` from ``result``'s registration. Returns the new
    :class:`~.relative.CaptureRegistration` (``result`` itself when nothing is left). ``checkpoint``: see
    :func:`~.relative.register_capture`."""
    from .relative import register_capture

    rest = np.asarray(leave, bool) & ~result.registered
    if not rest.any():
        return result
    options = round_options()
    _attach_sift(capture, trial, result, frames_for_rounds(~rest, options.max_time_gap, partners), starts=starts,
                 stride=stride, first=first, max_features=max_features)
    features = [[(s.keypoints, s.descriptors) for s in row] for row in result.states]
    initial = [[(s.world_from_camera, s.point_ids, s.how) for s in row] for row in result.states]
    second = register_capture(features, result.cameras, index, options, frames=result.frames, initial=initial,
                              initial_points=result.points, checkpoint=checkpoint, progress=progress)
    second.new_point_ids |= result.new_point_ids
    second.rounds = result.rounds + second.rounds[1:]
    return second


def round_seeds(registered: np.ndarray, stride: int) -> np.ndarray:
    """``(T, C)`` bool: the unregistered frames the rounds of relative registration work on — in each run of
    a camera's unregistered frames, every ``stride``-th from its first, and its last; the others are
    tracked from them afterwards (:func:`track_after_rounds`). ``stride`` 1: every unregistered frame."""
    registered = np.asarray(registered, bool)
    seeds = np.zeros_like(registered)
    for c in range(registered.shape[1]):
        unreg = np.flatnonzero(~registered[:, c])
        for run in np.split(unreg, np.flatnonzero(np.diff(unreg) > 1) + 1) if len(unreg) else []:
            seeds[run[::stride], c] = True
            seeds[run[-1], c] = True
    return seeds


def states_for_rounds(capture, trial: str, tracks: list, keyframe_features: list, index: ReferenceIndex, *,
                      starts, stride: int, first: int, stop: int, options: TrackingOptions = TrackingOptions(),
                      round_stride: int = 3, log: Callable[[str], None] = print) -> tuple:
    """What :func:`~.relative.register_capture` needs for the processed frames ``first … stop − 1`` after
    tracking: the frames tracking left go through :func:`relocalise` and :func:`retrack` (``tracks`` are
    updated); of those still left, the rounds work on :func:`round_seeds` (every ``round_stride``-th of
    each run; at most the rounds' ``max_time_gap``, so that seeds of one camera are matched with each other),
    so SIFT is extracted for them and their neighbours only (the camera's frames up to
    ``max_time_gap`` away; at the same time, the other cameras whose maps its frames matched most), and
    :func:`tracking_states` assembles features, initial registration and points.

    Returns ``(features, initial, points, leave, partners)``: ``leave (T, C)`` the unregistered frames the
    rounds skip (``register_capture(..., leave=leave)``; :func:`track_after_rounds` fills them), ``partners[c]``
    the cameras whose frames at the same time camera ``c``'s frames are matched with."""
    from ..io.colmap import to_pycolmap

    cams = [to_pycolmap(c.intrinsics) for c in capture.cameras]
    found, affinity = relocalise(tracks, keyframe_features, cams, index, first, stop, options.registration)
    retracked = retrack(capture, trial, tracks, found, keyframe_features, index, starts=starts, stride=stride,
                        first=first, stop=stop, options=options)
    registered = np.stack([t.registered[first:stop] for t in tracks], 1)
    for t, c in found:
        registered[t - first, c] = True
    seeds = round_seeds(registered, round_stride)
    log(f"{trial}: frames {first}-{stop - 1}: {len(found)} relocalised against the tracked map, {retracked} "
        f"tracked from them; {int((~registered).sum())} left, {int(seeds.sum())} of them for the rounds")
    rounds = round_options()
    np.fill_diagonal(affinity, 0)
    partners = []
    for row in affinity:
        best = np.argsort(-row, kind="stable")[:rounds.max_other_cameras]
        partners.append(best[row[best] > 0] if row.sum() else np.arange(len(row)))
    leave = ~registered & ~seeds
    need = frames_for_rounds(~seeds, rounds.max_time_gap, partners) & ~leave  # the frames left need no SIFT
    need &= ~np.stack([t.keyframe[first:stop] for t in tracks], 1)  # keyframes have their SIFT already
    extra = sift_at(capture, trial, need, starts=starts, stride=stride, first=first,
                    max_features=options.registration.max_features)
    return (*tracking_states(tracks, keyframe_features, extra, first, stop, found), leave, partners)
