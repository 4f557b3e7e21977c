"""Photo pairs whose relative rotations agree with one set of absolute rotations (the reference photos' pairs).

A pair of photos that sees a repeated pattern (floor tiles, a brick wall) can be verified by a fundamental matrix
fitted to aliases: tile A of one photo matched to tile B of the other. Such a pair has hundreds of inliers and a
relative pose that is wrong, and a few dozen of them lead the incremental mapper to a model that registers every
photo with a small reprojection error and is metres wrong (the studio's repeated room: the model from every
pair about 1.1 m off at the median camera). Most such pairs give a relative rotation that loops of correct pairs
contradict (the loop constraints of Zach, Klopschitz and Pollefeys, CVPR 2010): in a first version of that room,
202 of the 213 wrong pairs' rotations were more than 2° off. An alias that is a pure shift along one periodic
plane keeps the true rotation and passes: in the suite's repeated room the model from the consistent pairs
still placed 5 of 24 photos 1.7–2.6 m off.

:func:`rotation_consistent_pairs` takes each pair's relative rotation (:func:`pair_rotations`: pycolmap's two-view
geometry of its matches' bearings), then grows absolute rotations from triplets whose loop closes:
a photo joins when at least two of its pairs with photos already placed agree on its rotation. The pairs kept are
those between placed photos whose relative rotation matches the absolute ones; the largest such set over the
seed triplets wins. Photos that never join lose their pairs (the mapper leaves them out rather than placing them
wrongly).
"""

from __future__ import annotations

import itertools

import numpy as np

from ..geometry import rotation_from_covariance

__all__ = ["pair_rotations", "rotation_consistent_pairs"]


def _angle_deg(rotation: np.ndarray) -> float:
    """Angle (degrees) of a 3×3 rotation matrix."""
    return float(np.degrees(np.arccos(np.clip(0.5 * (np.trace(rotation) - 1.0), -1.0, 1.0))))


_VIRTUAL_FOCAL = 1000.0  # normalised image coordinates are scaled by this into the pinhole camera given to pycolmap


def pair_rotations(verified: dict, bearings: dict, *, threshold_rad: float, seed: int = 0) -> dict:
    """``{(a, b): (3, 3) R}`` with ``x_b = R x_a + t``: each pair's relative rotation from its matches' two-view
    geometry (``pycolmap.estimate_calibrated_two_view_geometry``, then ``estimate_two_view_geometry_pose``).

    pycolmap fits the essential matrix and a homography side by side and, where the matches lie mostly on one
    plane (a wall, the floor), takes the pose from the homography's decomposition; the five-point essential matrix
    alone (``cv2.findEssentialMat``, used here before) picks one of a plane's two solutions at random. On the
    distinctive pairs of the studio's repeated room (the run's, seed 0) whose matches are true, the rotations were
    1.26° off at the median that way and 0.20° this way, 24 and 9 of 50 pairs more than 1.5° off (a development
    measurement; tests/test_frontend_pair_rotations.py pins the planar case).

    Args:
        verified: ``{(a, b): (M, 2) matches}`` (rows index the photos' keypoints).
        bearings: ``{name: (N, 3)}`` unit rays of each photo's keypoints (camera frame); rays with z ≤ 0.1 are
            left out of the pair's estimate.
        threshold_rad: RANSAC threshold on the normalised image plane (pixels × radians per pixel).
        seed: seed of pycolmap's RANSAC (the same matches and seed give the same rotations).
    """
    from ..native_crashes import load_pycolmap

    pycolmap = load_pycolmap()
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=2, height=2, params=[_VIRTUAL_FOCAL, 0.0, 0.0])
    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.max_error = threshold_rad * _VIRTUAL_FOCAL
    options.ransac.random_seed = seed
    # pycolmap's watermark check looks for pairs whose matches near the image border all move alike; every point
    # lies outside the 2×2 virtual image, so it would call any pair that mostly translates a watermark and give it
    # no pose
    options.detect_watermark = False
    rotations = {}
    for (a, b), matches in verified.items():
        ra, rb = bearings[a][matches[:, 0]], bearings[b][matches[:, 1]]
        front = (ra[:, 2] > 0.1) & (rb[:, 2] > 0.1)
        if front.sum() < 8:
            continue
        pa = _VIRTUAL_FOCAL * ra[front, :2] / ra[front, 2:]
        pb = _VIRTUAL_FOCAL * rb[front, :2] / rb[front, 2:]
        index = np.repeat(np.arange(len(pa), dtype=np.uint32)[:, None], 2, axis=1)
        geometry = pycolmap.estimate_calibrated_two_view_geometry(camera, pa, camera, pb, index, options)
        if pycolmap.estimate_two_view_geometry_pose(camera, pa, camera, pb, geometry):
            rotations[(a, b)] = np.asarray(geometry.cam2_from_cam1.rotation.matrix(), np.float64)
    return rotations


def rotation_consistent_pairs(names, rotations: dict, inliers: dict, *, tolerance_deg: float = 1.5,
                              seeds: int = 64) -> set:
    """The pairs consistent with the best set of absolute rotations (module docstring).

    Args:
        names: the photos; rotations: :func:`pair_rotations`'s; inliers: ``{(a, b): matches}`` counts, which
            order the seed triplets (strongest first).
        tolerance_deg: how far a loop may be from closing, and a pair from the absolute rotations (degrees).
        seeds: seed triplets tried (the ``seeds`` whose loops close, of those with the most inliers; a seed whose
            pairs the best set holds already is skipped).

    Returns:
        The kept pairs (a subset of ``rotations``' keys); empty when no triplet closes.
    """
    neighbours: dict = {n: {} for n in names}
    for (a, b), rotation in rotations.items():
        neighbours[a][b] = rotation  # b_from_a
        neighbours[b][a] = rotation.T
    order = {n: i for i, n in enumerate(names)}
    triplets = [(a, b, c) for a in names for b in neighbours[a] if order[b] > order[a]
                for c in neighbours[a] if order[c] > order[b] and c in neighbours[b]]  # the graph's triangles
    strength = {t: sum(inliers.get(p, 0) for p in itertools.combinations(t, 2)) for t in triplets}
    closing = [t for t in sorted(triplets, key=lambda t: -strength[t])
               if _angle_deg(neighbours[t[2]][t[0]] @ neighbours[t[1]][t[2]] @ neighbours[t[0]][t[1]]) <= tolerance_deg]
    best: set = set()
    for a, b, c in closing[:seeds]:
        if len(best) == len(rotations):
            break
        if {(a, b), (a, c), (b, c)} <= best:  # grown already from a seed of the same consistent set
            continue
        absolute = _grow(names, neighbours, {a: np.eye(3), b: neighbours[a][b], c: neighbours[a][c]}, tolerance_deg)
        kept = {p for p in rotations if p[0] in absolute and p[1] in absolute
                and _angle_deg(rotations[p] @ absolute[p[0]] @ absolute[p[1]].T) <= tolerance_deg}
        if len(kept) > len(best):
            best = kept
    return best


def _grow(names, neighbours: dict, absolute: dict, tolerance_deg: float) -> dict:
    """Absolute rotations (``{name: photo_from_seed}``) grown from a seed: a photo joins when at least two of
    its pairs with placed photos agree on its rotation (their chordal mean)."""
    changed = True
    while changed:
        changed = False
        for name in names:
            if name in absolute:
                continue
            votes = [neighbours[m][name] @ absolute[m] for m in neighbours[name] if m in absolute]
            if len(votes) < 2:
                continue
            agreeing = max(([q for q in votes if _angle_deg(q @ p.T) <= tolerance_deg] for p in votes), key=len)
            if len(agreeing) >= 2:
                absolute[name] = rotation_from_covariance(sum(agreeing))
                changed = True
    return absolute
