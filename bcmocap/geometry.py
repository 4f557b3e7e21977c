"""Rotations and rigid transforms (thin helpers over jaxlie).

Quaternions are scalar-first ``(w, x, y, z)`` as in jaxlie. SE(3) parameters are ``(w, x, y, z,
tx, ty, tz)`` (``jaxlie.SE3.wxyz_xyz``); the SE(3) tangent is ordered (translation, rotation).
Transforms are named ``a_from_b``: ``p_a = a_from_b @ p_b``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

SO3 = jaxlie.SO3
SE3 = jaxlie.SE3


def quat_identity(*batch: int) -> jax.Array:
    """Identity quaternions, shape ``(*batch, 4)``."""
    return jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0, 0.0]), (*batch, 4))


def rotation_angle(q_a: jax.Array, q_b: jax.Array) -> jax.Array:
    """Geodesic angle (rad) between rotations given as quaternions ``(..., 4)``.

    Uses ``2 atan2(|vec(a⁻¹b)|, |w|)``, accurate near 0 and π and insensitive to the quaternion sign.
    """
    rel = (SO3(q_a).inverse() @ SO3(q_b)).wxyz
    n2 = jnp.sum(rel[..., 1:] ** 2, axis=-1)
    norm = jnp.where(n2 > 0, jnp.sqrt(jnp.where(n2 > 0, n2, 1.0)), 0.0)  # finite gradient at zero angle
    return 2.0 * jnp.arctan2(norm, jnp.abs(rel[..., 0]))


def canonical_quat(q: jax.Array) -> jax.Array:
    """Quaternions ``(..., 4)`` normalised and with a non-negative scalar part."""
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jnp.where(q[..., :1] < 0, -q, q)


def average_quaternions(q: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Chordal L2 mean of rotations (Markley et al. 2007): the dominant eigenvector of Σ w q qᵀ.

    Args:
        q: ``(N, 4)`` quaternions (either sign).
        weights: ``(N,)`` non-negative weights, or None for equal weights.

    Returns:
        ``(4,)`` unit quaternion with non-negative scalar part.
    """
    q = np.asarray(q, dtype=np.float64)
    w = np.ones(len(q)) if weights is None else np.asarray(weights, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 4 or len(w) != len(q):
        raise ValueError(f"average_quaternions: expected q (N, 4) and weights (N,), got {q.shape} and {w.shape}")
    if np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError("average_quaternions: weights must be finite and non-negative")
    if not np.any(w > 0):
        raise ValueError("average_quaternions: no rotation has a positive weight")
    m = (q * w[:, None]).T @ q
    _, vecs = np.linalg.eigh(m)
    mean = vecs[:, -1]
    return mean if mean[0] >= 0 else -mean


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation between quaternions ``(..., 4)`` at fractions ``t`` ``(...)``."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    small = theta < 1e-8
    sin_theta = np.where(small, 1.0, np.sin(theta))
    a = np.where(small, 1.0 - t, np.sin((1.0 - t) * theta) / sin_theta)
    b = np.where(small, t, np.sin(t * theta) / sin_theta)
    out = a * q0 + b * q1
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def quat_from_matrix(matrix: np.ndarray) -> np.ndarray:
    """Quaternions ``(..., 4)`` from rotation matrices ``(..., 3, 3)`` (numpy, any batch)."""
    matrix = np.asarray(matrix, dtype=np.float64)
    flat = matrix.reshape(-1, 3, 3)
    out = np.asarray(jax.vmap(lambda m: SO3.from_matrix(m).wxyz)(flat))
    return canonical_quat(out).reshape(*matrix.shape[:-2], 4)


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` from unit quaternions ``(..., 4)`` wxyz (numpy, no JAX dispatch)."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    rows = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of wxyz quaternions ``(..., 4)`` (numpy, broadcasting)."""
    w1, v1, w2, v2 = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate([w1 * w2 - np.sum(v1 * v2, -1, keepdims=True), w1 * v2 + w2 * v1 + np.cross(v1, v2)], -1)


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """The inverse of unit wxyz quaternions ``(..., 4)`` (numpy)."""
    return np.concatenate([q[..., :1], -q[..., 1:]], -1)


# ---- rigid transforms in numpy ------------------------------------------------------------------
# Host-side preprocessing (the range-of-motion solve, virtual cameras) runs on arrays whose sizes
# change with every segment and joint; jaxlie's eager ops would compile anew for each shape, so
# these wxyz_xyz operations are written in numpy.


def rotate_by_quat(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectors ``(..., 3)`` rotated by unit wxyz quaternions ``(..., 4)`` (numpy, broadcasting)."""
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def compose_poses(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for wxyz_xyz rigid transforms ``(..., 7)`` (numpy, broadcasting): ``a_from_c`` of
    ``a_from_b`` and ``b_from_c``."""
    rotation = quat_multiply(a[..., :4], b[..., :4])
    return np.concatenate([rotation, rotate_by_quat(a[..., :4], b[..., 4:]) + a[..., 4:]], -1)


def invert_pose(a: np.ndarray) -> np.ndarray:
    """Inverses ``(..., 7)`` of wxyz_xyz rigid transforms ``(..., 7)`` with unit quaternions (numpy):
    ``b_from_a`` of ``a_from_b``."""
    q = quat_conjugate(a[..., :4])
    return np.concatenate([q, -rotate_by_quat(q, a[..., 4:])], -1)


def apply_pose(a: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points ``(..., 3)`` mapped by wxyz_xyz rigid transforms ``(..., 7)``, ``R p + t`` (numpy, broadcasting)."""
    return rotate_by_quat(a[..., :4], p) + a[..., 4:]


def quat_exp(rotvec: np.ndarray) -> np.ndarray:
    """wxyz unit quaternions ``(..., 4)`` of rotation vectors ``(..., 3)`` (rad; numpy)."""
    v = np.asarray(rotvec, np.float64)
    theta = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * theta
    # sin(θ/2)/θ, with its Taylor series near 0
    k = np.where(theta > 1e-6, np.sin(half) / np.where(theta > 1e-6, theta, 1.0), 0.5 - theta**2 / 48.0)
    return np.concatenate([np.cos(half), k * v], axis=-1)


def quat_log(q: np.ndarray) -> np.ndarray:
    """Rotation vectors ``(..., 3)`` of wxyz quaternions ``(..., 4)`` (angle in [0, π]; numpy)."""
    q = np.where(q[..., :1] < 0, -q, q)
    n = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    theta = 2.0 * np.arctan2(n, q[..., :1])
    scale = np.where(n > 1e-12, theta / np.where(n > 1e-12, n, 1.0), 2.0 / q[..., :1])
    return scale * q[..., 1:]


def rotation_from_covariance(m):
    """The proper rotation (det +1) ``R`` maximising ``tr(Rᵀ M)``: the least-squares ``R source ≈ target``.

    Args:
        m: ``(..., 3, 3)`` cross-covariance ``M = Σ w_i target_i source_iᵀ`` (of centred points for a
            rigid fit). numpy in, numpy out; a JAX array (also traced) in, JAX out.

    Returns:
        ``(..., 3, 3)`` rotations (Kabsch, with the reflection fixed by the last singular vector).
    """
    xp = jnp if isinstance(m, jax.Array) else np
    u, _, vt = xp.linalg.svd(m)
    det = xp.sign(xp.linalg.det(u @ vt))
    det = xp.where(det == 0, 1.0, det)
    flip = xp.concatenate([xp.ones((*det.shape, 2)), det[..., None]], axis=-1)
    return (u * flip[..., None, :]) @ vt


def kabsch(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation with ``target ≈ R @ source + t`` in the weighted least-squares sense (numpy).

    Args:
        source, target: ``(..., N, 3)`` corresponding points (rows with NaN get zero weight).
        weights: ``(..., N)`` non-negative weights (None: all 1).

    Returns:
        ``R`` ``(..., 3, 3)`` proper rotations (det +1) and ``t`` ``(..., 3)``. With fewer than three
        non-collinear weighted points the rotation about their line is arbitrary (but proper).
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if source.shape != target.shape or source.shape[-1] != 3:
        raise ValueError(f"kabsch: source and target must have the same shape (..., N, 3), got {source.shape} and {target.shape}")
    w = np.ones(source.shape[:-1]) if weights is None else np.asarray(weights, dtype=np.float64)
    w = np.where(np.isfinite(source).all(-1) & np.isfinite(target).all(-1), w, 0.0)
    src, tgt = np.nan_to_num(source), np.nan_to_num(target)
    total = np.maximum(w.sum(-1, keepdims=True), 1e-300)
    mu_s = (w[..., None] * src).sum(-2) / total
    mu_t = (w[..., None] * tgt).sum(-2) / total
    r = rotation_from_covariance(np.einsum("...n,...ni,...nj->...ij", w, tgt - mu_t[..., None, :], src - mu_s[..., None, :]))
    return r, mu_t - np.einsum("...ij,...j->...i", r, mu_s)


def rotation_onto(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` smallest rotations taking directions ``a`` onto ``b`` (``(..., 3)``, any length; numpy);
    where they are opposite, a half turn about an axis perpendicular to ``a``."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    a = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-300)
    b = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-300)
    v = np.cross(a, b)
    c = np.sum(a * b, axis=-1)
    k = np.zeros((*v.shape[:-1], 3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k = k - np.swapaxes(k, -1, -2)
    opposite = c < -1 + 1e-9
    rot = np.eye(3) + k + k @ k / np.where(opposite, 1.0, 1.0 + c)[..., None, None]
    perp = np.cross(a, np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]))
    perp /= np.maximum(np.linalg.norm(perp, axis=-1, keepdims=True), 1e-300)
    half = 2 * perp[..., :, None] * perp[..., None, :] - np.eye(3)
    return np.where(opposite[..., None, None], half, rot)


def similarity(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: ``(s, R, t)`` minimising ``Σ |s R source_i + t − target_i|²`` over points ``(N, 3)`` (numpy),
    e.g. to align a reconstruction to the world by its camera centres (§5.1)."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    mu_s, mu_t = source.mean(0), target.mean(0)
    a, b = source - mu_s, target - mu_t
    m = b.T @ a
    r = rotation_from_covariance(m)
    scale = float(np.trace(r.T @ m) / np.sum(a**2))
    return scale, r, mu_t - scale * r @ mu_s


def euler_to_matrix(angles_rad: np.ndarray, order: str) -> np.ndarray:
    """Rotation matrices from intrinsic-order Euler angles as BVH and ASF write them.

    ``order`` names the axes in the order the rotations are *composed* from the left, e.g. "ZXY"
    gives ``Rz(a0) @ Rx(a1) @ Ry(a2)`` (BVH channel order; ASF "XYZ" axis order is written
    ``Rx @ Ry @ Rz`` when it means ``v' = Rz Ry Rx v``: pass the order the matrices multiply in).

    Args:
        angles_rad: ``(..., len(order))`` angles in radians.
        order: axes, each of "X", "Y", "Z".
    """
    angles_rad = np.asarray(angles_rad, dtype=np.float64)
    if angles_rad.shape[-1] != len(order):
        raise ValueError(f"euler_to_matrix: {len(order)} axes '{order}' but angles have shape {angles_rad.shape}")
    out = np.broadcast_to(np.eye(3), (*angles_rad.shape[:-1], 3, 3)).copy()
    for k, axis in enumerate(order.upper()):
        c, s = np.cos(angles_rad[..., k]), np.sin(angles_rad[..., k])
        m = np.zeros((*angles_rad.shape[:-1], 3, 3))
        i = "XYZ".index(axis)
        j, l = (i + 1) % 3, (i + 2) % 3
        m[..., i, i] = 1.0
        m[..., j, j] = c
        m[..., l, l] = c
        m[..., j, l] = -s
        m[..., l, j] = s
        out = out @ m
    return out


def transform_points(transform: SE3, points: jax.Array) -> jax.Array:
    """Apply rigid transforms (batch ``S``) to points ``(*S', 3)`` with broadcasting batch shapes.

    Builds the 3×4 matrix once per transform: jaxlie's ``SE3 @ p`` broadcasts a quaternion sandwich
    over every point, ~10× slower in the hot loops (projecting thousands of points per camera).
    """
    m = transform.as_matrix()
    return jnp.einsum("...ij,...j->...i", m[..., :3, :3], points) + m[..., :3, 3]


def rotate_vectors(rotation: SO3, vectors: jax.Array) -> jax.Array:
    """Apply rotations to vectors ``(..., 3)`` through their matrices (see :func:`transform_points`)."""
    return jnp.einsum("...ij,...j->...i", rotation.as_matrix(), vectors)
