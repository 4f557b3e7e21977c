"""The windowed structured LM solver: reference solves, seams, recovery and bad input."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

from bcmocap.correspondences import Correspondences
from bcmocap.eval import evaluate_motion
from bcmocap.geometry import SE3, SO3, transform_points
from bcmocap.kinematics import Motion, camera_poses
from bcmocap.residuals import CauchyLoss, FrameTerm, JointSmoothness, MultiFrameTerm, Reprojection, RootSmoothness, pair_mask
from bcmocap.residuals.variables import CAMERA_OFFSETS, Euclidean, PerCamera, Rotation
from bcmocap.solver import Problem, SolverOptions, motion_from_tangent, solve, whole_sequence_residual_function, window_starts
from bcmocap.solver.objective import ObjectiveWeights, paper_problem

from conftest import make_rig, make_skeleton, random_motion, scene_points

T = 6


def smooth_motion(skeleton, rng):
    """A slowly changing motion of T frames."""
    base = random_motion(skeleton, None, rng, max_angle=0.6)
    steps = 0.03 * rng.normal(size=(T, skeleton.num_dofs))
    return skeleton.retract(jax.tree.map(lambda a: jnp.broadcast_to(a, (T, *a.shape)), base), jnp.cumsum(steps, axis=0))


def observe(skeleton, rig, motion, points, rng, sigma=0.5, outliers=0.0, camera_offsets=None):
    """Noisy pixels of ``points`` in every camera; ``camera_offsets`` ``(T, C, 6)`` move the cameras on their mounts."""
    world_from_camera = camera_poses(skeleton, rig, motion)
    if camera_offsets is not None:
        world_from_camera = world_from_camera @ SE3.exp(jnp.asarray(camera_offsets))
    cam_from_world = world_from_camera.inverse()
    n = len(points)
    ids = np.full((motion.num_frames, rig.num_cameras, n), -1, np.int32)
    pix = np.zeros((motion.num_frames, rig.num_cameras, n, 2))
    w = np.zeros((motion.num_frames, rig.num_cameras, n))
    for c in range(rig.num_cameras):
        cam = jax.tree.map(lambda a: a[c], rig.intrinsics)
        uv, valid = cam.project(transform_points(SE3(cam_from_world.wxyz_xyz[:, c, None]), points[None]))
        valid = np.asarray(valid & cam.in_image(uv))
        uv = np.asarray(uv) + sigma * rng.normal(size=uv.shape)
        bad = rng.random(valid.shape) < outliers
        uv[bad] = rng.uniform(0, 100, size=(bad.sum(), 2))
        ids[:, c] = np.where(valid, np.arange(n), -1)
        pix[:, c] = np.where(valid[..., None], uv, 0.0)
        w[:, c] = valid / sigma**2
    return ids, pix, w


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(7)
    skeleton = make_skeleton()
    rig = make_rig(skeleton)
    truth = smooth_motion(skeleton, rng)
    points = scene_points(rng, 40)
    ids, pix, w = observe(skeleton, rig, truth, points, rng)
    assert (w > 0).sum(axis=2).min() >= 6, "every camera-frame should see a few points"
    init = skeleton.retract(truth, 0.02 * rng.normal(size=(T, skeleton.num_dofs)))
    return skeleton, rig, truth, points, (ids, pix, w), init


def make_problem(setup, loss=None, root=10.0, joints=1.0):
    skeleton, rig, _, points, (ids, pix, w), _ = setup
    kwargs = {} if loss is None else {"loss": loss}
    terms = [
        Reprojection({"point_ids": ids, "pixels": pix, "weights": w}, points=points, name="reprojection", **kwargs),
        RootSmoothness(pair_mask(T), weight=root),
        JointSmoothness(pair_mask(T), skeleton=skeleton, weight=joints),
    ]
    return Problem(skeleton, rig, terms)


def scipy_minimum(problem, init):
    """The whole sequence's residual function (tangent offsets from ``init``) and scipy's minimum of it."""
    fn = whole_sequence_residual_function(problem, init)
    jac = jax.jit(jax.jacfwd(fn))
    ref = scipy.optimize.least_squares(
        lambda y: np.asarray(fn(y)), np.zeros(T * problem.skeleton.num_dofs), jac=lambda y: np.asarray(jac(y)),
        method="trf", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=200,
    )
    return fn, ref


@pytest.mark.slow
@pytest.mark.parametrize("loss", [None, CauchyLoss(3.0)], ids=["least-squares", "cauchy"])
def test_whole_sequence_matches_scipy(setup, loss):
    """One window over all frames reaches scipy's minimum of the same residuals to 1e-6 relative cost."""
    skeleton, _, _, _, _, init = setup
    problem = make_problem(setup, loss)
    fn, ref = scipy_minimum(problem, init)
    ours = solve(problem, init, SolverOptions(window=T, overlap=0, rtol=1e-10, atol=1e-12, max_steps=60))
    assert ours.converged
    cost_ref = ref.cost
    cost_ours = ours.reports[0].final_cost
    assert abs(cost_ours - cost_ref) <= 1e-6 * cost_ref
    # the same minimiser, too
    y_ours = np.asarray(skeleton.difference(init, ours.motion)).ravel()
    assert np.allclose(y_ours, ref.x, atol=1e-6)
    assert cost_ours == pytest.approx(0.5 * np.sum(np.asarray(fn(ref.x)) ** 2), rel=1e-6)
    # the report's costs are those of the start and of the returned motion
    assert ours.reports[0].initial_cost == pytest.approx(0.5 * np.sum(np.asarray(fn(np.zeros_like(ref.x))) ** 2), rel=1e-12)
    assert cost_ours == pytest.approx(0.5 * np.sum(np.asarray(fn(y_ours)) ** 2), rel=1e-9)


@pytest.mark.slow
def test_windows_agree_with_whole_sequence(setup):
    """Overlapping windows (the first frame of each held by the previous one) leave no visible seam."""
    skeleton, rig, truth, _, _, init = setup
    problem = make_problem(setup)
    whole = solve(problem, init, SolverOptions(window=T, overlap=0, rtol=1e-10, atol=1e-12))
    windowed = solve(problem, init, SolverOptions(window=3, overlap=1, rtol=1e-10, atol=1e-12))
    assert [r.start for r in windowed.reports] == window_starts(T, 3, 1) == [0, 2, 3]
    diff = evaluate_motion(skeleton, windowed.motion, whole.motion)
    assert diff["joint_position_error_cm"]["max"] < 0.05
    err = evaluate_motion(skeleton, windowed.motion, truth)
    assert err["joint_position_error_cm"]["mean"] < 1.0


@pytest.mark.slow
def test_recovers_truth_with_outliers(setup):
    """With 15 % outliers a Cauchy loss still recovers the motion."""
    skeleton, rig, truth, points, _, init = setup
    rng = np.random.default_rng(3)
    ids, pix, w = observe(skeleton, rig, truth, points, rng, sigma=0.5, outliers=0.15)
    problem = Problem(skeleton, rig, [
        Reprojection({"point_ids": ids, "pixels": pix, "weights": w}, points=points, loss=CauchyLoss(3.0)),
        RootSmoothness(pair_mask(T), weight=1.0),
    ])
    before = evaluate_motion(skeleton, init, truth)
    after = evaluate_motion(skeleton, solve(problem, init, SolverOptions(window=T, overlap=0)).motion, truth)
    assert after["joint_angle_error_deg"]["mean"] < 0.25 * before["joint_angle_error_deg"]["mean"]
    assert after["joint_position_error_cm"]["mean"] < 0.5 * before["joint_position_error_cm"]["mean"]


class JointLimit(FrameTerm):
    """A tiny custom term: keep the knee angle below 0.1 rad."""

    def residual(self, state, data, variables):
        angle = 2 * jnp.arctan2(jnp.linalg.norm(state.motion.rotations[4, 1:]), state.motion.rotations[4, 0])
        return jnp.maximum(angle - 0.1, 0.0)[None, None], jnp.ones(1, bool)


@pytest.mark.slow
def test_custom_frame_term_is_honoured(setup):
    skeleton, rig, truth, points, (ids, pix, w), init = setup
    problem = Problem(skeleton, rig, [
        Reprojection({"point_ids": ids, "pixels": pix, "weights": w}, points=points),
        JointLimit(np.zeros(T), weight=1e8),
    ])
    result = solve(problem, init, SolverOptions(window=T, overlap=0))
    knee = np.asarray(result.motion.rotations[:, 4])
    angle = 2 * np.arctan2(np.linalg.norm(knee[:, 1:], axis=1), np.abs(knee[:, 0]))
    assert angle.max() < 0.1 + 1e-3


def test_bad_input_is_named(setup):
    skeleton, rig, truth, points, (ids, pix, w), init = setup
    bad = pix.copy()
    bad[2, 1, np.argmax(w[2, 1] > 0)] = np.nan
    with pytest.raises(ValueError, match=r"pixels has NaN/inf at frame 2, camera 1"):
        Problem(skeleton, rig, [Reprojection({"point_ids": ids, "pixels": bad, "weights": w}, points=points)])
    with pytest.raises(ValueError, match=r"data\['weights'\] has shape"):
        Problem(skeleton, rig, [Reprojection({"point_ids": ids, "pixels": pix, "weights": w[:, :2]}, points=points)])
    with pytest.raises(ValueError, match="point_ids reach"):
        Problem(skeleton, rig, [Reprojection({"point_ids": ids + 100, "pixels": pix, "weights": w}, points=points)])
    with pytest.raises(ValueError, match="cover different numbers of frames"):
        Problem(skeleton, rig, [Reprojection({"point_ids": ids, "pixels": pix, "weights": w}, points=points),
                                RootSmoothness(pair_mask(T + 1))])
    empty = Problem(skeleton, rig, [Reprojection({"point_ids": ids, "pixels": pix, "weights": 0 * w}, points=points)])
    with pytest.raises(ValueError, match=r"no usable observation in the window of frames \[0, 6\)"):
        solve(empty, init, SolverOptions(window=T, overlap=0))
    with pytest.raises(ValueError, match="initial_motion has 5 frames"):
        solve(make_problem(setup), init[:5])
    nan_init = Motion(np.where(np.arange(T)[:, None] == 3, np.nan, np.asarray(init.root_position)), init.rotations)
    with pytest.raises(ValueError, match=r"initial_motion: root_position has NaN/inf \(first at index \(3, 0\)\)"):
        solve(make_problem(setup), nan_init)
    with pytest.raises(ValueError, match="overlap must be in"):
        SolverOptions(window=4, overlap=4)


def test_paper_problem_from_correspondences(setup):
    skeleton, rig, truth, points, (ids, pix, w), init = setup
    c = Correspondences(points, ids, pix, w, np.zeros((T, rig.num_cameras, 2, 2)), np.zeros((T, rig.num_cameras, 2, 2)),
                        np.zeros((T, rig.num_cameras, 2)), np.zeros((T, rig.num_cameras, 7)),
                        np.zeros((T, rig.num_cameras), bool), 60.0)
    problem = paper_problem(c, skeleton, rig, ObjectiveWeights(loss="huber", loss_scale=2.0))
    assert [t.label for t in problem.terms] == ["reprojection", "root smoothness", "joint smoothness"]
    with pytest.raises(ValueError, match="correspondences have 6 cameras, the rig has 5"):
        from bcmocap.kinematics import Rig
        paper_problem(c, skeleton, Rig(rig.names[:5], rig.segments[:5], rig.segment_from_camera[:5],
                                          jax.tree.map(lambda a: a[:5], rig.intrinsics)))


def test_motion_from_tangent_roundtrip(setup):
    skeleton, _, truth, _, _, init = setup
    y = np.asarray(skeleton.difference(init, truth)).ravel()
    back = motion_from_tangent(make_problem(setup), init, y)
    assert evaluate_motion(skeleton, back, truth)["joint_position_error_cm"]["max"] < 1e-6


@pytest.mark.slow
def test_a_window_stopped_at_max_steps_reports_it(setup):
    """A window cut short by max_steps is reported as not converged, with its step count, and the cost it
    reached; given the steps it needs, the same window converges."""
    _, _, _, _, _, init = setup
    problem = make_problem(setup)
    short = solve(problem, init, SolverOptions(window=T, overlap=0, max_steps=1, rtol=1e-12, atol=1e-12))
    (report,) = short.reports
    assert not report.converged and not short.converged
    assert report.num_steps == 1 and report.final_cost <= report.initial_cost
    full = solve(problem, init, SolverOptions(window=T, overlap=0, max_steps=50))
    assert full.converged and full.reports[0].num_steps > 1
    assert full.reports[0].final_cost < report.final_cost


class _BrokenPrior(FrameTerm):
    """A user term with a bug: the log of a negative number on frame 2 (NaN residual)."""

    def residual(self, state, data, variables):
        return jnp.log(data - 2.5 + state.motion.root_position[0] * 0.0)[None, None], jnp.ones(1, bool)


@pytest.mark.slow
def test_a_non_finite_window_is_rejected_naming_the_window_and_term(setup):
    skeleton, rig, truth, points, (ids, pix, w), init = setup
    problem = Problem(skeleton, rig, [
        Reprojection({"point_ids": ids, "pixels": pix, "weights": w}, points=points, name="reprojection"),
        _BrokenPrior(np.where(np.arange(T) == 2, 1.0, 3.0), name="broken prior"),
    ])
    with pytest.raises(FloatingPointError, match=r"window of frames \[0, 6\) has a non-finite cost or motion: "
                                                 r"term\(s\) 'broken prior' are non-finite at its initial motion"):
        solve(problem, init, SolverOptions(window=T, overlap=0, max_steps=3))


class CentreAcceleration(MultiFrameTerm):
    """Three frames: each camera centre's second difference equals a measured one (m per frame²)."""

    span = 3

    def residual(self, states, data, variables):
        centres = states.world_from_camera.translation()  # (3, C, 3)
        return centres[2] - 2.0 * centres[1] + centres[0] - data, jnp.ones(data.shape[0], bool)


@pytest.mark.slow
def test_a_three_frame_term_reaches_scipys_minimum_in_windows(setup):
    """With a three-frame term (bandwidth 2, two fixed frames before each window) one window over all frames
    reaches scipy's minimum, and overlapping windows agree with it."""
    skeleton, rig, truth, _, _, init = setup
    centres = np.asarray(camera_poses(skeleton, rig, truth).translation())
    acceleration = np.zeros_like(centres)
    acceleration[2:] = centres[2:] - 2 * centres[1:-1] + centres[:-2]
    acceleration += 0.002 * np.random.default_rng(11).normal(size=acceleration.shape)
    base = make_problem(setup)
    problem = Problem(skeleton, rig, [*base.terms, CentreAcceleration(acceleration, weight=1e5, name="acceleration")])
    _, ref = scipy_minimum(problem, init)
    whole = solve(problem, init, SolverOptions(window=T, overlap=0, rtol=1e-10, atol=1e-12, max_steps=60))
    assert whole.converged
    assert abs(whole.reports[0].final_cost - ref.cost) <= 1e-6 * ref.cost
    assert np.allclose(np.asarray(skeleton.difference(init, whole.motion)).ravel(), ref.x, atol=1e-6)
    # The last of overlapping windows minimises the whole cost over its frames with the two frames before
    # it held: the whole sequence's gradient vanishes there (it would not if the seam dropped or
    # misplaced the three-frame blocks that reach into the fixed frames).
    windowed = solve(problem, init, SolverOptions(window=4, overlap=2, rtol=1e-12, atol=1e-14, max_steps=60))
    assert [r.start for r in windowed.reports] == [0, 2] and windowed.converged
    at_windowed = whole_sequence_residual_function(problem, windowed.motion)
    y0 = np.zeros(T * skeleton.num_dofs)
    grad = (np.asarray(jax.jacfwd(at_windowed)(y0)).T @ np.asarray(at_windowed(y0))).reshape(T, -1)
    scale = np.abs(grad).max()
    assert np.abs(grad[2:]).max() < 1e-6 * scale and np.abs(grad[:2]).max() > 1e-3 * scale
    diff = evaluate_motion(skeleton, windowed.motion, whole.motion)
    assert diff["joint_position_error_cm"]["max"] < 1.0


class BiasedCentres(FrameTerm):
    """Every camera centre measured with one unknown constant offset (a static variable, m)."""

    def static_variables(self):
        return {"centre_offset": 3}

    def residual(self, state, data, variables):
        centres = state.world_from_camera.translation()  # (C, 3)
        return centres + state.statics["centre_offset"] - data, jnp.ones(data.shape[0], bool)


@pytest.mark.slow
def test_static_variables_reach_scipys_minimum_and_are_recovered(setup):
    """A term with a static variable (an offset shared by all frames): the Schur-complement step reaches scipy's
    minimum over motion and offset together, the offset is recovered, and windows carry it over."""
    skeleton, rig, truth, _, _, init = setup
    offset = np.array([0.05, -0.03, 0.02])
    centres = np.asarray(camera_poses(skeleton, rig, truth).translation())
    measured = centres + offset + 0.001 * np.random.default_rng(12).normal(size=centres.shape)
    base = make_problem(setup)
    problem = Problem(skeleton, rig, [*base.terms, BiasedCentres(measured, weight=1e4, name="biased centres")])
    fn, ref = scipy_minimum_with_statics(problem, init, 3)
    whole = solve(problem, init, SolverOptions(window=T, overlap=0, rtol=1e-10, atol=1e-12, max_steps=60))
    assert whole.converged and set(whole.statics) == {"centre_offset"}
    assert abs(whole.reports[0].final_cost - ref.cost) <= 1e-6 * ref.cost
    np.testing.assert_allclose(whole.statics["centre_offset"], ref.x[-3:], atol=1e-6)
    np.testing.assert_allclose(np.asarray(skeleton.difference(init, whole.motion)).ravel(), ref.x[:-3], atol=1e-6)
    np.testing.assert_allclose(whole.statics["centre_offset"], offset, atol=5e-3)  # the motion is known to mm
    windowed = solve(problem, init, SolverOptions(window=4, overlap=2))
    np.testing.assert_allclose(windowed.statics["centre_offset"], offset, atol=5e-3)


def scipy_minimum_with_statics(problem, init, num_statics, frame_size=None):
    """scipy's minimum over each frame's ``frame_size`` variables (default: the motion's D) and ``num_statics``
    static variables together."""
    fn = whole_sequence_residual_function(problem, init)
    jac = jax.jit(jax.jacfwd(fn))
    ref = scipy.optimize.least_squares(
        lambda y: np.asarray(fn(y)), np.zeros(T * (frame_size or problem.skeleton.num_dofs) + num_statics),
        jac=lambda y: np.asarray(jac(y)), method="trf", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=200,
    )
    return fn, ref


class MountCompliance(FrameTerm):
    """Each camera may move on its mount by a per-frame offset (``CAMERA_OFFSETS``), with a prior of ``data``
    ``(T, 6)`` standard deviations (m, rad)."""

    num_cameras: int = eqx.field(static=True, kw_only=True)

    def frame_variables(self):
        return {CAMERA_OFFSETS: PerCamera(Euclidean(6), self.num_cameras)}

    def residual(self, state, data, variables):
        return state.variables[CAMERA_OFFSETS] / data, jnp.ones(self.num_cameras, bool)


class HeadingOfCentres(FrameTerm):
    """Camera centres measured in a frame turned by one unknown rotation about the root (a :class:`Rotation` static,
    as a compass's misalignment)."""

    def static_variables(self):
        return {"misalignment": Rotation()}

    def residual(self, state, data, variables):
        centres = state.world_from_camera.translation()  # (C, 3)
        turned = jax.vmap(SO3(state.statics["misalignment"]).apply)(centres)
        return turned - data, jnp.ones(data.shape[0], bool)


@pytest.mark.slow
def test_per_frame_camera_offsets_and_rotation_statics_reach_scipys_minimum_and_resume(setup):
    """Cameras wobbling on their mounts (per-frame offsets with a prior) and a rotation static: one window reaches
    scipy's minimum over motion, offsets and rotation together, and a windowed solve resumed from its checkpoint
    (motion, statics and per-frame values) equals the uninterrupted one. (With one camera per segment a camera's
    turn is nearly that of its segment, so the prior, not the data, splits the wobble between them.)"""
    skeleton, rig, truth, points, _, init = setup
    rng = np.random.default_rng(21)
    c = rig.num_cameras
    phase = rng.uniform(0, 6, size=(1, c, 6))
    wobble = np.array([0.002] * 3 + [0.03] * 3) * np.sin(np.arange(T)[:, None, None] + phase)  # 2 mm, 1.7°
    ids, pix, w = observe(skeleton, rig, truth, points, rng, sigma=0.2, camera_offsets=wobble)
    turn = np.asarray(SO3.exp(jnp.array([0.0, 0.0, 0.05])).wxyz)
    centres = np.asarray((camera_poses(skeleton, rig, truth) @ SE3.exp(jnp.asarray(wobble))).translation())
    seen = np.asarray(jax.vmap(jax.vmap(SO3(jnp.asarray(turn)).apply))(jnp.asarray(centres)))
    terms = [Reprojection({"point_ids": ids, "pixels": pix, "weights": w}, points=points, name="reprojection"),
             RootSmoothness(pair_mask(T), weight=10.0), JointSmoothness(pair_mask(T), skeleton=skeleton, weight=1.0),
             MountCompliance(np.broadcast_to([0.01] * 3 + [0.05] * 3, (T, c, 6)), name="mount compliance", num_cameras=c),
             HeadingOfCentres(seen + 0.002 * rng.normal(size=seen.shape), weight=1e4, name="heading")]
    problem = Problem(skeleton, rig, terms)
    frame_size = skeleton.num_dofs + 6 * c
    fn, ref = scipy_minimum_with_statics(problem, init, 3, frame_size)
    whole = solve(problem, init, SolverOptions(window=T, overlap=0, rtol=1e-10, atol=1e-12, max_steps=60))
    assert whole.converged and abs(whole.reports[0].final_cost - ref.cost) <= 1e-6 * ref.cost
    y = ref.x[: T * frame_size].reshape(T, frame_size)
    np.testing.assert_allclose(whole.frame_variables[CAMERA_OFFSETS], y[:, skeleton.num_dofs :].reshape(T, c, 6), atol=1e-6)
    np.testing.assert_allclose(whole.statics["misalignment"], np.asarray(SO3.exp(jnp.asarray(ref.x[-3:])).wxyz), atol=1e-6)
    assert np.asarray(SO3(whole.statics["misalignment"]).log())[2] == pytest.approx(0.05, abs=2e-3)
    assert np.abs(whole.frame_variables[CAMERA_OFFSETS]).max() > 1e-3  # the offsets moved

    saved = {}
    options = SolverOptions(window=4, overlap=2, rtol=1e-10, atol=1e-12, max_steps=60)
    windowed = solve(problem, init, options, checkpoint=lambda i, report, so_far: saved.setdefault(i, so_far))
    first = saved[0]
    assert first.frame_variables[CAMERA_OFFSETS].shape == (T, c, 6) and set(first.statics) == {"misalignment"}
    resumed = solve(problem, first.motion, options, skip_windows=1, initial_statics=first.statics,
                    initial_frame_variables=first.frame_variables)
    np.testing.assert_allclose(np.asarray(resumed.motion.rotations), np.asarray(windowed.motion.rotations), atol=1e-12)
    np.testing.assert_allclose(resumed.frame_variables[CAMERA_OFFSETS], windowed.frame_variables[CAMERA_OFFSETS], atol=1e-12)
    np.testing.assert_allclose(resumed.statics["misalignment"], windowed.statics["misalignment"], atol=1e-12)


def rolling_shutter_observations(skeleton, rig, motion, points, readout, sigma, rng, time_offsets=None):
    """Pixels ``(T, C, P, 2)`` of a rolling shutter: row ``r`` of ``H`` seen at ``(r/(H−1) − ½)·readout`` frames from
    the frame's time (plus camera ``c``'s ``time_offsets[c]`` frames), the body moving linearly in its tangent space
    between frames (not the term's model of a camera at constant velocity)."""
    offsets = np.zeros(rig.num_cameras) if time_offsets is None else np.asarray(time_offsets, float)
    num = motion.num_frames
    forward = np.array(skeleton.difference(motion[np.arange(num)], motion[np.minimum(np.arange(num) + 1, num - 1)]))
    backward = np.array(skeleton.difference(motion[np.maximum(np.arange(num) - 1, 0)], motion[np.arange(num)]))
    forward[-1], backward[0] = backward[-1], forward[0]  # extrapolate at the ends

    def pixels_at(s):  # s: (T, C, P) frame offsets → pixels, valid
        step = np.where(s[..., None] >= 0, forward[:, None, None], backward[:, None, None]) * s[..., None]
        moved = skeleton.retract(jax.tree.map(lambda a: a[:, None, None], motion), jnp.asarray(step))
        poses = camera_poses(skeleton, rig, moved).inverse().wxyz_xyz  # (T, C, P, C, 7): every camera
        index = np.arange(rig.num_cameras)
        own = SE3(poses[:, index, :, index].transpose(1, 0, 2, 3))  # (T, C, P, 7): camera c of slot c
        cam = transform_points(own, jnp.asarray(points)[None, None])
        return jax.vmap(jax.vmap(lambda k, p: k.project(p), in_axes=(None, 0)), in_axes=(0, 1), out_axes=1)(rig.intrinsics, cam)

    s = np.zeros((num, rig.num_cameras, len(points))) + offsets[None, :, None]
    for _ in range(12):  # a pixel's row sets its time, which sets the pixel
        uv, valid = pixels_at(s)
        rows = np.asarray(uv)[..., 1] / (rig.intrinsics.height - 1) - 0.5
        s = np.clip(rows, -0.5, 0.5) * readout + offsets[None, :, None]
    valid = np.asarray(valid) & np.asarray(jax.vmap(lambda k, p: k.in_image(p), in_axes=(0, 1), out_axes=1)(rig.intrinsics, uv))
    pix = np.asarray(uv) + sigma * rng.normal(size=np.shape(uv))
    ids = np.where(valid, np.arange(len(points)), -1).astype(np.int32)
    return ids, np.where(valid[..., None], pix, 0.0), valid / sigma**2


@pytest.mark.slow
def test_rolling_shutter_term_recovers_what_a_global_shutter_bends(setup):
    """Pixels from a rolling shutter (a full frame period of readout) bend the motion a global-shutter
    reprojection finds; the rolling-shutter term at the true readout finds it much closer to the truth (its
    camera moves at the velocity of the previous frame interval, the body here changes speed every frame), and
    estimating the readout from zero recovers it."""
    from bcmocap.residuals.rolling_shutter import READOUT, RollingShutterReprojection
    from bcmocap.residuals.self_calibration import StaticPrior

    skeleton, rig, truth, points, _, init = setup
    rng = np.random.default_rng(31)
    ids, pix, w = rolling_shutter_observations(skeleton, rig, truth, points, 1.0, 0.05, rng)
    data = {"point_ids": ids, "pixels": pix, "weights": w}
    smooth = [RootSmoothness(pair_mask(T), weight=1.0), JointSmoothness(pair_mask(T), skeleton=skeleton, weight=0.1)]
    options = SolverOptions(window=T, overlap=0, rtol=1e-10, atol=1e-12, max_steps=60)
    frames = slice(1, None)  # the first frame has no previous one: the rolling-shutter term drops it
    error = lambda solution: evaluate_motion(skeleton, solution.motion[frames], truth[frames])["joint_angle_error_deg"]["mean"]  # noqa: E731
    global_shutter = solve(Problem(skeleton, rig, [Reprojection(data, points=points), *smooth]), init, options)
    rolling = solve(Problem(skeleton, rig, [RollingShutterReprojection(data, points=points, readout=1.0), *smooth]), init, options)
    assert error(rolling) < 0.6 * error(global_shutter), (error(rolling), error(global_shutter))
    estimated = solve(Problem(skeleton, rig, [
        RollingShutterReprojection(data, points=points, readout=0.0, estimate_readout=True),
        StaticPrior(np.full(T, 1.0 / T), block=READOUT, variable=Euclidean(1), sigma=10.0), *smooth]), init, options)
    readout = float(estimated.statics[READOUT][0])
    assert abs(readout - 1.0) < 0.3 and error(estimated) < 0.8 * error(global_shutter), (readout, error(estimated))


def time_offset_observations(skeleton, rig, motion, points, readout, offsets):
    """Pixels ``(T, C, P, 2)`` as :class:`RollingShutterReprojection` predicts them: camera ``c`` of frame ``t``
    exposed ``offsets[c]`` frame periods after the frame's time (row ``r`` a further ``(r/(H−1) − ½)·readout``),
    moving at its velocity between frames ``t − 1`` and ``t``; frame 0 has no previous frame and sees nothing."""
    from bcmocap.residuals.rolling_shutter import rolling_shutter_projection

    cam_from_world = np.asarray(camera_poses(skeleton, rig, motion).inverse().wxyz_xyz)  # (T, C, 7)
    num, cams = cam_from_world.shape[:2]
    pix = np.zeros((num, cams, len(points), 2))
    valid = np.zeros((num, cams, len(points)), bool)
    for t in range(1, num):
        for c in range(cams):
            camera = jax.tree.map(lambda a: a[c], rig.intrinsics)
            pose = SE3(jnp.asarray(cam_from_world[t, c]))
            velocity = (pose @ SE3(jnp.asarray(cam_from_world[t - 1, c])).inverse()).log()
            rows = jnp.full(len(points), 0.5 * (camera.height - 1))
            for _ in range(8):  # a pixel's row sets its time, which sets the pixel
                uv, ok = rolling_shutter_projection(camera, pose, velocity, readout, jnp.asarray(points), rows, offsets[c])
                rows = jnp.clip(uv[:, 1], 0, camera.height - 1)
            pix[t, c], valid[t, c] = np.asarray(uv), np.asarray(ok & camera.in_image(uv))
    ids = np.where(valid, np.arange(len(points)), -1).astype(np.int32)
    return ids, np.where(valid[..., None], pix, 0.0), valid.astype(np.float64)


@pytest.mark.slow
def test_each_cameras_time_offset_is_recovered_with_the_motion(setup):
    """Cameras exposed up to 0.3 frame periods off the frames' times (what audio sync leaves: each camera's audio
    latency), pixels exactly as the rolling-shutter term models them: solving for each camera's time offset (a
    per-camera static from zero, a weak prior) recovers the offsets and the motion exactly, where a
    solve that ignores them is degrees off."""
    from bcmocap.residuals.rolling_shutter import TIME_OFFSET, RollingShutterReprojection, time_offsets
    from bcmocap.residuals.self_calibration import StaticPrior

    skeleton, rig, truth, points, _, init = setup
    offsets = np.random.default_rng(32).uniform(-0.3, 0.3, rig.num_cameras)
    ids, pix, w = time_offset_observations(skeleton, rig, truth, points, 0.5, offsets)
    data = {"point_ids": ids, "pixels": pix, "weights": w}
    smooth = [RootSmoothness(pair_mask(T), weight=1e-6), JointSmoothness(pair_mask(T), skeleton=skeleton, weight=1e-6)]
    options = SolverOptions(window=T, overlap=0, rtol=1e-12, atol=1e-14, max_steps=80)
    frames = slice(1, None)
    error = lambda solution: evaluate_motion(skeleton, solution.motion[frames], truth[frames])["joint_angle_error_deg"]["mean"]  # noqa: E731
    ignored = solve(Problem(skeleton, rig, [RollingShutterReprojection(data, points=points, readout=0.5), *smooth]),
                    init, options)
    estimated = solve(Problem(skeleton, rig, [
        RollingShutterReprojection(data, points=points, readout=0.5, estimate_time_offsets=True,
                                   num_cameras=rig.num_cameras),
        StaticPrior(np.full(T, 1.0 / T), block=TIME_OFFSET, variable=time_offsets(rig.num_cameras), sigma=10.0),
        *smooth]), init, options)
    found = np.asarray(estimated.statics[TIME_OFFSET])[:, 0]
    assert np.abs(found - offsets).max() < 0.01, (found, offsets)
    assert error(estimated) < 0.02 and error(ignored) > 0.2, (error(estimated), error(ignored))
