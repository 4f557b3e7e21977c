"""Whole-body slips of a trial's registrations: every camera jumping at once by a repeated pattern's period.

In a room of repeated tiles the frontend can carry a trial's registrations onto a copy of the pattern: from one
frame on, every camera is registered a tile's period away from where it was (the studio's realistic walk in the
repeated room, seed 2: all 15 registered cameras 1.33 m off over the last 24 of 75 frames), consistently with one
another, so no check between the cameras of a frame sees it. Between two consecutive frames the body cannot move
that far: :func:`find_slips` finds the frame pairs whose cameras, in the median, moved further than a body moves
(``max_speed_m_s``), and :func:`undo_slips` moves each stretch between slips back by the jumps that separate it from
the stretch with the most registrations (each jump: the cameras' median displacement at the slip less the body's
median displacement over the frame pairs on either side). Cameras do not all slip at the same frame, and some come
back earlier: :func:`repair_slips` then moves each camera-frame that lies further from the frame's median camera than
any camera sits on a body by the slips' jumps that bring it back, and leaves out those no jump brings back.

Poses are ``world_from_camera`` wxyz_xyz in any frame whose unit is ``metres_per_unit`` metres (the reference
model's, with the world stage's scale).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["Slip", "SlipRepair", "find_slips", "repair_slips", "undo_slips"]


@dataclasses.dataclass(frozen=True)
class Slip:
    """Between frames ``frame - 1`` and ``frame`` the registered cameras jumped by ``jump`` ``(3,)`` (the poses'
    units; the body's own motion taken off): the median over the ``cameras`` cameras registered in both frames that
    jumped (those that slipped earlier do not)."""

    frame: int
    jump: np.ndarray
    cameras: int


def _displacements(positions: np.ndarray, registered: np.ndarray, min_cameras: int) -> np.ndarray:
    """``(T - 1, 3)`` the median displacement of the cameras registered in frames ``t`` and ``t + 1`` (NaN where
    fewer than ``min_cameras`` are)."""
    both = registered[:-1] & registered[1:]
    step = positions[1:] - positions[:-1]
    out = np.full((len(step), 3), np.nan)
    for t in np.flatnonzero(both.sum(axis=1) >= min_cameras):
        out[t] = np.median(step[t, both[t]], axis=0)
    return out


def find_slips(world_from_camera: np.ndarray, registered: np.ndarray, fps: float, metres_per_unit: float, *,
               max_speed_m_s: float = 10.0, noise_m: float = 0.05, min_cameras: int = 3) -> list[Slip]:
    """The frame pairs where the cameras registered in both moved, in the median, further than the body can.

    Args:
        world_from_camera: ``(T, C, 7)`` registered poses (only registered rows are read).
        registered: ``(T, C)`` bool. fps: the frames' rate (Hz).
        metres_per_unit: metres per unit of the poses' positions.
        max_speed_m_s: fastest the body moves (a sprinter's peak is about 12 m/s; the limbs' cameras, which swing
            faster, are outvoted by the median); noise_m: registration noise allowed on top (m).
        min_cameras: fewer cameras registered in both frames give no verdict.

    Returns:
        The slips in frame order; ``jump`` is the median displacement of the cameras that jumped less the body's
        motion (the mean median displacement of the nearest verdict-giving pairs on either side that are not slips
        themselves), in the poses' units.
    """
    world_from_camera = np.asarray(world_from_camera, np.float64)
    registered = np.asarray(registered, bool)
    if world_from_camera.ndim != 3 or world_from_camera.shape[-1] != 7 or registered.shape != world_from_camera.shape[:2]:
        raise ValueError(f"find_slips: expected poses (T, C, 7) and registered (T, C), got {world_from_camera.shape} "
                         f"and {registered.shape}")
    if not (fps > 0 and metres_per_unit > 0):
        raise ValueError(f"find_slips: fps and metres_per_unit must be > 0, got {fps} and {metres_per_unit}")
    if len(registered) < 2:
        return []
    moved = _displacements(world_from_camera[..., 4:], registered, min_cameras)
    limit = (max_speed_m_s / fps + noise_m) / metres_per_unit
    slipped = np.linalg.norm(moved, axis=1) > limit  # NaN compares False
    body = np.where(slipped[:, None], np.nan, moved)
    slips = []
    positions = world_from_camera[..., 4:]
    for t in np.flatnonzero(slipped):
        around = [body[k] for k in (_nearest(body, t, -1), _nearest(body, t, 1)) if k is not None]
        motion = np.mean(around, axis=0) if around else np.zeros(3)
        both = registered[t] & registered[t + 1]
        step = positions[t + 1, both] - positions[t, both]
        jumped = np.linalg.norm(step - motion, axis=1) > limit  # the cameras that slipped here (some did earlier)
        slips.append(Slip(int(t + 1), np.median(step[jumped], axis=0) - motion, int(jumped.sum())))
    return slips


def _nearest(values: np.ndarray, t: int, direction: int) -> int | None:
    """The nearest row before (``-1``) or after (``1``) ``t`` that is finite, or None."""
    k = t + direction
    while 0 <= k < len(values):
        if np.isfinite(values[k]).all():
            return k
        k += direction
    return None


def undo_slips(world_from_camera: np.ndarray, registered: np.ndarray, slips: list[Slip]) -> tuple[np.ndarray, np.ndarray]:
    """Each stretch of frames between slips moved back onto the stretch with the most registered camera-frames.

    Returns:
        ``(T, C, 7)`` the poses with the moved stretches' positions shifted (rotations kept: a pattern's copy keeps
        the orientation), and ``(T,)`` bool, the frames moved.
    """
    world_from_camera = np.array(world_from_camera, np.float64)
    registered = np.asarray(registered, bool)
    bounds = [0, *(s.frame for s in slips), len(registered)]
    counts = [int(registered[a:b].sum()) for a, b in zip(bounds[:-1], bounds[1:])]
    anchor = int(np.argmax(counts))
    offsets = np.zeros((len(counts), 3))  # each stretch's position relative to the anchor's
    for k in range(anchor + 1, len(counts)):
        offsets[k] = offsets[k - 1] + slips[k - 1].jump
    for k in range(anchor - 1, -1, -1):
        offsets[k] = offsets[k + 1] - slips[k].jump
    moved = np.zeros(len(registered), bool)
    for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
        if k != anchor:
            world_from_camera[a:b, :, 4:] -= offsets[k]
            moved[a:b] = True
    return world_from_camera, moved


@dataclasses.dataclass(frozen=True)
class SlipRepair:
    """What :func:`repair_slips` did: ``world_from_camera`` ``(T, C, 7)`` and ``registered`` ``(T, C)`` repaired;
    ``moved`` ``(T, C)`` the registered camera-frames it shifted, ``left_out`` ``(T, C)`` those it unregistered (their
    measurements were made on the pattern's copy: a solve should not read them); ``slips`` the body's slips."""

    world_from_camera: np.ndarray
    registered: np.ndarray
    moved: np.ndarray
    left_out: np.ndarray
    slips: list[Slip]

    @property
    def changed(self) -> np.ndarray:
        """``(T, C)`` the camera-frames moved or left out."""
        return self.moved | self.left_out


def repair_slips(world_from_camera: np.ndarray, registered: np.ndarray, fps: float, metres_per_unit: float, *,
                 max_limb_speed_m_s: float = 15.0, noise_m: float = 0.05, min_cameras: int = 3,
                 **limits) -> SlipRepair:
    """The body's slips undone (:func:`find_slips`, :func:`undo_slips`), then each camera's own slips.

    A camera's step between two of its registered frames, less the body's (the median step of the cameras registered
    in both, at least ``min_cameras``), is at most what a limb moves (``max_limb_speed_m_s`` times the time between
    them, plus ``noise_m``). The camera's registered frames are cut where a step is more; from the longest piece
    outwards each frame is kept where its step from the last kept frame fits, else moved by the difference between
    two stretches' places (the sum of the body's jumps between them, either sign) that makes it fit (of those that do,
    the one nearest the last kept frame's move);
    else left out, as are the frames that go on from a left-out one within a limb's step.
    ``limits``: :func:`find_slips`'s."""
    registered = np.asarray(registered, bool)
    given = np.asarray(world_from_camera, np.float64)
    slips = find_slips(given, registered, fps, metres_per_unit, min_cameras=min_cameras, **limits)
    poses, _ = undo_slips(given, registered, slips)
    # a camera left on one stretch's copy while the body moved to another's: the differences of the stretches' places
    places = np.concatenate([np.zeros((1, 3)), np.cumsum([slip.jump for slip in slips], axis=0).reshape(-1, 3)])
    candidates = np.unique(np.round((places[:, None] - places[None]).reshape(-1, 3), 12), axis=0)
    step_limit = (max_limb_speed_m_s / fps + noise_m) / metres_per_unit
    positions = poses[..., 4:]

    def own_step(c: int, a: int, b: int) -> np.ndarray | None:
        """Camera ``c``'s step from frame ``a`` to ``b`` less the body's (None: too few cameras in both)."""
        both = registered[a] & registered[b]
        both[c] = False
        if both.sum() < min_cameras:
            return None
        return positions[b, c] - positions[a, c] - np.median(positions[b, both] - positions[a, both], axis=0)

    left_out = np.zeros_like(registered)
    for c in range(registered.shape[1]):
        frames = np.flatnonzero(registered[:, c])
        if len(frames) < 2:
            continue
        steps = [own_step(c, a, b) for a, b in zip(frames[:-1], frames[1:])]
        cuts = [i + 1 for i, (step, gap) in enumerate(zip(steps, np.diff(frames)))
                if step is not None and np.linalg.norm(step) > step_limit * gap]
        pieces = np.split(np.arange(len(frames)), cuts)
        anchor = pieces[int(np.argmax([len(p) for p in pieces]))]
        for start, order in ((frames[anchor[-1]], frames[anchor[-1] + 1:]), (frames[anchor[0]], frames[:anchor[0]][::-1])):
            # outwards from the longest piece, each frame from the last kept; a frame that goes on from a left-out
            # one within a limb's step is on the same copy, however far the last kept frame lies behind
            last, previous, shift = int(start), None, np.zeros(3)
            for f in map(int, order):
                step = own_step(c, last, f)
                if step is None:
                    last, previous = f, None
                    continue
                fits = np.linalg.norm(step + candidates, axis=1) <= step_limit * abs(f - last)
                if previous is not None:
                    on = own_step(c, previous, f)
                    if on is not None and np.linalg.norm(on) <= step_limit * abs(f - previous):
                        fits &= np.any(candidates != 0.0, axis=1)
                if not fits.any():
                    left_out[f, c], previous = True, f
                    continue
                # of the moves that fit, the one nearest the last kept frame's (a camera stays on its copy)
                shift = candidates[fits][np.argmin(np.linalg.norm(candidates[fits] - shift, axis=1))]
                positions[f, c] += shift
                last, previous = f, None
    repaired = registered & ~left_out
    moved = repaired & (np.linalg.norm(np.where(registered[..., None], poses[..., 4:] - given[..., 4:], 0.0), axis=-1)
                        > 1e-9 * step_limit)
    poses = np.where(left_out[..., None], given, poses)
    return SlipRepair(poses, repaired, moved, left_out, slips)
