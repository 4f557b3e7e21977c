"""Reference reconstruction from the reference photos (§4.1): OpenCV SIFT, FLANN matching with a ratio
test, fundamental-matrix RANSAC, then pycolmap's incremental mapper.

:func:`build_reference` runs the whole chain on a folder of photos:

1. :func:`extract_sift` — ``cv2.SIFT_create`` keypoints (x, y, scale, orientation) and uint8 descriptors;
2. :func:`match_descriptors` — approximate nearest neighbours (FLANN k-d trees), Lowe's ratio test and,
   by default, mutual consistency;
3. :func:`verify_matches` — ``cv2.findFundamentalMat`` with RANSAC keeps the epipolar inliers;
4. keypoints (shifted by +0.5 px into COLMAP's pixel convention), descriptors and the verified matches
   go into a pycolmap database; ``pycolmap.geometric_verification`` estimates each pair's two-view
   geometry from them (RANSAC threshold as in step 3) and ``pycolmap.incremental_mapping`` builds the
   model;
5. pycolmap's verification and mapping are repeated with new seeds while the model leaves photos out or
   its mean reprojection error is poor (``attempts``, ``good_error_px``); the best model is kept. Steps 2–3
   are deterministic (FLANN's trees from :data:`FLANN_SEED`; OpenCV's RANSAC seeds itself), so they run once.

6. with the photos' camera known, the model is checked against one built from only the *distinctive* pairs (the
   geometry of their coarse features' matches, :func:`verify_distinctive`) whose relative rotations agree with
   one set of absolute rotations (:mod:`~bcmocap.frontend.pair_rotations`): pairs verified on a repeated
   pattern's aliases make a model metres wrong; if the two disagree, the second is kept, with its points
   triangulated again from every verified pair's matches (its photos held where they are).

The result, :class:`ReferenceModel`, holds the largest ``pycolmap.Reconstruction`` and reports how many
photos were registered and the mean reprojection error.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..cameras import CameraModel
from ..geometry import similarity
from ..io.colmap import to_pycolmap
from ..native_crashes import load_pycolmap
from .threads import default_threads

__all__ = ["DescriptorIndex", "ReferenceModel", "build_reference", "extract_sift", "match_descriptors", "models_agree",
           "verify_matches"]


def extract_sift(image: np.ndarray, *, max_features: int = 8000) -> tuple[np.ndarray, np.ndarray]:
    """SIFT features of an image (BGR or gray uint8).

    Returns:
        ``keypoints (N, 4)`` float32 (x, y in OpenCV pixels, scale, orientation in radians) and
        ``descriptors (N, 128)`` uint8.
    """
    import cv2

    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    sift = cv2.SIFT_create(nfeatures=max_features)
    kps, desc = sift.detectAndCompute(gray, None)
    if desc is None or not kps:
        return np.zeros((0, 4), np.float32), np.zeros((0, 128), np.uint8)
    keypoints = np.column_stack([cv2.KeyPoint_convert(kps), [k.size for k in kps], np.deg2rad([k.angle for k in kps])])
    keypoints = keypoints.astype(np.float32)
    return keypoints, uint8_descriptors(desc)


def uint8_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """``(N, 128)`` SIFT descriptors as uint8 (rounded, clipped to 0–255), the form features are kept in.
    Already uint8 descriptors are returned as they are (a view: memory-mapped ones stay on disk)."""
    descriptors = np.asarray(descriptors)
    if descriptors.dtype == np.uint8:
        return descriptors.reshape(-1, 128)
    return np.clip(np.round(np.asarray(descriptors).reshape(-1, 128)), 0, 255).astype(np.uint8)


FLANN_SEED = 0
"""Seed of OpenCV's RNG when FLANN builds its randomised k-d trees: the same descriptors always give the same
trees, whichever thread builds them and whatever it did before (OpenCV's RNG is per thread, and a thread of a
pool builds the trees of whichever pairs it is handed). Anything drawing on OpenCV's RNG afterwards in that
thread must seed it itself (:func:`verify_matches` takes a ``seed``)."""


class DescriptorIndex:
    """FLANN randomised k-d trees over ``(M, 128)`` descriptors, searched with arrays (no per-match Python
    objects; OpenCV releases the GIL, so threads search in parallel). Each thread gets its own copy of the
    trees, built on first use from :data:`FLANN_SEED`, so every copy is the same and so are the matches.

    Args:
        descriptors: ``(M, 128)`` uint8 or float32; trees: k-d trees; checks: leaves visited per query
            (fewer is faster and more approximate).
    """

    def __init__(self, descriptors: np.ndarray, *, trees: int = 4, checks: int = 64):
        import threading

        self.descriptors = np.ascontiguousarray(descriptors, np.float32).reshape(-1, 128)
        self.trees, self.checks = int(trees), int(checks)
        self._local = threading.local()
        self.copies = 0  # threads that built their copy of the trees

    def __getstate__(self) -> dict:
        """Pickled without the trees (a cluster task gets the descriptors and builds the same trees)."""
        return {"descriptors": self.descriptors, "trees": self.trees, "checks": self.checks}

    def __setstate__(self, state: dict) -> None:
        import threading

        self.descriptors, self.trees, self.checks = state["descriptors"], state["trees"], state["checks"]
        self._local = threading.local()
        self.copies = 0

    def nearest(self, query: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
        """``(nearest (N,), good (N,))``: index of each query row's nearest neighbour (−1 when the index holds
        fewer than two rows) and whether it passes Lowe's ratio test (distance < ``ratio`` × second)."""
        import cv2

        query = np.ascontiguousarray(query, np.float32).reshape(-1, 128)
        if len(self.descriptors) < 2 or not len(query):
            return np.full(len(query), -1, np.int64), np.zeros(len(query), bool)
        flann = getattr(self._local, "flann", None)
        if flann is None:
            cv2.setRNGSeed(FLANN_SEED)  # this thread's RNG: the trees do not depend on timing or history
            flann = self._local.flann = cv2.flann_Index(self.descriptors, {"algorithm": 1, "trees": self.trees})
            self.copies += 1
        idx, dist2 = flann.knnSearch(query, 2, params={"checks": self.checks})
        return idx[:, 0].astype(np.int64), dist2[:, 0] < ratio**2 * dist2[:, 1]  # squared L2 distances


def match_descriptors(desc_a: np.ndarray, desc_b: np.ndarray, *, ratio: float = 0.8,
                      mutual: bool = True, checks: int = 64, index_a: DescriptorIndex | None = None,
                      index_b: DescriptorIndex | None = None, rows_b: np.ndarray | None = None) -> np.ndarray:
    """Approximate nearest-neighbour matches (FLANN k-d trees, :class:`DescriptorIndex`) passing Lowe's
    ratio test. ``index_a``/``index_b``: the index of ``desc_a``/``desc_b`` if already built (its trees are
    the ones built here, :data:`FLANN_SEED`, so the matches are the same). ``rows_b`` (mutual only): just the
    matches of these rows of ``desc_b``, found by searching from them (e.g. the few hundred features of a
    registered frame that observe a 3D point, instead of its thousands).

    Each query's neighbours do not depend on the other queries, so the way back searches only the rows the
    first way chose (a sixth of them or fewer between body-camera frames), and ``rows_b`` gives the rows of
    the whole matching whose ``desc_b`` row is in ``rows_b``: the matches are those of every row searched
    both ways.

    Returns:
        ``(K, 2)`` uint32 pairs of indices into ``desc_a`` and ``desc_b``, in the order of ``desc_a``; with
        ``mutual`` only pairs that are each other's nearest neighbour (and pass the test both ways).
    """
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.uint32)
    if rows_b is not None:
        if not mutual:
            raise ValueError("match_descriptors: rows_b needs mutual matching")
        rows_b = np.asarray(rows_b, np.int64)
        index_a = index_a or DescriptorIndex(desc_a, checks=checks)
        index_b = index_b or DescriptorIndex(desc_b, checks=checks)
        ba, good_ba = index_a.nearest(np.asarray(desc_b)[rows_b], ratio)  # each row's nearest in desc_a
        rows_b, ba = rows_b[good_ba], ba[good_ba]
        chosen, back = np.unique(ba, return_inverse=True)
        ab, good_ab = index_b.nearest(np.asarray(desc_a)[chosen], ratio)
        keep = (ab[back] == rows_b) & good_ab[back]
        return np.stack([ba[keep], rows_b[keep]], axis=1)[np.argsort(ba[keep], kind="stable")].astype(np.uint32)
    ab, good_ab = (index_b or DescriptorIndex(desc_b, checks=checks)).nearest(desc_a, ratio)
    idx = np.flatnonzero(good_ab)
    if mutual and len(idx):
        chosen, back = np.unique(ab[idx], return_inverse=True)
        ba, good_ba = (index_a or DescriptorIndex(desc_a, checks=checks)).nearest(np.asarray(desc_b)[chosen], ratio)
        idx = idx[(ba[back] == idx) & good_ba[back]]
    return np.stack([idx, ab[idx]], axis=1).astype(np.uint32)


def verify_matches(xy_a: np.ndarray, xy_b: np.ndarray, matches: np.ndarray, *, threshold_px: float = 1.5,
                   confidence: float = 0.999, min_inliers: int = 15) -> np.ndarray:
    """Matches consistent with one fundamental matrix (``cv2.findFundamentalMat``, RANSAC). OpenCV's RANSAC
    draws its samples from a generator of its own with a fixed seed, not from ``cv2.setRNGSeed``'s (which
    FLANN's trees use, :data:`FLANN_SEED`): the same matches always give the same inliers.

    Returns:
        The inlier rows of ``matches`` (empty when fewer than ``min_inliers`` survive).
    """
    import cv2

    if len(matches) < max(min_inliers, 8):
        return np.zeros((0, 2), np.uint32)
    pa = np.asarray(xy_a, np.float64)[matches[:, 0], :2]
    pb = np.asarray(xy_b, np.float64)[matches[:, 1], :2]
    F, mask = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, threshold_px, confidence, 10000)
    if F is None or mask is None:
        return np.zeros((0, 2), np.uint32)
    inliers = matches[mask.ravel().astype(bool)]
    return inliers if len(inliers) >= min_inliers else np.zeros((0, 2), np.uint32)


DISTINCTIVE_SIZE = 0.008
"""The smallest keypoint of a distinctive match (:func:`verify_distinctive`), as a fraction of the photo's larger side
(8 px across on the studio's 1024-pixel reference photos). On four of the studio's repeated rooms (development
measurement), the pairs verified this way were 189 right and 51 aliases (every match: 190 and 904); at 0.010, 135 and
11, but with the rotation check after them the models kept fewer photos (docs/benchmarks/suite.md)."""


def verify_distinctive(keypoints_a: np.ndarray, keypoints_b: np.ndarray, matches: np.ndarray, *,
                       min_size_px: float, threshold_px: float = 1.5, min_distinctive: int = 8,
                       min_inliers: int = 15) -> np.ndarray:
    """Matches consistent with the epipolar geometry of the pair's *distinctive* matches: those whose keypoints
    are both at least ``min_size_px`` across (SIFT's size), so that their descriptors span more than one tile,
    brick or panel of a repeated pattern.

    On a floor of tiles printed with a few faces, a fine feature's nearest descriptor in another photo is often the
    same face on another tile seen at the same distance, and the fundamental matrix with most inliers is then an
    alias (the studio's repeated room: 225 of 275 verified pairs). The coarse features' fundamental matrix
    (RANSAC, at least ``min_distinctive`` inliers) picks the right geometry, or none where the photos share only the
    pattern; every match within twice ``threshold_px`` of its epipolar lines is then verified again
    (:func:`verify_matches`, ``min_inliers``).

    Returns:
        The rows of ``matches`` kept (empty when the distinctive matches do not agree on a geometry).
    """
    import cv2

    empty = np.zeros((0, 2), np.uint32)
    if len(matches) < max(min_inliers, 8):
        return empty
    xy_a = np.asarray(keypoints_a, np.float64)[matches[:, 0]]
    xy_b = np.asarray(keypoints_b, np.float64)[matches[:, 1]]
    coarse = (xy_a[:, 2] >= min_size_px) & (xy_b[:, 2] >= min_size_px)
    seed = verify_matches(keypoints_a, keypoints_b, matches[coarse], threshold_px=threshold_px,
                          min_inliers=min_distinctive)
    if not len(seed):
        return empty
    fundamental, _ = cv2.findFundamentalMat(np.asarray(keypoints_a, np.float64)[seed[:, 0], :2],
                                            np.asarray(keypoints_b, np.float64)[seed[:, 1], :2], cv2.FM_8POINT)
    if fundamental is None or fundamental.shape != (3, 3):
        return empty
    lines = np.column_stack([xy_a[:, :2], np.ones(len(xy_a))]) @ fundamental.T  # epipolar lines in b
    distance = np.abs(np.sum(lines[:, :2] * xy_b[:, :2], 1) + lines[:, 2]) / np.hypot(lines[:, 0], lines[:, 1])
    return verify_matches(keypoints_a, keypoints_b, matches[distance < 2 * threshold_px], threshold_px=threshold_px,
                          min_inliers=min_inliers)


@dataclasses.dataclass
class ReferenceModel:
    """The reference reconstruction.

    Attributes:
        reconstruction: the largest ``pycolmap.Reconstruction`` the mapper built.
        image_names: every photo given; registered: those in the model.
        mean_reprojection_error_px: over all observations of the model's 3D points.
        num_points3D: 3D points in the model.
        database_path: the pycolmap database (keypoints, descriptors, matches, two-view geometries).
        pair_inliers: ``{(name_a, name_b): number of F-RANSAC inliers}`` of the pairs the model's poses come from
            (every verified pair, or the consistent distinctive ones of a replacing model, whose points come from
            every verified pair in ``database_path``).
        seconds: wall time per stage (``features``, ``matching``, ``mapping`` — every run of the mapper and the
            triangulation of a replacing model —, and
            ``rotations`` where the pairs' rotations were checked).
        mapping_attempts: how many times the mapper ran (see ``attempts`` of :func:`build_reference`; the check's
            second model included).
        distinctive_pairs: pairs verified on their distinctive matches (:func:`verify_distinctive`), the pairs the
            rotation check weighs (0 where no check was asked for: no camera, or ``consistent_rotations`` off).
        inconsistent_pairs: distinctive pairs whose rotations disagreed with the consistent set's
            (``consistent_rotations`` of :func:`build_reference`; 0 where nothing was checked).
        rotation_check: "agreed" (the model from every verified pair was checked against the one from the
            rotation-consistent distinctive pairs, or those include every verified pair), "replaced" (it
            disagreed, and the model is the one from the consistent distinctive pairs, its points triangulated
            from every verified pair) or "not checked" (no camera, or one bcmocap does not read; no three photos
            whose rotations close a loop; the consistent pairs' model registered fewer than three photos; or
            turned off).
    """

    reconstruction: object
    image_names: tuple[str, ...]
    registered: tuple[str, ...]
    mean_reprojection_error_px: float
    num_points3D: int
    database_path: Path
    pair_inliers: dict
    seconds: dict
    mapping_attempts: int = 1
    inconsistent_pairs: int = 0
    rotation_check: str = "not checked"
    distinctive_pairs: int = 0

    @property
    def num_registered(self) -> int:
        return len(self.registered)


def _reader_options(camera):
    pycolmap = load_pycolmap()

    options = pycolmap.ImageReaderOptions()
    if camera is None:
        return options
    if isinstance(camera, CameraModel):
        camera = to_pycolmap(camera)
    options.camera_model = camera.model.name
    options.camera_params = ",".join(f"{float(p):.12g}" for p in camera.params)
    return options


def _match_pairs(names, features, *, ratio, threshold_px, min_inliers, distinctive_px: dict | None = None,
                 min_distinctive: int = 8, workers: int | None = None) -> tuple[dict, dict]:
    """``({(name_a, name_b): (M, 2) verified matches}, {pair: distinctive matches})`` over all pairs of photos with
    enough inliers (:func:`verify_matches`; :func:`verify_distinctive` with the smaller of the two photos'
    ``distinctive_px`` where given, else no distinctive pairs). Pairs run in threads, since FLANN and OpenCV's
    RANSAC release the GIL; both are kept in pair order."""
    from concurrent.futures import ThreadPoolExecutor

    indices = {name: DescriptorIndex(features[name][1]) for name in names}  # trees built once per photo and thread
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]

    def pair(ab):
        (ka, da), (kb, db) = features[ab[0]], features[ab[1]]
        matches = match_descriptors(da, db, ratio=ratio, index_a=indices[ab[0]], index_b=indices[ab[1]])
        verified = verify_matches(ka, kb, matches, threshold_px=threshold_px, min_inliers=min_inliers)
        if distinctive_px is None:
            return verified, np.zeros((0, 2), np.uint32)
        smallest = min(distinctive_px[ab[0]], distinctive_px[ab[1]])
        return verified, verify_distinctive(ka, kb, matches, min_size_px=smallest, threshold_px=threshold_px,
                                            min_distinctive=min_distinctive, min_inliers=min_inliers)

    with ThreadPoolExecutor(max_workers=max(1, workers or default_threads())) as pool:
        found = list(pool.map(pair, pairs))
    return ({ab: m for ab, (m, _) in zip(pairs, found) if len(m)},
            {ab: m for ab, (_, m) in zip(pairs, found) if len(m)})


def _write_database(db_path: Path, image_dir: Path, names, camera, features, verified) -> Path:
    """A fresh pycolmap database holding the photos, their keypoints, descriptors and matches."""
    pycolmap = load_pycolmap()

    if db_path.exists():
        db_path.unlink()
    pycolmap.Database.open(str(db_path)).close()
    pycolmap.import_images(str(db_path), str(image_dir), pycolmap.CameraMode.SINGLE, list(names),
                           _reader_options(camera))
    with pycolmap.Database.open(str(db_path)) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        for name in names:
            kp, desc = features[name]
            kp = kp.copy()
            kp[:, :2] += 0.5  # OpenCV -> COLMAP pixel convention
            db.write_keypoints(ids[name], kp)
            db.write_descriptors(ids[name], pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, desc))
        for (a, b), m in verified.items():
            db.write_matches(ids[a], ids[b], np.ascontiguousarray(m, np.uint32))
    return db_path


def build_reference(image_dir: str | os.PathLike, image_names: Sequence[str] | None = None, *,
                    camera: CameraModel | object | None = None, workdir: str | os.PathLike | None = None,
                    max_features: int = 8000, ratio: float = 0.8, threshold_px: float = 1.5,
                    min_inliers: int = 15, refine_intrinsics: bool = True, random_seed: int = 0,
                    attempts: int = 3, good_error_px: float = 0.5, consistent_rotations: bool = True,
                    rotation_tolerance_deg: float = 1.5, centre_tolerance: float = 0.05,
                    distinctive_size: float = DISTINCTIVE_SIZE, min_distinctive: int = 8) -> ReferenceModel:
    """Build the reference model of a set of photos (the module docstring lists the steps).

    Args:
        image_dir: folder of the photos; image_names: which ones (default: every .jpg/.jpeg/.png, sorted).
        camera: intrinsics shared by all photos (a :class:`~bcmocap.cameras.CameraModel` in OpenCV's
            pixel convention, or a ``pycolmap.Camera`` in COLMAP's); ``None`` lets pycolmap guess.
        workdir: where the database and the model go (default: a temporary folder that is kept).
        max_features: SIFT features per photo; ratio: Lowe's ratio; threshold_px: RANSAC epipolar
            threshold; min_inliers: fewest verified matches for a pair to be written.
        refine_intrinsics: let bundle adjustment refine focal length and distortion.
        random_seed: seed of pycolmap's two-view RANSAC and of the mapper (OpenCV's F-RANSAC and FLANN's trees
            are seeded on their own); the same seed and photos give the same model on one machine.
        attempts: a poor two-view geometry can lead the incremental mapper to a distorted model (seen on
            small photo sets: mean reprojection error ~1 px instead of ~0.15 px, poses tens of degrees
            off). pycolmap's verification and mapping are repeated with seeds ``random_seed + k`` until a model
            registers every photo with mean reprojection error <= ``good_error_px``, at most ``attempts``
            times; the model with most photos, then least error, is kept.
        consistent_rotations: with a ``camera``, check the model against a second one built from only the
            distinctive pairs (:func:`verify_distinctive`) whose relative rotations agree with one set of absolute
            rotations within ``rotation_tolerance_deg`` (:mod:`~bcmocap.frontend.pair_rotations`): pairs verified
            on the aliases of a repeated pattern lead the mapper to a model metres wrong with a small reprojection
            error. When the second registers at least three photos and the two place their common photos
            differently (RMS of the camera centres, after a similarity, over ``centre_tolerance`` of their spread,
            or fewer than three in common), the second replaces the first; when they agree the first, with more
            photos, is kept.
        distinctive_size: the smallest keypoint of a distinctive match, as a fraction of the photo's larger side
            (0.008: 8 px across on a 1024-pixel photo); min_distinctive: fewest distinctive inliers for a pair
            to be checked.

    Raises:
        ValueError: if the folder or a photo is missing or unreadable, or nothing could be reconstructed.
    """
    import cv2
    pycolmap = load_pycolmap()

    if attempts < 1:
        raise ValueError(f"attempts must be >= 1, got {attempts}")
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise ValueError(f"{image_dir}: photo folder does not exist")
    if image_names is None:
        image_names = sorted(p.name for p in image_dir.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    names = tuple(image_names)
    if len(names) < 2:
        raise ValueError(f"{image_dir}: need at least 2 photos, found {len(names)}")
    work = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="bcmocap_reference_"))
    work.mkdir(parents=True, exist_ok=True)
    seconds = {}

    clock = time.perf_counter()
    features, distinctive_px = {}, {}
    for name in names:
        image = cv2.imread(str(image_dir / name), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ValueError(f"{image_dir / name}: missing or not a readable image")
        features[name] = extract_sift(image, max_features=max_features)
        distinctive_px[name] = distinctive_size * max(image.shape)
    seconds["features"] = time.perf_counter() - clock

    checked = camera is not None and consistent_rotations
    clock = time.perf_counter()  # matching is deterministic (seeded trees, OpenCV's own RANSAC seed): once
    verified, distinctive = _match_pairs(names, features, ratio=ratio, threshold_px=threshold_px,
                                         min_inliers=min_inliers, distinctive_px=distinctive_px if checked else None,
                                         min_distinctive=min_distinctive)
    seconds["matching"] = time.perf_counter() - clock
    seconds["mapping"] = 0.0
    mapping = dict(image_dir=image_dir, names=names, camera=camera, features=features, threshold_px=threshold_px,
                   refine_intrinsics=refine_intrinsics, random_seed=random_seed, attempts=attempts,
                   good_error_px=good_error_px, seconds=seconds)
    best, runs = _map(work, verified, **mapping)
    check, inconsistent = "not checked", 0
    if checked and best is not None:
        clock = time.perf_counter()
        estimated, kept = _rotation_consistent(names, features, distinctive, camera, threshold_px,
                                               rotation_tolerance_deg)
        seconds["rotations"] = time.perf_counter() - clock
        inconsistent = len(estimated - kept) if kept else 0
        if kept and kept >= set(verified):  # every verified pair distinctive and consistent: nothing to compare
            check = "agreed"
        elif kept:
            consistent, more = _map(work / "consistent", {p: m for p, m in distinctive.items() if p in kept}, **mapping)
            runs += more
            if consistent is not None and consistent[1].num_reg_images() >= 3:
                if models_agree(_camera_centres(consistent[1]), _camera_centres(best[1]), centre_tolerance):
                    check = "agreed"
                else:
                    clock = time.perf_counter()
                    check, best = "replaced", _triangulated_from_every_pair(consistent, best[3], image_dir,
                                                                             work / "consistent" / "triangulated")
                    seconds["mapping"] += time.perf_counter() - clock
    if best is None:
        raise ValueError(f"{image_dir}: pycolmap could not reconstruct the photos "
                         f"({len(verified)} of {len(names) * (len(names) - 1) // 2} pairs verified)")
    _, rec, used, db_path = best
    registered = tuple(sorted(rec.image(i).name for i in rec.reg_image_ids()))
    return ReferenceModel(rec, names, registered, float(rec.compute_mean_reprojection_error()), int(rec.num_points3D()),
                          db_path, {k: len(v) for k, v in used.items()}, seconds, runs, inconsistent, check,
                          len(distinctive) if checked else 0)


def _map(work: Path, verified: dict, *, image_dir, names, camera, features, threshold_px, refine_intrinsics,
         random_seed, attempts, good_error_px, seconds) -> tuple[tuple | None, int]:
    """pycolmap's verification and incremental mapping of ``verified`` in ``work``, repeated with new seeds while
    the model leaves photos out or its error is poor: ``((score, reconstruction, verified, database), runs)``, the
    best model (None when the mapper built nothing) and how many times the mapper ran."""
    pycolmap = load_pycolmap()

    best = None
    for attempt in range(attempts):
        seed = random_seed + attempt
        clock = time.perf_counter()
        db_name = "database.db" if attempt == 0 else f"database_attempt{attempt}.db"
        work.mkdir(parents=True, exist_ok=True)
        db_path = _write_database(work / db_name, image_dir, names, camera, features, verified)
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = seed
        # COLMAP's default 4 px lets a homography absorb the parallax of a room seen from nearby
        # viewpoints; the pair is then called planar and the mapper may start from the wrong
        # homography decomposition.
        verification.ransac.max_error = threshold_px
        pycolmap.geometric_verification(str(db_path), two_view_geometry_options=verification)
        options = pycolmap.IncrementalPipelineOptions()
        options.random_seed = seed
        # One thread: the same photos give the same model to the last bit. With its threads the mapper's bundle
        # adjustments summed in another order each time (camera centres 2e-15 apart on the studio's 24 textured-room
        # photos), and a run's registrations can grow such differences (a realistic walk: 1.61 or 2.29 cm). Mapping
        # 24 photos took as long either way, 48 a few seconds more (20-24 s against 20 s).
        options.num_threads = 1
        if not refine_intrinsics:
            options.ba_refine_focal_length = False
            options.ba_refine_extra_params = False
        out = work / "sparse" / f"attempt{attempt}"
        out.mkdir(parents=True, exist_ok=True)
        models = pycolmap.incremental_mapping(str(db_path), str(image_dir), str(out), options=options)
        seconds["mapping"] += time.perf_counter() - clock
        if not models:
            continue
        rec = max(models.values(), key=lambda r: r.num_reg_images())
        score = (rec.num_reg_images(), -float(rec.compute_mean_reprojection_error()))
        if best is None or score > best[0]:
            best = (score, rec, verified, db_path)
        if score[0] == len(names) and -score[1] <= good_error_px:
            break
    return best, attempt + 1


def _triangulated_from_every_pair(consistent: tuple, database: Path, image_dir: Path, out: Path) -> tuple:
    """The consistent model (``(score, reconstruction, pairs, database)`` of :func:`_map`) with its points
    triangulated again, its photos' poses held, from the matches of every verified pair in ``database``
    (``pycolmap.triangulate_points``: tracks of three photos or more whose rays meet; an alias's matches do not
    meet under the right poses). The consistent pairs alone leave the model sparse: on the repeated room's walk
    (seed 1) 2507 points, and 6550 this way, the photos where they were; the run from the sparse one tracked its
    map from too few points and came out at 18.0 cm. Returns the same kind of tuple, with ``database`` (pycolmap
    changes the given reconstruction in place and returns it). Both databases are :func:`_write_database`'s of the
    same photos in the same order, so they number the photos alike."""
    pycolmap = load_pycolmap()

    score, reconstruction, pairs, _ = consistent
    out.mkdir(parents=True, exist_ok=True)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = 1  # bitwise reproducible, as the mapping (see _map)
    triangulated = pycolmap.triangulate_points(reconstruction, str(database), str(image_dir), str(out),
                                               clear_points=False, options=options)
    return score, triangulated, pairs, database


def _camera_centres(reconstruction) -> dict:
    """``{photo name: (3,) camera centre}`` of a reconstruction's registered photos."""
    return {reconstruction.image(i).name: np.asarray(reconstruction.image(i).projection_center(), np.float64)
            for i in reconstruction.reg_image_ids()}


def models_agree(centres: dict, other: dict, tolerance: float) -> bool:
    """Whether two models place their common photos alike: at least three in common, and their camera centres
    (``{name: (3,)}``, each model's own frame and scale) within ``tolerance`` × their spread (RMS distance from
    their mean in ``other``) of each other after the best similarity (Umeyama's)."""
    common = sorted(set(centres) & set(other))
    if len(common) < 3:
        return False
    a = np.array([centres[n] for n in common], np.float64)
    b = np.array([other[n] for n in common], np.float64)
    scale, rotation, shift = similarity(a, b)
    spread = float(np.sqrt(((b - b.mean(0)) ** 2).sum(1).mean()))
    rms = float(np.sqrt(((b - (scale * a @ rotation.T + shift)) ** 2).sum(1).mean()))
    return rms <= tolerance * spread


def _rotation_consistent(names, features, verified: dict, camera, threshold_px: float,
                         tolerance_deg: float) -> tuple[set, set]:
    """``(pairs with a rotation estimate, those that rotation_consistent_pairs keeps)`` (keypoints turned into rays
    by ``camera``; the RANSAC threshold is ``threshold_px`` at the image centre). Both empty for a pycolmap camera
    model that bcmocap does not read."""
    from ..io.colmap import from_pycolmap
    from .pair_rotations import pair_rotations, rotation_consistent_pairs

    if not isinstance(camera, CameraModel):
        try:
            camera = from_pycolmap(camera)
        except ValueError:
            return set(), set()
    centre = np.array([[0.5 * (camera.width - 1), 0.5 * (camera.height - 1)]])
    ray0, ray1 = np.asarray(camera.unproject(np.concatenate([centre, centre + [[1.0, 0.0]]])), np.float64)
    radians_per_px = float(np.arccos(np.clip(ray0 @ ray1, -1.0, 1.0)))
    pixels = [np.asarray(features[name][0][:, :2], np.float64) for name in names]  # one unprojection for all
    rays = np.split(np.asarray(camera.unproject(np.concatenate(pixels)), np.float64),
                    np.cumsum([len(p) for p in pixels])[:-1])
    bearings = dict(zip(names, rays))
    rotations = pair_rotations(verified, bearings, threshold_rad=threshold_px * radians_per_px)
    return set(rotations), rotation_consistent_pairs(names, rotations, {pair: len(m) for pair, m in verified.items()},
                                                     tolerance_deg=tolerance_deg)


def save_reference(model: ReferenceModel, folder: str | os.PathLike) -> Path:
    """Write the model (``folder/model/``, COLMAP's binary format) and its report (``folder/reference.json``)
    so :func:`load_reference` can resume without rebuilding it. Returns the JSON's path."""
    import json

    folder = Path(folder)
    (folder / "model").mkdir(parents=True, exist_ok=True)
    model.reconstruction.write(str(folder / "model"))
    report = {"image_names": list(model.image_names), "registered": list(model.registered),
              "mean_reprojection_error_px": model.mean_reprojection_error_px, "num_points3D": model.num_points3D,
              "database": os.path.relpath(model.database_path, folder),
              "pair_inliers": [[a, b, n] for (a, b), n in model.pair_inliers.items()],
              "seconds": model.seconds, "mapping_attempts": model.mapping_attempts,
              "inconsistent_pairs": model.inconsistent_pairs, "rotation_check": model.rotation_check,
              "distinctive_pairs": model.distinctive_pairs}
    from ..atomic import atomic_path

    path = folder / "reference.json"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(report, indent=1))
    return path


def load_reference(folder: str | os.PathLike) -> ReferenceModel:
    """Read a model written by :func:`save_reference`.

    Raises:
        ValueError: naming the file that is missing or unreadable.
    """
    import json

    pycolmap = load_pycolmap()

    folder = Path(folder)
    path = folder / "reference.json"
    try:
        report = json.loads(path.read_text())
        database = folder / report["database"]
    except (OSError, ValueError, KeyError) as err:
        raise ValueError(f"{path}: not a readable reference report ({err})") from None
    if not database.is_file():
        raise ValueError(f"{database}: the reference database is missing")
    try:
        rec = pycolmap.Reconstruction(str(folder / "model"))
    except Exception as err:  # pycolmap raises its own error types
        raise ValueError(f"{folder / 'model'}: not a readable reconstruction ({err})") from None
    return ReferenceModel(rec, tuple(report["image_names"]), tuple(report["registered"]),
                          float(report["mean_reprojection_error_px"]), int(report["num_points3D"]), database,
                          {(a, b): n for a, b, n in report["pair_inliers"]}, dict(report["seconds"]),
                          int(report["mapping_attempts"]), int(report.get("inconsistent_pairs", 0)),
                          str(report.get("rotation_check", "not checked")), int(report.get("distinctive_pairs", 0)))
