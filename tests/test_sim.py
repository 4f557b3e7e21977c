"""Tests for bcmocap.sim: the synthetic capture's determinism, counts and consistency with its truth.

The standard capture parses CMU files and compiles the observation simulator (the slow part): one
module-scoped capture of 0.2 s and at most 3 frames of correspondences serve every test here.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import KNEE_AXIS, quat_distance, random_motion, random_quaternions

from bcmocap.eval import joint_position_errors
from bcmocap.geometry import SE3, SO3
from bcmocap.kinematics import JointType, Motion, Skeleton, camera_poses, forward_kinematics, world_rotations
from bcmocap.sim import (
    BODY_SEGMENTS,
    CMU_TRIALS,
    BodySegment,
    load_body_motion,
    make_textured_scene,
    make_world,
    reduce_motion,
    resample,
    standard_capture,
    standard_rig,
)

FRAMES = 3


@pytest.fixture(scope="module")
def capture():
    return standard_capture("walk", seconds=0.2, seed=3)


@pytest.fixture(scope="module")
def corr(capture):
    return capture.correspondences(0, FRAMES)


def test_standard_capture_model(capture):
    skeleton = capture.skeleton
    assert capture.num_frames == 12  # 0.2 s at 60 Hz
    assert skeleton.names == tuple(s.name for s in BODY_SEGMENTS)
    assert skeleton.num_dofs == 40
    assert capture.rig.num_cameras == 18
    assert sum(t == JointType.HINGE for t in skeleton.joint_types) == 4
    capture.motion.check(skeleton)


def test_frames_depend_only_on_seed_and_frame_index(capture, corr):
    later = capture.correspondences(1, FRAMES)
    again = capture.correspondences(0, FRAMES)
    for f in dataclasses.fields(corr):
        a, b, c = getattr(corr, f.name), getattr(later, f.name), getattr(again, f.name)
        np.testing.assert_array_equal(a, c, err_msg=f.name)
        if f.name not in ("points", "fps"):
            np.testing.assert_array_equal(a[1:FRAMES], b, err_msg=f.name)


@pytest.mark.slow
def test_same_seed_gives_identical_measurements(capture, corr):
    # A second capture with the same truth, scene and seed (this compiles a second simulator: one frame only).
    twin = dataclasses.replace(capture)
    assert twin._simulator is not capture._simulator
    last = twin.correspondences(FRAMES - 1, FRAMES)
    for f in dataclasses.fields(corr):
        if f.name not in ("points", "fps"):
            np.testing.assert_array_equal(getattr(last, f.name), getattr(corr, f.name)[FRAMES - 1 :], err_msg=f.name)


def test_world_is_deterministic_per_seed():
    path = np.array([[0.0, 0.0], [1.0, 0.5]])
    a, b, c = make_world(path, seed=5), make_world(path, seed=5), make_world(path, seed=6)
    np.testing.assert_array_equal(a.points, b.points)
    assert a.points.shape != c.points.shape or not np.array_equal(a.points, c.points)
    assert np.all(a.points >= a.lower - 1e-9) and np.all(a.points <= a.upper + 1e-9)
    assert a.points.shape[1] == 3 and len(a.points) > 500


def test_observation_counts_and_slots(capture, corr):
    used = corr.weights > 0
    counts = used.sum(axis=-1)  # (T, C)
    reg = corr.registered
    assert reg[0].all()  # frame 0 has no previous frame for the homography
    assert 0 < (~reg).sum() <= 0.25 * reg.size
    assert counts.max() <= capture.noise.max_observations
    assert np.mean(counts[reg] >= 150) >= 0.9
    # Unregistered camera-frames have no point observations but homography matches, and only they do.
    np.testing.assert_array_equal(counts[~reg], 0)
    has_matches = (corr.homography_weights > 0).any(axis=-1)
    np.testing.assert_array_equal(has_matches & reg, False)
    assert np.all((corr.homography_weights > 0).sum(axis=-1)[~reg] >= 30)
    # Empty slots are marked −1 and have zero weight; used ones point at scene points.
    np.testing.assert_array_equal(corr.point_ids < 0, ~used)
    assert corr.point_ids.max() < len(corr.points)


def project(capture, motion, points_per_camera):
    """Pixels ``(T, C, N, 2)`` of points ``(T, C, N, 3)`` seen from the true cameras."""
    cam_from_world = camera_poses(capture.skeleton, capture.rig, motion).inverse()
    p_cam = SE3(cam_from_world.wxyz_xyz[:, :, None, :]) @ jnp.asarray(points_per_camera)
    uv, valid = jax.vmap(lambda p: jax.vmap(lambda cam, q: cam.project(q))(capture.rig.intrinsics, p))(p_cam)
    return np.asarray(uv), np.asarray(valid)


def test_measurements_agree_with_the_truth(capture, corr):
    truth = capture.motion[:FRAMES]
    used = corr.weights > 0
    uv, valid = project(capture, truth, corr.points[corr.point_ids.clip(0)])
    assert valid[used].all()
    err = np.linalg.norm(uv - corr.pixels, axis=-1)[used]
    # 1 px noise and 10 % outliers.
    assert np.median(err) < 2.0
    assert 0.8 < np.mean(err < 5.0) < 0.97
    # In the image, up to the 1 px noise added to points projected near its border.
    width, height = capture.rig.intrinsics.width, capture.rig.intrinsics.height
    u, v = corr.pixels[..., 0][used], corr.pixels[..., 1][used]
    assert np.all((u > -6) & (u < width + 5) & (v > -6) & (v < height + 5))
    # Registered poses are near the true camera poses (SfM-like noise of 1° and 2 cm).
    true_poses = np.asarray(camera_poses(capture.skeleton, capture.rig, truth).wxyz_xyz)
    reg = corr.registered
    angle = quat_distance(corr.world_from_camera[..., :4], true_poses[..., :4])[reg]
    dist = np.linalg.norm(corr.world_from_camera[..., 4:] - true_poses[..., 4:], axis=-1)[reg]
    assert np.median(np.rad2deg(angle)) < 3.0 and np.rad2deg(angle).max() < 6.0
    assert np.median(dist) < 0.06 and dist.max() < 0.15


def test_initial_motion_from_noisy_poses_is_near_the_truth(capture, corr):
    initial = capture.initial_motion(corr)
    truth = capture.motion[:FRAMES]
    assert initial.rotations.shape == truth.rotations.shape
    err = joint_position_errors(capture.skeleton, initial, truth)  # (T, J) m
    assert np.median(err) < 0.1


def test_capture_hinges_are_exact(capture):
    skeleton, rot = capture.skeleton, np.asarray(capture.motion.rotations)
    for j, kind in enumerate(skeleton.joint_types):
        if kind == JointType.HINGE:
            axis = np.asarray(skeleton.hinge_axes[j])
            np.testing.assert_allclose(np.cross(rot[:, j, 1:], axis), 0.0, atol=1e-12)


# ---- reduce_motion and resample on a small hand-built skeleton ---------------------------------------

SMALL = (
    BodySegment("hips", None, "pelvis", "pelvis", JointType.FREE),
    BodySegment("knee", "leg", "shin", "shin", JointType.HINGE),  # listed before its parent on purpose
    BodySegment("upper", "hips", "head", "torso", JointType.BALL),
    BodySegment("leg", "hips", "thigh", "thigh", JointType.BALL),
)


def test_reduce_motion(skeleton):
    rng = np.random.default_rng(0)
    full = random_motion(skeleton, 4, rng, max_angle=1.5)
    # Give the full knee some swing: the reduced hinge must keep only the twist about its axis.
    rot = np.array(full.rotations)
    rot[:, 4] = random_quaternions(rng, (4,), max_angle=1.0)
    full = Motion(full.root_position, rot)
    reduced_skeleton, reduced = reduce_motion(skeleton, full, SMALL)
    assert reduced_skeleton.names == ("hips", "upper", "leg", "knee")
    assert reduced_skeleton.parents == (-1, 0, 0, 2)
    assert reduced_skeleton.joint_types == (JointType.FREE, JointType.BALL, JointType.BALL, JointType.HINGE)
    axis = KNEE_AXIS / np.linalg.norm(KNEE_AXIS)
    np.testing.assert_allclose(reduced_skeleton.hinge_axes[3], axis, atol=1e-15)
    np.testing.assert_allclose(reduced_skeleton.offsets[1], skeleton.offsets[1], atol=1e-15)
    np.testing.assert_allclose(reduced_skeleton.offsets[3], skeleton.offsets[4], atol=1e-15)
    # Hinge rotations are exactly about their axis.
    q = np.asarray(reduced.rotations)
    np.testing.assert_allclose(np.cross(q[:, 3, 1:], axis), 0.0, atol=1e-15)
    # Ball segments take the world orientation of their bone; joints sit where the full skeleton's are.
    world_full = np.asarray(world_rotations(skeleton, full))
    world_reduced = np.asarray(world_rotations(reduced_skeleton, reduced))
    np.testing.assert_allclose(quat_distance(world_reduced[:, :3], world_full[:, [0, 2, 3]]), 0.0, atol=1e-7)
    pos_full = np.asarray(forward_kinematics(skeleton, full).translation())
    pos_reduced = np.asarray(forward_kinematics(reduced_skeleton, reduced).translation())
    np.testing.assert_allclose(pos_reduced, pos_full[:, [0, 1, 3, 4]], atol=1e-13)


def test_reduce_motion_rejects_a_hinge_on_a_ball_bone(skeleton):
    segments = SMALL[:1] + (BodySegment("arm", "hips", "torso", "torso", JointType.HINGE),)
    with pytest.raises(ValueError, match="'arm' is a hinge but bone 'torso' is not"):
        reduce_motion(skeleton, skeleton.rest_motion(2), segments)
    with pytest.raises(ValueError, match=r"unknown parents: \['arm'\]"):
        reduce_motion(skeleton, skeleton.rest_motion(2), (SMALL[0], BodySegment("arm", "nope", "torso", "torso", JointType.BALL)))


def test_resample(skeleton):
    src = random_motion(skeleton, 9, np.random.default_rng(1), max_angle=0.5)
    same = resample(src, 120.0, 120.0)
    np.testing.assert_allclose(same.root_position, src.root_position, atol=1e-15)
    np.testing.assert_allclose(quat_distance(same.rotations, src.rotations), 0.0, atol=1e-7)
    half = resample(src, 120.0, 60.0)  # every other frame, both ends kept
    assert half.num_frames == 5
    np.testing.assert_allclose(half.root_position, np.asarray(src.root_position)[::2], atol=1e-15)
    np.testing.assert_allclose(quat_distance(half.rotations, np.asarray(src.rotations)[::2]), 0.0, atol=1e-7)
    double = resample(src, 120.0, 240.0)  # midpoints between frames
    assert double.num_frames == 17
    p = np.asarray(src.root_position)
    np.testing.assert_allclose(double.root_position[1::2], 0.5 * (p[:-1] + p[1:]), atol=1e-15)
    np.testing.assert_allclose(quat_distance(double.rotations[-1], src.rotations[-1]), 0.0, atol=1e-7)
    r = np.asarray(src.rotations)
    mid = np.asarray(double.rotations)[1::2]
    np.testing.assert_allclose(quat_distance(mid, r[:-1]), quat_distance(mid, r[1:]), atol=1e-7)
    np.testing.assert_allclose(2 * quat_distance(mid, r[:-1]), quat_distance(r[:-1], r[1:]), atol=1e-7)
    odd = resample(src, 120.0, 50.0)  # frame times 0, 2.4, 4.8, 7.2 (in source frames)
    assert odd.num_frames == 4
    np.testing.assert_allclose(odd.root_position[0], p[0], atol=1e-15)
    np.testing.assert_allclose(odd.root_position[1], 0.6 * p[2] + 0.4 * p[3], atol=1e-14)


@pytest.mark.slow
def test_lazy_problem_windows_equal_the_in_memory_problem(capture, corr):
    """Simulating a window on demand gives the same terms as slicing the whole sequence's problem."""
    from bcmocap.solver.objective import paper_terms

    whole = paper_terms(corr, capture.skeleton, include_homography=True)
    lazy = capture.lazy_problem()
    assert lazy.num_frames == capture.num_frames
    for start, stop in ((0, 2), (1, 3)):
        expected = [t.window(start, stop) for t in whole]
        got = lazy.window(start, stop)
        assert [t.label for t in got] == [t.label for t in expected]
        for g, e in zip(got[:2], expected[:2]):
            for key in e.data:
                np.testing.assert_array_equal(np.asarray(g.data[key]), np.asarray(e.data[key]))
        for g in got[2:]:  # smoothness pairs: the sequence's first pair is dropped, later windows keep theirs
            assert np.asarray(g.data)[0] == (0.0 if start == 0 else 1.0)


def test_segment_distance_squared_matches_a_dense_sampling():
    from bcmocap.sim.observe import segment_distance_squared

    rng = np.random.default_rng(3)
    p1, q1, p2, q2 = rng.normal(size=(4, 20, 3))
    q2[0] = p2[0]  # a degenerate segment counts as its point
    q1[1] = p1[1] + 2.0 * (q2[1] - p2[1])  # parallel segments
    got = np.asarray(segment_distance_squared(p1, q1, p2, q2))
    s = np.linspace(0.0, 1.0, 801)
    a = p1[:, None] + s[None, :, None] * (q1 - p1)[:, None]  # (20, S, 3)
    b = p2[:, None] + s[None, :, None] * (q2 - p2)[:, None]
    brute = np.min(np.sum((a[:, :, None] - b[:, None]) ** 2, -1), axis=(1, 2))
    assert got.shape == (20,)
    assert np.all(got <= brute + 1e-9) and np.allclose(got, brute, atol=2e-4)


# ---- the bundled CMU trials that are not walk, run or jump ---------------------------------------------

#: Frames of the added trials at 60 fps: scoop 600 frames at 120 Hz (5 s), hop 1006 (8.4 s).
ADDED_TRIALS = {"scoop": 300, "hop": 503}


@pytest.fixture(scope="module", params=sorted(ADDED_TRIALS))
def added_trial(request):
    return request.param, *load_body_motion(request.param, fps=60.0)


def test_added_trials_load_whole_finite_and_on_the_camera_skeleton(added_trial):
    name, skeleton, motion = added_trial
    assert motion.num_frames == ADDED_TRIALS[name]  # all the bundled frames, 120 Hz resampled to 60 fps
    root, rotations = np.asarray(motion.root_position), np.asarray(motion.rotations)
    assert np.all(np.isfinite(root)) and np.all(np.isfinite(rotations))
    walk, _ = load_body_motion("walk", fps=60.0, seconds=0.05)
    assert skeleton.names == walk.names == tuple(s.name for s in BODY_SEGMENTS)
    assert skeleton.parents == walk.parents and skeleton.joint_types == walk.joint_types
    hinges = [j for j, t in enumerate(skeleton.joint_types) if t == JointType.HINGE]
    np.testing.assert_allclose(np.linalg.norm(np.asarray(skeleton.hinge_axes)[hinges], axis=1), 1.0, atol=1e-12)
    # Knees and elbows turn about their axes only; the 18 cameras follow the motion without a NaN.
    np.testing.assert_allclose(np.asarray(skeleton.project_rotations(rotations)), rotations, atol=1e-12)
    poses = np.asarray(standard_rig(skeleton, 64, 36).world_from_camera(forward_kinematics(skeleton, motion)).wxyz_xyz)
    assert poses.shape == (motion.num_frames, 18, 7) and np.all(np.isfinite(poses))


def test_added_trials_stay_in_the_studio_room_and_do_what_they_were_chosen_for(added_trial):
    from bcmocap.sim.studio import capsule_ends

    name, skeleton, motion = added_trial
    ends, radii, _ = capsule_ends(skeleton, motion)  # (T, K, 2, 3), (K,)
    scene = make_textured_scene(np.asarray(motion.root_position)[:, :2], seed=0)
    r = radii[None, :, None]
    xy = ends[..., :2]
    assert np.all(xy - r[..., None] > scene.lower[:2]) and np.all(xy + r[..., None] < scene.upper[:2])
    assert np.all(ends[..., 2] + r < scene.upper[2])
    low = np.min(ends[..., 2] - r, axis=(1, 2))  # (T,) lowest point of the body per frame
    assert -0.02 < low.min() < 0.0  # CMU's floor, as for walk, run and jump: the body touches it
    for (lo, hi) in scene.boxes:  # clutter is kept off the path: no body part reaches a box or a pillar
        gap = np.maximum(np.maximum(lo[:2] - xy, xy - hi[:2]), 0.0)
        assert np.all((np.linalg.norm(gap, axis=-1) > r) | (ends[..., 2] - r > hi[2]))
    for x, y, radius in scene.pillars:
        assert np.all(np.linalg.norm(xy - [x, y], axis=-1) > radius + r)
    world = forward_kinematics(skeleton, motion)
    joints = np.asarray(world.translation())
    if name == "scoop":  # the trunk bends past horizontal; a wrist reaches the floor and goes above the neck
        up = joints[:, skeleton.index("head")] - joints[:, skeleton.index("torso")]
        assert np.degrees(np.arccos(np.min(up[:, 2] / np.linalg.norm(up, axis=1)))) > 90.0
        wrists = joints[:, [skeleton.index("left_hand"), skeleton.index("right_hand")], 2]
        assert wrists.min() < 0.1 and np.any(wrists.max(axis=1) > joints[:, skeleton.index("head"), 2] + 0.3)
    else:  # a leap with both feet off the floor, and the heading sweeps more than a full turn
        assert low.max() > 0.2
        forward = np.asarray(world.rotation().as_matrix())[:, 0, :2, 0]  # the pelvis's x axis, horizontal part
        assert np.ptp(np.degrees(np.unwrap(np.arctan2(forward[:, 1], forward[:, 0])))) > 400.0


def test_an_excerpt_of_an_added_trial_is_the_same_motion_on_the_same_skeleton(added_trial):
    """The BVH trial's hinges are fitted over the whole trial, so an excerpt has the whole trial's skeleton."""
    name, skeleton, motion = added_trial
    part_skeleton, part = load_body_motion(name, fps=60.0, seconds=0.5, start_seconds=2.0)
    np.testing.assert_array_equal(np.asarray(part_skeleton.offsets), np.asarray(skeleton.offsets))
    np.testing.assert_array_equal(np.asarray(part_skeleton.hinge_axes), np.asarray(skeleton.hinge_axes))
    np.testing.assert_allclose(np.asarray(part.root_position), np.asarray(motion.root_position)[120:150], atol=1e-12)
    np.testing.assert_allclose(np.asarray(part.rotations), np.asarray(motion.rotations)[120:150], atol=1e-12)


def test_every_trial_rests_in_a_t_pose_and_turning_the_arms_up_moves_no_joint(added_trial):
    """The rig mounts arm cameras on the arm's upper side at rest and the range-of-motion trial starts at rest, so
    the studio's subjects rest in a T-pose: the hop's BVH rests with hanging arms and is turned up, with the same
    joint positions over the motion; the ASF trials already rest in a T-pose and are left exactly as they were."""
    from bcmocap.sim.motions import ARM_T_POSE_TOLERANCE_DEG, arms_in_t_pose

    name, skeleton, motion = added_trial
    rest = np.asarray(forward_kinematics(skeleton, skeleton.rest_motion()).translation())
    for side, sign in (("left", 1.0), ("right", -1.0)):
        shoulder, hand = rest[skeleton.index(f"{side}_upper_arm")], rest[skeleton.index(f"{side}_hand")]
        along = (hand - shoulder) / np.linalg.norm(hand - shoulder)
        assert abs(along[2]) < np.sin(np.radians(ARM_T_POSE_TOLERANCE_DEG)) and sign * along[0] > 0.9
    walk, walk_motion = load_body_motion("walk", fps=60.0, seconds=0.05)
    same_skeleton, same_motion = arms_in_t_pose(walk, walk_motion)
    assert same_skeleton is walk and same_motion is walk_motion
    hanging = np.array(skeleton.offsets)  # the same body with the arms hanging: every joint where it was
    for side in ("left", "right"):
        for segment in ("forearm", "hand"):
            j = skeleton.index(f"{side}_{segment}")
            hanging[j] = [0.0, 0.0, -np.linalg.norm(hanging[j])]
    down = Skeleton(skeleton.names, skeleton.parents, hanging, skeleton.joint_types, skeleton.hinge_axes)
    turned, again = arms_in_t_pose(down, motion[:30])
    assert not np.allclose(np.asarray(turned.offsets), hanging)
    np.testing.assert_allclose(np.asarray(forward_kinematics(turned, again).translation()),
                               np.asarray(forward_kinematics(down, motion[:30]).translation()), atol=1e-12)
    np.testing.assert_allclose(np.asarray(turned.project_rotations(again.rotations)), np.asarray(again.rotations),
                               atol=1e-12)
    # Each segment's world frame is the old one, turned by one fixed rotation for the arm's segments (its rest
    # turned sideways: the cameras on the hand move with it) and by none elsewhere.
    before = np.asarray(world_rotations(down, motion[:30]))  # (T, J, 4)
    after = np.asarray(world_rotations(turned, again))
    offset = np.asarray((SO3(before).inverse() @ SO3(after)).as_matrix())  # (T, J, 3, 3)
    np.testing.assert_allclose(offset, np.broadcast_to(offset[:1], offset.shape), atol=1e-9)
    arms = [skeleton.index(f"{side}_{segment}") for side in ("left", "right") for segment in ("upper_arm", "forearm", "hand")]
    others = [j for j in range(len(skeleton.names)) if j not in arms]
    np.testing.assert_allclose(offset[0, others], np.broadcast_to(np.eye(3), (len(others), 3, 3)), atol=1e-9)
    assert all(np.degrees(np.arccos(np.clip((np.trace(offset[0, j]) - 1) / 2, -1, 1))) > 45 for j in arms)
    rest = np.asarray(forward_kinematics(turned, turned.rest_motion()).translation())
    for side, sign in (("left", 1.0), ("right", -1.0)):  # and the turned body rests in a T-pose
        along = rest[turned.index(f"{side}_hand")] - rest[turned.index(f"{side}_upper_arm")]
        assert sign * along[0] / np.linalg.norm(along) > 0.99


def test_added_trials_are_bundled_with_their_terms_and_accepted_by_simulate(tmp_path, capsys):
    from conftest import one_line_error

    from bcmocap.cli import main
    from bcmocap.io.bvh import read_bvh
    from bcmocap.sim.motions import cmu_trial_path

    readme = (cmu_trial_path("walk")[0].parent / "README.md").read_text()
    for name in ADDED_TRIALS:
        paths = cmu_trial_path(name)
        assert all(p.is_file() and f"`{p.name}`" in readme for p in paths) and CMU_TRIALS[name][2]
        # "--motion NAME" is taken: the command stops at a bad option given after it, naming that option only.
        assert main(["simulate", str(tmp_path / name), "--motion", name, "--vignetting", "2"]) == 2
        assert "--motion" not in one_line_error(capsys, "simulate", "--vignetting")
    (bvh,) = cmu_trial_path("hop")
    assert (bvh.parent / "bvh11_LICENSE.txt").is_file() and "bvh11_LICENSE.txt" in readme
    data = read_bvh(bvh, length_unit_m=0.0254 / 0.45)
    assert data.motion.num_frames == 1006 and data.frame_time_s == pytest.approx(1 / 120, abs=1e-6)
