"""Tests for the pose helpers of the registration modules (bcmocap.frontend.poses): a camera over a floor whose
features match a copy of the pattern one period away (a repeated pattern) is refused, not registered a period off."""

import dataclasses

import numpy as np
import pycolmap
import pytest

from bcmocap.frontend.poses import estimate_pose, second_pose
from bcmocap.frontend.register import RegistrationOptions

PERIOD = np.array([0.6, 0.6, 0.0])  # a diagonal step of 0.6 m floor tiles: the repeated room's worst alias


def _floor_view(copied: float, outliers: float = 0.0, seed: int = 0, period=PERIOD):
    """Correspondences of a camera 1.2 m over the floor looking down: ``copied`` of them matched to the point one
    period away (the pattern's copy), ``outliers`` to random points. Returns the camera, its true centre, pixels
    (OpenCV convention) and points."""
    rng = np.random.default_rng(seed)
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[400.0, 400.0, 320.0, 240.0])
    centre = np.array([0.3, -0.2, 1.2])
    cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([1.0, 0.0, 0.0, 0.0])), -np.diag([1.0, -1.0, -1.0]) @ centre)
    points = np.column_stack([rng.uniform(-0.9, 1.5, 400), rng.uniform(-1.1, 0.7, 400), np.zeros(400)])
    in_cam = np.asarray(cam_from_world * points)
    xy = np.asarray(cam.img_from_cam(in_cam), np.float64) - 0.5 + rng.normal(0, 0.3, (400, 2))
    seen = (in_cam[:, 2] > 0) & (xy[:, 0] > 0) & (xy[:, 0] < 639) & (xy[:, 1] > 0) & (xy[:, 1] < 479)
    xy, points = xy[seen], points[seen].copy()
    pick = rng.permutation(len(points))
    n_copy, n_out = int(copied * len(points)), int(outliers * len(points))
    points[pick[:n_copy]] += period
    points[pick[n_copy:n_copy + n_out]] = rng.uniform(-2, 2, (n_out, 3))
    return cam, centre, xy, points


def _centre(cam_from_world) -> np.ndarray:
    return np.asarray(cam_from_world.inverse().translation)


def test_the_true_pose_is_accepted_beside_a_few_copies_and_outliers():
    cam, centre, xy, points = _floor_view(copied=0.05, outliers=0.2)
    found = estimate_pose(xy, points, cam, RegistrationOptions())
    assert found is not None
    assert np.linalg.norm(_centre(found[0]) - centre) < 0.01


@pytest.mark.parametrize("copied", [0.3, 0.45])
def test_a_pose_the_pattern_could_place_a_period_away_is_refused(copied):
    cam, centre, xy, points = _floor_view(copied=copied)
    options = RegistrationOptions()
    assert estimate_pose(xy, points, cam, options) is None
    unchecked = estimate_pose(xy, points, cam, dataclasses.replace(options, ambiguity_ratio=0.0))
    assert unchecked is not None  # without the check one of the two is taken
    first = unchecked[0]
    second, inliers = second_pose(xy, points, unchecked[1], first, cam, options)
    shifts = sorted([np.linalg.norm(_centre(first) - centre), np.linalg.norm(_centre(second) - centre)])
    assert shifts[0] < 0.01 and abs(shifts[1] - np.linalg.norm(PERIOD)) < 0.01  # the truth and its copy
    assert inliers.sum() >= options.ambiguity_ratio * unchecked[1].sum()


def test_a_second_pose_next_to_the_first_is_no_copy():
    """Correspondences 5 cm off (a fine pattern, or a lens or shutter error over part of the view) give a second pose
    within a tenth of the depth: the view is kept, and with ``ambiguity_shift`` 0 it would be refused."""
    cam, centre, xy, points = _floor_view(copied=0.3, period=np.array([0.05, 0.0, 0.0]))
    options = RegistrationOptions()
    found = estimate_pose(xy, points, cam, options)
    assert found is not None and np.linalg.norm(_centre(found[0]) - centre) < 0.01
    assert second_pose(xy, points, found[1], found[0], cam, options) is None
    assert estimate_pose(xy, points, cam, dataclasses.replace(options, ambiguity_shift=0.0)) is None


def test_no_first_inliers_or_no_ratio_is_no_second_pose():
    cam, _, xy, points = _floor_view(copied=0.3)
    first = estimate_pose(xy, points, cam, dataclasses.replace(RegistrationOptions(), ambiguity_ratio=0.0))[0]
    assert second_pose(xy, points, np.zeros(len(xy), bool), first, cam, RegistrationOptions()) is None
    for ratio in (0.0, float("nan")):
        assert second_pose(xy, points, np.ones(len(xy), bool), first, cam,
                           dataclasses.replace(RegistrationOptions(), ambiguity_ratio=ratio)) is None
