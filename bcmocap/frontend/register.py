"""Absolute registration of body-camera frames to the reference model (§4.1, issue 5 item 4).

A frame is registered on its own against the reference reconstruction:

1. :func:`reference_index` stacks, once, the SIFT descriptor of every reference keypoint that observes a
   3D point of the model (read back from the reference's pycolmap database, in keypoint order, so the
   reconstruction's ``point2D_idx`` indexes them) together with that 3D point's id and position;
2. :func:`register_frame` extracts OpenCV SIFT from the frame, matches it to the index (FLANN k-d trees,
   Lowe's ratio test, several reference observations of one 3D point allowed but one 2D feature per 3D
   point kept), and hands the 2D–3D correspondences (+0.5 px into COLMAP's pixel convention) with the
   frame's camera (e.g. the FOV fisheye, via :func:`~bcmocap.io.colmap.to_pycolmap`) to
   ``pycolmap.estimate_and_refine_absolute_pose`` (LO-RANSAC P3P, then non-linear refinement);
3. the pose is accepted with more than ``min_inliers`` inliers and a mean inlier reprojection error
   below ``max_mean_error_px``, unless the correspondences it leaves support a second pose elsewhere with a
   quarter of its inliers or more (:func:`~bcmocap.frontend.poses.second_pose`: a repeated pattern).

Poses are ``world_from_camera`` as ``wxyz_xyz`` (bcmocap's convention; COLMAP's ``cam_from_world``
inverted). :func:`register_trial` does it for every ``stride``-th frame of one camera of a trial.

New points, bundle adjustment with the reference fixed and relative registration of a whole trial are in
:mod:`bcmocap.frontend.relative`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from ..cameras import CameraModel
from ..io.colmap import to_pycolmap
from ..native_crashes import load_pycolmap
from .poses import second_pose, world_from_camera_wxyz_xyz
from .reference import DescriptorIndex, ReferenceModel, extract_sift

__all__ = ["ReferenceIndex", "FrameRegistration", "RegistrationOptions", "TrialRegistration",
           "match_to_reference", "reference_index", "register_frame", "register_trial"]


@dataclasses.dataclass(frozen=True)
class RegistrationOptions:
    """Thresholds of absolute registration.

    Attributes:
        ratio: Lowe's ratio test; max_features: SIFT features per frame.
        checks: FLANN leaves visited per query when matching to the reference (32: 4× faster than a
            pycolmap-like exhaustive search and 2× faster than 64, with as many registered frames).
        ransac_max_error_px: RANSAC inlier threshold (COLMAP's ``max_error``).
        min_inliers: a pose needs more than this many inliers; max_mean_error_px: and a mean inlier
            reprojection error below this.
        ambiguity_ratio, ambiguity_shift: and no second pose (:func:`~.poses.second_pose`) with this share of its
            inliers among the correspondences it leaves, centred more than ``ambiguity_shift`` × the inliers'
            median depth away (``ambiguity_ratio`` 0: no check). In the repeated room the limb cameras' poses a period of the floor
            off had a second pose with 33–95 % of their inliers, right poses there up to 83 % (an ambiguous view is
            refused even when it happened to be right); in the sparse room, right poses at most 8 %.
    """

    ratio: float = 0.8
    max_features: int = 8000
    checks: int = 32
    ransac_max_error_px: float = 4.0
    min_inliers: int = 50
    max_mean_error_px: float = 1.0
    ambiguity_ratio: float = 0.25
    ambiguity_shift: float = 0.1


@dataclasses.dataclass
class ReferenceIndex:
    """Descriptors of the reference keypoints that observe a 3D point.

    Attributes:
        descriptors: ``(M, 128)`` float32; point3D_ids: ``(M,)`` the 3D point each one observes;
        xyz: ``(M, 3)`` that point's position (model frame).
    """

    descriptors: np.ndarray
    point3D_ids: np.ndarray
    xyz: np.ndarray
    _search: dict = dataclasses.field(default_factory=dict, repr=False)
    _by_id: tuple | None = dataclasses.field(default=None, repr=False)

    def search(self, checks: int = 32) -> DescriptorIndex:
        """The FLANN index of the descriptors (built once per ``checks``; safe to share between threads)."""
        if checks not in self._search:
            self._search[checks] = DescriptorIndex(self.descriptors, checks=checks)
        return self._search[checks]

    def xyz_of(self, point_ids: np.ndarray) -> np.ndarray:
        """``(K, 3)`` positions of the 3D points with these ids (all must be in the index)."""
        if self._by_id is None:
            order = np.argsort(self.point3D_ids, kind="stable")
            self._by_id = (self.point3D_ids[order], self.xyz[order])
        ids, xyz = self._by_id
        return xyz[np.searchsorted(ids, np.asarray(point_ids, np.int64))]


@dataclasses.dataclass
class FrameRegistration:
    """One frame's registration.

    Attributes:
        registered: accepted by the thresholds; world_from_camera: ``(7,)`` wxyz_xyz (NaN if no pose).
        points2D: ``(K, 2)`` inlier pixels (OpenCV convention); point3D_ids: ``(K,)`` their 3D points.
        num_matches: 2D–3D correspondences tried; num_inliers; mean_error_px over the inliers.
    """

    registered: bool
    world_from_camera: np.ndarray
    points2D: np.ndarray
    point3D_ids: np.ndarray
    num_matches: int
    num_inliers: int
    mean_error_px: float


@dataclasses.dataclass
class TrialRegistration:
    """One camera's frames of a trial, each registered on its own (:func:`register_trial`): ``frames (T,)`` frame
    numbers, ``poses (T, 7)`` world_from_camera (NaN where not registered), ``registered (T,)`` mask and the
    per-frame :class:`FrameRegistration` results."""

    frames: np.ndarray
    poses: np.ndarray
    registered: np.ndarray
    results: list

    @property
    def registered_fraction(self) -> float:
        return float(self.registered.mean()) if len(self.registered) else 0.0


def reference_index(model: ReferenceModel) -> ReferenceIndex:
    """Stack the descriptors of the reference keypoints with a 3D point (read from the model's database)."""
    pycolmap = load_pycolmap()

    rec = model.reconstruction
    desc, ids = [], []
    with pycolmap.Database.open(str(model.database_path)) as db:
        # By id: a model read back from disk lists its images so, a model just reconstructed in registration order,
        # and the index's row order decides FLANN's trees, so a resumed run would match differently.
        for image_id in sorted(rec.reg_image_ids()):
            image = rec.image(image_id)
            idx = np.array([i for i, p in enumerate(image.points2D) if p.has_point3D()], np.int64)
            if not len(idx):
                continue
            d = db.read_descriptors(image.image_id)
            data = np.asarray(d.data if hasattr(d, "data") else d)
            desc.append(data[idx].astype(np.float32))
            ids.append(np.array([image.points2D[int(i)].point3D_id for i in idx], np.int64))
    if not desc:
        raise ValueError("reference_index: the reference model has no 3D points")
    point_ids = np.concatenate(ids)
    xyz = np.array([rec.point3D(int(i)).xyz for i in point_ids], np.float64)
    return ReferenceIndex(np.ascontiguousarray(np.concatenate(desc)), point_ids, xyz)


def _failed(num_matches: int, num_inliers: int = 0, error: float = np.inf, pose=None) -> FrameRegistration:
    pose = np.full(7, np.nan) if pose is None else pose
    return FrameRegistration(False, pose, np.zeros((0, 2)), np.zeros(0, np.int64), num_matches, num_inliers, error)


def match_to_reference(descriptors: np.ndarray, index: ReferenceIndex, ratio: float,
                       checks: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """2D–3D candidates: ``(query, rows)`` indices into ``descriptors`` and into ``index``, nearest neighbours
    passing the ratio test, one 2D feature per 3D point (the first in keypoint order)."""
    nearest, good = index.search(checks).nearest(descriptors, ratio)
    query = np.flatnonzero(good)
    _, first = np.unique(index.point3D_ids[nearest[query]], return_index=True)
    return query[first], nearest[query][first]


def register_frame(image: np.ndarray, camera: CameraModel | object, index: ReferenceIndex,
                   options: RegistrationOptions = RegistrationOptions()) -> FrameRegistration:
    """Register one frame (gray or BGR uint8) of a camera (a :class:`~bcmocap.cameras.CameraModel` in
    OpenCV's pixel convention, or a ``pycolmap.Camera``) to the reference (see the module docstring)."""
    pycolmap = load_pycolmap()

    cam = to_pycolmap(camera) if isinstance(camera, CameraModel) else camera
    keypoints, desc = extract_sift(image, max_features=options.max_features)
    if len(desc) < 2:
        return _failed(0)
    query, rows = match_to_reference(desc, index, options.ratio, options.checks)
    if len(query) < 4:
        return _failed(len(query))
    xy = keypoints[query, :2].astype(np.float64) + 0.5  # OpenCV -> COLMAP pixels
    xyz = index.xyz[rows]
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = options.ransac_max_error_px
    est.ransac.random_seed = 0  # the same frame gives the same pose (COLMAP's default, -1, seeds at random)
    result = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, cam, est)
    if result is None:
        return _failed(len(query))
    inl = np.asarray(result["inlier_mask"], bool)
    cam_from_world = result["cam_from_world"]
    proj = np.asarray(cam.img_from_cam(np.asarray(cam_from_world * xyz[inl])), np.float64)
    errors = np.linalg.norm(proj - xy[inl], axis=1)
    mean_error = float(np.nanmean(errors)) if len(errors) else np.inf
    pose = world_from_camera_wxyz_xyz(cam_from_world)
    ok = int(inl.sum()) > options.min_inliers and mean_error < options.max_mean_error_px
    ok = ok and second_pose(xy - 0.5, xyz, inl, cam_from_world, cam, options) is None
    if not ok:
        return _failed(len(query), int(inl.sum()), mean_error, pose)
    return FrameRegistration(True, pose, xy[inl] - 0.5, index.point3D_ids[rows[inl]], len(query), int(inl.sum()),
                             mean_error)


def register_trial(capture, trial: str, camera: str | int, index: ReferenceIndex, *, stride: int = 1,
                   start: int = 0, stop: int | None = None, options: RegistrationOptions = RegistrationOptions(),
                   progress: Callable[[int, int], None] | None = None) -> TrialRegistration:
    """Register every ``stride``-th frame of one camera's video of a trial.

    Args:
        capture: a :class:`~bcmocap.frontend.capture.Capture`; trial, camera: names in it.
        progress: called as ``progress(done, total)`` after each frame (``total`` may be an estimate).

    Returns:
        :class:`TrialRegistration` with ``(T, 7)`` poses and the registered mask.
    """
    cam = to_pycolmap(capture.cameras[capture.camera_index(camera)].intrinsics)
    info = capture.video_info(trial, camera)
    end = info.num_frames if stop is None else min(stop, info.num_frames)
    total = max(0, -(-(end - start) // stride))
    frames, results = [], []
    for k, (frame, gray) in enumerate(capture.frames(trial, camera, stride=stride, start=start, stop=stop, gray=True)):
        frames.append(int(frame))
        results.append(register_frame(gray, cam, index, options))
        if progress is not None:
            progress(k + 1, max(total, k + 1))
    poses = np.array([r.world_from_camera for r in results]).reshape(-1, 7)
    mask = np.array([r.registered for r in results], bool)
    poses[~mask] = np.nan
    return TrialRegistration(np.array(frames, np.int64), poses, mask, results)

