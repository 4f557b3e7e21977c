"""Tests for bcmocap.residuals and the structured normal equations of bcmocap.solver.window.

Derivatives are checked against central finite differences in float64, and the solver's block
tridiagonal ``JᵀJ`` / ``Jᵀr`` against a dense autodiff Jacobian of the same window.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import KNEE_AXIS, central_difference, quat_multiply, random_motion, random_quaternions, scene_points

from bcmocap.cameras import camera_at
from bcmocap.geometry import SE3, SO3, transform_points
from bcmocap.kinematics import Motion, camera_poses
from bcmocap.residuals import (
    CameraPairTerm,
    CameraTerm,
    CauchyLoss,
    FrameTerm,
    HomographyTransfer,
    MultiFrameTerm,
    PairTerm,
    HuberLoss,
    JointSmoothness,
    Reprojection,
    RootSmoothness,
    TrivialLoss,
    camera_slots,
    loss_from_name,
    pair_mask,
)
from bcmocap.residuals.base import CameraView, stacked
from bcmocap.residuals.mount_compliance import MountCompliance, MountSmoothness
from bcmocap.residuals.registered_pose import RegisteredPose, registered_pose_data
from bcmocap.residuals.rolling_shutter import READOUT, TIME_OFFSET, RollingShutterReprojection
from bcmocap.residuals.self_calibration import INTRINSICS_CORRECTION, SelfCalibratingReprojection, StaticPrior, intrinsics_correction
from bcmocap.residuals.variables import CAMERA_OFFSETS, Rotation
from bcmocap.solver.model_parameters import ModelParameters, parameter_layout
from bcmocap.solver.window import frame_state, make_window_problem, normal_equations, residuals

W = 3  # frames per window
N = 8  # observation slots per camera-frame
M = 6  # homography slots per camera-frame


def assert_jacobian_close(jac, ref, rtol=1e-7):
    """Entrywise agreement relative to the Jacobian's largest entry (central differences: O(ε²) + O(1e-16/ε))."""
    jac, ref = np.asarray(jac), np.asarray(ref)
    assert jac.shape == ref.shape
    assert np.all(np.isfinite(jac))
    scale = max(np.abs(ref).max(), 1.0)
    np.testing.assert_allclose(jac, ref, rtol=0, atol=rtol * scale)


# ---- robust losses --------------------------------------------------------------------------------

LOSSES = [HuberLoss(1.5), CauchyLoss(2.0), HuberLoss(0.3), CauchyLoss(0.5)]


def rho_reference(loss, s):
    c = loss.scale
    if isinstance(loss, HuberLoss):
        return np.where(s <= c * c, s, 2 * c * np.sqrt(s) - c * c)
    return c * c * np.log1p(s / (c * c))


@pytest.mark.parametrize("loss", LOSSES, ids=repr)
def test_scaled_residual_squared_norm_is_rho(loss):
    rng = np.random.default_rng(0)
    r = rng.normal(size=(50, 3)) * np.logspace(-4, 2, 50)[:, None]
    s = np.sum(r * r, axis=-1)
    np.testing.assert_allclose(loss.rho(s), rho_reference(loss, s), rtol=1e-13)
    scaled = np.asarray(loss.scale_residual(r))
    np.testing.assert_allclose(np.sum(scaled * scaled, axis=-1), rho_reference(loss, s), rtol=1e-12)
    # The scaling keeps each block's direction.
    factor = np.sum(scaled * r, -1) / s
    np.testing.assert_allclose(scaled, factor[:, None] * r, rtol=1e-12, atol=1e-300)
    assert np.all(factor > 0) and np.all(factor <= 1 + 1e-15)


@pytest.mark.parametrize("loss", LOSSES, ids=repr)
def test_losses_are_the_identity_for_small_residuals(loss):
    r = np.array([[1e-9, -2e-9], [3e-6, 1e-6], [0.0, 1e-7]])
    np.testing.assert_allclose(loss.scale_residual(r), r, rtol=1e-10)
    if isinstance(loss, HuberLoss):  # exactly the identity inside the quadratic zone
        inside = np.array([[0.99 * loss.scale / np.sqrt(2), 0.99 * loss.scale / np.sqrt(2)]])
        np.testing.assert_array_equal(loss.scale_residual(inside), inside)


@pytest.mark.parametrize("loss", LOSSES + [TrivialLoss()], ids=repr)
def test_loss_derivatives_are_finite_at_zero_and_match_finite_differences(loss):
    zero = jnp.zeros((1, 2))
    jac0 = np.asarray(jax.jacfwd(loss.scale_residual)(zero))
    np.testing.assert_array_equal(jac0.reshape(2, 2), np.eye(2))  # ρ'(0) = 1
    grad0 = jax.grad(lambda r: 0.5 * jnp.sum(loss.scale_residual(r) ** 2))(zero)
    np.testing.assert_array_equal(grad0, 0.0)
    rev0 = np.asarray(jax.jacrev(loss.scale_residual)(zero))
    np.testing.assert_array_equal(rev0, jac0)
    rng = np.random.default_rng(1)
    for r in rng.normal(size=(4, 1, 2)) * np.array([0.1, 1.0, 3.0, 20.0])[:, None, None]:
        jac = jax.jacfwd(loss.scale_residual)(jnp.asarray(r))
        assert_jacobian_close(jac, central_difference(lambda x: loss.scale_residual(x), r), rtol=1e-8)


def test_huber_is_smooth_at_its_threshold():
    loss = HuberLoss(2.0)
    direction = np.array([[0.6, 0.8]])
    jac_at = np.asarray(jax.jacfwd(loss.scale_residual)(jnp.asarray(2.0 * direction)))
    assert np.all(np.isfinite(jac_at))
    below = np.asarray(jax.jacfwd(loss.scale_residual)(jnp.asarray((2.0 - 1e-7) * direction)))
    above = np.asarray(jax.jacfwd(loss.scale_residual)(jnp.asarray((2.0 + 1e-7) * direction)))
    np.testing.assert_allclose(below, above, atol=1e-6)


def test_loss_from_name():
    assert isinstance(loss_from_name("none"), TrivialLoss)
    assert isinstance(loss_from_name("Huber", 3.0), HuberLoss) and loss_from_name("huber", 3.0).scale == 3.0
    assert isinstance(loss_from_name("CAUCHY", 2.0), CauchyLoss)
    with pytest.raises(ValueError, match="unknown robust loss 'tukey'; choose one of none, huber, cauchy"):
        loss_from_name("tukey")


# ---- a tiny window --------------------------------------------------------------------------------


def smooth_truth(skeleton, num_frames, rng) -> Motion:
    """A representable motion whose frames differ by a few degrees and centimetres (numpy, no eager JAX)."""
    first = random_motion(skeleton, None, rng, max_angle=0.8)
    steps = random_quaternions(rng, (num_frames - 1, skeleton.num_segments), max_angle=0.08)
    rot = [np.asarray(first.rotations)]
    for step in steps:
        rot.append(quat_multiply(rot[-1], step))
    rot = np.asarray(skeleton.project_rotations(np.stack(rot)))
    root = np.asarray(first.root_position) + np.cumsum(rng.normal(scale=0.03, size=(num_frames, 3)), axis=0)
    return Motion(root, rot)


def project_all(rig, cam_from_world, points):
    """Pixels ``(T, C, P, 2)`` and validity of all points in all cameras."""
    p_cam = SE3(cam_from_world[:, :, None, :]) @ jnp.asarray(points)[None, None]
    uv, valid = jax.vmap(lambda p: jax.vmap(lambda cam, q: cam.project(q))(rig.intrinsics, p))(p_cam)
    return np.asarray(uv), np.asarray(valid)


@pytest.fixture(scope="module")
def scene(skeleton, rig):
    """Truth over ``W + 1`` frames (index 0 is the frame before the window), measurements, and a reference motion."""
    rng = np.random.default_rng(42)
    c = rig.num_cameras
    truth = smooth_truth(skeleton, W + 1, rng)
    points = scene_points(rng, 20)
    cam_from_world = np.asarray(camera_poses(skeleton, rig, truth).inverse().wxyz_xyz)
    uv, valid = project_all(rig, cam_from_world, points)

    ids = np.stack([np.stack([rng.choice(len(points), N, replace=False) for _ in range(c)]) for _ in range(W)])
    ids[:, :, -1] = -1  # an empty slot
    frames = np.arange(1, W + 1)[:, None, None]
    cams = np.arange(c)[None, :, None]
    pixels = uv[frames, cams, np.clip(ids, 0, None)] + rng.normal(scale=0.7, size=(W, c, N, 2))
    outlier = rng.random((W, c, N)) < 0.15
    pixels[outlier] += rng.normal(scale=40.0, size=(outlier.sum(), 2))
    weights = np.where(ids >= 0, rng.choice([1.0, 0.25, 4.0], size=(W, c, N)), 0.0)
    weights[0, 0, 0] = 0.0
    pixels[ids < 0] = 0.0
    # The homography term pairs window row t with extended frames (t, t + 1).
    hid = ids[:, :, :M].clip(0)
    h_pix = uv[frames, cams, hid] + rng.normal(scale=0.5, size=(W, c, M, 2))
    h_prev = uv[frames - 1, cams, hid] + rng.normal(scale=0.5, size=(W, c, M, 2))
    h_w = np.where(valid[frames, cams, hid] & valid[frames - 1, cams, hid] & (ids[:, :, :M] >= 0), 1.0, 0.0)
    h_w[1, 2] = 0.0  # a camera-frame without matches
    offset = random_quaternions(rng, (W + 1, skeleton.num_segments), max_angle=0.03)
    reference = Motion(
        np.asarray(truth.root_position) + rng.normal(scale=0.02, size=(W + 1, 3)),
        np.asarray(skeleton.project_rotations(quat_multiply(np.asarray(truth.rotations), offset))),
    )
    return dict(
        truth=truth, reference=reference, points=points, cam_from_world=cam_from_world,
        reprojection={"point_ids": ids.astype(np.int32), "pixels": pixels, "weights": weights},
        homography={"pixels": h_pix, "pixels_prev": h_prev, "weights": h_w},
    )


def window_terms(skeleton, scene):
    mask = np.ones(W)
    mask[2] = 0.0  # one pair switched off
    terms = [
        Reprojection(scene["reprojection"], points=scene["points"], loss=CauchyLoss(2.0), name="reprojection"),
        HomographyTransfer(scene["homography"], weight=0.5, loss=HuberLoss(1.0), name="homography"),
        RootSmoothness(mask, rotation_scale=0.5, weight=300.0, name="root smoothness"),
        JointSmoothness(mask, skeleton=skeleton, weight=20.0, name="joint smoothness"),
    ]
    return [t.window(0, W) for t in terms]


@eqx.filter_jit
def dense_system(problem, y):
    """Residual vector and its dense Jacobian ``(m, W, D)`` by forward-mode autodiff."""
    flat = lambda yy: jnp.concatenate([r.reshape(-1) for r in residuals(problem, yy)])
    return flat(y), jax.jacfwd(flat)(y)


def flat_residual_blocks(problem, y):
    """The residual blocks of each term, cut from the (compiled) dense system."""
    r, _ = dense_system(problem, y)
    shapes = [a.shape for a in jax.eval_shape(lambda: residuals(problem, y))]
    parts = np.split(np.asarray(r), np.cumsum([int(np.prod(sh)) for sh in shapes])[:-1])
    return [p.reshape(sh) for p, sh in zip(parts, shapes)]


structured_system = eqx.filter_jit(normal_equations)


@pytest.fixture(scope="module")
def problems(skeleton, rig, scene):
    """The window with and without a previous frame (one compilation serves both: has_previous is traced).

    Robust losses on both image terms (Cauchy on reprojection, with 40 px outliers far beyond its 2 px
    scale; Huber on homography); the smoothness terms are plain least squares.
    """
    terms = window_terms(skeleton, scene)
    return {has_previous: make_window_problem(skeleton, rig, terms, scene["reference"], has_previous)
            for has_previous in (False, True)}


def irls_reference(problem, y):
    """``Σ λ ρ'(s) JᵀJ`` from the dense Jacobian of the raw residual blocks (losses removed, λ = 1)."""
    raw_terms = tuple(eqx.tree_at(lambda t: (t.loss, t.weight), t, (TrivialLoss(), jnp.asarray(1.0))) for t in problem.terms)
    raw = eqx.tree_at(lambda p: p.terms, problem, raw_terms)
    blocks = residuals(raw, y)
    row_weights = [
        jnp.broadcast_to((t.weight * t.loss.derivative(jnp.sum(b * b, axis=-1)))[..., None], b.shape).reshape(-1)
        for t, b in zip(problem.terms, blocks)
    ]
    _, jac = dense_system(raw, y)
    jac = np.asarray(jac).reshape(jac.shape[0], -1)
    return jac.T @ (np.concatenate([np.asarray(w) for w in row_weights])[:, None] * jac)


@pytest.mark.slow
@pytest.mark.parametrize("has_previous", [False, True])
def test_normal_equations_match_dense_jacobian(problems, skeleton, has_previous):
    """The structured system equals the dense one: the exact gradient Jᵀr of the cost, and the IRLS
    Gauss–Newton matrix Σ λρ'(s) JᵀJ of the raw residuals (what Ceres uses where ρ'' ≤ 0)."""
    problem = problems[has_previous]
    y = jnp.asarray(np.random.default_rng(3).normal(scale=0.01, size=(W, skeleton.num_dofs)))
    hess, scale = assert_structured_matches_dense(problem, y)
    for t in range(W - 1):
        assert np.abs(hess[t, :, t + 1]).max() > 1e-3 * scale  # frames really are coupled
    np.testing.assert_array_equal(hess[0, :, 2], 0.0)  # and only neighbours are


def assert_structured_matches_dense(problem, y):
    """Check the structured normal equations of ``problem`` at ``y (W, D)`` against the dense autodiff
    Jacobian (gradient Jᵀr and IRLS matrix); return the dense matrix ``(W, D, W, D)`` and its largest entry."""
    d = y.shape[1]
    r, jac = dense_system(problem, y)
    r, jac = np.asarray(r), np.asarray(jac).reshape(len(r), W * d)
    assert np.all(np.isfinite(jac)) and np.abs(r).max() > 1.0
    grad = (jac.T @ r).reshape(W, d)
    hess = irls_reference(problem, y).reshape(W, d, W, d)
    ne = structured_system(problem, y)
    assert ne.diag.shape == (W, d, d) and ne.grad.shape == (W, d)
    assert [b.shape for b in ne.bands] == [(W - k, d, d) for k in range(1, problem.history + 1)]
    scale = np.abs(hess).max()
    for t in range(W):
        np.testing.assert_allclose(ne.diag[t], hess[t, :, t], rtol=1e-8, atol=1e-9 * scale)
        np.testing.assert_allclose(ne.grad[t], grad[t], rtol=1e-8, atol=1e-9 * np.abs(grad).max())
    for k, band in enumerate(ne.bands, start=1):
        for t in range(W - k):
            np.testing.assert_allclose(band[t], hess[t, :, t + k], rtol=1e-8, atol=1e-9 * scale)
    for t in range(W):  # nothing outside the band
        for u in range(t + problem.history + 1, W):
            np.testing.assert_array_equal(hess[t, :, u], 0.0)
    return hess, scale


def test_has_previous_switches_the_seam_pair(problems):
    y = jnp.zeros((W, problems[False].skeleton.num_dofs))
    without = [np.asarray(a) for a in flat_residual_blocks(problems[False], y)]
    with_prev = [np.asarray(a) for a in flat_residual_blocks(problems[True], y)]
    for a, b in zip(without[1:], with_prev[1:]):  # homography and the smoothness terms: pair terms
        np.testing.assert_array_equal(a[0], 0.0)
        assert np.abs(b[0]).max() > 0
        np.testing.assert_array_equal(a[1:], b[1:])
    np.testing.assert_array_equal(without[0], with_prev[0])  # reprojection does not pair frames
    # The switched-off pair (mask 0 at row 2) stays zero.
    np.testing.assert_array_equal(with_prev[2][2], 0.0)
    np.testing.assert_array_equal(with_prev[3][2], 0.0)


def test_window_jacobian_matches_finite_differences(problems, skeleton):
    """The dense Jacobian used as the reference above is itself right (retract → FK → rig → lens → loss)."""
    problem = problems[True]
    y = np.random.default_rng(4).normal(scale=0.01, size=(W, skeleton.num_dofs))
    _, jac = dense_system(problem, jnp.asarray(y))
    fd = central_difference(lambda yy: dense_system(problem, jnp.asarray(yy))[0], y, eps=1e-7)
    assert_jacobian_close(jac, fd, rtol=1e-7)


# ---- per-term Jacobians against finite differences ------------------------------------------------


def _view(poses, camera) -> CameraView:
    """What a camera term sees of one camera at one pose, or at two (stacked, oldest first)."""
    return CameraView(poses[0] if len(poses) == 1 else stacked(*poses), camera)


def _camera_term_residual(xi, term, poses, camera, data):
    """A camera term's finished residual with each pose moved by a left perturbation ``exp(ξ_i) · pose_i``."""
    moved = [SE3.exp(xi[6 * i : 6 * i + 6]) @ SE3(p) for i, p in enumerate(poses)]
    return term.finish(*term.residual(_view(moved, camera), data, {}))


# Compiled once per term class, loss and data shape; shared by the tests below.
camera_term_residual = eqx.filter_jit(_camera_term_residual)
camera_term_jacfwd = eqx.filter_jit(jax.jacfwd(_camera_term_residual))
camera_term_jacrev = eqx.filter_jit(jax.jacrev(_camera_term_residual))


def reprojection_term(data) -> Reprojection:
    """A windowed reprojection term like the one of the window problem (so compilations are shared)."""
    return Reprojection(data, points=jnp.zeros((0, 3)), loss=CauchyLoss(2.0), name="reprojection")


def check_camera_term_jacobian(term, xi, poses, camera, data, eps=1e-6, rtol=1e-7):
    term = eqx.tree_at(lambda t: t.data, term, data)  # the term's own data is not used: share compilations
    poses = tuple(jnp.asarray(p.wxyz_xyz if isinstance(p, SE3) else p) for p in poses)
    f = lambda x: camera_term_residual(jnp.asarray(x), term, poses, camera, data)
    jac = np.asarray(camera_term_jacfwd(jnp.asarray(xi), term, poses, camera, data))
    assert_jacobian_close(jac, central_difference(f, np.asarray(xi), eps=eps), rtol=rtol)
    return jac


def test_reprojection_jacobian_wrt_camera_pose(rig, problems, scene):
    term = problems[True].terms[0]
    t, c = 1, 2
    data = jax.tree.map(lambda a: a[t, c], term.data)
    xi = np.random.default_rng(5).normal(scale=1e-3, size=6)
    check_camera_term_jacobian(term, xi, (scene["cam_from_world"][t + 1, c],), camera_at(rig.intrinsics, c), data)


def test_registered_pose_residual_and_jacobian(rig):
    """Zero at the registered pose; a rotation of 0.01 rad about x and a centre 3 cm off read as such over σ;
    the Jacobian with respect to the camera pose matches central differences."""
    rng = np.random.default_rng(11)
    world_from_camera = SE3.from_rotation_and_translation(SO3.exp(jnp.asarray(rng.normal(size=3))), jnp.asarray(rng.normal(size=3)))
    data = {"world_from_camera": world_from_camera.wxyz_xyz, "weights": jnp.asarray(1.0)}
    term = RegisteredPose(data, sigma=np.array([0.02, np.deg2rad(1.0)]), loss=CauchyLoss(8.0), name="registered pose")
    camera = camera_at(rig.intrinsics, 0)
    r, valid = term.residual(CameraView(world_from_camera.inverse(), camera), data, {})
    np.testing.assert_allclose(r, 0.0, atol=1e-12)
    assert r.shape == (1, 6) and bool(valid[0])
    moved = SE3.from_rotation_and_translation(world_from_camera.rotation() @ SO3.exp(jnp.array([0.01, 0.0, 0.0])),
                                              world_from_camera.translation() + jnp.array([0.0, 0.03, 0.0]))
    r, _ = term.residual(CameraView(moved.inverse(), camera), data, {})
    np.testing.assert_allclose(r[0], [0.0, 1.5, 0.0, 2 * np.sin(0.005) / np.deg2rad(1.0), 0.0, 0.0], atol=1e-9)
    _, valid = term.residual(CameraView(moved.inverse(), camera), {**data, "weights": jnp.asarray(0.0)}, {})
    assert not bool(valid[0])
    xi = rng.normal(scale=1e-2, size=6)
    check_camera_term_jacobian(term, xi, (np.asarray(moved.inverse().wxyz_xyz),), camera, data)


def test_registered_pose_applies_to_registered_camera_frames_with_few_measurements():
    poses = np.full((2, 3, 7), np.nan)
    poses[:, :, 0] = 1.0
    poses[:, :, 1:] = 0.5
    registered = np.array([[True, True, False], [True, False, True]])
    weights = np.zeros((2, 3, 30))
    weights[0, 0, :25] = 1.0  # 25 measurements: enough
    weights[1, 2, :3] = 1.0   # 3: too few
    data = registered_pose_data(poses, registered, weights, below=20)
    np.testing.assert_array_equal(data["weights"], [[0, 1, 0], [1, 0, 1]])
    assert np.all(np.isfinite(data["world_from_camera"]))
    np.testing.assert_array_equal(data["world_from_camera"][0, 2], [1, 0, 0, 0, 0, 0, 0])  # unused: identity


def test_unmeasured_orientation_holds_the_rotation_alone_of_camera_frames_with_nothing_else(rig):
    # Only camera-frames with neither a registration nor a measurement, on a segment no other camera of which is
    # measured in that frame, are held, at the initial poses given (the window's own frames of them); every window
    # gets the term. With the centre's σ infinite, a centre 1 m off reads nothing and a rotation of 0.02 rad reads
    # 0.02 rad over σ; the Jacobian matches central differences.
    import types

    from bcmocap.residuals.registered_pose import unmeasured_orientation_data, unmeasured_orientation_terms

    rng = np.random.default_rng(5)
    poses = np.zeros((2, 4, 7))
    poses[..., 0] = 1.0
    poses[..., 4:] = rng.normal(size=(2, 4, 3))
    segments = np.array([0, 1, 2, 2])  # cameras 2 and 3 on one segment
    registered = np.array([[True, False, False, False], [False, False, True, False]])
    weights = np.zeros((2, 4, 10))
    weights[0, 2, 4] = 1.0  # one measurement: held by it, not by the prior, and so is camera 3 on its segment
    data = unmeasured_orientation_data(poses, registered, weights, segments)
    np.testing.assert_array_equal(data["weights"], [[0, 1, 0, 0], [1, 1, 0, 1]])
    window = types.SimpleNamespace(start=1, stop=2, rig=types.SimpleNamespace(segments=segments),
                                   correspondences=types.SimpleNamespace(registered=registered[1:], weights=weights[1:]))
    (term,) = unmeasured_orientation_terms(window, poses, sigma_deg=5.0)
    np.testing.assert_array_equal(np.asarray(term.data["weights"]), [[1, 1, 0, 1]])
    np.testing.assert_array_equal(np.asarray(term.data["world_from_camera"])[0, [0, 1, 3]], poses[1, [0, 1, 3]])
    nothing = types.SimpleNamespace(start=0, stop=1, rig=window.rig, correspondences=types.SimpleNamespace(
        registered=np.ones((1, 4), bool), weights=weights[:1]))
    (term,) = unmeasured_orientation_terms(nothing, poses, sigma_deg=5.0)
    assert not np.asarray(term.data["weights"]).any()
    with pytest.raises(ValueError, match="sigma_deg must be > 0, got 0"):
        unmeasured_orientation_terms(window, poses, sigma_deg=0)
    initial = SE3.from_rotation_and_translation(SO3.exp(jnp.asarray(rng.normal(size=3))), jnp.asarray(rng.normal(size=3)))
    one = {"world_from_camera": initial.wxyz_xyz, "weights": jnp.asarray(1.0)}
    held = RegisteredPose(one, sigma=np.array([np.inf, np.deg2rad(5.0)]), loss=CauchyLoss(8.0), name="unmeasured")
    camera = camera_at(rig.intrinsics, 0)
    moved = SE3.from_rotation_and_translation(initial.rotation() @ SO3.exp(jnp.array([0.0, 0.02, 0.0])),
                                              initial.translation() + jnp.array([1.0, 0.0, 0.0]))
    r, _ = held.residual(CameraView(moved.inverse(), camera), one, {})
    np.testing.assert_allclose(r[0], [0.0, 0.0, 0.0, 0.0, 2 * np.sin(0.01) / np.deg2rad(5.0), 0.0], atol=1e-12)
    check_camera_term_jacobian(held, rng.normal(scale=1e-2, size=6), (np.asarray(moved.inverse().wxyz_xyz),), camera, one)


def off_axis_points(theta_deg, cam_from_world, distance=4.0):
    theta = np.deg2rad(theta_deg)
    azimuth = np.linspace(0.3, 2 * np.pi, N, endpoint=False)
    p_cam = distance * np.stack(
        [np.sin(theta) * np.cos(azimuth), np.sin(theta) * np.sin(azimuth), np.full(N, np.cos(theta))], axis=1
    )
    return p_cam, np.asarray(cam_from_world.inverse() @ p_cam)


@pytest.mark.parametrize("off_axis_deg", [0.0, 30.0, 80.0, 85.0, 89.0, 95.0, 150.0, 178.0])
def test_reprojection_jacobian_across_the_fisheye_field(rig, off_axis_deg):
    """Points up to the edge of the lens model's domain (179°), past the 170° lens's image edge (85°) and 90°."""
    camera = camera_at(rig.intrinsics, 0)
    cam_from_world = SE3.from_rotation_and_translation(SO3.exp(jnp.array([0.3, -0.2, 0.1])), jnp.array([0.1, 0.2, -0.3]))
    p_cam, points = off_axis_points(off_axis_deg, cam_from_world)
    uv, valid = camera.project(p_cam)
    assert np.all(valid)
    data = {"points": jnp.asarray(points), "pixels": jnp.asarray(np.asarray(uv) + 1.5), "weights": np.full(N, 2.0)}
    term = reprojection_term(data)
    # Small steps: at 178° a large one would cross the 179° limit of the model.
    check_camera_term_jacobian(term, np.zeros(6), (cam_from_world,), camera, data, eps=1e-7, rtol=1e-6)


def test_invalid_observations_give_zero_residuals_and_finite_jacobians(rig):
    camera = camera_at(rig.intrinsics, 1)
    p_cam = np.array([
        [0.5, -0.2, 3.0],  # valid
        [0.0, 0.0, -5.0],  # straight behind the camera
        [0.05, 0.0, -5.0],  # 179.4° off axis: beyond the model's domain
        [1.0, 0.5, 2.0],  # valid but weight 0
        [0.0, 0.0, 0.0],  # at the camera centre
        [-0.3, 0.4, 2.5],  # weight 0 and NaN pixels (a padded slot)
        [0.01, 0.0, -5.0],  # 179.9° off axis
        [0.0, 0.0, 1e-160],  # (almost) at the camera centre
    ])
    pixels = np.full((N, 2), 50.0)
    pixels[5] = np.nan
    weights = np.array([1.0, 1.0, 1.0, 0.0, 1.0, 0.0, 1.0, 1.0])
    data = {"points": jnp.asarray(p_cam), "pixels": jnp.asarray(pixels), "weights": jnp.asarray(weights)}
    term = reprojection_term(data)
    identity = jnp.asarray(SE3.identity().wxyz_xyz)
    _, valid = term.residual(CameraView(SE3(identity), camera), data, {})
    np.testing.assert_array_equal(valid, [True] + [False] * (N - 1))
    args = (jnp.zeros(6), eqx.tree_at(lambda t: t.data, term, data), (identity,), camera, data)
    out = np.asarray(camera_term_residual(*args))
    np.testing.assert_array_equal(out[1:], 0.0)
    assert np.all(out[0] != 0.0)
    for jac in (camera_term_jacfwd(*args), camera_term_jacrev(*args)):
        jac = np.asarray(jac)
        assert np.all(np.isfinite(jac))
        np.testing.assert_array_equal(jac[1:], 0.0)
        assert np.abs(jac[0]).max() > 1.0


def test_homography_jacobian_wrt_both_camera_poses(rig, problems, scene):
    term = problems[True].terms[1]
    t, c = 2, 3
    data = jax.tree.map(lambda a: a[t, c], term.data)
    assert np.asarray(data["weights"]).sum() > 0
    poses = (scene["cam_from_world"][t, c], scene["cam_from_world"][t + 1, c])
    xi = np.random.default_rng(6).normal(scale=1e-3, size=12)
    jac = check_camera_term_jacobian(term, xi, poses, camera_at(rig.intrinsics, c), data)
    # Rotation-only transfer: camera translations do not matter (tangent order: translation, rotation).
    np.testing.assert_allclose(jac[..., :3], 0.0, atol=1e-12)
    np.testing.assert_allclose(jac[..., 6:9], 0.0, atol=1e-12)
    assert np.abs(jac[..., 3:6]).max() > 1.0 and np.abs(jac[..., 9:]).max() > 1.0


def test_homography_of_a_pure_rotation_is_exact(rig):
    """With exact matches of a rotating camera the transfer residual vanishes."""
    camera = camera_at(rig.intrinsics, 0)
    rng = np.random.default_rng(7)
    curr = SE3.from_rotation_and_translation(SO3.exp(jnp.array([0.1, 0.2, 0.3])), jnp.array([0.5, 0.0, 1.0]))
    prev = SE3.from_rotation_and_translation(SO3.exp(jnp.array([0.15, 0.1, 0.35])), jnp.array([-2.0, 1.0, 0.0]))
    rays = rng.normal(size=(10, 3)) + np.array([0.0, 0.0, 2.5])  # directions in the world
    uv_curr, ok_curr = camera.project(curr.rotation() @ rays)
    uv_prev, ok_prev = camera.project(prev.rotation() @ rays)
    assert np.all(ok_curr & ok_prev)
    data = {"pixels": uv_curr, "pixels_prev": uv_prev, "weights": jnp.ones(10)}
    r, valid = HomographyTransfer(data).residual(_view((prev, curr), camera), data, {})
    assert np.all(valid)
    np.testing.assert_allclose(r, 0.0, atol=1e-9)


@pytest.fixture(scope="module")
def smoothness_terms(skeleton):
    return (RootSmoothness(np.ones(1), rotation_scale=0.7, weight=4.0),
            JointSmoothness(np.ones(1), skeleton=skeleton, weight=9.0))


def _smoothness_residuals(y2, terms, skeleton, rig, reference):
    """Both smoothness terms' finished residuals ``(6 + D - 6,)`` of the pair of frames ``reference[0], reference[1]``."""
    prev = frame_state(skeleton, rig, reference[0], y2[0])
    curr = frame_state(skeleton, rig, reference[1], y2[1])
    return jnp.concatenate([t.finish(*t.residual(stacked(prev, curr), jnp.asarray(1.0), {})).ravel() for t in terms])


smoothness_residuals = eqx.filter_jit(_smoothness_residuals)
smoothness_jacobian = eqx.filter_jit(jax.jacfwd(_smoothness_residuals))


@pytest.mark.parametrize("case", ["generic", "identical frames, straight knee"])
def test_smoothness_jacobians_wrt_frame_tangents(skeleton, rig, smoothness_terms, case):
    rng = np.random.default_rng(8)
    if case == "generic":
        reference = random_motion(skeleton, 2, rng, max_angle=2.0)
        y2 = rng.normal(scale=0.05, size=(2, skeleton.num_dofs))
    else:  # log at the identity and a knee at exactly 0 rad
        one = random_motion(skeleton, None, rng)
        rot = np.array(one.rotations)
        rot[4] = [1.0, 0, 0, 0]
        reference = Motion(np.tile(one.root_position, (2, 1)), np.tile(rot, (2, 1, 1)))
        y2 = np.zeros((2, skeleton.num_dofs))
    args = (smoothness_terms, skeleton, rig, reference)
    f = lambda yy: smoothness_residuals(jnp.asarray(yy), *args)
    jac = np.asarray(smoothness_jacobian(jnp.asarray(y2), *args))
    assert jac.shape == (skeleton.num_dofs, 2, skeleton.num_dofs)
    assert_jacobian_close(jac, central_difference(f, y2), rtol=1e-8)
    if case != "generic":
        np.testing.assert_array_equal(np.asarray(f(y2)), 0.0)
        # At equal frames the residual is linear in the tangents: ±sqrt(weight) times the DOF selection.
        np.testing.assert_allclose(jac[:, 0], -jac[:, 1], atol=1e-12)
        np.testing.assert_allclose(jac[:, 1], np.diag(np.r_[np.full(3, 2.0), np.full(3, 1.4), np.full(10, 3.0)]),
                                   atol=1e-12)


def test_smoothness_values(skeleton, rig, smoothness_terms):
    base = skeleton.rest_motion(2)
    knee = KNEE_AXIS / np.linalg.norm(KNEE_AXIS)
    rot = np.array(base.rotations)
    rot[0, 4] = np.r_[np.cos(0.1), np.sin(0.1) * knee]  # knee at 0.2 rad
    rot[1, 4] = np.r_[np.cos(0.35), np.sin(0.35) * knee]  # knee at 0.7 rad
    rot[1, 0] = np.r_[np.cos(0.05), 0.0, 0.0, np.sin(0.05)]  # root yaws by 0.1 rad
    motion = Motion(np.array([[0.0, 0.0, 1.0], [0.1, -0.2, 1.0]]), rot)
    r = np.asarray(smoothness_residuals(jnp.zeros((2, skeleton.num_dofs)), smoothness_terms, skeleton, rig, motion))
    # Root: sqrt(4) × (translation (m), 0.7 × rotation (rad)).
    np.testing.assert_allclose(r[:6], 2.0 * np.array([0.1, -0.2, 0.0, 0.0, 0.0, 0.7 * 0.1]), atol=1e-14)
    # Joints: sqrt(9) × each DOF's change; only the knee angle moved, by 0.5 rad.
    expected = np.zeros(10)
    expected[-1] = 3.0 * 0.5
    np.testing.assert_allclose(r[6:], expected, atol=1e-14)


def test_pair_mask():
    np.testing.assert_array_equal(pair_mask(4), [0.0, 1.0, 1.0, 1.0])


def test_term_check_errors(scene):
    rep = Reprojection(scene["reprojection"], points=scene["points"], name="reprojection")
    rep.check(W, 6)
    with pytest.raises(ValueError, match=r"reprojection: data\['point_ids'\] has shape \(3, 6, 8\), expected \(3, 5, 8\)"):
        rep.check(W, 5)
    bad = dict(scene["reprojection"], point_ids=np.full_like(scene["reprojection"]["point_ids"], 20))
    with pytest.raises(ValueError, match="point_ids reach 20 but there are only 20 points"):
        Reprojection(bad, points=scene["points"], name="reprojection").check(W, 6)
    hom = HomographyTransfer({k: v for k, v in scene["homography"].items() if k != "pixels_prev"}, name="hom")
    with pytest.raises(ValueError, match="hom: data has no 'pixels_prev'"):
        hom.check(W, 6)
    root = RootSmoothness(np.ones(W + 1), name="root smoothness")
    with pytest.raises(ValueError, match=r"root smoothness: data has shape \(4,\); expected leading axes \(3,\)"):
        root.check(W, 6)


def test_homography_check_allows_nan_in_unused_slots(scene):
    data = {k: np.array(v) for k, v in scene["homography"].items()}
    data["pixels_prev"][0, 0] = np.nan
    data["weights"][0, 0] = 0.0
    HomographyTransfer(data, name="homography").check(W, 6)


def test_camera_slots_keep_the_cameras_with_weight_in_order():
    weights = np.zeros((3, 5, 2))
    weights[0, 3, 1] = weights[0, 1, 0] = weights[2, 4, 0] = 1.0
    pixels = np.arange(3 * 5 * 2 * 2, dtype=float).reshape(3, 5, 2, 2)
    slots = camera_slots({"weights": weights, "pixels": pixels}, multiple=1)
    np.testing.assert_array_equal(slots["camera"], [[1, 3], [0, 0], [4, 0]])
    assert slots["camera"].dtype == np.int32
    np.testing.assert_array_equal(slots["pixels"][0], pixels[0, [1, 3]])
    np.testing.assert_array_equal(slots["pixels"][2, 0], pixels[2, 4])
    np.testing.assert_array_equal(slots["weights"][1], 0.0)  # padded slots carry no weight
    np.testing.assert_array_equal(slots["weights"][2, 1], 0.0)
    assert camera_slots({"weights": weights}, multiple=4)["camera"].shape == (3, 4)
    assert camera_slots({"weights": weights}, multiple=8)["camera"].shape == (3, 5)  # never more than C
    with pytest.raises(ValueError, match="already has a 'camera' key"):
        camera_slots(slots)


@pytest.mark.slow
def test_camera_slots_give_the_same_cost_and_normal_equations(skeleton, rig, scene, problems):
    """A homography term in camera slots is the same term: same residuals, same structured system."""
    sparse = {k: np.array(v) for k, v in scene["homography"].items()}
    keep = np.zeros(sparse["weights"].shape[:2], bool)
    keep[0, [1, 4]] = keep[1, 5] = keep[2, [0, 2]] = True
    sparse["weights"] = np.where(keep[..., None], sparse["weights"], 0.0)
    slotted = camera_slots(sparse, multiple=1)
    assert slotted["camera"].shape == (W, 2)
    y = jnp.asarray(np.random.default_rng(5).normal(scale=0.01, size=(W, skeleton.num_dofs)))
    systems, costs = [], []
    for data in (sparse, slotted):
        term = HomographyTransfer(data, weight=0.5, loss=HuberLoss(1.0), name="homography")
        term.check(W, rig.num_cameras)
        terms = [t for t in window_terms(skeleton, scene) if t.label != "homography"] + [term.window(0, W)]
        problem = make_window_problem(skeleton, rig, terms, scene["reference"], True)
        costs.append(float(sum(jnp.sum(r * r) for r in residuals(problem, y))))
        systems.append(structured_system(problem, y))
    assert costs[0] == pytest.approx(costs[1], rel=1e-12)
    for a, b in zip(jax.tree.leaves(systems[0]), jax.tree.leaves(systems[1])):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(a).max(initial=0.0))


def test_camera_slot_errors_are_named(scene):
    slotted = camera_slots(dict(scene["homography"]), multiple=1)
    bad = dict(slotted, camera=slotted["camera"] + 6)
    with pytest.raises(ValueError, match=r"hom: data\['camera'\] names cameras outside \[0, 6\)"):
        HomographyTransfer(bad, name="hom").check(W, 6)
    bad = dict(slotted, camera=slotted["camera"].astype(float))
    with pytest.raises(ValueError, match=r"hom: data\['camera'\] has shape .* expected integer camera indices"):
        HomographyTransfer(bad, name="hom").check(W, 6)


class _HeadUp(FrameTerm):
    """A user's frame term: the head segment's z axis towards world +z (3 residuals per frame)."""

    def residual(self, state, data, variables):
        z = state.world_from_segment.rotation().as_matrix()[2, :, 2]
        return (z - jnp.array([0.0, 0.0, 1.0]))[None], data[None] > 0


class _Bearings(CameraTerm):
    """A user's generic camera term: unit bearings to known points, through the whole 6-DOF pose (no
    world_points shortcut)."""

    def residual(self, x, data, variables):
        p = transform_points(x.cam_from_world, data["points"])
        return p / jnp.linalg.norm(p, axis=-1, keepdims=True) - data["bearings"], data["valid"]


class _CentreStep(CameraPairTerm):
    """A user's camera pair term with translation: the camera centre's step between frames (odometry)."""

    def residual(self, x, data, variables):
        step = x[1].cam_from_world.inverse().translation() - x[0].cam_from_world.inverse().translation()
        return (step - data["step"])[None], data["valid"][None]


@pytest.mark.slow
def test_user_frame_camera_and_translating_pair_terms_match_the_dense_jacobian(skeleton, rig, scene):
    """Terms written by a user in the three generic shapes — a FrameTerm through forward kinematics, a
    CameraTerm on the full pose, a CameraPairTerm that reads translations — give the structured solver the
    exact gradient and Gauss–Newton matrix of the dense autodiff Jacobian."""
    rng = np.random.default_rng(5)
    c = rig.num_cameras
    pose = scene["cam_from_world"]  # (W + 1, C, 7), frame 0 before the window
    points = rng.normal(size=(W, c, 4, 3)) + np.array([0.0, 0.0, 3.0])
    cam = SE3(jnp.asarray(pose[1:, :, None]))
    p = np.asarray(transform_points(cam, jnp.asarray(points)))
    bearings = p / np.linalg.norm(p, axis=-1, keepdims=True) + rng.normal(scale=0.01, size=p.shape)
    centres = np.asarray(SE3(jnp.asarray(pose)).inverse().translation())
    steps = centres[1:] - centres[:-1] + rng.normal(scale=0.005, size=(W, c, 3))
    terms = [
        Reprojection(scene["reprojection"], points=scene["points"], name="reprojection"),
        _HeadUp(np.ones(W), weight=4.0, name="head up"),
        _Bearings({"points": points, "bearings": bearings, "valid": np.ones((W, c, 4), bool)}, weight=50.0,
                  loss=HuberLoss(0.05), name="bearings"),
        _CentreStep({"step": steps, "valid": np.ones((W, c), bool)}, weight=100.0, name="centre step"),
        RegisteredPose({"world_from_camera": np.asarray(SE3(jnp.asarray(pose[1:])).inverse().wxyz_xyz)
                        + rng.normal(scale=0.01, size=(W, c, 7)), "weights": (rng.random((W, c)) < 0.5) * 1.0},
                       sigma=np.array([0.02, 0.02]), loss=CauchyLoss(8.0), name="registered pose"),
    ]
    problem = make_window_problem(skeleton, rig, [t.window(0, W) for t in terms], scene["reference"], True)
    hess, scale = assert_structured_matches_dense(problem, jnp.asarray(rng.normal(scale=0.01, size=(W, skeleton.num_dofs))))
    # only the pair term couples neighbouring frames: every camera centre moves with the root position, so
    # the root-position block of the coupling is −λ·C·I
    np.testing.assert_allclose(hess[0, :3, 1, :3], -100.0 * c * np.eye(3), atol=1e-9 * scale)


class _CentreAcceleration(MultiFrameTerm):
    """A user's three-frame term: each camera centre's second difference (an accelerometer's view of the
    camera, in m per frame²)."""

    span = 3

    def residual(self, states, data, variables):
        centres = states.world_from_camera.translation()  # (3, C, 3)
        return centres[2] - 2.0 * centres[1] + centres[0] - data["acceleration"], data["valid"]


def _with_history(reference, history, rng):
    """``reference`` (1 frame before the window) with ``history`` frames before the window."""
    extra = history - 1
    root = np.asarray(reference.root_position)
    rot = np.asarray(reference.rotations)
    root = np.concatenate([root[:1] + rng.normal(scale=0.02, size=(extra, 3)), root])
    return Motion(root, np.concatenate([np.repeat(rot[:1], extra, axis=0), rot]))


@pytest.fixture(scope="module")
def span_problems(skeleton, rig, scene):
    """Reprojection, root smoothness and a three-frame term over the window, with 0, 1 and 2 fixed frames."""
    rng = np.random.default_rng(8)
    c = rig.num_cameras
    terms = [
        Reprojection(scene["reprojection"], points=scene["points"], loss=CauchyLoss(2.0), name="reprojection"),
        RootSmoothness(np.ones(W), weight=30.0, name="root smoothness"),
        _CentreAcceleration({"acceleration": rng.normal(scale=0.01, size=(W, c, 3)), "valid": np.ones((W, c), bool)},
                            weight=1e4, loss=HuberLoss(0.02), name="acceleration"),
    ]
    reference = _with_history(scene["reference"], 2, rng)
    return {n: make_window_problem(skeleton, rig, [t.window(0, W) for t in terms], reference, n) for n in (0, 1, 2)}


@pytest.mark.slow
@pytest.mark.parametrize("num_previous", [0, 2])
def test_multi_frame_term_gives_the_banded_dense_system(span_problems, skeleton, num_previous):
    """A three-frame term makes the window's matrix block banded with bandwidth 2; the structured system is
    the dense one (gradient and IRLS matrix) and really couples frames two apart."""
    problem = span_problems[num_previous]
    assert problem.history == 2 and problem.num_frames == W
    y = jnp.asarray(np.random.default_rng(9).normal(scale=0.01, size=(W, skeleton.num_dofs)))
    hess, scale = assert_structured_matches_dense(problem, y)
    assert np.abs(hess[0, :, 2]).max() > 1e-3 * scale


def test_multi_frame_term_is_dropped_where_its_frames_are_missing(span_problems, skeleton):
    """Block t of a three-frame term reads frames t−2…t: it exists iff t − 2 ≥ −num_previous."""
    y = jnp.zeros((W, skeleton.num_dofs))
    blocks = {n: np.asarray(residuals(p, y)[2]) for n, p in span_problems.items()}
    for n, b in blocks.items():
        for t in range(W):
            present = t - 2 >= -n
            assert (np.abs(b[t]).max() > 0) == present, (n, t)
    np.testing.assert_array_equal(blocks[0][2], blocks[2][2])  # the full block does not depend on the history


class _OffsetHeadUp(FrameTerm):
    """A user's frame term reading a static variable: the head's z axis equals world +z plus a constant tilt."""

    def static_variables(self):
        return {"tilt": 3}

    def residual(self, state, data, variables):
        z = state.world_from_segment.rotation().as_matrix()[2, :, 2]
        return (z - jnp.array([0.0, 0.0, 1.0]) - state.statics["tilt"])[None], data[None] > 0


class _OffsetRootStep(PairTerm):
    """A pair term sharing the static variable: the root's step between frames equals the tilt (a drift)."""

    def static_variables(self):
        return {"tilt": 3}

    def residual(self, x, data, variables):
        step = x[1].motion.root_position - x[0].motion.root_position
        return (step - variables["tilt"])[None], data[None] > 0


@pytest.mark.slow
def test_static_variables_give_the_dense_bordered_system(skeleton, rig, scene):
    """Frame and pair terms reading one static variable: the structured system's banded part, its border
    (coupling H[t, z], H[z, z]) and both gradients are those of the dense autodiff Jacobian over (y, z)."""
    terms = [Reprojection(scene["reprojection"], points=scene["points"], loss=CauchyLoss(2.0), name="reprojection"),
             _OffsetHeadUp(np.ones(W), weight=4.0, name="head up"),
             _OffsetRootStep(np.ones(W), weight=30.0, loss=HuberLoss(0.01), name="root step")]
    problem = make_window_problem(skeleton, rig, [t.window(0, W) for t in terms], scene["reference"], True,
                                  {"tilt": np.array([0.01, -0.02, 0.03])})
    assert problem.num_statics == 3
    hess, n = assert_bordered_matches_dense(problem, np.random.default_rng(13))
    assert np.abs(hess[:n, n:]).max() > 1.0  # the border is really there (λ = 4 and 30 terms)


@pytest.mark.slow
def test_model_parameters_give_the_dense_bordered_system(skeleton, rig, scene):
    """The skeleton and mounts as static variables (offsets, mounts, the knee's axis, away from their base
    values) next to a term's own static variable: every term of the paper (reprojection, homography over
    two frames' camera poses, both smoothness terms) and the prior couple to them as the dense autodiff
    Jacobian over (y, z) says."""
    rng = np.random.default_rng(17)
    layout = parameter_layout(skeleton, rig)
    sigmas = layout.sigmas(0.01, 0.01, 1.0, 1.0)[np.asarray(layout.active)]
    parameters = ModelParameters(skeleton, rig, jnp.asarray(0.01 * rng.normal(size=layout.size)), jnp.asarray(1.0 / sigmas), layout)
    terms = window_terms(skeleton, scene) + [_OffsetHeadUp(np.ones(W), weight=4.0, name="head up").window(0, W)]
    problem = make_window_problem(skeleton, rig, terms, scene["reference"], True, {"tilt": np.array([0.01, -0.02, 0.03])},
                                  parameters)
    assert problem.num_statics == 3 + parameters.size
    hess, n = assert_bordered_matches_dense(problem, rng)
    model = slice(n + 3, None)
    camera_rows = np.abs(hess[:n, model]).max(axis=0)
    assert np.sum(camera_rows > 1e-6 * np.abs(hess).max()) > 0.5 * parameters.size  # most of θ is seen by the window


class _Lean(FrameTerm):
    """A per-frame Euclidean block ("lean") follows the head's z axis, with a prior."""

    def frame_variables(self):
        return {"lean": 2}

    def residual(self, state, data, variables):
        lean = state.world_from_segment.rotation().as_matrix()[2, :2, 2] - state.variables["lean"]
        return jnp.stack([lean, 10.0 * state.variables["lean"]]), jnp.full(2, data > 0)


class _HeadFrame(FrameTerm):
    """The head's orientation equals an unknown constant rotation (a static :class:`Rotation`)."""

    def static_variables(self):
        return {"head frame": Rotation()}

    def residual(self, state, data, variables):
        head = SO3(state.world_from_segment.rotation().wxyz[2])
        return (head.inverse() @ SO3(state.statics["head frame"])).log()[None], data[None] > 0


class _CameraTurn(CameraPairTerm):
    """Each camera's rotation between frames equals an unknown constant turn (a static :class:`Rotation` read by a
    camera pair term), on camera slots."""

    def static_variables(self):
        return {"turn": Rotation()}

    def residual(self, x, data, variables):
        turn = x[1].cam_from_world.rotation() @ x[0].cam_from_world.rotation().inverse() @ SO3(variables["turn"])
        return turn.log()[None], data["weights"][None] > 0


@pytest.mark.slow
def test_per_frame_variables_and_camera_term_statics_give_the_dense_bordered_system(skeleton, rig, scene):
    """Per-frame blocks (cameras moving on their mounts: MountCompliance, MountSmoothness; a Euclidean block) read
    by frame and pair terms and through the camera poses by the camera terms; per-camera intrinsics corrections
    and a readout correction read by camera and camera-pair terms (SelfCalibratingReprojection,
    RollingShutterReprojection) with a StaticPrior; rotations (manifold statics) read by a frame term and a
    camera pair term on slots: the structured system (banded blocks of D + E, the border, both gradients) is
    that of the dense autodiff Jacobian over (y, z)."""
    rng = np.random.default_rng(23)
    c = rig.num_cameras
    turn_weights = np.where(rng.random((W, c)) < 0.6, 1.0, 0.0)
    turn_weights[:, 0] = 1.0
    terms = [
        SelfCalibratingReprojection(scene["reprojection"], points=scene["points"], loss=CauchyLoss(2.0),
                                    name="reprojection", num_cameras=c),
        RollingShutterReprojection(scene["reprojection"], points=scene["points"], readout=0.6, estimate_readout=True,
                                   calibrate=True, estimate_time_offsets=True, num_cameras=c, weight=0.5,
                                   loss=HuberLoss(1.0), name="rolling shutter"),
        StaticPrior(np.full(W, 1.0 / W), block=INTRINSICS_CORRECTION, variable=intrinsics_correction(c),
                    sigma=jnp.array([0.01, 3.0, 3.0]), name="intrinsics prior"),
        HomographyTransfer(scene["homography"], weight=0.5, loss=HuberLoss(1.0), name="homography"),
        MountCompliance(np.ones(W), num_cameras=c, sigma=jnp.array([0.01] * 3 + [0.02] * 3), name="mount compliance"),
        MountSmoothness(np.ones(W), num_cameras=c, sigma=jnp.array([0.002] * 3 + [0.005] * 3), loss=HuberLoss(3.0),
                        name="mount smoothness"),
        _Lean(np.ones(W), weight=4.0, name="lean"),
        _HeadFrame(np.ones(W), weight=4.0, name="head frame"),
        _CameraTurn(camera_slots({"weights": turn_weights}), weight=2.0, name="turn"),
    ]
    frame_values = {CAMERA_OFFSETS: rng.normal(scale=0.01, size=(W + 1, c, 6)), "lean": rng.normal(scale=0.1, size=(W + 1, 2))}
    statics = {"head frame": random_quaternions(rng, (), max_angle=0.5), "turn": random_quaternions(rng, (), max_angle=0.1),
               INTRINSICS_CORRECTION: rng.normal(scale=[0.003, 1.0, 1.0], size=(c, 3)), READOUT: np.array([0.05]),
               TIME_OFFSET: rng.normal(scale=0.2, size=(c, 1))}
    problem = make_window_problem(skeleton, rig, [t.window(0, W) for t in terms], scene["reference"], True, statics,
                                  frame_values=frame_values)
    assert problem.frame_size == skeleton.num_dofs + 6 * c + 2 and problem.num_statics == 3 + 3 * c + 1 + c + 3
    hess, n = assert_bordered_matches_dense(problem, rng)
    d = problem.frame_size
    offsets = slice(skeleton.num_dofs, skeleton.num_dofs + 6 * c)  # blocks sorted by name: "camera_offsets", "lean"
    assert np.abs(hess[:d, :d][:skeleton.num_dofs, offsets]).max() > 1e-3 * np.abs(hess).max()  # the cameras see them
    assert np.abs(hess[:n, n + 3 : n + 3 + 3 * c]).max() > 1.0  # the intrinsics couple to the frames
    assert np.abs(hess[:n, n + 3 + 3 * c]).max() > 1e-3  # so does the readout
    assert np.abs(hess[:n, n + 4 + 3 * c: n + 4 + 4 * c]).max() > 1e-3  # and each camera's time offset


@pytest.mark.parametrize("turn", [0.3, 1e-2, 1e-3, 5e-4, 1e-5, 0.0])
def test_moved_points_is_the_se3_exponential_with_its_derivatives(turn):
    """The rolling shutter's closed-form motion of points, ``exp(ε ξ) · q``, against the 4×4 matrix exponential
    (scipy's expm) for turns of 0.3 rad to none per frame period (its series branch below 1e-3 rad): the points to
    1e-12 m and the derivatives in the velocity and in ε to central differences of expm. jaxlie's ``SE3.exp``, which
    the term used before, drops the turn's effect on the translation below ~1e-3 rad (a 0.04 error in the
    derivative at rest)."""
    from scipy.linalg import expm

    from bcmocap.residuals.rolling_shutter import moved_points

    rng = np.random.default_rng(11)
    axis = rng.normal(size=3)
    velocity = np.concatenate([rng.normal(size=3) * 0.05, turn * axis / np.linalg.norm(axis)])
    points, periods = rng.normal(size=(12, 3)) * 3.0, rng.uniform(-1.5, 1.5, 12)

    def hat(xi):
        m = np.zeros((4, 4))
        m[:3, :3] = [[0, -xi[5], xi[4]], [xi[5], 0, -xi[3]], [-xi[4], xi[3], 0]]
        m[:3, 3] = xi[:3]
        return m

    def reference(v, e):
        return np.stack([(expm(hat(ei * v)) @ np.append(p, 1.0))[:3] for ei, p in zip(e, points)])

    moved = lambda v, e: moved_points(jnp.asarray(points), v, e)
    np.testing.assert_allclose(np.asarray(moved(jnp.asarray(velocity), jnp.asarray(periods))),
                               reference(velocity, periods), atol=1e-12)
    step = 1e-6
    by_velocity = np.stack([(reference(velocity + step * np.eye(6)[k], periods)
                             - reference(velocity - step * np.eye(6)[k], periods)) / (2 * step) for k in range(6)], -1)
    np.testing.assert_allclose(np.asarray(jax.jacfwd(moved)(jnp.asarray(velocity), jnp.asarray(periods))), by_velocity,
                               atol=1e-7)
    by_period = (reference(velocity, periods + step) - reference(velocity, periods - step)) / (2 * step)
    along = jax.jvp(lambda e: moved(jnp.asarray(velocity), e), (jnp.asarray(periods),), (jnp.ones(12),))[1]
    np.testing.assert_allclose(np.asarray(along), by_period, atol=1e-7)


def test_rolling_shutter_reprojection_explains_row_times(rig):
    """Pixels seen by a rolling shutter from a camera turning and moving at constant velocity: the rolling-shutter
    term's residuals vanish at the true readout, a global-shutter reprojection's do not, and with no readout
    the two terms agree."""
    rng = np.random.default_rng(4)
    camera = jax.tree.map(lambda a: a[0], rig.intrinsics)
    velocity = jnp.array([0.05, -0.02, 0.01, 0.04, 0.08, -0.03])  # per frame: 5 cm, 5° turn
    curr = SE3.exp(jnp.array([0.1, 0.0, 0.2, 0.1, -0.2, 0.05]))
    prev = SE3.exp(-velocity) @ curr
    points = jnp.asarray(rng.uniform([-2, -2, 2], [2, 2, 5], size=(40, 3)))
    readout = 0.8
    pixels, _ = camera.project(curr.apply(points))
    for _ in range(30):  # each pixel's row sets its time, which sets its pixel
        s = (pixels[:, 1] / (camera.height - 1) - 0.5) * readout
        pixels, valid = camera.project(jax.vmap(lambda si, p: (SE3.exp(si * velocity) @ curr).apply(p))(s, points))
    data = {"points": points, "pixels": pixels, "weights": jnp.where(valid, 1.0, 0.0)}
    assert int(valid.sum()) > 20
    shutter = RollingShutterReprojection(data, readout=readout)
    r, ok = shutter.residual(_view((prev, curr), camera), data, {})
    assert np.abs(np.asarray(r)[np.asarray(ok)]).max() < 1e-6
    r_global, ok_global = Reprojection(data).residual(CameraView(curr, camera), data, {})
    assert np.abs(np.asarray(r_global)[np.asarray(ok_global)]).max() > 1.0
    r0, _ = RollingShutterReprojection(data, readout=0.0).residual(_view((prev, curr), camera), data, {})
    np.testing.assert_allclose(np.asarray(r0), np.asarray(r_global), atol=1e-9)


def test_a_cameras_time_offset_moves_it_along_its_velocity_with_finite_difference_derivatives(rig):
    """The rolling-shutter term with a per-camera time offset (static block TIME_OFFSET): pixels exposed a time
    offset after the frame give zero residuals at that offset; the residuals' derivative in the offset is the
    finite-difference one, and an offset of a whole frame period back is the previous frame's global-shutter view."""
    rng = np.random.default_rng(5)
    camera = jax.tree.map(lambda a: a[0], rig.intrinsics)
    velocity = jnp.array([0.05, -0.02, 0.01, 0.04, 0.08, -0.03])
    curr = SE3.exp(jnp.array([0.1, 0.0, 0.2, 0.1, -0.2, 0.05]))
    prev = SE3.exp(-velocity) @ curr
    points = jnp.asarray(rng.uniform([-2, -2, 2], [2, 2, 5], size=(40, 3)))
    readout, offset = 0.6, 0.35
    pixels, _ = camera.project(curr.apply(points))
    for _ in range(30):
        s = (pixels[:, 1] / (camera.height - 1) - 0.5) * readout + offset
        pixels, valid = camera.project(jax.vmap(lambda si, p: (SE3.exp(si * velocity) @ curr).apply(p))(s, points))
    data = {"points": points, "pixels": pixels, "weights": jnp.where(valid, 1.0, 0.0)}
    term = RollingShutterReprojection(data, readout=readout, estimate_time_offsets=True, num_cameras=1)
    assert set(term.static_variables()) == {TIME_OFFSET}

    def residual(value):
        return term.residual(_view((prev, curr), camera), data, {TIME_OFFSET: jnp.reshape(value, (1,))})[0]

    assert np.abs(np.asarray(residual(offset))[np.asarray(valid)]).max() < 1e-6
    for value in (0.0, 0.2, -0.4):
        step = 1e-6
        numeric = (residual(value + step) - residual(value - step)) / (2 * step)
        np.testing.assert_allclose(np.asarray(jax.jacfwd(residual)(value)), np.asarray(numeric), atol=1e-5)
    back = RollingShutterReprojection(data, readout=0.0, estimate_time_offsets=True, num_cameras=1)
    r_back, _ = back.residual(_view((prev, curr), camera), data, {TIME_OFFSET: jnp.array([-1.0])})
    r_prev, _ = Reprojection(data).residual(CameraView(prev, camera), data, {})
    np.testing.assert_allclose(np.asarray(r_back), np.asarray(r_prev), atol=1e-9)


def test_variable_declarations_are_checked(skeleton, rig, scene):
    """Conflicting or malformed declarations and mis-shaped values are refused, naming the block."""
    c = rig.num_cameras
    mount = MountCompliance(np.ones(W), num_cameras=c + 1, sigma=jnp.ones(6), name="mount prior").window(0, W)
    with pytest.raises(ValueError, match="camera_offsets.*rig has"):
        make_window_problem(skeleton, rig, [mount], scene["reference"], True)
    head = _HeadFrame(np.ones(W), name="head frame").window(0, W)
    with pytest.raises(ValueError, match="static variable 'head frame': value of shape"):
        make_window_problem(skeleton, rig, [head], scene["reference"], True, {"head frame": np.ones(3)})

    class _Clash(FrameTerm):
        def static_variables(self):
            return {"head frame": 3}

        def residual(self, state, data, variables):
            return state.statics["head frame"][None], data[None] > 0

    with pytest.raises(ValueError, match="'head frame'.*head frame declares Rotation.*clash declares Euclidean"):
        make_window_problem(skeleton, rig, [head, _Clash(np.ones(W), name="clash").window(0, W)], scene["reference"], True)

    class _Bad(FrameTerm):
        def frame_variables(self):
            return {"x": 0}

        def residual(self, state, data, variables):
            return jnp.zeros((1, 1)), data[None] > 0

    with pytest.raises(ValueError, match="bad: per-frame variable 'x'"):
        make_window_problem(skeleton, rig, [_Bad(np.ones(W), name="bad").window(0, W)], scene["reference"], True)


def assert_bordered_matches_dense(problem, rng):
    """Check the structured bordered system of ``problem`` at random ``(y, z)`` against the dense autodiff
    Jacobian over ``(y, z)``: the IRLS matrix (banded part, coupling, static block) and the gradient. Blocks
    after the terms' (the model's prior) are plain least squares. Returns the dense matrix and ``W·(D + E)``."""
    d, s = problem.frame_size, problem.num_statics
    y, z = jnp.asarray(rng.normal(scale=0.01, size=(W, d))), jnp.asarray(rng.normal(scale=0.01, size=s))
    flat = lambda v: jnp.concatenate([r.reshape(-1) for r in residuals(problem, v[: W * d].reshape(W, d), v[W * d :])])
    raw = eqx.tree_at(lambda p: p.terms, problem,
                      tuple(eqx.tree_at(lambda t: (t.loss, t.weight), t, (TrivialLoss(), jnp.asarray(1.0))) for t in problem.terms))
    raw_flat = lambda v: jnp.concatenate([r.reshape(-1) for r in residuals(raw, v[: W * d].reshape(W, d), v[W * d :])])
    v = jnp.concatenate([y.reshape(-1), z])
    r, jac = np.asarray(flat(v)), np.asarray(jax.jacfwd(flat)(v))
    blocks = residuals(raw, y, z)
    row_weights = np.concatenate([np.asarray(jnp.broadcast_to(
        (t.weight * t.loss.derivative(jnp.sum(b * b, axis=-1)))[..., None], b.shape)).reshape(-1)
        for t, b in zip(problem.terms, blocks)] + [np.ones(b.size) for b in blocks[len(problem.terms):]])
    raw_jac = np.asarray(jax.jacfwd(raw_flat)(v))
    hess = raw_jac.T @ (row_weights[:, None] * raw_jac)
    grad = jac.T @ r
    ne = eqx.filter_jit(normal_equations)(problem, y, z)
    scale = np.abs(hess).max()
    n = W * d
    np.testing.assert_allclose(np.asarray(ne.static_matrix), hess[n:, n:], rtol=1e-8, atol=1e-9 * scale)
    np.testing.assert_allclose(np.asarray(ne.coupling).reshape(n, s), hess[:n, n:], rtol=1e-8, atol=1e-9 * scale)
    np.testing.assert_allclose(np.asarray(ne.static_grad), grad[n:], rtol=1e-8, atol=1e-9 * np.abs(grad).max())
    np.testing.assert_allclose(np.asarray(ne.grad).reshape(-1), grad[:n], rtol=1e-8, atol=1e-9 * np.abs(grad).max())
    for t in range(W):
        np.testing.assert_allclose(ne.diag[t], hess[t * d : (t + 1) * d, t * d : (t + 1) * d], rtol=1e-8, atol=1e-9 * scale)
    for k, band in enumerate(ne.bands, start=1):
        for t in range(W - k):
            np.testing.assert_allclose(band[t], hess[t * d : (t + 1) * d, (t + k) * d : (t + k + 1) * d], rtol=1e-8,
                                       atol=1e-9 * scale)
    return hess, n
