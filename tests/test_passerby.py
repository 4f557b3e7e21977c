"""Tests for the passer-by of the studio's room "passerby" (bcmocap.sim.passerby).

A subject running back and forth for 16 s at 30 fps in the textured room, passed by a runner (CMU's run, read once):
long enough for several passes and pauses. The capture written with a passer-by is tested in test_studio.py (slow).
"""

import numpy as np
import pytest

from bcmocap.cameras import PinholeCamera
from bcmocap.kinematics import forward_kinematics
from bcmocap.sim.motions import back_and_forth
from bcmocap.sim.passerby import _recorded, looped_gait, passerby_motion, subject_facing
from bcmocap.sim.render import Renderer
from bcmocap.sim.scene import make_textured_scene
from bcmocap.sim.studio import _AWAY, capsule_ends

FPS = 30.0


@pytest.fixture(scope="module")
def walk():
    skeleton, run = _recorded("run", FPS)  # the passer-by's own cache: the trial is parsed once
    subject = back_and_forth(run, int(16 * FPS))
    scene = make_textured_scene(np.asarray(subject.root_position)[:, :2], seed=2)
    return skeleton, subject, scene, passerby_motion(scene, skeleton, subject, FPS, motion="run")


def test_passerby_crosses_ahead_of_the_subject_and_keeps_clear(walk):
    skeleton, subject, scene, (walker, motion, present, path) = walk
    again = passerby_motion(scene, skeleton, subject, FPS, motion="run")
    np.testing.assert_array_equal(again[1].rotations, motion.rotations)  # deterministic
    np.testing.assert_array_equal(again[2], present)
    middle = subject.num_frames // 2
    body = np.asarray(forward_kinematics(skeleton, subject).translation())
    root = np.asarray(forward_kinematics(walker, motion).translation())[:, 0]
    # At the middle frame it crosses the subject's heading 2-3.5 m ahead; it paces, out of the room between passes.
    assert present[middle] and 0.3 < present.mean() < 0.95 and np.sum(np.diff(present.astype(int)) == 1) >= 1
    np.testing.assert_allclose(root[middle, :2], path.crossing, atol=0.3)
    facing = subject_facing(skeleton, body[middle: middle + 1])[0]
    assert 2.0 <= (path.crossing - body[middle, 0, :2]) @ facing <= 3.5
    # In the room it keeps clear of the subject, the walls and the clutter, and faces where it goes.
    gap = np.linalg.norm(root[present, :2] - body[present, 0, :2], axis=1)
    assert gap.min() >= 0.9 and path.subject_clearance_m == pytest.approx(gap.min())
    assert np.all(root[present, :2] > scene.lower[:2] + 0.5) and np.all(root[present, :2] < scene.upper[:2] - 0.5)
    assert not scene.inside_clutter(np.column_stack([root[present, :2], np.full(present.sum(), 0.5)]), -0.3).any()
    joints = np.asarray(forward_kinematics(walker, motion).translation())
    velocity = np.gradient(root[:, :2], axis=0)
    moving = present & np.roll(present, 1) & np.roll(present, -1)
    along = np.sum(subject_facing(walker, joints) * velocity, axis=1)
    heading = along[moving] / np.linalg.norm(velocity[moving], axis=1)
    assert heading.min() > 0.9


def test_where_clutter_blocks_every_usual_line_a_wider_search_finds_one(walk):
    """Crossings 30 m ahead are outside the room, as blocked as the usual lines were behind a crowded corner in the
    realistic room of the scoop (seed 0) and of the run (seed 1): the wider search still finds a clear line."""
    skeleton, subject, scene, _ = walk
    _, motion, present, path = passerby_motion(scene, skeleton, subject, FPS, motion="run", lead_m=(30.0,))
    body = np.asarray(forward_kinematics(skeleton, subject).translation())
    middle = subject.num_frames // 2
    facing = subject_facing(skeleton, body[middle: middle + 1])[0]
    assert 1.0 <= (path.crossing - body[middle, 0, :2]) @ facing <= 4.0 and present.any()
    root = np.asarray(motion.root_position)
    assert not scene.inside_clutter(np.column_stack([root[present, :2], np.full(present.sum(), 0.5)]), -0.3).any()


def test_looped_gait_is_seamless():
    _, run = _recorded("run", FPS)
    gait = looped_gait(run, FPS, 200)
    step = np.linalg.norm(np.diff(np.asarray(gait.root_position)[:, :2], axis=0), axis=1)
    assert step.max() < 1.3 * np.median(step)  # no jump where the loop starts again
    rotations = np.asarray(gait.rotations)
    turn = 2 * np.arccos(np.clip(np.abs(np.sum(rotations[1:] * rotations[:-1], axis=-1)), 0, 1))
    assert turn.max() < 0.6  # rad per frame at 30 fps: no joint snaps at a seam
    with pytest.raises(ValueError, match="fewer than a loop"):
        looped_gait(run[:5], FPS, 10)


def test_passerby_is_seen_ahead_when_present_and_never_when_away(walk):
    skeleton, subject, scene, (walker, motion, present, _) = walk
    middle = subject.num_frames // 2
    body = np.asarray(forward_kinematics(skeleton, subject).translation())
    facing = subject_facing(skeleton, body[middle: middle + 1])[0]
    forward = np.array([*facing, -0.2]) / np.linalg.norm([*facing, -0.2])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    rotation = np.stack([right, np.cross(forward, right), forward], axis=1)
    origin = body[middle, skeleton.index("head")] + [0.0, 0.0, 0.15]  # above the subject's own head
    renderer = Renderer(scene, PinholeCamera(48, 27, focal=(24.0, 24.0), principal_point=(23.5, 13.0)))
    ends, radii, _ = capsule_ends(walker, motion)
    depth, seen = renderer.depth(rotation, origin, ends[middle], radii)
    distance = np.linalg.norm(ends[middle, :, 0] - origin, axis=1)
    assert seen.sum() > 20 and distance.min() - 0.3 < np.median(depth[seen]) < distance.max()
    # Where it is out of the room, the studio renders its capsules under the floor: never seen.
    away = np.flatnonzero(~present)[0]
    _, seen = renderer.depth(rotation, origin, np.broadcast_to(_AWAY, ends[away].shape), radii)
    assert not seen.any()
