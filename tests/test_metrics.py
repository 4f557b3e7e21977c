"""Tests for bcmocap.eval.metrics: errors against ground truth in cm and degrees."""

import numpy as np
import pytest
from conftest import random_motion

from bcmocap.eval import ErrorStats, camera_centre_errors, evaluate_motion, joint_angle_errors, joint_position_errors
from bcmocap.geometry import SO3
from bcmocap.kinematics import Motion


@pytest.fixture(scope="module")
def truth(skeleton):
    return random_motion(skeleton, 4, np.random.default_rng(0))


def test_identical_motions_have_zero_error(skeleton, rig, truth):
    # A quaternion sign flip is the same motion.
    same = Motion(truth.root_position, -truth.rotations)
    assert joint_position_errors(skeleton, same, truth).shape == (4, 6)
    assert joint_angle_errors(skeleton, same, truth).shape == (4, 5)
    report = evaluate_motion(skeleton, same, truth, rig)
    assert set(report) == {"joint_position_error_cm", "joint_angle_error_deg", "camera_centre_error_cm"}
    for stats in report.values():
        assert set(stats) == {"mean", "median", "max"}
        np.testing.assert_allclose(list(stats.values()), 0.0, atol=1e-6)


def test_rotation_offset_on_one_joint_gives_that_angle(skeleton, truth):
    angle = np.deg2rad(7.5)
    rot = np.array(truth.rotations)
    rot[:, 1] = np.asarray((SO3(rot[:, 1]) @ SO3.exp(angle * np.array([0.6, 0.0, 0.8]))).wxyz)  # torso
    estimate = Motion(truth.root_position, rot)
    errors = joint_angle_errors(skeleton, estimate, truth)
    np.testing.assert_allclose(errors[:, 0], angle, rtol=1e-10)
    np.testing.assert_array_equal(errors[:, 1:], 0.0)
    report = evaluate_motion(skeleton, estimate, truth)
    assert "camera_centre_error_cm" not in report
    np.testing.assert_allclose(report["joint_angle_error_deg"]["max"], 7.5, rtol=1e-10)
    np.testing.assert_allclose(report["joint_angle_error_deg"]["mean"], 7.5 / 5, rtol=1e-10)
    np.testing.assert_allclose(report["joint_angle_error_deg"]["median"], 0.0, atol=1e-12)
    # The torso's joint and the root do not move; the head (its child) moves by 2 sin(θ/2)·|offset|.
    pos = joint_position_errors(skeleton, estimate, truth)
    np.testing.assert_allclose(pos[:, [0, 1, 3, 4, 5]], 0.0, atol=1e-15)
    head_offset = np.linalg.norm(np.asarray(skeleton.offsets[2]))
    np.testing.assert_array_less(pos[:, 2], 2 * np.sin(angle / 2) * head_offset + 1e-12)
    assert np.all(pos[:, 2] > 0)


def test_root_translation_gives_joint_and_camera_errors_in_cm(skeleton, rig, truth):
    shift = np.array([0.03, 0.0, -0.04])  # 5 cm
    estimate = Motion(np.asarray(truth.root_position) + shift, truth.rotations)
    np.testing.assert_allclose(joint_position_errors(skeleton, estimate, truth), 0.05, rtol=1e-10)
    np.testing.assert_allclose(camera_centre_errors(skeleton, rig, estimate, truth), 0.05, rtol=1e-10)
    report = evaluate_motion(skeleton, estimate, truth, rig)
    for key in ("joint_position_error_cm", "camera_centre_error_cm"):
        np.testing.assert_allclose(list(report[key].values()), 5.0, rtol=1e-10)
    np.testing.assert_allclose(list(report["joint_angle_error_deg"].values()), 0.0, atol=1e-12)


def test_error_stats():
    stats = ErrorStats.of(np.array([[1.0, 2.0], [3.0, 10.0]]))
    assert stats == ErrorStats(mean=4.0, median=2.5, max=10.0)
    assert stats.as_dict() == {"mean": 4.0, "median": 2.5, "max": 10.0}
    with pytest.raises(ValueError, match="ErrorStats: no values"):
        ErrorStats.of(np.array([]))


def test_mismatched_or_invalid_motions(skeleton, truth):
    with pytest.raises(ValueError, match=r"estimate and truth differ in shape: \(3, 6, 4\) vs \(4, 6, 4\)"):
        joint_position_errors(skeleton, truth[:3], truth)
    bad = np.array(truth.root_position)
    bad[2, 1] = np.inf
    with pytest.raises(ValueError, match=r"estimate: root_position has NaN/inf \(first at index \(2, 1\)\)"):
        joint_angle_errors(skeleton, Motion(bad, truth.rotations), truth)
    with pytest.raises(ValueError, match="truth: rotations have 5 segments, the skeleton has 6"):
        joint_angle_errors(skeleton, truth, Motion(truth.root_position, truth.rotations[:, :5]))
