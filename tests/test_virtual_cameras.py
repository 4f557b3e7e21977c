"""Tests for bcmocap.kinematics.virtual: robust pose averages, virtual cameras, rig re-parameterisation."""

import numpy as np
import pytest
from conftest import quat_distance, random_quaternions
from test_sim_rom import TRIAL, model  # noqa: F401 (shared module fixture)

from bcmocap.geometry import SO3, average_quaternions
from bcmocap.kinematics import (
    camera_poses,
    estimate_virtual_camera,
    reparameterise_rig,
    robust_average_poses,
    segment_from_virtual,
)
from bcmocap.sim import range_of_motion_trial

PELVIS = ["waist_front", "waist_left", "waist_back"]


@pytest.fixture(scope="module")
def noiseless(model):
    """Exact poses with 20 % of camera-frames missing."""
    return range_of_motion_trial(*model, rotation_sigma_deg=0.0, position_sigma_m=0.0, missing_fraction=0.2, **TRIAL)


def pelvis_poses(model, trial):
    idx = [model[1].index(c) for c in PELVIS]
    return trial.world_from_camera[:, idx], trial.registered[:, idx]


def poses_near(rng, n, centre_q, centre_p, deg=1.0, m=0.01):
    """``(n, 7)`` poses scattered around a centre by ``deg`` (per axis) and ``m`` metres."""
    q = np.asarray((SO3(centre_q) @ SO3.exp(np.deg2rad(deg) * rng.normal(size=(n, 3)))).wxyz)
    return np.concatenate([q, centre_p + m * rng.normal(size=(n, 3))], axis=1)


def test_robust_average_of_identical_and_masked_poses(rng):
    pose = np.concatenate([random_quaternions(rng, ()), [0.3, -0.2, 1.0]])
    poses = np.tile(pose, (2, 5, 1))
    poses[0, 3] = np.nan  # masked rows are never read
    mask = np.ones((2, 5), bool)
    mask[0, 3] = False
    mean, w = robust_average_poses(poses, mask)
    assert mean.shape == (2, 7) and w.shape == (2, 5) and w[0, 3] == 0
    np.testing.assert_allclose(quat_distance(mean[:, :4], pose[:4]), 0.0, atol=1e-12)
    np.testing.assert_allclose(mean[:, 4:], [pose[4:]] * 2, atol=1e-12)
    none, _ = robust_average_poses(poses, np.zeros((2, 5), bool))
    assert np.isnan(none).all()
    with pytest.raises(ValueError, match=r"expected poses \(..., N, 7\) and mask \(..., N\), got \(5, 6\)"):
        robust_average_poses(np.zeros((5, 6)))


def test_robust_average_drops_outliers(rng):
    q0, p0 = random_quaternions(rng, ()), np.array([1.0, 2.0, 0.5])
    inliers = poses_near(rng, 40, q0, p0)
    bad = poses_near(rng, 6, random_quaternions(rng, ()), p0 + 0.4)
    mean, w = robust_average_poses(np.concatenate([inliers, bad]))
    assert (w[40:] == 0).all() and (w[:40] > 0).all()
    plain, w_plain = robust_average_poses(np.concatenate([inliers, bad]), robust=False)
    assert (w_plain == 1).all()
    assert np.rad2deg(quat_distance(mean[:4], q0)) < 0.5 < np.rad2deg(quat_distance(plain[:4], q0))
    assert np.linalg.norm(mean[4:] - p0) < 0.005 < np.linalg.norm(plain[4:] - p0)
    np.testing.assert_allclose(quat_distance(plain[:4], average_quaternions(np.concatenate([inliers, bad])[:, :4])), 0, atol=1e-9)
    # two of five agree on a wrong pose: the medoid start still picks the majority
    few = np.concatenate([poses_near(rng, 3, q0, p0), np.tile(bad[0], (2, 1))])
    mean, w = robust_average_poses(few)
    np.testing.assert_array_equal(w[3:], 0.0)
    assert np.linalg.norm(mean[4:] - p0) < 0.02


def test_virtual_camera_reproduces_the_physical_cameras(model, noiseless):
    poses, registered = pelvis_poses(model, noiseless)
    vc = estimate_virtual_camera(PELVIS, poses, registered, name="pelvis")
    assert vc.reference in PELVIS and (vc.frames > 0.5 * len(poses)).all() and (vc.inlier_fraction == 1).all()
    # centred: the cameras' centres average to V's origin
    np.testing.assert_allclose(vc.virtual_from_camera[:, 4:].mean(axis=0), 0.0, atol=1e-12)
    world_v, known = vc.world_from_virtual(poses, registered)
    np.testing.assert_array_equal(known, registered.any(axis=1))
    again = vc.camera_poses(world_v)
    np.testing.assert_allclose(quat_distance(again[registered][:, :4], poses[registered][:, :4]), 0.0, atol=1e-9)
    np.testing.assert_allclose(again[registered][:, 4:], poses[registered][:, 4:], atol=1e-9)
    # the paper's choice: V is the reference camera
    at_ref = estimate_virtual_camera(PELVIS, poses, registered, reference="waist_left", centred=False)
    np.testing.assert_allclose(at_ref.virtual_from_camera[1], [1, 0, 0, 0, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(at_ref.camera_from_virtual()[1], [1, 0, 0, 0, 0, 0, 0], atol=1e-12)


def test_reparameterised_rig_leaves_camera_poses_unchanged(model, noiseless):
    skeleton, rig = model
    vc = estimate_virtual_camera(PELVIS, *pelvis_poses(model, noiseless), name="pelvis")
    mount = segment_from_virtual(rig, vc)
    same = reparameterise_rig(rig, [vc], {"pelvis": mount})
    assert same.names == rig.names and same.segments == rig.segments
    motion = noiseless.motion[::40]
    want = np.asarray(camera_poses(skeleton, rig, motion).wxyz_xyz)
    got = np.asarray(camera_poses(skeleton, same, motion).wxyz_xyz)
    np.testing.assert_allclose(quat_distance(got[..., :4], want[..., :4]), 0.0, atol=1e-9)
    np.testing.assert_allclose(got[..., 4:], want[..., 4:], atol=1e-9)
    # moving V on its segment moves all its cameras together, the others stay
    shifted = reparameterise_rig(rig, [vc], {"pelvis": mount + np.r_[0, 0, 0, 0, 0.1, 0, 0]})
    moved = np.asarray(shifted.segment_from_camera)[:, 4:] - np.asarray(rig.segment_from_camera)[:, 4:]
    np.testing.assert_allclose(moved[:3], [[0.1, 0, 0]] * 3, atol=1e-12)
    np.testing.assert_allclose(moved[3:], 0.0, atol=1e-12)
    with pytest.raises(ValueError, match="no segment_from_virtual for virtual camera 'pelvis'"):
        reparameterise_rig(rig, [vc], {})
    idx = [rig.index("waist_front"), rig.index("chest")]
    mixed = estimate_virtual_camera(["waist_front", "chest"], noiseless.world_from_camera[:, idx], noiseless.registered[:, idx])
    with pytest.raises(ValueError, match=r"cameras of virtual camera 'waist_front\+chest' are on different segments"):
        reparameterise_rig(rig, [mixed], {"waist_front+chest": mount})


def test_a_camera_that_failed_at_one_frame_is_outvoted(model, noiseless):
    poses, registered = pelvis_poses(model, noiseless)
    vc = estimate_virtual_camera(PELVIS, poses, registered)
    frame = int(np.flatnonzero(registered.all(axis=1))[3])
    bad = poses.copy()
    bad[frame, 0, 4:] += 0.3
    bad[frame, 0, :4] = [0.9, 0.3, 0.3, 0.1]
    exact, _ = vc.world_from_virtual(poses, registered)
    robust, _ = vc.world_from_virtual(bad, registered)
    plain, _ = vc.world_from_virtual(bad, registered, robust=False)
    np.testing.assert_allclose(robust[frame, 4:], exact[frame, 4:], atol=1e-9)
    assert np.linalg.norm(plain[frame, 4:] - exact[frame, 4:]) > 0.05


def test_noisy_relative_transforms_are_averaged(model):
    skeleton, rig = model
    trial = range_of_motion_trial(skeleton, rig, outlier_fraction=0.03, seed=6, **TRIAL)
    vc = estimate_virtual_camera(PELVIS, *pelvis_poses(model, trial), name="pelvis")
    truth = estimate_virtual_camera(PELVIS, *pelvis_poses(model, range_of_motion_trial(
        skeleton, rig, rotation_sigma_deg=0.0, position_sigma_m=0.0, missing_fraction=0.0, **TRIAL)), name="pelvis")
    # with ~250 co-registered frames of 1° / 1 cm noise the relative mounts are known to a few tenths
    assert np.rad2deg(quat_distance(vc.virtual_from_camera[:, :4], truth.virtual_from_camera[:, :4])).max() < 0.3
    assert np.linalg.norm(vc.virtual_from_camera[:, 4:] - truth.virtual_from_camera[:, 4:], axis=1).max() < 0.005
    assert (vc.inlier_fraction < 1).any()


def test_bad_input_names_the_camera(model, noiseless):
    poses, registered = pelvis_poses(model, noiseless)
    lonely = registered.copy()
    lonely[:, 2] = ~registered[:, 0] & ~registered[:, 1]  # never together with the others
    lonely[:, 0] = registered[:, 0] & ~lonely[:, 2]
    with pytest.raises(ValueError, match="camera 'waist_back' is never registered in the same frame as the reference"):
        estimate_virtual_camera(PELVIS, poses, lonely, reference="waist_front")
    few = registered.copy()
    few[10:, 1] = False
    with pytest.warns(UserWarning, match=r"camera 'waist_left' is registered with 'waist_\w+' in only \d frames"):
        estimate_virtual_camera(PELVIS, poses, few)
    with pytest.raises(ValueError, match="reference camera 'chest' is not one of"):
        estimate_virtual_camera(PELVIS, poses, registered, reference="chest")
    with pytest.raises(ValueError, match=r"expected world_from_camera \(T, 3, 7\) and registered \(T, 3\)"):
        estimate_virtual_camera(PELVIS, poses[:, :2], registered[:, :2])
