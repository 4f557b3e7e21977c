"""Tests for bcmocap.kinematics.ik: FK then IK returns the motion; gaps are interpolated; errors."""

import numpy as np
import pytest
from conftest import KNEE_AXIS, quat_distance, random_motion

from bcmocap.geometry import SO3
from bcmocap.kinematics import Motion, camera_poses, motion_from_camera_poses


def assert_same_motion(got: Motion, want: Motion, atol=1e-9):
    np.testing.assert_allclose(got.root_position, want.root_position, atol=atol)
    np.testing.assert_allclose(quat_distance(got.rotations, want.rotations), 0.0, atol=atol)


def test_exact_camera_poses_give_the_exact_motion(skeleton, rig, rng):
    truth = random_motion(skeleton, 5, rng, max_angle=2.5)  # includes a bent (hinge) knee and a fixed foot
    poses = np.array(camera_poses(skeleton, rig, truth).wxyz_xyz)
    got = motion_from_camera_poses(skeleton, rig, poses, np.ones((5, rig.num_cameras), bool))
    assert got.rotations.shape == (5, 6, 4) and got.root_position.shape == (5, 3)
    assert_same_motion(got, truth)


def test_a_subset_of_the_root_cameras_is_enough(skeleton, rig, rng):
    truth = random_motion(skeleton, 3, rng)
    poses = np.array(camera_poses(skeleton, rig, truth).wxyz_xyz)
    registered = np.ones((3, rig.num_cameras), bool)
    registered[0, 0] = registered[1, 1] = False  # one of the two pelvis cameras missing at frames 0 and 1
    poses[0, 0] = poses[1, 1] = np.nan  # unregistered poses must not be read
    assert_same_motion(motion_from_camera_poses(skeleton, rig, poses, registered), truth)


def smooth_motion(skeleton, num_frames, rng) -> Motion:
    """Root moving on a line at constant rotation, torso and knee turning at constant rates, rest fixed."""
    base = random_motion(skeleton, None, rng, max_angle=1.0)
    t = np.arange(num_frames, dtype=float)
    root = np.asarray(base.root_position) + t[:, None] * np.array([0.05, -0.02, 0.01])
    rot = np.tile(np.asarray(base.rotations), (num_frames, 1, 1))
    torso_axis = np.array([0.3, -0.5, 0.8])
    rot[:, 1] = np.asarray((SO3(rot[:, 1]) @ SO3.exp(0.15 * t[:, None] * torso_axis)).wxyz)
    knee = KNEE_AXIS / np.linalg.norm(KNEE_AXIS)
    rot[:, 4] = np.c_[np.cos(0.2 + 0.1 * t), np.sin(0.2 + 0.1 * t)[:, None] * knee]
    return Motion(root, rot)


def test_unregistered_frames_are_interpolated(skeleton, rig, rng):
    truth = smooth_motion(skeleton, 6, rng)
    poses = np.array(camera_poses(skeleton, rig, truth).wxyz_xyz)
    registered = np.ones((6, rig.num_cameras), bool)
    registered[2:4, :2] = False  # the root's cameras miss frames 2 and 3: root pose is interpolated
    registered[2, 2] = False  # the chest camera misses frame 2: the torso's orientation is slerped
    registered[0, 5] = registered[5, 5] = False  # the shin camera misses the ends: nearest frame
    got = motion_from_camera_poses(skeleton, rig, poses, registered)
    # The root moves linearly and every segment's world orientation turns about a fixed axis at a
    # constant rate here, so interpolation is exact except where a segment is held at the ends.
    np.testing.assert_allclose(got.root_position, truth.root_position, atol=1e-12)
    angle = quat_distance(got.rotations, truth.rotations)
    np.testing.assert_allclose(angle[:, :4], 0.0, atol=1e-7)
    np.testing.assert_allclose(angle[1:5, 4], 0.0, atol=1e-7)
    # The knee's world orientation at frame 0 is copied from frame 1 (the nearest known one).
    assert 0.05 < angle[0, 4] < 0.3 and 0.05 < angle[5, 4] < 0.3


def test_interpolated_frame_of_a_smooth_motion_is_close(skeleton, rig):
    # A joint rotating smoothly (not at a constant rate about a fixed axis): a frame interpolated
    # between its neighbours is within a small fraction of the frame-to-frame motion.
    t = np.linspace(0.0, 0.4, 5)
    rot = np.tile([1.0, 0, 0, 0], (5, 6, 1))
    rot[:, 1] = np.asarray((SO3.exp(np.c_[t, 0.5 * t**2, np.zeros(5)])).wxyz)
    truth = Motion(np.zeros((5, 3)), rot)
    poses = np.array(camera_poses(skeleton, rig, truth).wxyz_xyz)
    registered = np.ones((5, rig.num_cameras), bool)
    registered[2, 2] = False
    got = motion_from_camera_poses(skeleton, rig, poses, registered)
    step = quat_distance(truth.rotations[1, 1], truth.rotations[2, 1])
    err = quat_distance(got.rotations[2, 1], truth.rotations[2, 1])
    assert err < 0.05 * step
    np.testing.assert_allclose(quat_distance(np.asarray(got.rotations)[[0, 1, 3, 4]], rot[[0, 1, 3, 4]]), 0.0, atol=1e-7)


def test_root_cameras_never_registered(skeleton, rig, rng):
    truth = random_motion(skeleton, 3, rng)
    poses = np.array(camera_poses(skeleton, rig, truth).wxyz_xyz)
    registered = np.ones((3, rig.num_cameras), bool)
    registered[:, :2] = False
    with pytest.raises(ValueError, match="root segment's cameras are never registered"):
        motion_from_camera_poses(skeleton, rig, poses, registered)


def test_shape_mismatch(skeleton, rig):
    with pytest.raises(ValueError, match=r"expected world_from_camera \(3, 6, 7\) and registered \(3, 6\), got \(3, 5, 7\)"):
        motion_from_camera_poses(skeleton, rig, np.zeros((3, 5, 7)), np.ones((3, 6), bool))
    with pytest.raises(ValueError, match=r"expected world_from_camera \(3, 6, 7\).*got \(3, 5, 7\) and \(3, 5\)"):
        motion_from_camera_poses(skeleton, rig, np.zeros((3, 5, 7)), np.ones((3, 5), bool))


def test_root_without_cameras(skeleton):
    from conftest import fov_camera

    from bcmocap.kinematics import Rig

    rig = Rig.from_mounts(skeleton, [("chest", "torso", np.r_[1.0, 0, 0, 0, 0, 0, 0], fov_camera())])
    with pytest.raises(ValueError, match="no camera is mounted on the root segment"):
        motion_from_camera_poses(skeleton, rig, np.tile([1.0, 0, 0, 0, 0, 0, 0], (2, 1, 1)), np.ones((2, 1), bool))


def test_one_dimensional_registered_mask_is_reported_with_shapes(skeleton, rig):
    with pytest.raises(ValueError, match=r"registered \(3, 6\)"):
        motion_from_camera_poses(skeleton, rig, np.zeros((3, 6, 7)), np.ones(3, bool))


def test_robust_average_outvotes_a_badly_registered_root_camera(skeleton, rig, rng):
    # A third pelvis camera (the paper's waist has three); one of them off by 20° and 30 cm at frame 1.
    from conftest import fov_camera

    from bcmocap.geometry import SE3
    from bcmocap.kinematics import Rig

    extra = SE3.from_rotation_and_translation(SO3.exp(np.array([0.1, -1.4, 0.2])), np.array([0.0, 0.17, 0.05]))
    mounts = [(n, skeleton.names[s], m, fov_camera()) for n, s, m in zip(rig.names, rig.segments, np.asarray(rig.segment_from_camera))]
    rig3 = Rig.from_mounts(skeleton, mounts + [("waist_side", "pelvis", extra, fov_camera())])
    truth = random_motion(skeleton, 3, rng)
    poses = np.array(camera_poses(skeleton, rig3, truth).wxyz_xyz)
    poses[1, 0, :4] = np.asarray((SO3(poses[1, 0, :4]) @ SO3.exp(np.array([0.35, 0.0, 0.0]))).wxyz)
    poses[1, 0, 4:] += 0.3
    registered = np.ones((3, rig3.num_cameras), bool)
    robust = motion_from_camera_poses(skeleton, rig3, poses, registered, robust=True)
    plain = motion_from_camera_poses(skeleton, rig3, poses, registered)
    assert_same_motion(robust, truth)
    assert np.linalg.norm(np.asarray(plain.root_position[1] - truth.root_position[1])) > 0.05
    assert_same_motion(plain[np.array([0, 2])], truth[np.array([0, 2])])  # the default (plain mean) is unchanged elsewhere


def test_fill_gaps_interpolates_inside_and_holds_at_the_ends():
    from bcmocap.kinematics.ik import fill_gaps

    known = np.array([False, True, False, False, True, False])
    values = np.array([[0.0], [1.0], [9.0], [9.0], [4.0], [9.0]])
    assert fill_gaps(values, known, rotations=False).ravel().tolist() == [1.0, 1.0, 2.0, 3.0, 4.0, 4.0]
    half = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])  # 90 degrees about z
    quats = np.array([[1.0, 0, 0, 0], [0.0, 0, 0, 0], half])
    mid = fill_gaps(quats, np.array([True, False, True]), rotations=True)[1]
    assert np.allclose(mid, [np.cos(np.pi / 8), 0, 0, np.sin(np.pi / 8)])
