"""Tests for bcmocap.sim.rom: the synthetic range-of-motion trial and the skeleton comparison.

``leg_model`` (a 5-segment body with a straight hinged leg and three cameras on the pelvis) is shared
with test_rom.py and test_virtual_cameras.py; every trial here has the same number of frames so the
forward kinematics compiles once.
"""

import numpy as np
import pytest
from conftest import fov_camera, quat_distance

from bcmocap.geometry import SE3, SO3
from bcmocap.kinematics import Rig, Skeleton, camera_poses
from bcmocap.sim import range_of_motion, range_of_motion_trial, skeleton_errors
from bcmocap.sim.rom import ROM_AMPLITUDE_DEG

LEG_SEGMENTS = ("pelvis", "torso", "thigh", "shin", "foot")
# The root sits at the torso joint as in the CMU skeletons; hip, knee and ankle are collinear at rest.
LEG_OFFSETS = np.array([[0, 0, 0], [0, 0, 0], [0.1, -0.02, -0.1], [0.02, 0, -0.42], [0.019, 0, -0.399]], float)
LEG_KNEE_AXIS = np.array([0.42, 0.0, 0.02])
# (camera, segment, rotation vector of segment_from_camera, translation in the segment frame (m))
LEG_MOUNTS = (
    ("waist_front", "pelvis", (1.4, 0.1, 0.2), (0.15, 0.0, 0.05)),
    ("waist_left", "pelvis", (0.3, 1.3, -0.1), (0.02, 0.16, 0.05)),
    ("waist_back", "pelvis", (-1.3, 0.3, -0.1), (-0.15, 0.02, 0.05)),
    ("chest", "torso", (1.2, -0.4, 0.3), (0.12, 0.0, 0.3)),
    ("thigh", "thigh", (0.2, 1.5, 0.1), (0.1, 0.0, -0.2)),
    ("shin", "shin", (-0.3, 1.4, 0.4), (0.08, 0.0, -0.2)),
    ("foot", "foot", (0.5, -0.2, 1.0), (0.05, 0.1, -0.03)),
)
TRIAL = dict(fps=30.0, hold_seconds=0.5, seconds_per_joint=2.0)  # 15 + 5 x 60 + 7 = 322 frames


def leg_model() -> tuple[Skeleton, Rig]:
    axes = np.zeros((5, 3))
    axes[3] = LEG_KNEE_AXIS
    skeleton = Skeleton(LEG_SEGMENTS, (-1, 0, 0, 2, 3), LEG_OFFSETS, ("free", "ball", "ball", "hinge", "ball"), axes)
    mounts = [
        (name, seg, SE3.from_rotation_and_translation(SO3.exp(np.asarray(r, float)), np.asarray(t, float)), fov_camera())
        for name, seg, r, t in LEG_MOUNTS
    ]
    return skeleton, Rig.from_mounts(skeleton, mounts)


@pytest.fixture(scope="module")
def model():
    return leg_model()


@pytest.fixture(scope="module")
def noiseless(model):
    return range_of_motion_trial(*model, rotation_sigma_deg=0.0, position_sigma_m=0.0, missing_fraction=0.0, **TRIAL)


def test_rest_hold_then_each_joint_in_turn(model):
    skeleton, _ = model
    motion, rest = range_of_motion(skeleton, **TRIAL)
    assert motion.num_frames == 322 and np.array_equal(rest, np.arange(15))
    rot = np.asarray(motion.rotations)
    angle = quat_distance(rot, np.array([1.0, 0, 0, 0]))  # (T, J) rotation away from rest
    np.testing.assert_allclose(angle[rest], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(motion.root_position)[rest], [[0, 0, 0.95]] * 15)
    for slot, j in enumerate(range(5)):
        frames = slice(15 + 60 * slot, 15 + 60 * (slot + 1))
        others = np.delete(np.arange(5), j)
        assert angle[frames, j].max() > np.deg2rad(25)  # every joint is exercised ...
        np.testing.assert_allclose(angle[frames][:, others], 0.0, atol=1e-12)  # ... alone
    knee = rot[:, 3]
    axis = LEG_KNEE_AXIS / np.linalg.norm(LEG_KNEE_AXIS)
    np.testing.assert_allclose(np.cross(knee[:, 1:], axis), 0.0, atol=1e-12)  # the hinge turns about its axis
    flex = 2 * np.arctan2(knee[:, 1:] @ axis, knee[:, 0])
    assert flex.min() >= -1e-12 and np.isclose(flex.max(), np.deg2rad(ROM_AMPLITUDE_DEG["shin"]), rtol=0.01)


def test_exercised_subset_leaves_the_others_at_rest(model):
    skeleton, _ = model
    motion, _ = range_of_motion(skeleton, exercised=["thigh", "shin"], fps=30.0, hold_seconds=0.5, seconds_per_joint=1.0)
    angle = quat_distance(np.asarray(motion.rotations), np.array([1.0, 0, 0, 0]))
    assert motion.num_frames == 15 + 60 + 7
    np.testing.assert_allclose(angle[:, [0, 1, 4]], 0.0, atol=1e-12)
    assert angle[:, 2].max() > 0.5 and angle[:, 3].max() > 1.0
    with pytest.raises(ValueError, match="unknown segment 'knee'"):
        range_of_motion(skeleton, exercised=["knee"])


def test_trial_noise_is_sfm_like_and_seeded(model, noiseless):
    skeleton, rig = model
    trial = range_of_motion_trial(skeleton, rig, seed=4, **TRIAL)
    again = range_of_motion_trial(skeleton, rig, seed=4, **TRIAL)
    np.testing.assert_array_equal(trial.world_from_camera, again.world_from_camera)
    np.testing.assert_array_equal(trial.registered, again.registered)
    assert not np.array_equal(range_of_motion_trial(skeleton, rig, seed=5, **TRIAL).registered, trial.registered)
    reg = trial.registered
    assert 0.07 < 1 - reg.mean() < 0.13  # 10 % missing
    assert np.isnan(trial.world_from_camera[~reg]).all() and np.isfinite(trial.world_from_camera[reg]).all()
    truth = np.asarray(camera_poses(skeleton, rig, trial.motion).wxyz_xyz)
    np.testing.assert_allclose(noiseless.world_from_camera, truth, atol=1e-12)
    rot = np.rad2deg(quat_distance(trial.world_from_camera[reg][:, :4], truth[reg][:, :4]))
    pos = np.linalg.norm(trial.world_from_camera[reg][:, 4:] - truth[reg][:, 4:], axis=-1)
    # per-axis σ of 1° and 1 cm: the RMS of a 3-D error is √3 σ
    assert np.sqrt(np.mean(rot**2)) == pytest.approx(np.sqrt(3), rel=0.1)
    assert np.sqrt(np.mean(pos**2)) == pytest.approx(0.01 * np.sqrt(3), rel=0.1)
    assert not trial.outliers.any()
    assert trial.assignment == {name: seg for name, seg, _, _ in LEG_MOUNTS}
    assert trial.root_origin == ("torso",)


def test_outliers_are_gross_and_flagged(model):
    trial = range_of_motion_trial(*model, outlier_fraction=0.05, seed=1, **TRIAL)
    assert 0.02 < trial.outliers.mean() < 0.08 and not (trial.outliers & ~trial.registered).any()
    truth = np.asarray(camera_poses(*model, trial.motion).wxyz_xyz)
    pos = np.linalg.norm(trial.world_from_camera[trial.outliers][:, 4:] - truth[trial.outliers][:, 4:], axis=-1)
    assert pos.min() > 0.05


def test_skeleton_errors(model):
    skeleton, rig = model
    zero = skeleton_errors(skeleton, rig, skeleton, np.asarray(rig.segment_from_camera))
    assert set(zero["joint_centre_m"]) == {"torso", "thigh", "shin", "foot"}
    assert set(zero["bone_length_pct"]) == {"torso~thigh", "thigh→shin", "shin→foot"}  # no bone of zero length
    for values in zero.values():
        np.testing.assert_allclose(list(values.values()), 0.0, atol=1e-12)
    longer = Skeleton(skeleton.names, skeleton.parents, LEG_OFFSETS * np.array([[1], [1], [1], [1.1], [1]]),
                      skeleton.joint_types, skeleton.hinge_axes)
    errors = skeleton_errors(skeleton, rig, longer, np.asarray(rig.segment_from_camera))
    assert errors["bone_length_pct"]["thigh→shin"] == pytest.approx(10.0)
    # the thigh camera sees the knee 4 cm lower, the shin camera (moved with the shin) does not
    assert errors["joint_centre_m"]["shin"] == pytest.approx(0.05 * np.linalg.norm(LEG_OFFSETS[3]), rel=1e-9)
    assert errors["joint_centre_m"]["thigh"] == 0.0
    with pytest.raises(ValueError, match="different topologies"):
        skeleton_errors(skeleton, rig, Skeleton(["pelvis"], [-1], np.zeros((1, 3))), np.asarray(rig.segment_from_camera))

