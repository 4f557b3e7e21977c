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
from bcmocap.residuals import FrameTerm
from bcmocap.solver.objective import ObjectiveWeights

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


class _ShinLength(FrameTerm):
    """A user term: a tape measurement of the shin, the distance between the knee and the ankle (m)."""

    length: float = 0.0

    def residual(self, state, data, variables):
        joints = state.world_from_segment.translation()
        return (jnp.linalg.norm(joints[FOOT] - joints[KNEE]) - self.length)[None, None], data[None] > 0


@pytest.mark.slow
def test_user_terms_reach_the_refinement(setup):
    """The refinement minimises the solve's objective, user terms included: a tape-measured shin length
    (the camera-less foot's offset, which no camera sees: without the tape the prior keeps it where it
    started) moves the skeleton to it."""
    skeleton, rig, motion, correspondences, start_skeleton, start_rig = setup
    truth = float(np.linalg.norm(np.asarray(skeleton.offsets[FOOT])))
    measured = lambda w: [_ShinLength(np.ones(w.stop - w.start), weight=1e8, name="tape", length=truth)]  # noqa: E731
    shin = lambda result: float(np.linalg.norm(np.asarray(result.skeleton.offsets[FOOT])))  # noqa: E731
    taped = refine_skeleton_and_rig(correspondences, start_skeleton, start_rig, motion, LOOSE, extra_terms=[measured])
    assert abs(float(np.linalg.norm(np.asarray(start_skeleton.offsets[FOOT]))) - truth) > 2e-3
    assert abs(shin(taped) - truth) < 1e-4
    assert taped.report.converged


@pytest.mark.slow
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
