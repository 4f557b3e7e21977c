"""Tests for the rotation check of the reference photos' pairs (bcmocap.frontend.pair_rotations) and for the
comparison of two models (bcmocap.frontend.reference.models_agree)."""

import itertools

import numpy as np
from scipy.spatial.transform import Rotation

from bcmocap.frontend.pair_rotations import pair_rotations, rotation_consistent_pairs
from bcmocap.frontend.reference import models_agree


def _angle_deg(r):
    return np.degrees(np.linalg.norm(Rotation.from_matrix(r).as_rotvec()))


def test_pair_rotation_is_the_two_view_rotation():
    rng = np.random.default_rng(0)
    points = rng.uniform([-2, -2, 4], [2, 2, 8], (200, 3))  # a scene in depth, seen by photo a at the origin
    rotation = Rotation.from_euler("xyz", [4.0, -12.0, 3.0], degrees=True).as_matrix()  # x_b = R x_a + t
    seen_b = points @ rotation.T + [0.6, 0.1, -0.2]
    bearings = {"a": points / np.linalg.norm(points, axis=1, keepdims=True),
                "b": seen_b / np.linalg.norm(seen_b, axis=1, keepdims=True)}
    matches = np.stack([np.arange(200), np.arange(200)], axis=1)
    matches[:30, 1] = rng.permutation(matches[:30, 1])  # outliers
    found = pair_rotations({("a", "b"): matches}, bearings, threshold_rad=1e-3)
    assert _angle_deg(found[("a", "b")] @ rotation.T) < 1e-3
    # Too few rays in front of both cameras: no estimate.
    assert pair_rotations({("a", "b"): matches[:7]}, bearings, threshold_rad=1e-3) == {}


def test_pair_rotation_of_a_scene_mostly_on_one_plane():
    # A wall with a few things in front of it, seen with 0.3 mrad of noise: the essential matrix alone (five-point,
    # OpenCV's, as pair_rotations had it before) was more than 1 deg off on 2 of these 30 pairs; with the homography
    # beside it (pycolmap's two-view geometry) every one is within 0.3 deg.
    rng = np.random.default_rng(3)
    for _ in range(30):
        xy = rng.uniform(-2, 2, (200, 2))
        points = np.column_stack([xy, 5.0 + 0.3 * xy[:, 0] - 0.2 * xy[:, 1]])
        off_wall = rng.random(200) > 0.9
        points[off_wall, 2] -= rng.uniform(0.5, 2.0, off_wall.sum())
        rotation = Rotation.from_euler("xyz", rng.uniform(-15, 15, 3), degrees=True).as_matrix()
        shift = rng.normal(size=3)
        seen_b = points @ rotation.T + 0.8 * shift / np.linalg.norm(shift)
        bearings = {name: rays / np.linalg.norm(rays, axis=1, keepdims=True) + rng.normal(0, 0.3e-3, rays.shape)
                    for name, rays in (("a", points), ("b", seen_b))}
        matches = np.stack([np.arange(200), np.arange(200)], axis=1)
        found = pair_rotations({("a", "b"): matches}, bearings, threshold_rad=1.5e-3)
        assert _angle_deg(found[("a", "b")] @ rotation.T) < 0.3


def test_pair_rotation_of_a_sideways_step_before_a_far_wall():
    # A photo taken one step to the side of the other, before a distant wall: every match moves alike in the image.
    # pycolmap's watermark check (on by default) reads such a pair as a watermark when the points lie outside the
    # image it is told of, and gives no pose; pair_rotations turns it off.
    rng = np.random.default_rng(5)
    xy = rng.uniform(-3, 3, (150, 2))
    points = np.column_stack([xy, 20.0 + rng.uniform(0, 0.5, 150)])
    rotation = Rotation.from_euler("xyz", [0.5, -2.0, 0.3], degrees=True).as_matrix()
    seen_b = points @ rotation.T + [0.5, 0.0, 0.0]
    bearings = {name: rays / np.linalg.norm(rays, axis=1, keepdims=True) for name, rays in (("a", points), ("b", seen_b))}
    matches = np.stack([np.arange(150), np.arange(150)], axis=1)
    found = pair_rotations({("a", "b"): matches}, bearings, threshold_rad=1e-3)
    assert _angle_deg(found[("a", "b")] @ rotation.T) < 0.1  # a far, nearly flat scene: 0.055 deg here


def test_pairs_that_contradict_the_loops_are_left_out():
    rng = np.random.default_rng(1)
    names = [f"p{i}" for i in range(8)]
    absolute = {n: Rotation.random(random_state=rng).as_matrix() for n in names}  # photo_from_world
    pairs = list(itertools.combinations(names, 2))
    rotations = {(a, b): absolute[b] @ absolute[a].T for a, b in pairs}
    for pair in pairs:  # noise well inside the tolerance
        rotations[pair] = Rotation.from_rotvec(rng.normal(0, np.radians(0.1), 3)).as_matrix() @ rotations[pair]
    wrong = [("p0", "p3"), ("p1", "p5"), ("p2", "p6"), ("p4", "p7")]
    for pair in wrong:  # aliases: rotations off by 5-40 degrees
        turn = Rotation.from_rotvec(rng.normal(size=3) / 3 * np.radians(rng.uniform(5, 40))).as_matrix()
        rotations[pair] = turn @ rotations[pair]
    # Every pair of p7 but one is wrong, each its own way: p7 cannot be placed, and all its pairs go.
    for k, other in enumerate(names[:6]):
        turn = Rotation.from_euler("zx", [20 + 10 * k, 5 * k], degrees=True).as_matrix()
        rotations[(other, "p7")] = turn @ rotations[(other, "p7")]
    inliers = {pair: 100 for pair in pairs}
    kept = rotation_consistent_pairs(names, rotations, inliers, tolerance_deg=1.5)
    assert kept == {pair for pair in pairs if pair not in wrong and "p7" not in pair}
    # Nothing closes a loop: nothing is kept.
    assert rotation_consistent_pairs(names[:2], {("p0", "p1"): rotations[("p0", "p1")]}, inliers) == set()


def test_models_agree_up_to_a_similarity():
    rng = np.random.default_rng(2)
    centres = {f"p{i}": rng.normal(size=3) for i in range(10)}
    turn = Rotation.random(random_state=rng).as_matrix()
    same = {n: 2.5 * turn @ c + [1.0, -3.0, 0.5] for n, c in centres.items()}
    assert models_agree(centres, same, 0.05)
    moved = dict(same, p3=same["p3"] + 2.0 * np.linalg.norm(same["p3"] - same["p4"]))  # one photo far off
    assert not models_agree(centres, moved, 0.05)
    assert not models_agree({n: centres[n] for n in ("p0", "p1")}, same, 0.05)  # fewer than three in common
