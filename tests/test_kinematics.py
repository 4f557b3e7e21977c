"""Tests for bcmocap.kinematics: skeleton validation and layout, FK against numpy, retract/difference, rigs."""

import numpy as np
import pytest
from conftest import (
    KNEE_AXIS,
    MOUNTS,
    OFFSETS,
    PARENTS,
    SEGMENTS,
    TYPES,
    fov_camera,
    quat_distance,
    quat_matrix,
    quat_multiply,
    random_motion,
    random_quaternions,
    se3_matrix,
)

from bcmocap.geometry import SE3
from bcmocap.kinematics import (
    JointType,
    Motion,
    Rig,
    Skeleton,
    camera_poses,
    forward_kinematics,
    joint_positions,
    world_rotations,
)

# ---- Skeleton validation --------------------------------------------------------------------------


def skeleton_kwargs(**changes):
    axes = np.zeros((6, 3))
    axes[4] = KNEE_AXIS
    kwargs = dict(names=SEGMENTS, parents=PARENTS, offsets=OFFSETS, joint_types=TYPES, hinge_axes=axes)
    kwargs.update(changes)
    return kwargs


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(names=("pelvis", "torso", "head", "thigh", "torso", "foot")), r"duplicate segment names \['torso'\]"),
        (dict(parents=(-1, 0, 3, 0, 3, 4)), r"segment 2 \('head'\) has parent 3; parents must come before"),
        (dict(parents=(-1, 0, 1, -1, 3, 4)), r"segment 3 \('thigh'\) has parent -1"),
        (dict(parents=(0, 0, 1, 0, 3, 4)), r"segment 0 \('pelvis'\) must be the root"),
        (dict(parents=(-1, 0, 1)), "6 names but 3 parents"),
        (dict(joint_types=("ball",) * 6), r"the root 'pelvis' must have a FREE joint, got BALL"),
        (dict(joint_types=("free", "free", "ball", "ball", "hinge", "fixed")), "only the root may be FREE, but 'torso'"),
        (dict(joint_types=("free", "ball")), "6 segments but 2 joint types"),
        (dict(hinge_axes=np.zeros((6, 3))), "hinge joint 'shin' needs a non-zero axis"),
        (dict(hinge_axes=np.zeros((5, 3))), r"hinge_axes must have shape \(6, 3\), got \(5, 3\)"),
        (dict(offsets=np.zeros((6, 2))), r"offsets must have shape \(6, 3\), got \(6, 2\)"),
        (dict(offsets=np.zeros(18)), r"offsets must have shape \(6, 3\), got \(18,\)"),
        (dict(offsets=np.full((6, 3), np.nan)), "offsets contain NaN"),
        (dict(names=(), parents=(), offsets=np.zeros((0, 3)), joint_types=(), hinge_axes=None), "at least one segment"),
    ],
)
def test_skeleton_validation_errors(changes, message):
    with pytest.raises(ValueError, match=message):
        Skeleton(**skeleton_kwargs(**changes))


def test_skeleton_layout(skeleton):
    assert skeleton.num_segments == 6
    assert skeleton.levels == ((0,), (1, 3), (2, 4), (5,))
    assert skeleton.depths == (0, 1, 2, 1, 2, 3)
    assert skeleton.dof_starts == (0, 6, 9, 12, 15, 16)
    assert skeleton.num_dofs == 16
    assert skeleton.joint_types == (
        JointType.FREE, JointType.BALL, JointType.BALL, JointType.BALL, JointType.HINGE, JointType.FIXED
    )
    assert skeleton.dof_names() == (
        "pelvis.tx", "pelvis.ty", "pelvis.tz", "pelvis.rx", "pelvis.ry", "pelvis.rz",
        "torso.rx", "torso.ry", "torso.rz", "head.rx", "head.ry", "head.rz",
        "thigh.rx", "thigh.ry", "thigh.rz", "shin.angle",
    )
    assert len(skeleton.dof_names()) == skeleton.num_dofs
    assert skeleton.chain(5) == (0, 3, 4, 5)
    assert skeleton.children(0) == (1, 3)
    assert skeleton.subtree(3) == (3, 4, 5)
    np.testing.assert_allclose(skeleton.hinge_axes[4], KNEE_AXIS / np.linalg.norm(KNEE_AXIS), atol=1e-15)
    np.testing.assert_array_equal(np.asarray(skeleton.hinge_axes)[[0, 1, 2, 3, 5]], 0.0)
    with pytest.raises(ValueError, match=r"unknown segment 'knee'; the skeleton has \['pelvis'"):
        skeleton.index("knee")


def test_default_joint_types_are_free_root_and_ball_joints():
    s = Skeleton(["a", "b", "c"], [-1, 0, 0], np.zeros((3, 3)))
    assert s.joint_types == (JointType.FREE, JointType.BALL, JointType.BALL)
    assert s.num_dofs == 12


def test_rotation_basis(skeleton):
    basis = np.asarray(skeleton.rotation_basis())
    assert basis.shape == (6, 3, 16)
    np.testing.assert_array_equal(basis[0][:, 3:6], np.eye(3))
    np.testing.assert_array_equal(basis[0][:, :3], 0.0)
    np.testing.assert_array_equal(basis[2][:, 9:12], np.eye(3))
    np.testing.assert_allclose(basis[4][:, 15], KNEE_AXIS / np.linalg.norm(KNEE_AXIS))
    np.testing.assert_array_equal(basis[5], 0.0)
    assert np.count_nonzero(basis[4]) == 2


# ---- Motion ---------------------------------------------------------------------------------------


def test_motion_validation_and_check(skeleton):
    with pytest.raises(ValueError, match=r"expected root_position \(\.\.\., 3\)"):
        Motion(np.zeros((4, 2)), np.zeros((4, 6, 4)))
    with pytest.raises(ValueError, match=r"batch shapes differ: root_position \(4, 3\), rotations \(3, 6, 4\)"):
        Motion(np.zeros((4, 3)), np.zeros((3, 6, 4)))
    with pytest.raises(ValueError, match="rotations have 5 segments, the skeleton has 6"):
        Motion(np.zeros((2, 3)), np.ones((2, 5, 4))).check(skeleton)
    bad = np.asarray(skeleton.rest_motion(3).rotations).copy()
    bad[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"truth: rotations has NaN/inf \(first at index \(1, 2, 0\)\)"):
        Motion(np.zeros((3, 3)), bad).check(skeleton, "truth")


# ---- forward kinematics ---------------------------------------------------------------------------


def numpy_fk(offsets, parents, root_position, rotations):
    """Plain recursive FK for one frame: world rotation matrices (J, 3, 3) and joint positions (J, 3)."""
    local = quat_matrix(rotations)
    n = len(parents)
    rot, pos = [None] * n, [None] * n

    def visit(j):
        if rot[j] is not None:
            return
        if parents[j] < 0:
            rot[j], pos[j] = local[j], np.asarray(root_position)
        else:
            visit(parents[j])
            rot[j] = rot[parents[j]] @ local[j]
            pos[j] = pos[parents[j]] + rot[parents[j]] @ offsets[j]

    for j in reversed(range(n)):
        visit(j)
    return np.stack(rot), np.stack(pos)


def test_forward_kinematics_matches_numpy_recursion(skeleton, rng):
    # Unprojected random rotations: FK itself does not care about joint types.
    t = 4
    motion = Motion(rng.normal(size=(t, 3)), random_quaternions(rng, (t, 6)))
    world = forward_kinematics(skeleton, motion)
    assert world.wxyz_xyz.shape == (t, 6, 7)
    got_rot = np.asarray(world.rotation().as_matrix())
    got_pos = np.asarray(world.translation())
    for f in range(t):
        ref_rot, ref_pos = numpy_fk(OFFSETS, PARENTS, motion.root_position[f], np.asarray(motion.rotations[f]))
        np.testing.assert_allclose(got_rot[f], ref_rot, atol=1e-13)
        np.testing.assert_allclose(got_pos[f], ref_pos, atol=1e-13)
    np.testing.assert_allclose(joint_positions(skeleton, motion), got_pos, atol=0)
    np.testing.assert_allclose(quat_matrix(world_rotations(skeleton, motion)), got_rot, atol=1e-13)


def test_forward_kinematics_batched_equals_per_frame(skeleton, rng):
    motion = Motion(rng.normal(size=(2, 3, 3)), random_quaternions(rng, (2, 3, 6)))
    batched = np.asarray(forward_kinematics(skeleton, motion).wxyz_xyz)
    assert batched.shape == (2, 3, 6, 7)
    for i in range(2):
        for k in range(3):
            single = forward_kinematics(skeleton, Motion(motion.root_position[i, k], motion.rotations[i, k]))
            np.testing.assert_allclose(batched[i, k], single.wxyz_xyz, rtol=0, atol=1e-15)


def test_rest_pose_joint_positions_are_summed_offsets(skeleton):
    pos = np.asarray(joint_positions(skeleton, skeleton.rest_motion()))
    np.testing.assert_allclose(pos[5], OFFSETS[3] + OFFSETS[4] + OFFSETS[5], atol=1e-15)
    np.testing.assert_allclose(pos[2], OFFSETS[1] + OFFSETS[2], atol=1e-15)
    assert skeleton.rest_motion(3).rotations.shape == (3, 6, 4)


# ---- retract / difference / project_rotations ------------------------------------------------------


def test_difference_inverts_retract(skeleton, rng):
    a = random_motion(skeleton, 5, rng)
    delta = rng.normal(scale=0.2, size=(5, skeleton.num_dofs))
    b = skeleton.retract(a, delta)
    np.testing.assert_allclose(skeleton.difference(a, b), delta, atol=1e-12)
    # Retracting keeps the motion representable: the fixed foot stays at identity, the knee on its axis.
    np.testing.assert_allclose(quat_distance(b.rotations[:, 5], [1.0, 0, 0, 0]), 0.0, atol=1e-12)
    axis = KNEE_AXIS / np.linalg.norm(KNEE_AXIS)
    np.testing.assert_allclose(np.cross(np.asarray(b.rotations[:, 4, 1:]), axis), 0.0, atol=1e-12)


def test_retract_inverts_difference_for_representable_motions(skeleton, rng):
    a = random_motion(skeleton, 4, rng, max_angle=1.0)
    b = random_motion(skeleton, 4, rng, max_angle=1.0)
    back = skeleton.retract(a, skeleton.difference(a, b))
    np.testing.assert_allclose(back.root_position, b.root_position, atol=1e-13)
    np.testing.assert_allclose(quat_distance(back.rotations, b.rotations), 0.0, atol=1e-7)


def test_retract_hinge_dof_rotates_about_the_axis(skeleton):
    rest = skeleton.rest_motion()
    delta = np.zeros(skeleton.num_dofs)
    delta[skeleton.dof_starts[4]] = 0.7
    moved = skeleton.retract(rest, delta)
    axis = KNEE_AXIS / np.linalg.norm(KNEE_AXIS)
    np.testing.assert_allclose(moved.rotations[4], np.r_[np.cos(0.35), np.sin(0.35) * axis], atol=1e-15)
    np.testing.assert_allclose(np.asarray(moved.rotations)[[0, 1, 2, 3, 5]], np.tile([1.0, 0, 0, 0], (5, 1)), atol=0)
    with pytest.raises(ValueError, match="delta has 15 entries per frame, the skeleton has 16 DOFs"):
        skeleton.retract(rest, np.zeros(15))


def test_project_rotations(skeleton, rng):
    axis = KNEE_AXIS / np.linalg.norm(KNEE_AXIS)
    perp = np.cross(axis, [0.0, 0.0, 1.0])
    perp /= np.linalg.norm(perp)
    twist = np.r_[np.cos(0.4), np.sin(0.4) * axis]  # 0.8 rad about the knee axis
    swing = np.r_[np.cos(0.3), np.sin(0.3) * perp]
    q = random_quaternions(rng, (3, 6))
    q[0, 4] = quat_multiply(swing, twist)
    q[1, 4] = quat_multiply(twist, swing)
    q[2, 4] = twist
    out = np.asarray(skeleton.project_rotations(q))
    # Ball joints and the root are untouched, the fixed joint becomes the identity.
    np.testing.assert_array_equal(out[:, [0, 1, 2, 3]], q[:, [0, 1, 2, 3]])
    np.testing.assert_array_equal(out[:, 5], np.tile([1.0, 0, 0, 0], (3, 1)))
    # The hinge keeps exactly the twist about its axis (swing–twist decomposition).
    for f in range(3):
        np.testing.assert_allclose(quat_distance(out[f, 4], twist), 0.0, atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(out[:, 4], axis=-1), 1.0, atol=1e-14)


def test_project_rotations_of_pure_swing_is_identity_not_nan(skeleton):
    axis = KNEE_AXIS / np.linalg.norm(KNEE_AXIS)
    perp = np.cross(axis, [0.0, 0.0, 1.0])
    perp /= np.linalg.norm(perp)
    q = np.tile([1.0, 0, 0, 0], (6, 1))
    q[4] = np.r_[0.0, perp]  # half turn about an axis orthogonal to the hinge: no twist at all
    out = np.asarray(skeleton.project_rotations(q))
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(quat_distance(out[4], [1.0, 0, 0, 0]), 0.0, atol=1e-7)


# ---- rigs -----------------------------------------------------------------------------------------


def test_rig_from_mounts_names_camera_and_segment(skeleton):
    mounts = [("cam_a", "pelvis", np.r_[1.0, 0, 0, 0, 0, 0, 0], fov_camera()),
              ("cam_b", "knee", np.r_[1.0, 0, 0, 0, 0, 0, 0], fov_camera())]
    with pytest.raises(ValueError, match=r"Rig: camera 'cam_b': unknown segment 'knee'"):
        Rig.from_mounts(skeleton, mounts)
    with pytest.raises(ValueError, match="no cameras given"):
        Rig.from_mounts(skeleton, [])


def test_rig_constructor_errors():
    cams = [fov_camera(), fov_camera()]
    from bcmocap.cameras import stack_cameras

    stacked = stack_cameras(cams)
    ident = np.tile([1.0, 0, 0, 0, 0, 0, 0], (2, 1))
    with pytest.raises(ValueError, match=r"duplicate camera names \['a'\]"):
        Rig(["a", "a"], [0, 1], ident, stacked)
    with pytest.raises(ValueError, match="2 camera names but 1 segment indices"):
        Rig(["a", "b"], [0], ident, stacked)
    with pytest.raises(ValueError, match=r"segment_from_camera must have shape \(2, 7\) \(wxyz_xyz\), got \(2, 6\)"):
        Rig(["a", "b"], [0, 1], ident[:, :6], stacked)
    with pytest.raises(ValueError, match="intrinsics must be stacked over the 2 cameras"):
        Rig(["a", "b"], [0, 1], ident, fov_camera())


def test_rig_layout_and_check(skeleton, rig):
    assert rig.num_cameras == 6
    assert rig.names == tuple(m[0] for m in MOUNTS)
    assert rig.segments == (0, 0, 1, 2, 3, 4)
    assert rig.index("chest") == 2
    with pytest.raises(ValueError, match=r"unknown camera 'nose'; the rig has \['waist_front'"):
        rig.index("nose")
    small = Skeleton(["a", "b"], [-1, 0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="camera 'head' is on segment 2, the skeleton has 2"):
        rig.check(small)


def test_camera_poses_compose_segment_and_mount(skeleton, rig, rng):
    motion = random_motion(skeleton, 3, rng)
    got = np.asarray(camera_poses(skeleton, rig, motion).wxyz_xyz)
    assert got.shape == (3, 6, 7)
    world_from_segment = se3_matrix(forward_kinematics(skeleton, motion).wxyz_xyz)
    segment_from_camera = se3_matrix(rig.segment_from_camera)
    for c, s in enumerate(rig.segments):
        ref = world_from_segment[:, s] @ segment_from_camera[c]
        np.testing.assert_allclose(se3_matrix(got[:, c]), ref, atol=1e-13)
    # The same through the SE3 API of the rig, for an arbitrary batch of segment poses.
    seg = forward_kinematics(skeleton, motion)
    np.testing.assert_allclose(rig.world_from_camera(seg).wxyz_xyz, got, atol=0)
    assert isinstance(camera_poses(skeleton, rig, motion[0]), SE3)


def test_unknown_joint_type_name_is_a_value_error():
    with pytest.raises(ValueError, match="slider"):
        Skeleton(**skeleton_kwargs(joint_types=("free", "ball", "ball", "ball", "slider", "fixed")))
