"""Whole-body and per-camera slips of a trial's registrations onto a repeated pattern's copy: found from the motion
a body cannot make, and moved back (bcmocap.pipeline.slips)."""

import numpy as np
import pytest

from bcmocap.pipeline.slips import find_slips, repair_slips

FPS, METRES_PER_UNIT = 30.0, 0.46  # the solver's frame rate of the realistic walk; the reference model's scale
PERIOD = np.array([0.9, 0.98, 0.0])  # a repeated pattern's period (m): 1.33 m, as in the studio's repeated room


def walk(seed=0, frames=75, cameras=15):
    """True camera centres ``(T, C, 3)`` (m) of a body walking at 1.4 m/s with swinging limbs, and ``(T, C)``
    registrations with 15 % missing."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / FPS
    body = np.stack([1.4 * t, 0.1 * np.sin(2 * t), 0.9 + 0.02 * np.sin(12 * t)], axis=1)
    swing = 0.2 * np.sin(6 * t)[:, None, None] * rng.uniform(-1, 1, (1, cameras, 3))
    true = body[:, None] + rng.uniform(-0.5, 0.5, (cameras, 3))[None] + swing
    return true, rng.uniform(size=(frames, cameras)) > 0.15


def as_poses(centres, rng):
    poses = np.zeros((*centres.shape[:2], 7))
    poses[..., 0] = 1.0
    poses[..., 4:] = (centres + rng.normal(0.0, 0.005, centres.shape)) / METRES_PER_UNIT  # 5 mm registration noise
    return poses


def test_a_body_that_slips_onto_the_copy_and_cameras_that_slip_alone_are_moved_back():
    # As on the realistic walk in the repeated room (seed 2): from frame 51 most cameras are registered a period
    # away, one of them comes back at frame 63 and one slipped 3 frames early; three never slip.
    true, registered = walk()
    seen = true.copy()
    seen[51:, :12] += PERIOD
    seen[63:, 0] -= PERIOD
    seen[48:51, 13] += PERIOD
    poses = as_poses(seen, np.random.default_rng(1))
    off = registered & (np.linalg.norm(seen - true, axis=-1) > 0.1)
    repair = repair_slips(poses, registered, FPS, METRES_PER_UNIT)
    (slip,) = repair.slips
    assert slip.frame == 51 and np.linalg.norm(slip.jump * METRES_PER_UNIT - PERIOD) < 0.05
    np.testing.assert_array_equal(repair.moved, off)
    assert not repair.left_out.any() and np.array_equal(repair.registered, registered)
    error = np.linalg.norm(repair.world_from_camera[..., 4:] * METRES_PER_UNIT - true, axis=-1)[registered]
    assert error.max() < 0.05  # the jump's estimate (the body's own motion taken off) and the noise
    np.testing.assert_array_equal(repair.world_from_camera[..., :4], poses[..., :4])  # a copy keeps the rotation


def test_a_camera_that_no_slip_brings_back_is_left_out_and_a_body_without_slips_is_kept():
    true, registered = walk(seed=2)
    seen = true.copy()
    seen[30:40, 4] += [0.0, 0.0, 2.0]  # 2 m up for 10 frames: no slip of the body explains it
    poses = as_poses(seen, np.random.default_rng(3))
    repair = repair_slips(poses, registered, FPS, METRES_PER_UNIT)
    assert not repair.slips and not repair.moved.any()
    np.testing.assert_array_equal(repair.left_out[:, 4], registered[:, 4] & (np.arange(75) >= 30) & (np.arange(75) < 40))
    assert repair.left_out.sum() == repair.left_out[:, 4].sum()
    np.testing.assert_array_equal(repair.world_from_camera, poses)  # left out, not moved
    clean = repair_slips(as_poses(true, np.random.default_rng(4)), registered, FPS, METRES_PER_UNIT)
    assert not clean.slips and not clean.changed.any()
    # a sprint at 9 m/s is not a slip; a body jumping 1.33 m in one frame is
    fast = true + np.arange(75)[:, None, None] / FPS * np.array([9.0, 0.0, 0.0])
    assert not find_slips(as_poses(fast, np.random.default_rng(5)), registered, FPS, METRES_PER_UNIT)
    with pytest.raises(ValueError, match=r"find_slips: expected poses \(T, C, 7\) and registered \(T, C\), got "
                                         r"\(75, 15, 7\) and \(75, 14\)"):
        find_slips(as_poses(true, np.random.default_rng(6)), registered[:, 1:], FPS, METRES_PER_UNIT)


def test_a_slip_across_an_unregistered_frame_and_a_camera_seen_mostly_after_it():
    # Frame 50 registers no camera: the slip is found between frames 49 and 51. Camera 14 never slips and registers
    # in 11 frames before the slip and 24 after: its frames after the slip, moved back with the body's, are moved
    # forth again, not its right frames before the slip onto them.
    true, registered = walk(seed=4)
    registered[50] = False
    registered[:40, 14] = False
    seen = true.copy()
    seen[51:, :12] += PERIOD
    poses = as_poses(seen, np.random.default_rng(5))
    repair = repair_slips(poses, registered, FPS, METRES_PER_UNIT)
    (slip,) = repair.slips
    assert slip.frame == 51 and np.linalg.norm(slip.jump * METRES_PER_UNIT - PERIOD) < 0.05
    off = registered & (np.linalg.norm(seen - true, axis=-1) > 0.1)
    np.testing.assert_array_equal(repair.moved, off)
    error = np.linalg.norm(repair.world_from_camera[..., 4:] * METRES_PER_UNIT - true, axis=-1)[repair.registered]
    assert error.max() < 0.05 and not repair.left_out.any()


def test_a_body_moving_near_the_limit_has_no_slip_and_no_nan():
    true, registered = walk(seed=6)
    for speed in (11.0, 11.5, 12.5):  # m/s, at and past the 12 m/s limit (plus 5 cm of noise a frame)
        fast = true + np.arange(75)[:, None, None] / FPS * np.array([speed, 0.0, 0.0])
        repair = repair_slips(as_poses(fast, np.random.default_rng(7)), registered, FPS, METRES_PER_UNIT)
        assert np.isfinite(repair.world_from_camera[repair.registered]).all(), speed
        assert not repair.slips and not repair.changed.any(), speed
