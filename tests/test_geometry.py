"""Tests for bcmocap.geometry: rotation angles, quaternion averaging, slerp, Euler angles, conversions, rigid and
similarity fits."""

import itertools

import numpy as np
import pytest
from conftest import quat_distance, quat_matrix, quat_multiply, random_quaternions, rodrigues

from scipy.spatial.transform import Rotation

from bcmocap.geometry import (
    apply_pose,
    average_quaternions,
    canonical_quat,
    compose_poses,
    euler_to_matrix,
    invert_pose,
    kabsch,
    matrix_from_quat,
    quat_from_matrix,
    quat_identity,
    rotation_angle,
    rotate_by_quat,
    rotation_from_covariance,
    similarity,
    slerp,
)


def axis_angle_quat(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    angle = np.asarray(angle, float)[..., None]
    return np.concatenate([np.cos(angle / 2), np.sin(angle / 2) * axis], axis=-1)


def same_rotation(a, b) -> bool:
    """Quaternions equal up to sign."""
    return np.allclose(a, b, atol=1e-12) or np.allclose(a, -np.asarray(b), atol=1e-12)


# ---- rotation_angle -------------------------------------------------------------------------------


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.5, 2.0, np.pi - 1e-3, np.pi - 1e-6, np.pi - 1e-9, np.pi])
def test_rotation_angle_is_exact_near_zero_and_pi(angle):
    rng = np.random.default_rng(0)
    q_a = random_quaternions(rng, (5,))
    axis = rng.normal(size=3)
    q_b = quat_multiply(q_a, axis_angle_quat(axis, angle))
    got = np.asarray(rotation_angle(q_a, q_b))
    # An arccos of the dot product would lose half the digits near 0 (and near π): demand full precision.
    np.testing.assert_allclose(got, angle, rtol=1e-9, atol=1e-15)


def test_rotation_angle_is_insensitive_to_quaternion_sign():
    rng = np.random.default_rng(1)
    q_a, q_b = random_quaternions(rng, (2, 8))
    ref = np.asarray(rotation_angle(q_a, q_b))
    for sa, sb in itertools.product([1, -1], repeat=2):
        np.testing.assert_allclose(rotation_angle(sa * q_a, sb * q_b), ref, rtol=0, atol=1e-14)
    np.testing.assert_allclose(rotation_angle(q_a, -q_a), 0.0, atol=1e-15)
    np.testing.assert_allclose(ref, quat_distance(q_a, q_b), atol=1e-7)


def test_rotation_angle_is_the_geodesic_angle_at_most_pi():
    q = axis_angle_quat([0.0, 0.0, 1.0], 1.5 * np.pi)  # the same rotation as −π/2
    np.testing.assert_allclose(rotation_angle(quat_identity(), q), 0.5 * np.pi, rtol=1e-12)


# ---- average_quaternions --------------------------------------------------------------------------


def test_average_of_identical_rotations_is_that_rotation_whatever_the_signs():
    rng = np.random.default_rng(2)
    q = random_quaternions(rng, ())
    copies = np.tile(q, (7, 1)) * rng.choice([-1.0, 1.0], size=(7, 1))
    mean = average_quaternions(copies)
    assert mean[0] >= 0
    assert same_rotation(mean, q)
    np.testing.assert_allclose(np.linalg.norm(mean), 1.0, atol=1e-14)


def test_average_of_symmetric_spread_is_the_centre_and_sign_flips_do_not_matter():
    rng = np.random.default_rng(3)
    centre = random_quaternions(rng, ())
    perturb = []
    for axis in np.eye(3):
        for s in (1.0, -1.0):
            perturb.append(quat_multiply(centre, axis_angle_quat(axis, s * 0.3)))
    perturb = np.array(perturb)
    mean = average_quaternions(perturb)
    assert same_rotation(mean, canonical_quat(centre))
    flipped = perturb * rng.choice([-1.0, 1.0], size=(len(perturb), 1))
    np.testing.assert_allclose(average_quaternions(flipped), mean, atol=1e-12)


def test_average_weights_ignore_zero_weighted_rotations():
    rng = np.random.default_rng(4)
    q = random_quaternions(rng, (3,))
    mean = average_quaternions(q, weights=np.array([0.0, 2.0, 0.0]))
    assert same_rotation(mean, q[1])


def test_average_quaternions_errors():
    with pytest.raises(ValueError, match=r"expected q \(N, 4\)"):
        average_quaternions(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="weights"):
        average_quaternions(np.tile([1.0, 0, 0, 0], (3, 1)), weights=np.ones(2))
    with pytest.raises(ValueError, match="no rotation has a positive weight"):
        average_quaternions(np.tile([1.0, 0, 0, 0], (3, 1)), weights=np.zeros(3))


# ---- slerp ----------------------------------------------------------------------------------------


def test_slerp_endpoints_and_constant_angular_speed():
    rng = np.random.default_rng(5)
    q0, q1 = random_quaternions(rng, (2, 6), max_angle=np.pi)
    total = quat_distance(q0, q1)
    assert same_rotation(slerp(q0, q1, np.zeros(6)), q0)
    np.testing.assert_allclose(quat_distance(slerp(q0, q1, np.ones(6)), q1), 0.0, atol=1e-7)
    for t in (0.25, 0.5, 0.9):
        mid = slerp(q0, q1, np.full(6, t))
        np.testing.assert_allclose(np.linalg.norm(mid, axis=-1), 1.0, atol=1e-14)
        np.testing.assert_allclose(quat_distance(q0, mid), t * total, atol=1e-7)
        np.testing.assert_allclose(quat_distance(mid, q1), (1 - t) * total, atol=1e-7)


def test_slerp_takes_the_short_way_when_signs_differ():
    q0 = axis_angle_quat([0, 0, 1], 0.0)
    q1 = -axis_angle_quat([0, 0, 1], 0.4)
    mid = slerp(q0, q1, 0.5)
    assert same_rotation(mid, axis_angle_quat([0, 0, 1], 0.2))


def test_slerp_of_identical_rotations():
    q = random_quaternions(np.random.default_rng(6), ())
    out = slerp(q, q, 0.3)
    assert np.all(np.isfinite(out))
    assert same_rotation(out, q)


# ---- Euler angles ---------------------------------------------------------------------------------


@pytest.mark.parametrize("order", ["".join(p) for p in itertools.product("XYZ", repeat=3)] + ["X", "ZY", "yxz"])
def test_euler_to_matrix_matches_rodrigues_products(order):
    rng = np.random.default_rng(7)
    angles = rng.uniform(-np.pi, np.pi, size=(4, len(order)))
    got = euler_to_matrix(angles, order)
    assert got.shape == (4, 3, 3)
    for b in range(4):
        ref = np.eye(3)
        for k, axis in enumerate(order.upper()):
            ref = ref @ rodrigues(angles[b, k] * np.eye(3)["XYZ".index(axis)])
        np.testing.assert_allclose(got[b], ref, atol=1e-14)


def test_euler_to_matrix_shape_error():
    with pytest.raises(ValueError, match=r"3 axes 'ZXY' but angles have shape \(2,\)"):
        euler_to_matrix(np.zeros(2), "ZXY")


# ---- quaternion ↔ matrix --------------------------------------------------------------------------


def test_matrix_quaternion_round_trips():
    rng = np.random.default_rng(8)
    q = random_quaternions(rng, (2, 3, 5))
    m = matrix_from_quat(q)
    assert m.shape == (2, 3, 5, 3, 3)
    np.testing.assert_allclose(m, quat_matrix(q), atol=1e-14)
    back = quat_from_matrix(m)
    assert back.shape == q.shape
    assert np.all(back[..., 0] >= 0)
    np.testing.assert_allclose(back, canonical_quat(q), atol=1e-12)
    np.testing.assert_allclose(matrix_from_quat(back), m, atol=1e-14)


@pytest.mark.parametrize("axis", [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [1, -2, 0.5]])
def test_matrix_quaternion_round_trip_at_half_turns(axis):
    # w = 0: the branch of the matrix → quaternion conversion that must not use the trace.
    for angle in (np.pi, np.pi - 1e-7):
        m = rodrigues(angle * np.asarray(axis, float) / np.linalg.norm(axis))
        q = quat_from_matrix(m)
        np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-14)
        np.testing.assert_allclose(matrix_from_quat(q), m, atol=1e-12)


def test_rotation_angle_gradient_is_finite_at_equal_rotations():
    import jax

    q = random_quaternions(np.random.default_rng(9), ())
    grad = np.asarray(jax.grad(lambda a: rotation_angle(a, q))(q))
    assert np.all(np.isfinite(grad))


def test_kabsch_matches_scipy_and_is_a_proper_rotation():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(7, 3))
    rot = Rotation.random(random_state=4)
    tgt = rot.apply(src) + [0.1, -0.2, 0.3] + rng.normal(scale=1e-3, size=(7, 3))
    r, t = kabsch(src, tgt)
    ref, _ = Rotation.align_vectors(tgt - tgt.mean(0), src - src.mean(0))
    np.testing.assert_allclose(r, ref.as_matrix(), atol=1e-10)
    np.testing.assert_allclose(r, rot.as_matrix(), atol=5e-3)
    # a mirrored target still gives det +1
    r, _ = kabsch(src, src * [1, 1, -1])
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_similarity_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    rot = np.asarray(matrix_from_quat(np.array([0.8, 0.2, -0.4, 0.4]) / np.linalg.norm([0.8, 0.2, -0.4, 0.4])))
    s, r, t = similarity(src, 2.5 * src @ rot.T + [1.0, -2.0, 0.5])
    assert s == pytest.approx(2.5) and np.allclose(r, rot) and np.allclose(t, [1.0, -2.0, 0.5])


def test_rotation_from_covariance_is_the_same_in_numpy_and_jax_and_batched():
    import jax.numpy as jnp

    rng = np.random.default_rng(5)
    m = rng.normal(size=(4, 3, 3))
    r = rotation_from_covariance(m)
    np.testing.assert_allclose(np.asarray(rotation_from_covariance(jnp.asarray(m))), r, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    for k in range(4):  # R maximises tr(Rᵀ M) over rotations: no random rotation does better
        best = np.trace(r[k].T @ m[k])
        assert all(np.trace(q.T @ m[k]) <= best + 1e-12 for q in Rotation.random(200, random_state=k).as_matrix())


# ---- numpy rigid transforms (wxyz_xyz) ------------------------------------------------------------


def random_poses(rng: np.random.Generator, shape) -> np.ndarray:
    """wxyz_xyz poses ``(*shape, 7)``: random unit quaternions (either sign) and translations."""
    return np.concatenate([random_quaternions(rng, shape), rng.normal(size=(*shape, 3))], axis=-1)


def pose_matrix(pose: np.ndarray) -> np.ndarray:
    """``(..., 4, 4)`` homogeneous matrices of wxyz_xyz poses (through scipy, an independent reference)."""
    out = np.broadcast_to(np.eye(4), (*pose.shape[:-1], 4, 4)).copy()
    out[..., :3, :3] = Rotation.from_quat(pose[..., [1, 2, 3, 0]].reshape(-1, 4)).as_matrix().reshape(*pose.shape[:-1], 3, 3)
    out[..., :3, 3] = pose[..., 4:]
    return out


def test_rotate_by_quat_matches_scipy_and_matrix_from_quat_with_broadcasting():
    rng = np.random.default_rng(11)
    q = random_quaternions(rng, (5, 1))
    v = rng.normal(size=(1, 6, 3))
    out = rotate_by_quat(q, v)
    assert out.shape == (5, 6, 3)
    want = np.einsum("aij,abj->abi", Rotation.from_quat(q[:, 0, [1, 2, 3, 0]]).as_matrix(), np.broadcast_to(v, (5, 6, 3)))
    np.testing.assert_allclose(out, want, atol=1e-12)
    np.testing.assert_allclose(out, np.einsum("...ij,...j->...i", matrix_from_quat(q), v), atol=1e-12)
    # the quaternion's sign does not matter
    np.testing.assert_allclose(rotate_by_quat(-q, v), out, atol=1e-12)


def test_matrix_from_quat_columns_are_the_rotated_axes():
    """kinematics.rom relies on this: the matrix is the basis rotated by rotate_by_quat, bit for bit."""
    q = random_quaternions(np.random.default_rng(12), (200,))
    columns = np.stack([rotate_by_quat(q, e) for e in np.eye(3)], axis=-1)
    np.testing.assert_array_equal(matrix_from_quat(q), columns)


def test_apply_pose_is_rotation_then_translation():
    rng = np.random.default_rng(13)
    pose = random_poses(rng, (4, 1))
    points = rng.normal(size=(4, 7, 3))
    out = apply_pose(pose, points)
    np.testing.assert_allclose(out, np.einsum("...ij,...j->...i", matrix_from_quat(pose[..., :4]), points) + pose[..., 4:],
                               atol=1e-12)
    homogeneous = np.einsum("...ij,...j->...i", pose_matrix(pose), np.concatenate([points, np.ones((4, 7, 1))], -1))
    np.testing.assert_allclose(out, homogeneous[..., :3], atol=1e-12)


def test_compose_poses_is_the_matrix_product():
    rng = np.random.default_rng(14)
    a, b = random_poses(rng, (3, 1)), random_poses(rng, (1, 5))
    ab = compose_poses(a, b)
    assert ab.shape == (3, 5, 7)
    np.testing.assert_allclose(pose_matrix(ab), pose_matrix(a) @ pose_matrix(b), atol=1e-12)
    p = rng.normal(size=3)
    np.testing.assert_allclose(apply_pose(ab, p), apply_pose(a, apply_pose(b, p)), atol=1e-12)


def test_invert_pose_undoes_a_pose_from_either_side():
    rng = np.random.default_rng(15)
    pose = random_poses(rng, (6,))
    inverse = invert_pose(pose)
    np.testing.assert_allclose(pose_matrix(inverse), np.linalg.inv(pose_matrix(pose)), atol=1e-12)
    for both in (compose_poses(pose, inverse), compose_poses(inverse, pose)):
        np.testing.assert_allclose(both[:, 4:], 0.0, atol=1e-12)
        np.testing.assert_allclose(np.abs(both[:, 0]), 1.0, atol=1e-12)  # identity rotation, up to the sign of q
        np.testing.assert_allclose(both[:, 1:4], 0.0, atol=1e-12)
    points = rng.normal(size=(6, 3))
    np.testing.assert_allclose(apply_pose(inverse, apply_pose(pose, points)), points, atol=1e-12)


def test_rotation_onto_turns_a_direction_onto_another_by_the_smallest_rotation():
    from bcmocap.geometry import rotation_onto

    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    r = rotation_onto(a, 2.0 * b)  # any length
    unit = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)  # noqa: E731
    np.testing.assert_allclose(np.einsum("nij,nj->ni", r, unit(a)), unit(b), atol=1e-12)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    # The smallest: its angle is the angle between them, about their cross product.
    angle = np.arccos(np.clip((np.trace(r, axis1=-2, axis2=-1) - 1) / 2, -1, 1))
    np.testing.assert_allclose(angle, np.arccos(np.sum(unit(a) * unit(b), -1)), atol=1e-9)
    np.testing.assert_allclose(rotation_onto(a[0], a[0]), np.eye(3), atol=1e-12)
    half = rotation_onto(a[0], -a[0])  # opposite: a half turn
    np.testing.assert_allclose(half @ unit(a[0]), -unit(a[0]), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(half), 1.0)
