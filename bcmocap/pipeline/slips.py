"""Whole-body slips of a trial's registrations: every camera jumping at once by a repeated pattern's period.

In a room of repeated tiles the frontend can carry a trial's registrations onto a copy of the pattern: from one
frame on, the cameras are registered a tile's period away from where they were (the studio's realistic walk in the
repeated room, seed 2: most of its cameras 1.3 m off from frame 51 of 75 on, a few from earlier, some back before the
end), consistently with one another, so no check between the cameras of a frame sees it. Between two consecutive frames the body cannot move
that far: :func:`find_slips` finds the frame pairs where cameras registered in both jumped further than a body
moves (``max_speed_m_s``), and :func:`undo_slips` moves each stretch between slips back by the jumps that separate it
from the stretch with the most registrations (each jump: the median step of the cameras that jumped, less the
body's motion over the pairs on either side). Cameras do not all slip at the same frame, and some come back earlier:
:func:`repair_slips` then follows each camera's own step, less the body's, moves a frame that jumps faster than a
limb by the difference between two stretches' places that joins it back, and leaves out those that none does.

Poses are ``world_from_camera`` wxyz_xyz in any frame whose unit is ``metres_per_unit`` metres (the reference
model's, with the world stage's scale).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["Slip", "SlipRepair", "find_slips", "repair_slips", "undo_slips"]


@dataclasses.dataclass(frozen=True)
class Slip:
    """Between ``frame`` and the frame before it that :func:`find_slips` paired it with (the previous one, or a few
    back over frames too few cameras registered) the registered cameras jumped by ``jump`` ``(3,)`` (the poses' units;
    the body's own motion taken off): the median over the ``cameras`` cameras registered in both frames that jumped
    (those that slipped earlier do not)."""

    frame: int
    jump: np.ndarray
    cameras: int


def _verdict_pairs(registered: np.ndarray, min_cameras: int, max_gap: int) -> list[tuple[int, int, np.ndarray]]:
    """``(t, u, cameras)``: each frame ``t`` with the next frame ``u`` (at most ``max_gap`` later) where at least
    ``min_cameras`` cameras are registered in both, and those cameras ``(C,)`` bool (a sparse frame is stepped over)."""
    pairs = []
    for t in range(len(registered) - 1):
        for u in range(t + 1, min(t + max_gap, len(registered) - 1) + 1):
            both = registered[t] & registered[u]
            if both.sum() >= min_cameras:
                pairs.append((t, u, both))
                break
    return pairs


def find_slips(world_from_camera: np.ndarray, registered: np.ndarray, fps: float, metres_per_unit: float, *,
               max_speed_m_s: float = 12.0, noise_m: float = 0.05, min_cameras: int = 3, max_gap: int = 5) -> list[Slip]:
    """The frame pairs where at least ``min_cameras`` cameras registered in both jumped further than the body can move.

    Each frame is paired with the next one (at most ``max_gap`` frames on) where ``min_cameras`` cameras are registered
    in both. The body's motion over a pair is the median step of its cameras where that fits ``max_speed_m_s`` (plus
    ``noise_m``) over the time between them, else the mean of the nearest such pairs on either side; the cameras whose
    step, less that motion, exceeds the limit jumped.

    Args:
        world_from_camera: ``(T, C, 7)`` registered poses (only registered rows are read).
        registered: ``(T, C)`` bool. fps: the frames' rate (Hz).
        metres_per_unit: metres per unit of the poses' positions.
        max_speed_m_s: fastest the body moves (a sprinter's peak is about 12 m/s; the limbs' cameras, which swing
            faster, are outvoted by the median); noise_m: registration noise allowed on top (m).
        min_cameras: fewer cameras registered in both frames (or jumping) give no verdict.
        max_gap: frames looked ahead for a frame to pair with.

    Returns:
        The slips in frame order (``frame``: the pair's later frame); ``jump`` is the median step of the cameras that
        jumped less the body's motion, in the poses' units.
    """
    world_from_camera = np.asarray(world_from_camera, np.float64)
    registered = np.asarray(registered, bool)
    if world_from_camera.ndim != 3 or world_from_camera.shape[-1] != 7 or registered.shape != world_from_camera.shape[:2]:
        raise ValueError(f"find_slips: expected poses (T, C, 7) and registered (T, C), got {world_from_camera.shape} "
                         f"and {registered.shape}")
    if not (fps > 0 and metres_per_unit > 0):
        raise ValueError(f"find_slips: fps and metres_per_unit must be > 0, got {fps} and {metres_per_unit}")
    positions = world_from_camera[..., 4:]
    pairs = _verdict_pairs(registered, min_cameras, max_gap)
    limit = lambda gap: (max_speed_m_s * gap / fps + noise_m) / metres_per_unit  # noqa: E731
    steps = [positions[u, both] - positions[t, both] for t, u, both in pairs]
    medians = np.array([np.median(step, axis=0) for step in steps]).reshape(-1, 3)
    gaps = np.array([u - t for t, u, _ in pairs])
    fast = np.linalg.norm(medians, axis=1) > np.array([limit(g) for g in gaps])
    rate = np.where(fast[:, None], np.nan, medians / np.maximum(gaps, 1)[:, None])  # the body's motion per frame
    slips = []
    for k in np.flatnonzero(fast):
        t, u, both = pairs[k]
        around = [rate[m] for m in (_nearest(rate, k, -1), _nearest(rate, k, 1)) if m is not None]
        motion = (np.mean(around, axis=0) if around else np.zeros(3)) * gaps[k]
        jumped = np.linalg.norm(steps[k] - motion, axis=1) > limit(gaps[k])  # some cameras may have slipped before
        if jumped.sum() < min_cameras:
            continue
        jump = np.median(steps[k][jumped], axis=0) - motion
        if np.linalg.norm(jump) > limit(gaps[k]):
            slips.append(Slip(int(u), jump, int(jumped.sum())))
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
    if any(a >= b for a, b in zip(bounds[:-1], bounds[1:])):
        raise ValueError(f"undo_slips: slip frames {[s.frame for s in slips]} are not increasing within (0, "
                         f"{len(registered)})")
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
                 max_speed_m_s: float = 12.0, max_limb_speed_m_s: float = 15.0, noise_m: float = 0.05,
                 min_cameras: int = 3, max_gap: int = 5) -> SlipRepair:
    """The body's slips undone (:func:`find_slips` with ``max_speed_m_s``, ``noise_m``, ``min_cameras``, ``max_gap``;
    :func:`undo_slips`), then each camera's own slips.

    A camera's step between two of its registered frames, less the body's (the median step of the other cameras
    registered in both, at least ``min_cameras``, as the body's slips left them), is at most what a limb moves
    (``max_limb_speed_m_s`` times the time between them, plus ``noise_m``). The camera's registered frames are cut
    where a step is more, and where a slip of the body lies between two of them. From the piece with the most frames in the stretch the body's slips left in place (the
    longest, where none is), each frame outwards is kept where its step from the last kept frame fits, else moved by
    the difference between two stretches' places (the body's jumps between them, either sign) that makes it fit (of
    those, the one that joins it best where a slip of the body lies between them, else the nearest the last kept
    frame's move), else left out; a frame that goes on from a left-out one within a limb's step takes no move of zero,
    however long the gap behind it. A frame too few other cameras share with the
    last kept one takes the last kept frame's move."""
    registered = np.asarray(registered, bool)
    given = np.asarray(world_from_camera, np.float64)
    slips = find_slips(given, registered, fps, metres_per_unit, max_speed_m_s=max_speed_m_s, noise_m=noise_m,
                       min_cameras=min_cameras, max_gap=max_gap)
    poses, undone = undo_slips(given, registered, slips)
    # a camera left on one stretch's copy while the body moved to another's: the differences of the stretches' places
    places = np.concatenate([np.zeros((1, 3)), np.cumsum([slip.jump for slip in slips], axis=0).reshape(-1, 3)])
    candidates = np.unique(np.round((places[:, None] - places[None]).reshape(-1, 3), 12), axis=0)
    step_limit = (max_limb_speed_m_s / fps + noise_m) / metres_per_unit
    body = poses[..., 4:].copy()  # the other cameras' places, as the body's slips left them (no order dependence)
    positions = poses[..., 4:]

    def own_step(c: int, a: int, b: int) -> np.ndarray | None:
        """Camera ``c``'s step from frame ``a`` to ``b`` less the body's (None: too few other cameras in both)."""
        both = registered[a] & registered[b]
        both[c] = False
        if both.sum() < min_cameras:
            return None
        return positions[b, c] - positions[a, c] - np.median(body[b, both] - body[a, both], axis=0)

    left_out = np.zeros_like(registered)
    slip_frames = [slip.frame for slip in slips]
    for c in range(registered.shape[1]):
        frames = np.flatnonzero(registered[:, c])
        if len(frames) < 2:
            continue
        steps = [own_step(c, a, b) for a, b in zip(frames[:-1], frames[1:])]
        cuts = [i + 1 for i, (step, a, b) in enumerate(zip(steps, frames[:-1], frames[1:]))  # and at the body's slips
                if step is not None and np.linalg.norm(step) > step_limit * (b - a)
                or any(a < frame <= b for frame in slip_frames)]
        pieces = np.split(np.arange(len(frames)), cuts)
        anchor = max(pieces, key=lambda piece: (int(np.sum(~undone[frames[piece]])), len(piece)))
        for start, order in ((frames[anchor[-1]], frames[anchor[-1] + 1:]), (frames[anchor[0]], frames[:anchor[0]][::-1])):
            # outwards from the longest piece, each frame from the last kept; a frame that goes on from a left-out
            # one within a limb's step is on the same copy, however far the last kept frame lies behind
            last, previous, shift = int(start), None, np.zeros(3)
            for f in map(int, order):
                step = own_step(c, last, f)
                if step is None:
                    positions[f, c] += shift
                    continue
                fits = np.linalg.norm(step + candidates, axis=1) <= step_limit * abs(f - last)
                if previous is not None:
                    on = own_step(c, previous, f)
                    if on is not None and np.linalg.norm(on) <= step_limit * abs(f - previous):
                        fits &= np.any(candidates != 0.0, axis=1)
                if not fits.any():
                    left_out[f, c], previous = True, f
                    continue
                # of the moves that fit: across a slip of the body, the one that joins the frame best (a camera that
                # did not slip with the body was moved with it); elsewhere the nearest the last kept frame's (a camera
                # stays on its copy)
                if any(min(f, last) < frame <= max(f, last) for frame in slip_frames):
                    shift = candidates[fits][np.argmin(np.linalg.norm(step + candidates[fits], axis=1))]
                else:
                    shift = candidates[fits][np.argmin(np.linalg.norm(candidates[fits] - shift, axis=1))]
                positions[f, c] += shift
                last, previous = f, None
    repaired = registered & ~left_out
    moved = repaired & (np.linalg.norm(np.where(registered[..., None], poses[..., 4:] - given[..., 4:], 0.0), axis=-1)
                        > 1e-9 * step_limit)
    poses = np.where(left_out[..., None], given, poses)
    return SlipRepair(poses, repaired, moved, left_out, slips)
