"""A passer-by: a second person who walks through the capture (the studio's room "passerby").

The passer-by is a bundled CMU trial (a walk or a run, :data:`~bcmocap.sim.motions.CMU_TRIALS`) whose gait is looped
seamlessly (:func:`looped_gait`), so that it covers any distance in a straight line. It paces a line across the
room: the line passes ``lead_m`` ahead of the subject at the middle frame of the trial, crossing the subject's
heading, and the passer-by reaches that point then (shifted in time and space). A pass runs from near one wall to
near the other, or to the first box or pillar in the way; between passes the passer-by is out of the room (behind a
door) for ``pause_s`` and comes back the other way. Of the candidate lines (angles to the subject's heading, leads),
the first that stays clear of the clutter from wall to wall and never comes closer to the subject than
``subject_clearance_m`` is taken.

World frame Z up, metres; frames are trial frames at the trial's rate.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ..kinematics.fk import forward_kinematics
from ..kinematics.skeleton import Motion, Skeleton
from .motions import load_body_motion
from .scene import TexturedScene

__all__ = ["PASSERBY_PALETTE", "PasserbyPath", "looped_gait", "passerby_motion", "subject_facing"]

#: Skin, trousers and shirt of the passer-by (RGB in [0, 1]; the subject wears blue and grey).
PASSERBY_PALETTE = ((0.58, 0.42, 0.33), (0.55, 0.48, 0.36), (0.72, 0.22, 0.18))

_WALL_MARGIN_M = 0.6  # a pass ends this far from a wall
_CLUTTER_MARGIN_M = 0.5  # the line keeps this far from boxes and pillars
_ANGLES_DEG = (90.0, -90.0, 75.0, -75.0, 105.0, -105.0, 60.0, -60.0, 120.0, -120.0)
_LEADS_M = (2.5, 3.0, 2.0, 3.5)
# Tried only where every line above is blocked by clutter.
_MORE_ANGLES_DEG = (45.0, -45.0, 135.0, -135.0, 30.0, -30.0, 150.0, -150.0)
_MORE_LEADS_M = (1.5, 4.0, 2.5, 3.0, 2.0, 3.5, 1.0)


@dataclasses.dataclass(frozen=True)
class PasserbyPath:
    """The line a passer-by paces.

    Attributes:
        start, end: ``(2,)`` ends of a pass (m); passes alternate start → end and end → start.
        crossing: ``(2,)`` where the first pass is at the middle frame (m), ``lead_m`` ahead of the subject.
        wall_to_wall: True where the line runs from wall to wall (else it ends at a box or pillar).
        subject_clearance_m: the least distance between the two pelvises over the trial (m, horizontal).
    """

    start: np.ndarray
    end: np.ndarray
    crossing: np.ndarray
    wall_to_wall: bool
    subject_clearance_m: float


@functools.lru_cache(maxsize=4)
def _recorded(name: str, fps: float) -> tuple[Skeleton, Motion]:
    return load_body_motion(name, fps=fps)


def _quat_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 2.0 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0))


def looped_gait(motion: Motion, fps: float, num_frames: int, min_loop_s: float = 0.5) -> Motion:
    """``num_frames`` frames of a straight walk or run made from a recording of it.

    The two frames ``a < b`` at least ``min_loop_s`` apart whose poses differ least (joint rotations and pelvis
    height) bound a loop: frames ``a .. b - 1`` are played over and over, each time moved on horizontally by the
    ground the loop covers (``root[b] - root[a]``). Frame 0 is frame ``a``.
    """
    rot = np.asarray(motion.rotations, np.float64)
    root = np.asarray(motion.root_position, np.float64)
    n = len(rot)
    gap = max(1, int(round(min_loop_s * fps)))
    if n <= gap:
        raise ValueError(f"looped_gait: the motion has {n} frames, fewer than a loop of {min_loop_s} s at {fps} fps")
    cost = _quat_angle(rot[:, None], rot[None, :]).sum(axis=-1) + 10.0 * np.abs(root[:, None, 2] - root[None, :, 2])
    cost[np.arange(n)[:, None] + gap > np.arange(n)[None, :]] = np.inf  # b >= a + gap
    a, b = np.unravel_index(np.argmin(cost), cost.shape)
    k = np.arange(num_frames)
    period = b - a
    step = np.array([*(root[b, :2] - root[a, :2]), 0.0])
    source = a + k % period
    return Motion(root[source] + (k // period)[:, None] * step, rot[source])


def subject_facing(skeleton: Skeleton, joints: np.ndarray) -> np.ndarray:
    """``(T, 2)`` unit horizontal direction the subject faces (from its hips: left hip to right hip turned by 90°),
    from its joint positions ``(T, J, 3)``; +x where the hips are level with each other's vertical."""
    left = joints[:, skeleton.index("left_thigh"), :2] - joints[:, skeleton.index("right_thigh"), :2]
    facing = np.stack([left[:, 1], -left[:, 0]], axis=1)  # left × up
    norm = np.linalg.norm(facing, axis=1, keepdims=True)
    return np.where(norm > 1e-6, facing / np.maximum(norm, 1e-12), np.array([1.0, 0.0]))


def _clutter_distance(scene: TexturedScene, points: np.ndarray) -> np.ndarray:
    """``(N,)`` horizontal distance (m) from points ``(N, 2)`` to the nearest box or pillar (inf without clutter)."""
    out = np.full(len(points), np.inf)
    for lo, hi in np.asarray(scene.boxes, float):
        gap = np.maximum(np.maximum(lo[:2] - points, points - hi[:2]), 0.0)
        out = np.minimum(out, np.linalg.norm(gap, axis=1))
    for cx, cy, r in np.asarray(scene.pillars, float):
        out = np.minimum(out, np.hypot(points[:, 0] - cx, points[:, 1] - cy) - r)
    return out


def _reach(scene: TexturedScene, origin: np.ndarray, direction: np.ndarray) -> tuple[float, float]:
    """``(to_wall, to_clutter)``: how far (m) a walk from ``origin`` along ``direction`` may go before the wall
    margin, and before it first comes within the clutter margin (or ``to_wall`` if it never does)."""
    lo, hi = np.asarray(scene.lower[:2], float) + _WALL_MARGIN_M, np.asarray(scene.upper[:2], float) - _WALL_MARGIN_M
    with np.errstate(divide="ignore"):
        exits = np.where(direction > 0, (hi - origin) / direction,
                         np.where(direction < 0, (lo - origin) / direction, np.inf))
    to_wall = max(float(exits.min()), 0.0)
    s = np.arange(0.0, to_wall, 0.05)
    blocked = np.flatnonzero(_clutter_distance(scene, origin + s[:, None] * direction) < _CLUTTER_MARGIN_M)
    return to_wall, float(s[blocked[0]]) if len(blocked) else to_wall


def _paced(gait: Motion, start: np.ndarray, end: np.ndarray, crossing: np.ndarray, middle: int, num_frames: int,
           pause_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(root (T, 3), rotations (T, J, 4), present (T,))``: passes between ``start`` and ``end``, the first one
    (start → end) at ``crossing`` at frame ``middle``; absent frames hold the gait's first pose at ``start``."""
    root = np.asarray(gait.root_position)
    rot = np.asarray(gait.rotations)
    walked = root[:, :2] - root[0, :2]
    heading = walked[-1] / max(np.linalg.norm(walked[-1]), 1e-9)
    progress = walked @ heading
    length = float(np.linalg.norm(end - start))
    pass_frames = int(np.argmax(progress >= length)) + 1 if progress[-1] >= length else len(progress)
    first = middle - int(np.argmin(np.abs(progress - np.linalg.norm(crossing - start))))
    out_root = np.tile(np.array([*start, root[0, 2]]), (num_frames, 1))
    out_rot = np.broadcast_to(rot[0], (num_frames, *rot.shape[1:])).copy()
    present = np.zeros(num_frames, bool)
    period = pass_frames + pause_frames
    for j in range((0 - first) // period - 1, (num_frames - first) // period + 2):
        origin, target = (start, end) if j % 2 == 0 else (end, start)
        direction = (target - origin) / max(length, 1e-9)
        yaw = np.arctan2(direction[1], direction[0]) - np.arctan2(heading[1], heading[0])
        c, s = np.cos(yaw), np.sin(yaw)
        t = first + j * period + np.arange(pass_frames)
        k = np.arange(pass_frames)[(t >= 0) & (t < num_frames)]
        t = t[(t >= 0) & (t < num_frames)]
        xy = walked[k] @ np.array([[c, s], [-s, c]])  # rotated by yaw
        out_root[t] = np.column_stack([origin + xy, root[k, 2]])
        w, x, y, z = np.moveaxis(rot[k, 0], -1, 0)
        cw, sz = np.cos(yaw / 2), np.sin(yaw / 2)
        out_rot[t] = rot[k]
        out_rot[t, 0] = np.stack([cw * w - sz * z, cw * x - sz * y, cw * y + sz * x, cw * z + sz * w], axis=-1)
        present[t] = True
    return out_root, out_rot, present


def passerby_motion(scene: TexturedScene, skeleton: Skeleton, subject: Motion, fps: float, *, motion: str = "run",
                    lead_m: tuple[float, ...] = _LEADS_M, pause_s: float = 2.0,
                    subject_clearance_m: float = 0.9) -> tuple[Skeleton, Motion, np.ndarray, PasserbyPath]:
    """A passer-by pacing across the room in front of the subject (module docstring).

    Args:
        scene: the room (walls, boxes and pillars to keep clear of).
        skeleton, subject: the subject's skeleton and its motion over the trial (``T`` frames at ``fps`` Hz).
        motion: the passer-by's bundled CMU trial ("walk" or "run").
        lead_m: distances ahead of the subject at which the line may cross its heading, tried in turn (m).
        pause_s: time out of the room between two passes (s).
        subject_clearance_m: the least horizontal distance between the pelvises a line must keep (m).

    Returns:
        ``(skeleton, motion, present, path)``: the passer-by's skeleton, its motion over the ``T`` frames (where
        ``present`` ``(T,)`` is False it is out of the room: its pose there is a placeholder) and the line.
    """
    walker_skeleton, recorded = _recorded(motion, float(fps))
    num_frames = subject.num_frames
    middle = num_frames // 2
    joints = np.asarray(forward_kinematics(skeleton, subject).translation())
    subject_xy = joints[:, 0, :2]
    facing = subject_facing(skeleton, joints[middle: middle + 1])[0]
    room = np.asarray(scene.upper[:2], float) - np.asarray(scene.lower[:2], float)
    gait = looped_gait(recorded, fps, 1 + int(np.ceil(2.0 * np.linalg.norm(room) / _speed(recorded))))
    best, best_score = None, None
    # the lines of the module docstring first; where clutter blocks them all (a subject that stays in one place
    # before a crowded corner), wider angles, nearer and farther crossings and 1 m of clear way on each side
    for leads, angles, reach_m in ((lead_m, _ANGLES_DEG, 1.5), (_MORE_LEADS_M, _ANGLES_DEG + _MORE_ANGLES_DEG, 1.0)):
        for lead in leads:
            crossing = subject_xy[middle] + lead * facing
            for angle in np.radians(angles):
                c, s = np.cos(angle), np.sin(angle)
                direction = np.array([c * facing[0] - s * facing[1], s * facing[0] + c * facing[1]])
                ahead_wall, ahead = _reach(scene, crossing, direction)
                behind_wall, behind = _reach(scene, crossing, -direction)
                if min(ahead, behind) < reach_m:
                    continue
                start, end = crossing - behind * direction, crossing + ahead * direction
                root, rot, present = _paced(gait, start, end, crossing, middle, num_frames, int(round(pause_s * fps)))
                gap = np.linalg.norm(root[:, :2] - subject_xy, axis=1)
                clearance = float(gap[present].min()) if present.any() else np.inf
                wall_to_wall = ahead == ahead_wall and behind == behind_wall
                score = (clearance >= subject_clearance_m, wall_to_wall, min(clearance, subject_clearance_m),
                         min(ahead, behind))
                if best_score is None or score > best_score:
                    best_score = score
                    best = (Motion(root, rot), present, PasserbyPath(start, end, crossing, wall_to_wall, clearance))
                if score[:2] == (True, True):
                    break
            if best_score is not None and best_score[:2] == (True, True):
                break
        if best is not None:
            break
    if best is None:
        raise ValueError("passerby_motion: no line across the room clear of the clutter for 1 m on each side of a "
                         "crossing point 1 to 4 m ahead of the subject")
    return (walker_skeleton, *best)


def _speed(motion: Motion) -> float:
    """Mean horizontal speed of a recorded motion (m per frame, at least 1 mm)."""
    root = np.asarray(motion.root_position)
    return max(float(np.linalg.norm(root[-1, :2] - root[0, :2])) / max(len(root) - 1, 1), 1e-3)
