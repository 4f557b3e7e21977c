"""Joints and topology (Kirk et al. §3.2): where two marker groups connect, and which groups connect.

A rotational joint between two segments keeps a constant distance to every marker of both. For a pair of
groups ``a, b`` with markers ``m`` the joint cost is

    Q_ab = min_{c_f, d_m}  1/K Σ_m [ 1/|m| Σ_f v_fm (‖c_f − p_fm‖ − d_m)² + α d_m² ]

with ``K = |b_a| + |b_b|``, ``|m|`` the frames where marker ``m`` is seen (``v_fm``), ``c_f`` the joint
position at frame ``f`` and ``d_m`` its distance to marker ``m`` (at the optimum, the mean distance, so
the first term is the paper's variance of the marker–joint distance). The small distance penalty keeps
the joint of two unconnected groups from escaping to infinity; it is squared here (the paper adds
``α·d̄``) so that the problem stays a least-squares problem.

The minimisation is a Levenberg–Marquardt solve (:func:`bcmocap.solver.levenberg_marquardt`) over
``3F + K`` unknowns: the normal equations are block-arrow shaped (one 3×3 block per frame, coupled only
through the ``K`` distances, the solver's static variables), so the frames are eliminated (Schur
complement) and each step costs ``O(F K²)``. Every pair of groups is solved at once
(``vmap``) on a subsample of frames; the minimum spanning tree of ``Q`` is the topology; the chosen joints
are then re-solved on all frames in two stages: a larger penalty first (which places the joint along any
axis the motion leaves free: a hinge exercised about one axis only, where the variance is flat), then a
penalty 100 times smaller, from there. The paper drops the penalty in this pass; with it at zero, noise
tilts a hinge's flat axis and slid elbows and knees by 2–15 cm in our simulations, while 1e-4 biases a
joint the motion determines by about a millimetre (the paper notes the term "can improve results" on
motions that do not exercise every degree of freedom). ``alpha=(…, 0.0)`` gives the paper's variant.
The distances are constants, so the final pass solves them on a subsample of frames
(``max_solve_frames``) and then places the joint in every frame for those distances (a ``3 × 3`` solve
per frame, where four of the pair's markers are seen: three fit a point twice over, mirrored).

Gaps (real occlusion hides markers for long stretches, as the paper's data did not): only the frames that
say something about a pair's joint count (:func:`informative_frames`: a marker of each group, four of the
pair), each marker's variance over the frames it is seen in as in the paper; and a pair seen together only
while it barely moves would look jointed (every point keeps its distances when nothing moves), so the
share of the two groups' relative motion those frames show (*coverage*) decides whether the pair's cost
is known; unknown pairs are set apart (:data:`UNKNOWN_COST_FACTOR`) and the spanning tree takes one only
to connect groups no known pair connects (see :func:`joint_cost_matrix`).
"""

from __future__ import annotations

import dataclasses
import itertools
import warnings
from collections.abc import Sequence
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..solver.levenberg_marquardt import NormalEquations, levenberg_marquardt
from .preprocess import MarkerTrajectories

#: Eigenvalue ratio (smallest / largest of the reduced normal matrix) below which a direction of the
#: joint counts as not determined by the motion.
NULL_RATIO = 1e-3

#: A pair of groups whose informative frames show less than this share of their relative motion, or
#: that has fewer than :data:`MIN_FRAMES` of them, is unknown to the topology (:func:`joint_cost_matrix`).
MIN_COVERAGE = 0.3
MIN_FRAMES = 10

#: Factor on the joint cost of a pair of groups whose frames seen together do not show their relative
#: motion (see :func:`joint_cost_matrix`): the spanning tree uses such a pair only as a last resort.
UNKNOWN_COST_FACTOR = 1e6

__all__ = [
    "MIN_COVERAGE",
    "MIN_FRAMES",
    "NULL_RATIO",
    "UNKNOWN_COST_FACTOR",
    "JointSolution",
    "informative_frames",
    "joint_cost_matrix",
    "minimum_spanning_tree",
    "solve_joints",
]


@dataclasses.dataclass(frozen=True)
class JointSolution:
    """A solved joint between two marker groups.

    Attributes:
        groups: ``(a, b)`` group indices.
        markers: indices of the markers used (those of ``a`` then ``b``).
        positions: ``(F, 3)`` joint position per frame (m); NaN where fewer than three markers of the
            pair are seen (the joint is not determined there).
        distances: ``(K,)`` distance from the joint to each marker (m).
        cost: the joint cost ``Q`` at the optimum (m²).
        rms_m: root mean square of ``‖c_f − p_fm‖ − d_m`` over the seen samples (m).
        null_dims: number of directions in which the joint is not determined by the motion (0 for a
            joint exercised about two or more axes, 1 for a hinge-like motion, 3 for no relative motion).
        converged: the solver met its tolerance within the iteration limit.
        frames_used: frames that told the solve something about the joint (see :func:`informative_frames`).
        coverage: share of the two groups' relative motion those frames show (see :func:`joint_cost_matrix`;
            1 when not measured).
    """

    groups: tuple[int, int]
    markers: np.ndarray
    positions: np.ndarray
    distances: np.ndarray
    cost: float
    rms_m: float
    null_dims: int
    converged: bool
    frames_used: int = 0
    coverage: float = 1.0


def _safe_norm(x):
    n2 = jnp.sum(x * x, axis=-1)
    ok = n2 > 1e-24
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def joint_objective(c, d, points, seen, valid, alpha):
    """The joint cost of one pair for given joint positions ``c`` ``(F, 3)`` and distances ``d`` ``(K,)``.

    Args:
        points: ``(F, K, 3)`` marker positions (any finite value where unseen). seen: ``(F, K)`` 0/1.
        valid: ``(K,)`` 0/1, padding slots are 0. alpha: penalty weight (dimensionless).
    """
    w, beta = _weights(seen, valid, alpha)
    e = _safe_norm(c[:, None, :] - points) - d[None, :]
    return jnp.sum(w[None, :] * seen * e * e) + jnp.sum(beta * d * d)


def _weights(seen, valid, alpha):
    count = jnp.sum(seen, axis=0)  # frames each marker is seen
    k_eff = jnp.maximum(jnp.sum(valid), 1.0)
    w = valid / (jnp.maximum(count, 1.0) * k_eff)
    beta = alpha * valid / k_eff
    return w, beta


def _normal_equations(c, d, points, seen, w, beta):
    diff = c[:, None, :] - points  # (F, K, 3)
    dist = _safe_norm(diff)
    u = diff / jnp.where(dist > 0, dist, 1.0)[..., None]
    e = dist - d[None, :]
    ws = w[None, :] * seen  # (F, K)
    hcc = jnp.einsum("fk,fki,fkj->fij", ws, u, u)
    hcd = -ws[..., None] * u  # (F, K, 3): column k of the 3×K block, transposed
    hdd = jnp.sum(ws, axis=0) + beta
    gc = jnp.einsum("fk,fk,fki->fi", ws, e, u)
    gd = -jnp.sum(ws * e, axis=0) + beta * d
    cost = jnp.sum(ws * e * e) + jnp.sum(beta * d * d)
    return hcc, hcd, hdd, gc, gd, cost


def _pair_residuals(y, args):
    """Whitened residuals of one pair: ``(F, K)`` distance misfits and ``(K,)`` penalties; ``½ Σ r²`` is ``½ Q``."""
    (c, d), (points, seen, w, beta) = y, args
    e = _safe_norm(c[:, None, :] - points) - d[None, :]
    return jnp.sqrt(w[None, :] * seen) * e, jnp.sqrt(beta) * d


def _pair_system(args, valid, y):
    """The block-arrow Gauss–Newton system of one pair: a ``3 × 3`` block per frame (no bands between
    frames), bordered by the ``K`` distances, which :func:`bcmocap.solver.levenberg_marquardt` eliminates
    by a Schur complement. Padding slots get a unit diagonal and no gradient, so they stay at 0."""
    (c, d), (points, seen, w, beta) = y, args
    hcc, hcd, hdd, gc, gd, _ = _normal_equations(c, d, points, seen, w, beta)
    return NormalEquations(hcc, (), gc, jnp.swapaxes(hcd, 1, 2), jnp.diag(hdd + (1.0 - valid)), gd)


@partial(jax.jit, static_argnames=("max_iterations",))
def _solve_pair(points, seen, valid, c0, d0, alpha, max_iterations: int = 100):
    """Minimise the joint cost of one pair from ``(c0, d0)``; returns ``c``, ``d``, ``Q`` and whether it converged."""
    w, beta = _weights(seen, valid, alpha)
    args = (points, seen, w, beta)
    # Tolerances: about 10 nm on the joint and the distances, 1e-8 of the cost.
    (c, d), report = levenberg_marquardt(_pair_residuals, eqx.Partial(_pair_system, args, valid), (c0, d0), args,
                                         rtol=1e-8, atol=1e-12, max_steps=max_iterations)
    return c, d, 2.0 * report.final_cost, report.converged


@jax.jit
def _diagnostics(c, d, points, seen, valid):
    """Residual RMS, eigenvalues of the reduced normal matrix without penalty, and per-frame determinacy."""
    w, beta = _weights(seen, valid, 0.0)
    hcc, hcd, hdd, _, _, _ = _normal_equations(c, d, points, seen, w, beta)
    e = _safe_norm(c[:, None, :] - points) - d[None, :]
    rms = jnp.sqrt(jnp.sum(seen * e * e) / jnp.maximum(jnp.sum(seen), 1.0))
    ev_c = jnp.linalg.eigvalsh(hcc)  # (F, 3)
    scale = jnp.maximum(ev_c[:, -1], 1e-30)
    # three distances fit a point exactly twice over (mirrored in the markers' plane): ask for four
    determined = (ev_c[:, 0] > 1e-4 * scale) & (jnp.sum(seen, axis=1) >= jnp.minimum(4.0, jnp.sum(valid)))
    pinv = jnp.where(determined[:, None, None], jnp.linalg.inv(hcc + 1e-12 * scale[:, None, None] * jnp.eye(3)), 0.0)
    schur = jnp.diag(hdd) - jnp.einsum("fki,fij,flj->kl", hcd, pinv, hcd)
    schur = schur * valid[:, None] * valid[None, :]
    return rms, schur, determined


def _position_residuals(c, args):
    points, seen, d = args
    return jnp.sqrt(seen) * (_safe_norm(c[:, None, :] - points) - d[None, :])


def _position_system(args, c):
    """Block-diagonal system of the joint positions alone (distances held): a ``3 × 3`` block per frame."""
    points, seen, d = args
    hcc, _, _, gc, _, _ = _normal_equations(c, d, points, seen, jnp.ones_like(d), jnp.zeros_like(d))
    return NormalEquations(hcc, (), gc, jnp.zeros((*gc.shape, 0)), jnp.zeros((0, 0)), jnp.zeros(0))


@partial(jax.jit, static_argnames=("max_iterations",))
def _solve_positions(points, seen, d, c0, max_iterations: int = 30):
    """The joint position in every frame for given marker distances ``d``, from ``c0``."""
    args = (points, seen, d)
    c, _ = levenberg_marquardt(_position_residuals, eqx.Partial(_position_system, args), c0, args,
                               rtol=1e-8, atol=1e-10, max_steps=max_iterations)
    return c


def _free_directions(schur, valid) -> np.ndarray:
    """Number of directions of each pair's joint that the motion leaves (nearly) free.

    The reduced normal matrix (frames eliminated, no penalty) has eigenvalues ~ (angular spread)² for the
    directions the motion determines, relative to the largest; a direction it leaves free is held by noise
    only (~1e-4 with 1 mm noise and a 30° range). Counted below :data:`NULL_RATIO`; a diagnostic (noise
    and a biased joint can hide a hinge's free axis), used to warn about joints that are not exercised.
    """
    schur = np.asarray(schur)
    valid = np.asarray(valid) > 0
    count = np.zeros(len(schur), int)
    for i in range(len(schur)):
        idx = np.flatnonzero(valid[i])
        if len(idx):
            values = np.linalg.eigvalsh(schur[i][np.ix_(idx, idx)])
            count[i] = int(np.sum(values < NULL_RATIO * max(values[-1], 1e-30)))
    return count


def _pair_arrays(positions: np.ndarray, members: Sequence[np.ndarray], pairs, width: int):
    """Stack the markers of each pair, padded to ``width``: points (B, F, K, 3), seen (B, F, K), valid (B, K)."""
    f = positions.shape[0]
    b = len(pairs)
    points = np.zeros((b, f, width, 3))
    seen = np.zeros((b, f, width))
    valid = np.zeros((b, width))
    index = np.full((b, width), -1)
    for i, (ga, gb) in enumerate(pairs):
        idx = np.concatenate([members[ga], members[gb]])
        p = positions[:, idx]
        s = np.isfinite(p[..., 0])
        points[i, :, : len(idx)] = np.where(s[..., None], p, 0.0)
        seen[i, :, : len(idx)] = s
        valid[i, : len(idx)] = 1.0
        index[i, : len(idx)] = idx
    return points, seen, valid, index


def _initial_guess(points, seen, valid, n_a):
    """Joint at the midpoint of the two groups' centroids per frame (held over gaps), distances to match."""
    b, f, k, _ = points.shape
    side_a = (np.arange(k)[None, :] < n_a[:, None]) & (valid > 0)
    side_b = (np.arange(k)[None, :] >= n_a[:, None]) & (valid > 0)
    cents = []
    for side in (side_a, side_b):
        m = seen * side[:, None, :]
        cnt = m.sum(-1, keepdims=True)
        cent = (points * m[..., None]).sum(-2) / np.maximum(cnt, 1)
        have = cnt[..., 0] > 0
        for i in range(b):  # carry the last seen centroid over gaps (and the first one backwards)
            if not have[i].any():
                continue
            idx = np.where(have[i], np.arange(f), 0)
            idx = np.maximum.accumulate(idx)
            first = int(np.argmax(have[i]))
            idx[:first] = first
            cent[i] = cent[i, idx]
        cents.append(cent)
    c0 = 0.5 * (cents[0] + cents[1])
    dist = np.linalg.norm(c0[:, :, None, :] - points, axis=-1)
    d0 = (dist * seen).sum(1) / np.maximum(seen.sum(1), 1)
    return c0, d0


def informative_frames(seen: np.ndarray, valid: np.ndarray, n_a: np.ndarray) -> np.ndarray:
    """``(B, F)`` frames that tell something about each pair's joint: a marker of each group seen, and at least
    four of the pair's markers (three, when the pair has only three).

    A frame where only one group is seen lets the joint sit anywhere in that group's frame at no cost, and
    three markers fit it exactly: such frames would only dilute the cost of a pair in proportion to its
    gaps. (``seen`` ``(B, F, K)``, ``valid`` ``(B, K)``, ``n_a`` ``(B,)`` markers of the first group.)
    """
    k = np.arange(seen.shape[-1])
    side_a = (k[None, :] < n_a[:, None]) & (valid > 0)
    side_b = (k[None, :] >= n_a[:, None]) & (valid > 0)
    count = seen.sum(-1)
    return ((seen * side_a[:, None]).sum(-1) > 0) & ((seen * side_b[:, None]).sum(-1) > 0) & (
        count >= np.minimum(4, valid.sum(-1))[:, None])


def solve_joints(
    trajectories: MarkerTrajectories,
    groups: np.ndarray,
    pairs: Sequence[tuple[int, int]],
    *,
    alpha: float | Sequence[float],
    frames: np.ndarray | None = None,
    max_iterations: int = 400,
    max_solve_frames: int | None = None,
    place: bool = True,
) -> list[JointSolution]:
    """Solve the joint between each pair of marker groups, all pairs at once (``vmap``).

    The distances ``d`` (and the cost) come from the :func:`informative_frames` only: elsewhere the joint
    is not determined (fewer than three markers) or carries no information (one group seen), and such
    frames only slow the solver down. Then the joint is placed in every frame for those distances (a
    ``3 × 3`` solve per frame) where at least four of the pair's markers are seen (three fit it twice).

    Args:
        trajectories: marker positions ``(F, M, 3)``.
        groups: ``(M,)`` group of each marker.
        pairs: the ``(a, b)`` group pairs.
        alpha: distance penalty weight, or a decreasing sequence of weights solved one after the other,
            each starting from the previous solution (so a large first weight places the joint along any
            direction the motion leaves free, and a tiny last one removes its bias elsewhere).
        frames: frames to use (None: all).
        max_iterations: Levenberg–Marquardt iterations at most.
        max_solve_frames: solve for the distances on at most this many evenly spaced frames (they are
            constants: a subsample estimates them). None: on all frames.
        place: place the joint in every frame; False (the topology's costs): ``positions`` only holds the
            solved frames' joints, NaN elsewhere.

    Returns:
        One :class:`JointSolution` per pair; ``positions`` has one row per used frame.
    """
    groups = np.asarray(groups)
    num = int(groups.max()) + 1
    members = [np.flatnonzero(groups == g) for g in range(num)]
    positions = trajectories.positions if frames is None else trajectories.positions[np.asarray(frames)]
    pairs = [tuple(int(x) for x in p) for p in pairs]
    if not pairs:
        return []
    num_pairs, num_frames = len(pairs), positions.shape[0]
    # Shapes rounded up (pairs repeated, empty marker slots, unseen frames) so that captures of one marker
    # set share compilations: pairs to a multiple of 8, markers of a pair to 4, frames to 256, 512 or a
    # multiple of 512.
    width = -(-max(len(members[a]) + len(members[b]) for a, b in pairs) // 4) * 4
    padded = pairs + [pairs[-1]] * (-num_pairs % 8)
    bucket = 256 if num_frames <= 256 else 512 * -(-num_frames // 512)
    positions = np.concatenate([positions, np.full((bucket - num_frames, *positions.shape[1:]), np.nan)])
    points, seen, valid, index = _pair_arrays(positions, members, padded, width)
    n_a = np.array([len(members[a]) for a, _ in padded])
    useful = informative_frames(seen, valid, n_a)
    sub = np.arange(num_frames)
    if max_solve_frames is not None and num_frames > max_solve_frames:
        sub = np.unique(np.linspace(0, num_frames - 1, max_solve_frames).round().astype(int))
    c0, d0 = _initial_guess(points, seen, valid, n_a)  # (frames past the capture: held, never used)
    solve = jax.vmap(partial(_solve_pair, max_iterations=max_iterations), in_axes=(0, 0, 0, 0, 0, None))
    sub_points, sub_seen, jvalid = jnp.asarray(points[:, sub]), jnp.asarray(seen[:, sub] * useful[:, sub, None]), jnp.asarray(valid)
    c, d = jnp.asarray(c0[:, sub]), jnp.asarray(d0)
    for a in np.atleast_1d(np.asarray(alpha, dtype=np.float64)):
        c, d, cost, done = solve(sub_points, sub_seen, jvalid, c, d, float(a))
    rms, schur, _ = jax.vmap(_diagnostics)(c, d, sub_points, sub_seen, jvalid)
    null = _free_directions(schur, valid)
    c_sub = np.asarray(c)
    if place:  # every frame's joint for the distances found, from the solved frames' joints (in time) or the guess
        start = c0.copy()
        for i in range(len(pairs)):
            solved = sub[useful[i, sub]]
            if len(solved):
                start[i] = np.stack([np.interp(np.arange(start.shape[1]), solved, c_sub[i, useful[i, sub], x]) for x in range(3)], -1)
        enough = seen * (seen.sum(-1, keepdims=True) >= 3)
        all_points = jnp.asarray(points)
        c = jax.vmap(_solve_positions)(all_points, jnp.asarray(enough), d, jnp.asarray(start))
        _, _, determined = jax.vmap(_diagnostics)(c, d, all_points, jnp.asarray(seen), jvalid)
        c, determined = np.asarray(c), np.asarray(determined)
    else:
        c = np.full(points.shape[:2] + (3,), np.nan)
        c[:, sub] = c_sub
        determined = np.zeros(points.shape[:2], bool)
        determined[:, sub] = useful[:, sub]
    d, cost, done, rms = (np.asarray(x) for x in (d, cost, done, rms))
    out = []
    for i, (a, b) in enumerate(pairs):
        k = len(members[a]) + len(members[b])
        pos = np.where(determined[i, :num_frames, None], c[i, :num_frames], np.nan)
        out.append(
            JointSolution(
                groups=(a, b),
                markers=index[i, :k].copy(),
                positions=pos,
                distances=d[i, :k].copy(),
                cost=float(cost[i]),
                rms_m=float(rms[i]),
                null_dims=int(min(null[i], 3)),
                converged=bool(done[i]),
                frames_used=int(useful[i, sub].sum()),
            )
        )
    return out


def _relative_motion_coverage(positions: np.ndarray, a: np.ndarray, b: np.ndarray, useful: np.ndarray, floor_m: float) -> float:
    """Share of the variance of the distances between markers of groups ``a`` and ``b`` (over the frames where
    each two are seen) that the ``useful`` frames show, over the distances that vary by more than
    ``floor_m`` (std); 1 if none does: then there is no relative motion to miss."""
    d = np.linalg.norm(positions[:, a][:, :, None] - positions[:, b][:, None, :], axis=-1)  # (F, |a|, |b|), NaN gaps
    seen = np.isfinite(d)
    both = seen & useful[:, None, None]

    def total_variance(mask):
        n = mask.sum(0)
        x = np.where(mask, d, 0.0)
        mean = x.sum(0) / np.maximum(n, 1)
        var = np.where(mask, (d - mean) ** 2, 0.0).sum(0) / np.maximum(n - 1, 1)
        return np.where(n >= 2, var, 0.0)

    everything = total_variance(seen)
    moving = everything > floor_m**2
    if not moving.any():
        return 1.0
    return float(min(total_variance(both)[moving].sum() / everything[moving].sum(), 1.0))


def joint_cost_matrix(
    trajectories: MarkerTrajectories,
    groups: np.ndarray,
    *,
    alpha: float = 1e-3,
    max_frames: int = 200,
    max_iterations: int = 60,
    dof_corrected: bool = True,
    min_coverage: float = MIN_COVERAGE,
    min_frames: int = MIN_FRAMES,
) -> tuple[np.ndarray, list[JointSolution]]:
    """Joint cost ``Q_ab`` for every pair of groups, on at most ``max_frames`` evenly spaced frames.

    Pairs with fewer than three markers between them cannot fix a joint; their cost is ``inf`` (with a
    warning naming the groups).

    Gaps: each pair's cost counts only the frames that tell something about its joint
    (:func:`informative_frames`: a marker of each group seen, four of the pair's markers), with each
    marker's variance over the frames it is seen in, as in the paper. A pair seen together only while it
    barely moves would still look jointed (any point keeps its distances when nothing moves), so each
    pair's *coverage* is measured: the share of the variance of the distances between its two groups'
    markers, over all the frames where those are seen, that its informative frames show. A pair with
    coverage below ``min_coverage`` or fewer than ``min_frames`` informative frames is *unknown*: its cost
    is multiplied by :data:`UNKNOWN_COST_FACTOR`, so that the spanning tree takes it only if no known pair
    connects its groups (the solutions carry the coverage; a warning is the caller's).

    With ``dof_corrected`` each pair's cost is divided by the expected share of its residual left after
    fitting 3 joint coordinates per frame: ``Σ_m mean_f (n_f − 3)/n_f / K`` over the ``K`` markers and the
    frames ``f`` each is seen in (``n_f`` markers of the pair seen in frame ``f``) — ``(K − 3)/K`` without
    gaps, so the cost is multiplied by ``K / (K − 3)``, the correction of a residual variance for the
    fitted parameters: each frame's joint position takes 3 of its distances, so two small groups fit a
    joint between them far better than the same motion lets two large ones (two 2-marker thigh groups of
    a real Plug-in Gait walk: 5.3e-5 m² against 1.1e-4 to the 15-marker trunk, whose hips the topology
    then missed). ``K = 3`` fits exactly and is weighed as ``K − 3 = ½``. The paper's ``Q`` is
    ``dof_corrected=False``.

    Returns:
        ``(G, G)`` symmetric costs (diagonal ``inf``) and the per-pair solutions (uncorrected costs).
    """
    groups = np.asarray(groups)
    num = int(groups.max()) + 1
    sizes = np.bincount(groups, minlength=num)
    members = [np.flatnonzero(groups == g) for g in range(num)]
    frames = np.unique(np.linspace(0, trajectories.num_frames - 1, min(max_frames, trajectories.num_frames)).round().astype(int))
    pairs = [(a, b) for a, b in itertools.combinations(range(num), 2) if sizes[a] + sizes[b] >= 3]
    small = [(a, b) for a, b in itertools.combinations(range(num), 2) if sizes[a] + sizes[b] < 3]
    if small:
        warnings.warn(
            f"joint_cost_matrix: group pairs {small} have fewer than three markers between them; a joint "
            "cannot be placed there and they are not connected directly",
            UserWarning,
            stacklevel=2,
        )
    sols = solve_joints(trajectories, groups, pairs, alpha=alpha, frames=frames, max_iterations=max_iterations, place=False)
    positions = trajectories.positions[frames]
    q = np.full((num, num), np.inf)
    out = []
    for s in sols:
        a, b = s.groups
        k = sizes[a] + sizes[b]
        seen = np.isfinite(positions[:, s.markers, 0])
        useful = informative_frames(seen[None].astype(float), np.ones((1, k)), np.array([sizes[a]]))[0]
        if dof_corrected:
            n = np.where(useful[:, None] & seen, seen.sum(1, keepdims=True), 0)
            share = np.where(n > 0, (n - 3) / np.maximum(n, 1), 0.0).sum(0) / np.maximum((n > 0).sum(0), 1)
            left = share.sum() if k > 3 else 0.5
            factor = k / max(left, 0.5)
        else:
            factor = 1.0
        coverage = _relative_motion_coverage(positions, members[a], members[b], useful, floor_m=0.002)
        s = dataclasses.replace(s, coverage=coverage)
        known = coverage >= min_coverage and s.frames_used >= min_frames
        q[a, b] = q[b, a] = s.cost * factor * (1.0 if known else UNKNOWN_COST_FACTOR)
        out.append(s)
    return q, out


def minimum_spanning_tree(cost: np.ndarray, names: Sequence[str] | None = None) -> list[tuple[int, int]]:
    """Edges ``(a, b)`` of the minimum spanning tree of a symmetric cost matrix (Prim; ``inf`` = no edge).

    Raises:
        ValueError: the graph is not connected (names the groups that cannot be reached).
    """
    q = np.asarray(cost, dtype=np.float64)
    n = len(q)
    names = list(names) if names is not None else [f"group {k}" for k in range(n)]
    in_tree = np.zeros(n, bool)
    in_tree[0] = True
    best = q[0].copy()
    link = np.zeros(n, int)
    edges = []
    for _ in range(n - 1):
        cand = np.where(in_tree, np.inf, best)
        j = int(np.argmin(cand))
        if not np.isfinite(cand[j]):
            missing = [names[k] for k in range(n) if not in_tree[k]]
            raise ValueError(f"the marker groups cannot all be connected by joints: no finite joint cost reaches {missing}")
        edges.append((int(link[j]), j))
        in_tree[j] = True
        closer = q[j] < best
        best = np.where(closer, q[j], best)
        link = np.where(closer, j, link)
    return edges
