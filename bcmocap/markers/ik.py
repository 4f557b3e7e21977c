"""Inverse kinematics of the rigid marker skeleton (Kirk et al. §3.3, last paragraph).

Once the skeleton and each marker's offset in its segment are known, each frame's pose (root position,
root orientation, one rotation per ball joint) is the one whose markers best match the observed ones:
a Levenberg–Marquardt solve per frame, ``vmap``-ed over chunks of frames. Unseen markers
carry no weight, so the pose fills the gaps; a weak prior towards the initial pose keeps a segment with
no marker in sight at a frame where interpolation in time put it. The solver is the project's one
Levenberg–Marquardt (:func:`bcmocap.solver.levenberg_marquardt`) with a one-frame system: the Jacobian
by ``jacfwd``, ``D × D`` normal equations per frame.

The initial pose comes from per-segment rigid alignment (Kabsch) of the segment's markers and joints
(from the joint solve) where at least three are seen, interpolated in time (slerp) elsewhere.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import SO3, kabsch, quat_from_matrix
from ..kinematics.fk import forward_kinematics
from ..kinematics.ik import fill_gaps
from ..kinematics.skeleton import Motion, Skeleton
from ..solver.levenberg_marquardt import NormalEquations, levenberg_marquardt
from .rigid import RigidSkeleton

__all__ = ["IkResult", "initial_motion", "marker_model_positions", "solve_ik"]


@dataclasses.dataclass(frozen=True)
class IkResult:
    """Per-frame poses of the rigid skeleton.

    Attributes:
        motion: ``(F,)`` root position and rotations.
        marker_positions: ``(F, M, 3)`` model marker positions (m): the observed markers' fit, and the
            gaps filled.
        residual_rms_m: ``(F,)`` RMS distance between model and observed markers per frame (NaN if none seen).
        converged: ``(F,)`` the solver reported success.
    """

    motion: Motion
    marker_positions: np.ndarray
    residual_rms_m: np.ndarray
    converged: np.ndarray


def marker_model_positions(skeleton: Skeleton, motion: Motion, marker_segment, marker_offsets) -> jax.Array:
    """``(*S, M, 3)`` world positions of segment-fixed markers for a motion of batch shape ``S``."""
    poses = forward_kinematics(skeleton, motion)
    rot = poses.rotation().as_matrix()[..., jnp.asarray(marker_segment), :, :]
    trans = poses.translation()[..., jnp.asarray(marker_segment), :]
    return jnp.einsum("...mij,mj->...mi", rot, jnp.asarray(marker_offsets)) + trans


def initial_motion(rigid: RigidSkeleton, positions: np.ndarray, joint_positions: dict[tuple[int, int], np.ndarray]) -> Motion:
    """Pose per frame from per-segment Kabsch alignment, gaps filled in time.

    Args:
        rigid: the fitted skeleton.
        positions: ``(F, M, 3)`` observed markers (NaN gaps).
        joint_positions: ``(parent segment, child segment) → (F, 3)`` joint positions from the joint solve.

    Raises:
        ValueError: a segment is never seen with three points (names it).
    """
    skel = rigid.skeleton
    num_frames = positions.shape[0]
    world_q = np.zeros((num_frames, skel.num_segments, 4))
    for j in range(skel.num_segments):
        markers = np.flatnonzero(rigid.marker_segment == j)
        model = [rigid.marker_offsets[m] for m in markers]
        obs = [positions[:, m] for m in markers]
        # the segment's own joint (its origin) and its children's joints
        if skel.parents[j] >= 0:
            model.append(np.zeros(3))
            obs.append(joint_positions[(skel.parents[j], j)])
        for c in skel.children(j):
            model.append(np.asarray(skel.offsets[c]))
            obs.append(joint_positions[(j, c)])
        model = np.stack(model)
        obs = np.stack(obs, axis=1)  # (F, N, 3)
        w = np.isfinite(obs).all(-1).astype(float)
        known = w.sum(1) >= 3
        if not known.any():
            # two points fix all but the spin about their line; inverse kinematics settles the rest
            known = w.sum(1) >= 2
        if not known.any():
            raise ValueError(f"segment '{skel.names[j]}' is never seen with two markers or joints; it cannot be posed")
        r, t = kabsch(np.broadcast_to(model, obs.shape), obs, w)
        q = np.asarray(quat_from_matrix(np.where(known[:, None, None], r, np.eye(3))))
        world_q[:, j] = fill_gaps(q, known, rotations=True)
        if j == 0:
            origin = fill_gaps(t, known, rotations=False)
    local = world_q.copy()
    for j in range(1, skel.num_segments):
        p = skel.parents[j]
        local[:, j] = np.asarray((SO3(world_q[:, p]).inverse() @ SO3(world_q[:, j])).wxyz)
    return Motion(origin, local)


def _residual(delta, skeleton, start, observed, seen, segs, offsets, prior):
    """``(3M + D,)`` marker misfits (m) and the prior ``prior · δ`` at tangent ``delta`` ``(D,)`` from ``start``."""
    motion = skeleton.retract(start, delta)
    pred = marker_model_positions(skeleton, motion, segs, offsets)
    r = (pred - observed) * seen[:, None]
    return jnp.concatenate([r.reshape(-1), prior * delta])


def _frame_residual(y, frame):
    """:func:`_residual` for the solver's ``(1, D)`` variables; ``frame``: the other arguments."""
    return _residual(y[0], *frame)


def _frame_system(frame, y):
    """One frame's dense ``D × D`` Gauss–Newton system (a block-banded system of one frame, no bands)."""
    jac = jax.jacfwd(_frame_residual)(y, frame)[:, 0]  # (R, D)
    r = _frame_residual(y, frame)
    return NormalEquations.dense(jac.T @ jac, jac.T @ r)


def _lm_frame(skeleton, start, observed, seen, segs, offsets, prior, max_steps):
    """One frame's tangent by :func:`bcmocap.solver.levenberg_marquardt`; returns the pose and whether it converged."""
    frame = (skeleton, start, observed, seen, segs, offsets, prior)
    # Tolerances: 10 nm or rad·1e-8 for the pose, 1e-6 of the cost: far below marker noise.
    y, report = levenberg_marquardt(_frame_residual, eqx.Partial(_frame_system, frame), jnp.zeros((1, skeleton.num_dofs)),
                                    frame, rtol=1e-6, atol=1e-8, max_steps=max_steps)
    return skeleton.retract(start, y[0]), report.converged


@partial(jax.jit, static_argnames=("max_steps",))
def _solve_chunk(skeleton, start, observed, seen, segs, offsets, prior, max_steps: int):
    one = partial(_lm_frame, skeleton, segs=segs, offsets=offsets, prior=prior, max_steps=max_steps)
    return jax.vmap(lambda s, o, v: one(s, o, v))(start, observed, seen)


def solve_ik(
    rigid: RigidSkeleton,
    positions: np.ndarray,
    start: Motion,
    *,
    prior_weight: float = 1e-3,
    chunk: int = 256,
    max_steps: int = 30,
) -> IkResult:
    """Pose the rigid skeleton in every frame to fit the observed markers.

    Args:
        rigid: the fitted skeleton and marker offsets.
        positions: ``(F, M, 3)`` observed markers (m, NaN gaps).
        start: ``(F,)`` initial motion (e.g. :func:`initial_motion`).
        prior_weight: weight of ``‖δ‖`` (m per rad, and per m of root motion) pulling towards ``start``.
        chunk: frames solved together (one compilation per chunk size).
        max_steps: Levenberg–Marquardt steps per frame at most.
    """
    num_frames = positions.shape[0]
    seen = np.isfinite(positions).all(-1)
    observed = np.where(seen[..., None], positions, 0.0)
    # Segment names are static in a Skeleton, hence part of the compiled function's key: solve with
    # neutral names so that skeletons of the same shape share one compilation.
    skel = rigid.skeleton
    neutral = Skeleton([f"s{j}" for j in range(skel.num_segments)], skel.parents, skel.offsets, skel.joint_types, skel.hinge_axes)
    segs = jnp.asarray(rigid.marker_segment)
    offsets = jnp.asarray(rigid.marker_offsets)
    chunk = max(1, min(chunk, num_frames))
    pad = (-num_frames) % chunk
    root = np.concatenate([np.asarray(start.root_position), np.repeat(np.asarray(start.root_position)[-1:], pad, 0)])
    rots = np.concatenate([np.asarray(start.rotations), np.repeat(np.asarray(start.rotations)[-1:], pad, 0)])
    obs = np.concatenate([observed, np.zeros((pad, *observed.shape[1:]))])
    sn = np.concatenate([seen, np.zeros((pad, seen.shape[1]), bool)]).astype(float)
    out_root, out_rot, ok = [], [], []
    for a in range(0, num_frames + pad, chunk):
        m, good = _solve_chunk(
            neutral, Motion(root[a : a + chunk], rots[a : a + chunk]), jnp.asarray(obs[a : a + chunk]),
            jnp.asarray(sn[a : a + chunk]), segs, offsets, prior_weight, max_steps,
        )
        out_root.append(np.asarray(m.root_position))
        out_rot.append(np.asarray(m.rotations))
        ok.append(np.asarray(good))
    motion = Motion(np.concatenate(out_root)[:num_frames], np.concatenate(out_rot)[:num_frames])
    model = np.asarray(marker_model_positions(rigid.skeleton, motion, segs, offsets))
    err = np.where(seen, np.linalg.norm(model - np.nan_to_num(positions), axis=-1), np.nan)
    count = seen.sum(1)
    rms = np.where(count > 0, np.sqrt(np.nansum(err**2, axis=1) / np.maximum(count, 1)), np.nan)
    return IkResult(motion, model, rms, np.concatenate(ok)[:num_frames])
