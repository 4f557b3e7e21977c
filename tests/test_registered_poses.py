"""Registered camera poses re-fitted under the solver's camera model (bcmocap.solver.registered_poses)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import fov_camera

from bcmocap.cameras import stack_cameras
from bcmocap.correspondences import Correspondences
from bcmocap.geometry import SE3
from bcmocap.residuals.losses import CauchyLoss, TrivialLoss
from bcmocap.residuals.self_calibration import corrected_camera
from bcmocap.solver.registered_poses import (
    CameraSequence,
    PoseRefinementOptions,
    camera_velocities,
    refine_registered_poses,
    refine_trials,
    sequence_normal_equations,
    sequence_residuals,
)

T, C, N = 8, 2, 40
#: per frame period, per camera: a left increment of cam_from_world (translation m, rotation rad)
VELOCITIES = np.array([[0.04, -0.01, 0.02, 0.02, 0.05, -0.01], [-0.02, 0.03, 0.0, -0.04, 0.01, 0.03]])


def _scene(readout: float, cameras, rng, noise_px: float = 0.0):
    """Cameras on a constant-velocity screw (so the neighbours' central difference is the true velocity), each
    frame seeing ``N`` points of its own; pixels exposed row by row with a readout of ``readout`` frame periods."""
    start = SE3.exp(jnp.asarray(rng.normal(0, 0.3, (C, 6))))
    truth = np.stack([np.asarray((SE3.exp(jnp.asarray(t * VELOCITIES)) @ start).wxyz_xyz) for t in range(T)])
    points, ids, pixels = [], np.zeros((T, C, N), np.int32), np.zeros((T, C, N, 2))
    for t in range(T):
        for c in range(C):
            cam = jax.tree.map(lambda a: a[c], cameras)
            uv = rng.uniform([8, 8], [cam.width - 8, cam.height - 8], (N, 2))
            rays = np.asarray(cam.unproject(jnp.asarray(uv)))
            in_camera = rays * rng.uniform(2.0, 5.0, (N, 1))
            pose = SE3(jnp.asarray(truth[t, c]))
            world = np.asarray(pose.inverse().apply(jnp.asarray(in_camera)))
            px = uv
            for _ in range(40):  # a pixel's row sets its time, which sets its pixel
                s = (px[:, 1] / (cam.height - 1) - 0.5) * readout
                px = np.asarray(jax.vmap(lambda si, p: cam.project((SE3.exp(si * jnp.asarray(VELOCITIES[c])) @ pose).apply(p))[0])(
                    jnp.asarray(s), jnp.asarray(world)))
            ids[t, c] = len(points) * N + np.arange(N)
            points.append(world)
            pixels[t, c] = px + rng.normal(0, noise_px, px.shape)
    world_from_camera = np.asarray(SE3(jnp.asarray(truth)).inverse().wxyz_xyz)
    return np.concatenate(points), ids, pixels, world_from_camera


def _correspondences(points, ids, pixels, world_from_camera, registered=None):
    registered = np.ones((T, C), bool) if registered is None else registered
    empty = np.zeros((T, C, 0, 2))
    return Correspondences(points, ids, pixels, np.ones((T, C, N)), empty, empty, np.zeros((T, C, 0)),
                           world_from_camera, registered, fps=30.0)


def _perturbed(world_from_camera, rng, metres=0.01, radians=0.01):
    kick = np.concatenate([rng.normal(0, metres, (T, C, 3)), rng.normal(0, radians, (T, C, 3))], axis=-1)
    return np.asarray((SE3(jnp.asarray(world_from_camera)) @ SE3.exp(jnp.asarray(kick))).wxyz_xyz)


def _pose_errors(a, b):
    centre = np.linalg.norm(a[..., 4:] - b[..., 4:], axis=-1)
    angle = 2 * np.arccos(np.clip(np.abs(np.sum(a[..., :4] * b[..., :4], axis=-1)), 0, 1))
    return centre.max(), angle.max()


@pytest.mark.slow  # ~10 s: the heavy tier
def test_the_rolling_shutter_poses_are_found_from_perturbed_ones():
    """Noise-free rolling-shutter measurements on a constant-velocity motion: from poses 1 cm / 0.6° off, the
    refinement finds the true poses; without the readout it cannot explain the images."""
    rng = np.random.default_rng(0)
    cameras = stack_cameras([fov_camera(), fov_camera(focal=75.0)])
    points, ids, pixels, truth = _scene(0.8, cameras, rng)
    corr = _correspondences(points, ids, pixels, _perturbed(truth, rng))
    found = refine_registered_poses(corr, cameras, PoseRefinementOptions(readout=0.8, max_iterations=30, tolerance=1e-9))
    centre, angle = _pose_errors(found.world_from_camera, truth)
    assert centre < 1e-6 and angle < 1e-6
    assert found.refined.all() and np.all(found.rms_px[:, 1] < 1e-5) and np.all(found.rms_px[:, 0] > 0.1)
    global_shutter = refine_registered_poses(corr, cameras, PoseRefinementOptions(readout=0.0, max_iterations=30))
    assert np.all(global_shutter.rms_px[:, 1] > 0.05)
    assert _pose_errors(global_shutter.world_from_camera, truth)[0] > 1e-3


@pytest.mark.slow  # 15 s
def test_the_intrinsics_correction_is_estimated_with_the_poses():
    """Images through a lens 0.5 % longer and 1.5 px off-centre, the nominal lens given: with ``calibrate`` the
    correction and the poses are found (noise-free; the prior made weak: on one short sequence a focal scale is
    close to moving each camera along its axis)."""
    rng = np.random.default_rng(1)
    nominal = stack_cameras([fov_camera(), fov_camera(focal=75.0)])
    truth_correction = np.array([[np.log(1.005), 1.5, -1.0], [np.log(0.996), -0.8, 2.0]])
    true_lens = jax.vmap(corrected_camera)(nominal, jnp.asarray(truth_correction))
    points, ids, pixels, truth = _scene(0.0, true_lens, rng)
    corr = _correspondences(points, ids, pixels, _perturbed(truth, rng, 0.005, 0.005))
    found = refine_registered_poses(corr, nominal, PoseRefinementOptions(calibrate=True, max_iterations=40, tolerance=1e-9,
                                                                          intrinsics_sigma=(1.0, 100.0)))
    np.testing.assert_allclose(found.intrinsics_correction[:, 0], truth_correction[:, 0], atol=2e-4)
    np.testing.assert_allclose(found.intrinsics_correction[:, 1:], truth_correction[:, 1:], atol=0.1)
    centre, angle = _pose_errors(found.world_from_camera, truth)
    assert centre < 2e-3 and angle < 2e-3
    corrected = found.corrected_cameras(nominal)
    np.testing.assert_allclose(np.asarray(corrected.focal), np.asarray(nominal.focal) * np.exp(found.intrinsics_correction[:, :1]))
    fixed_lens = refine_registered_poses(corr, nominal, PoseRefinementOptions(max_iterations=40))
    assert np.all(fixed_lens.rms_px[:, 1] > 5 * found.rms_px[:, 1])


@pytest.mark.slow  # ~10 s: the heavy tier
def test_trials_share_the_intrinsics_correction():
    """Two trials of one rig: camera 1 measures nothing in the first, so its correction comes from the second,
    and both trials' poses are re-fitted through the one correction."""
    rng = np.random.default_rng(5)
    nominal = stack_cameras([fov_camera(), fov_camera(focal=75.0)])
    truth_correction = np.array([[np.log(1.004), 1.0, -1.5], [np.log(0.995), -1.2, 0.8]])
    true_lens = jax.vmap(corrected_camera)(nominal, jnp.asarray(truth_correction))
    first, second = _scene(0.0, true_lens, rng), _scene(0.0, true_lens, rng)
    first[1][:, 1] = -1  # camera 1: no measurement in the first trial
    trials = [_correspondences(*scene[:3], _perturbed(scene[3], rng, 0.005, 0.005)) for scene in (first, second)]
    options = PoseRefinementOptions(calibrate=True, max_iterations=40, tolerance=1e-9, intrinsics_sigma=(1.0, 100.0))
    found = refine_trials(trials, nominal, options)
    np.testing.assert_array_equal(found[0].intrinsics_correction, found[1].intrinsics_correction)
    np.testing.assert_allclose(found[0].intrinsics_correction[:, 0], truth_correction[:, 0], atol=2e-4)
    np.testing.assert_allclose(found[0].intrinsics_correction[:, 1:], truth_correction[:, 1:], atol=0.1)
    assert not found[0].refined[:, 1].any() and found[1].refined.all()
    assert _pose_errors(found[0].world_from_camera[:, :1], first[3][:, :1])[0] < 2e-3
    assert _pose_errors(found[1].world_from_camera, second[3])[0] < 2e-3
    alone = refine_registered_poses(trials[0], nominal, options)
    np.testing.assert_array_equal(alone.intrinsics_correction[1], 0.0)  # nothing calibrates camera 1 in trial 0


@pytest.mark.parametrize("loss", [TrivialLoss(), CauchyLoss(2.0)])
def test_normal_equations_match_finite_differences(loss):
    """The normal equations one Levenberg–Marquardt solve steps with, at a point away from zero increments: the
    gradient is the exact gradient of the cost (central differences), and without a robust loss the matrix is
    JᵀJ of the residuals' central differences (pose columns chained through the world point, intrinsics columns
    and the prior); with Cauchy's loss it is the IRLS model ``Σ ρ' JᵀJ``."""
    rng = np.random.default_rng(2)
    camera = fov_camera()
    frames, n = 3, 12
    poses = SE3.exp(jnp.asarray(rng.normal(0, 0.2, (frames, 6))))
    uv = rng.uniform([10, 10], [150, 110], (frames, n, 2))
    points = jax.vmap(lambda p, x: p.inverse().apply(x))(poses, camera.unproject(jnp.asarray(uv)) * 3.0)
    problem = CameraSequence(
        camera=camera, cam_from_world=poses.wxyz_xyz, velocity=jnp.asarray(np.tile(VELOCITIES[0], (frames, 1))),
        readout=jnp.full(frames, 0.7), points=points, pixels=jnp.asarray(uv + rng.normal(0, 1.5, uv.shape)),
        weights=jnp.asarray(rng.uniform(0.5, 2.0, (frames, n))), correction=jnp.zeros(3),
        prior=jnp.asarray([10.0, 0.2, 0.2]), loss=loss, calibrate=True, block_frames=2)
    y = (jnp.asarray(rng.normal(0, 0.01, (frames, 6))), jnp.asarray([0.003, 0.7, -0.4]))
    flat = np.concatenate([np.asarray(y[0]).ravel(), np.asarray(y[1])])
    unflat = lambda v: (jnp.asarray(v[:-3].reshape(frames, 6)), jnp.asarray(v[-3:]))
    at = jax.jit(lambda d, k: jnp.concatenate([a.ravel() for a in jax.tree.leaves(sequence_residuals((d, k), problem))]))
    residuals = lambda v: np.asarray(at(*unflat(v)))
    eps = 1e-6
    jac = np.stack([(residuals(flat + eps * e) - residuals(flat - eps * e)) / (2 * eps) for e in np.eye(flat.size)], axis=-1)
    system = jax.jit(lambda motion: sequence_normal_equations(problem, motion))(y)  # compiled once
    grad = np.concatenate([np.asarray(system.grad).ravel(), np.asarray(system.static_grad)])
    np.testing.assert_allclose(grad, jac.T @ residuals(flat), rtol=1e-5, atol=1e-6)
    if isinstance(loss, TrivialLoss):
        hessian = jac.T @ jac
        frame_blocks = np.stack([hessian[6 * t:6 * t + 6, 6 * t:6 * t + 6] for t in range(frames)])
        np.testing.assert_allclose(np.asarray(system.diag), frame_blocks, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.asarray(system.coupling).reshape(-1, 3), hessian[:-3, -3:], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.asarray(system.static_matrix), hessian[-3:, -3:], rtol=1e-5, atol=1e-6)
        off = hessian[:-3, :-3] - np.kron(np.eye(frames), np.ones((6, 6))) * hessian[:-3, :-3]
        np.testing.assert_allclose(off, 0.0, atol=1e-9)  # frames independent given the correction: no bands


def test_velocities_are_central_one_sided_or_zero():
    rng = np.random.default_rng(3)
    start = SE3.exp(jnp.asarray(rng.normal(0, 0.3, (C, 6))))
    cam_from_world = np.stack([np.asarray((SE3.exp(jnp.asarray(t * VELOCITIES)) @ start).wxyz_xyz) for t in range(T)])
    registered = np.ones((T, C), bool)
    registered[3, 0] = registered[5, 0] = registered[6, 0] = False  # camera 0: frames 4 and 7 without a neighbour,
    v = camera_velocities(cam_from_world, registered)                # 0 and 2 with one (1 and 1)
    expected = np.broadcast_to(VELOCITIES, (T, C, 6)).copy()
    expected[[3, 4, 5, 6, 7], 0] = 0.0
    np.testing.assert_allclose(v, expected, atol=1e-9)


@pytest.mark.slow  # 26 s (its own traces of the refinement); moved out of the fast tier for its 5-minute budget
def test_frames_with_too_few_measurements_keep_their_pose_and_bad_inputs_are_refused():
    rng = np.random.default_rng(4)
    cameras = stack_cameras([fov_camera(), fov_camera()])
    points, ids, pixels, truth = _scene(0.5, cameras, rng)
    start = _perturbed(truth, rng)
    ids[2, 1, 5:] = -1  # 5 measurements
    registered = np.ones((T, C), bool)
    registered[6, 0] = False
    corr = _correspondences(points, ids, pixels, start, registered)
    found = refine_registered_poses(corr, cameras, PoseRefinementOptions(readout=0.5))
    assert not found.refined[2, 1] and not found.refined[6, 0] and found.refined.sum() == T * C - 2
    np.testing.assert_array_equal(found.world_from_camera[2, 1], start[2, 1])
    np.testing.assert_array_equal(found.world_from_camera[6, 0], start[6, 0])
    assert found.moved_m[2, 1] == 0 and found.moved_m[0, 0] > 1e-3
    with pytest.raises(ValueError, match="3 cameras registered, intrinsics for"):
        refine_registered_poses(corr, cameras, world_from_camera=np.zeros((T, 3, 7)), registered=np.ones((T, 3), bool))
    with pytest.raises(ValueError, match="readout must lie in"):
        PoseRefinementOptions(readout=-1.0)
