"""Refining bone offsets and camera mounts (solver.refine): derivatives, recovery, gauge, bad input."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bcmocap.correspondences import Correspondences
from bcmocap.geometry import SE3, SO3, rotation_angle, transform_points
from bcmocap.kinematics import camera_poses
from bcmocap.solver import RefineOptions, SolverOptions, refine_skeleton_and_rig, reprojection_cost, solve_with_refinement
from bcmocap.solver.objective import ObjectiveWeights
from bcmocap.solver.refine import _apply, _frame_system, _layout, _Model, _reprojection_term, _without_data

from conftest import central_difference, make_rig, make_skeleton, random_motion, scene_points

T = 12
KNEE, FOOT = 4, 5  # the hinge, and a segment without a camera (its offset is invisible)
# Priors far wider than the perturbations, which the priors are centred on: recovery is the data's.
LOOSE = RefineOptions(offset_sigma_m=0.05, mount_translation_sigma_m=0.05, mount_rotation_sigma_deg=5.0, hinge_axis_sigma_deg=5.0)


def observe(skeleton, rig, motion, points, rng, sigma):
    """Correspondences of every visible point in every camera-frame, σ px noise, all cameras registered."""
    num_frames, num_cameras, n = motion.num_frames, rig.num_cameras, len(points)
    cam_from_world = camera_poses(skeleton, rig, motion).inverse()
    ids = np.full((num_frames, num_cameras, n), -1, np.int32)
    pix = np.zeros((num_frames, num_cameras, n, 2))
    w = np.zeros((num_frames, num_cameras, n))
    for c in range(num_cameras):
        cam = jax.tree.map(lambda a: a[c], rig.intrinsics)
        uv, valid = cam.project(transform_points(SE3(cam_from_world.wxyz_xyz[:, c, None]), points[None]))
        valid = np.asarray(valid & cam.in_image(uv))
        uv = np.asarray(uv) + sigma * rng.normal(size=uv.shape)
        ids[:, c] = np.where(valid, np.arange(n), -1)
        pix[:, c] = np.where(valid[..., None], uv, 0.0)
        w[:, c] = valid / sigma**2
    empty = np.zeros((num_frames, num_cameras, 1))
    return Correspondences(
        points, ids, pix, w, np.zeros((*empty.shape, 2)), np.zeros((*empty.shape, 2)), empty,
        np.asarray(cam_from_world.inverse().wxyz_xyz), np.ones((num_frames, num_cameras), bool), 60.0,
    )


def perturbed(skeleton, rig, rng, offset_m=0.01, mount_m=0.01, mount_deg=1.0, hinge_deg=1.0):
    offsets = np.asarray(skeleton.offsets).copy()
    offsets[1:] += offset_m * rng.normal(size=(skeleton.num_segments - 1, 3))
    kids = list(skeleton.children(0))  # keep the root's origin (the mean of its children's joints)
    offsets[kids] -= offsets[kids].mean(0) - np.asarray(skeleton.offsets)[kids].mean(0)
    mounts = np.asarray(rig.segment_from_camera)
    turn = SO3.exp(jnp.asarray(np.deg2rad(mount_deg) * rng.normal(size=(rig.num_cameras, 3))))
    shift = mount_m * rng.normal(size=(rig.num_cameras, 3))
    mounts = np.concatenate([np.asarray((turn @ SO3(mounts[:, :4])).wxyz), mounts[:, 4:] + shift], 1)
    axes = np.asarray(skeleton.hinge_axes).copy()
    axes[KNEE] = np.asarray(SO3.exp(jnp.asarray(np.deg2rad(hinge_deg) * rng.normal(size=3))).as_matrix()) @ axes[KNEE]
    return (eqx.tree_at(lambda s: (s.offsets, s.hinge_axes), skeleton, (jnp.asarray(offsets), jnp.asarray(axes))),
            eqx.tree_at(lambda r: r.segment_from_camera, rig, jnp.asarray(mounts)))


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(11)
    skeleton = make_skeleton()
    rig = make_rig(skeleton)
    motion = random_motion(skeleton, T, rng, max_angle=1.0)
    points = scene_points(rng, 60)
    correspondences = observe(skeleton, rig, motion, points, rng, sigma=0.02)
    assert (correspondences.weights > 0).sum(axis=2).min() >= 6
    start_skeleton, start_rig = perturbed(skeleton, rig, rng)
    return skeleton, rig, motion, correspondences, start_skeleton, start_rig


def camera_errors(skeleton, rig, motion, truth):
    """Largest camera-centre (m) and orientation (°) error of a model and motion against the truth."""
    est, ref = camera_poses(skeleton, rig, motion), camera_poses(*truth)
    centre = np.linalg.norm(np.asarray(est.translation() - ref.translation()), axis=-1).max()
    angle = np.rad2deg(np.asarray(rotation_angle(est.rotation().wxyz, ref.rotation().wxyz))).max()
    return centre, angle


@pytest.mark.slow
def test_frame_system_matches_finite_differences(setup):
    """Per-frame normal equations in (motion tangent, θ) from autodiff through the 3×4 camera matrices
    equal those of central-difference Jacobians of the reprojection residuals (IRLS-weighted for the
    Cauchy loss, whose gradient is the exact gradient of the robust cost). Linearised away from zero in
    both: a moved frame, θ with the mount rotations and the knee axis off their base values; the held
    means make some directions of θ null, which must hold as well."""
    _, _, motion, correspondences, skeleton, rig = setup
    weights = ObjectiveWeights(loss="cauchy", loss_scale=2.0)
    options = RefineOptions()
    layout = _layout(skeleton, rig, options)
    term = _reprojection_term(correspondences, skeleton, weights)
    model = _Model(skeleton, rig, _without_data(term), layout, False)
    rng = np.random.default_rng(0)
    theta = 0.01 * rng.normal(size=layout.size)
    t = 3
    data = jax.tree.map(lambda a: a[0], term.window(t, t + 1).data)
    reference = motion[t]
    d = skeleton.num_dofs
    tangent = 0.01 * rng.normal(size=d)

    # The frame's knee angle about the axis at θ: refining the axis keeps the angle, not the rotation.
    axes = _apply(layout, skeleton, rig, jnp.asarray(theta))[0].hinge_axes
    knee = np.asarray(reference.rotations[KNEE])
    angle = 2 * np.arctan2(knee[1:] @ np.asarray(axes[KNEE]), knee[0])

    @jax.jit
    def raw(z):  # (residual blocks, valid) straight from the term's residual, per camera
        sk, rg = _apply(layout, skeleton, rig, z[d:])
        turned = reference.rotations.at[KNEE].set(SO3.exp(angle * sk.hinge_axes[KNEE]).wxyz)
        m = type(reference)(reference.root_position, turned)
        m = sk.retract(m, z[:d])
        poses = camera_poses(sk, rg, m).inverse()
        cams = jax.vmap(lambda p, cam, dt: term.residual(SE3(p), cam, dt))
        return cams(poses.wxyz_xyz, rg.intrinsics, data)

    z0 = np.concatenate([tangent, theta])
    r, valid = raw(jnp.asarray(z0))
    r = np.asarray(term.masked(r, valid))
    jac = central_difference(lambda z: np.asarray(term.masked(*raw(jnp.asarray(z)))), z0, eps=1e-6)  # (C, n, 2, Z)
    rho = np.asarray(term.loss.derivative(np.sum(r * r, axis=-1)))[..., None]  # IRLS weights per block
    h = np.einsum("cnki,cnk,cnkj->ij", jac, np.broadcast_to(rho, r.shape), jac)
    g = np.einsum("cnki,cnk->i", jac, rho * r)
    got = eqx.filter_jit(_frame_system)(model, jnp.asarray(theta), axes, reference, jnp.asarray(tangent), data)
    for block, want in zip(got[:3], (h[:d, :d], h[:d, d:], h[d:, d:])):
        np.testing.assert_allclose(np.asarray(block), want, atol=1e-6 * np.abs(h).max())
    np.testing.assert_allclose(np.asarray(got[3]), g[:d], atol=1e-6 * np.abs(g).max())
    np.testing.assert_allclose(np.asarray(got[4]), g[d:], atol=1e-6 * np.abs(g).max())
    cost = 0.5 * np.sum(np.asarray(term.finish(*raw(jnp.asarray(z0)))) ** 2)
    np.testing.assert_allclose(float(got[5]), cost, rtol=1e-10)
    robust = lambda z: 0.5 * np.sum(np.asarray(term.finish(*raw(jnp.asarray(z)))) ** 2)  # noqa: E731
    for direction in rng.normal(size=(3, z0.size)):  # directional derivatives
        slope = central_difference(lambda e: robust(z0 + e[0] * direction), np.zeros(1))[0]
        np.testing.assert_allclose(g @ direction, slope, rtol=1e-5)


def test_recovers_offsets_and_mounts_with_known_motion(setup):
    """Motion known: 1 cm / 1° perturbations of offsets, mounts and the knee axis come back to ≤ 1 mm /
    0.02° (the axis 0.05°), except the directions no data can see (the knee's centre along its axis,
    the camera-less foot): 4 of them, left to the prior."""
    skeleton, rig, motion, correspondences, start_skeleton, start_rig = setup
    options = dataclasses.replace(LOOSE, hold_motion=True, hold_segment_frames=False)
    result = refine_skeleton_and_rig(correspondences, start_skeleton, start_rig, motion, options)
    report = result.report
    assert report.converged
    truth_cost = reprojection_cost(correspondences, skeleton, rig, motion)
    assert report.final_reprojection_cost < truth_cost < 0.05 * report.initial_cost
    assert report.prior_directions == 4
    axis = np.asarray(skeleton.hinge_axes[KNEE])
    off_axis = lambda v: v - np.outer(v @ axis, axis)  # noqa: E731
    off = np.array(result.skeleton.offsets - skeleton.offsets)
    off[KNEE] = off_axis(off[KNEE][None])[0]
    assert np.abs(np.asarray(start_skeleton.offsets - skeleton.offsets)[1:FOOT]).max() > 5e-3
    assert np.linalg.norm(off[1:FOOT], axis=1).max() < 1e-3
    shift = np.array(result.rig.segment_from_camera[:, 4:] - rig.segment_from_camera[:, 4:])
    shin = rig.index("shin")
    shift[shin] = off_axis(shift[shin][None])[0]
    assert np.linalg.norm(shift, axis=1).max() < 1e-3
    mount_rotations = result.rig.segment_from_camera[:, :4], rig.segment_from_camera[:, :4]
    angles = np.rad2deg(np.asarray(rotation_angle(*mount_rotations)))
    assert angles.max() < 0.02
    tilt = np.rad2deg(np.arccos(np.clip(np.asarray(result.skeleton.hinge_axes[KNEE]) @ axis, -1, 1)))
    assert tilt < 0.05 < np.rad2deg(np.arccos(np.asarray(start_skeleton.hinge_axes[KNEE]) @ axis))
    np.testing.assert_array_equal(np.asarray(result.motion.rotations)[:, :KNEE], np.asarray(motion.rotations)[:, :KNEE])


def test_eliminated_motion_reproduces_camera_poses(setup):
    """Motion free (the default): the refined model with its moved motion puts every camera where it
    was (≤ 2 mm, 0.03° from 3 cm, 1.5°: 0.02 px noise, free motion per frame); the root's origin
    stays at the mean of its children's joints and the cameras of the pelvis (FREE) keep their mean
    orientation: those frames are held, not left to the prior."""
    skeleton, rig, motion, correspondences, start_skeleton, start_rig = setup
    before = camera_errors(start_skeleton, start_rig, motion, (skeleton, rig, motion))
    result = refine_skeleton_and_rig(correspondences, start_skeleton, start_rig, motion, LOOSE)
    after = camera_errors(result.skeleton, result.rig, result.motion, (skeleton, rig, motion))
    assert before[0] > 0.03 and after[0] < 2e-3 and after[1] < 0.03 < before[1]
    kids = list(skeleton.children(0))
    mean = lambda s: np.asarray(s.offsets)[kids].mean(0)  # noqa: E731
    np.testing.assert_allclose(mean(result.skeleton), mean(start_skeleton), atol=1e-12)
    pelvis = [c for c, s in enumerate(rig.segments) if s == 0]
    turns = (SO3(result.rig.segment_from_camera[pelvis, :4]) @ SO3(start_rig.segment_from_camera[pelvis, :4]).inverse()).log()
    assert np.linalg.norm(np.asarray(turns[0] - turns[1])) > 1e-3  # relative to each other they moved...
    np.testing.assert_allclose(np.asarray(turns).mean(0), 0.0, atol=1e-12)  # ...but not on average
    truth_cost = reprojection_cost(correspondences, skeleton, rig, motion)
    assert result.report.final_reprojection_cost < 1.01 * truth_cost < result.report.initial_reprojection_cost / 10


@pytest.mark.slow
def test_solve_with_refinement_rounds(setup):
    """The alternation: round 0 is the plain solve; a refinement round lowers the reprojection cost
    and brings the cameras closer to the truth."""
    skeleton, rig, motion, correspondences, start_skeleton, start_rig = setup
    initial = start_skeleton.retract(motion, 0.01 * np.random.default_rng(2).normal(size=(T, skeleton.num_dofs)))
    seen = []
    result = solve_with_refinement(
        correspondences, start_skeleton, start_rig, initial, rounds=1,
        solver_options=SolverOptions(window=T, overlap=0), callback=lambda k, *rest: seen.append(k),
    )
    assert seen == [0, 1] and [r.round for r in result.rounds] == [0, 1]
    assert result.rounds[0].refinement is None and result.rounds[1].refinement is not None
    assert result.rounds[1].reprojection_cost < 0.1 * result.rounds[0].reprojection_cost
    truth = (skeleton, rig, motion)
    before = camera_errors(start_skeleton, start_rig, initial, truth)[0]
    assert camera_errors(result.skeleton, result.rig, result.motion, truth)[0] < 0.2 * before


def test_bad_input(setup):
    skeleton, rig, motion, correspondences, start_skeleton, start_rig = setup
    with pytest.raises(ValueError, match="motion has 11 frames"):
        refine_skeleton_and_rig(correspondences, skeleton, rig, motion[1:])
    with pytest.raises(ValueError, match="'head' is not a child of the root"):
        refine_skeleton_and_rig(correspondences, skeleton, rig, motion, RefineOptions(root_origin=("head",)))
    with pytest.raises(ValueError, match="unknown segment 'hips'"):
        refine_skeleton_and_rig(correspondences, skeleton, rig, motion, RefineOptions(root_origin=("hips",)))
    with pytest.raises(ValueError, match="root origin .* moved"):
        options = RefineOptions(root_origin=("torso",))
        refine_skeleton_and_rig(correspondences, skeleton, rig, motion, options, prior=(start_skeleton, start_rig))
    with pytest.raises(ValueError, match="nothing to refine"):
        RefineOptions(refine_offsets=False, refine_mounts=False, refine_hinge_axes=False)
    with pytest.raises(ValueError, match="mount_rotation_sigma_deg must be positive"):
        RefineOptions(mount_rotation_sigma_deg=0.0)
    with pytest.raises(ValueError, match="rounds must be"):
        solve_with_refinement(correspondences, skeleton, rig, motion, rounds=-1)
