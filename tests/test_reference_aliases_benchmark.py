"""benchmarks/reference_aliases.py (issue 42): a verified pair is labelled right or an alias by the true epipolar
geometry of its two photos."""

import numpy as np

from bcmocap.cameras import PinholeCamera
from bcmocap.geometry import SO3
from benchmarks import reference_aliases


def test_true_matches_are_right_and_shifted_ones_are_aliases():
    rng = np.random.default_rng(0)
    camera = PinholeCamera(width=1024, height=768, focal=[610.0, 610.0], principal_point=[511.5, 383.5])
    # Two photos 0.5 m apart, the second turned 20 degrees; points 2-5 m in front of both.
    pose_a = np.r_[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    turn = np.asarray(SO3.from_y_radians(np.radians(20.0)).wxyz)
    pose_b = np.r_[turn, 0.5, 0.0, 0.1]
    points = rng.uniform([-1.5, -1.0, 2.0], [1.5, 1.0, 5.0], (200, 3))
    rotation_b = np.asarray(SO3(turn).as_matrix())
    in_b = (points - pose_b[4:]) @ rotation_b  # camera b's frame: R^T (X - c)
    xy_a, ok_a = camera.project(points)
    xy_b, ok_b = camera.project(in_b)
    assert np.all(np.asarray(ok_a)) and np.all(np.asarray(ok_b))
    keypoints_a, keypoints_b = np.asarray(xy_a), np.asarray(xy_b)
    matches = np.stack([np.arange(200), np.arange(200)], axis=1)
    assert reference_aliases.true_match_fraction(keypoints_a, keypoints_b, matches, pose_a, pose_b, camera) == 1.0
    # An alias: each point matched to another one (as a repeated tile is to its neighbour).
    aliased = np.stack([np.arange(200), np.roll(np.arange(200), 7)], axis=1)
    assert reference_aliases.true_match_fraction(keypoints_a, keypoints_b, aliased, pose_a, pose_b, camera) < 0.1
    # The same true matches with the photos' poses swapped do not fit: the label depends on the geometry.
    assert reference_aliases.true_match_fraction(keypoints_a, keypoints_b, matches, pose_b, pose_a, camera) < 0.5
