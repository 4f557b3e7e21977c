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

__all__ = [
    "NULL_RATIO",
    "JointSolution",
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
    """

    groups: tuple[int, int]
    markers: np.ndarray
    positions: np.ndarray
    distances: np.ndarray
    cost: float
    rms_m: float
    null_dims: int
    converged: bool


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
    determined = ev_c[:, 0] > 1e-4 * scale
    pinv = jnp.where(determined[:, None, None], jnp.linalg.inv(hcc + 1e-12 * scale[:, None, None] * jnp.eye(3)), 0.0)
    schur = jnp.diag(hdd) - jnp.einsum("fki,fij,flj->kl", hcd, pinv, hcd)
    schur = schur * valid[:, None] * valid[None, :]
    return rms, schur, determined


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


def solve_joints(
    trajectories: MarkerTrajectories,
    groups: np.ndarray,
    pairs: Sequence[tuple[int, int]],
    *,
    alpha: float | Sequence[float],
    frames: np.ndarray | None = None,
    max_iterations: int = 400,
) -> list[JointSolution]:
    """Solve the joint between each pair of marker groups, all pairs at once (``vmap``).

    Args:
        trajectories: marker positions ``(F, M, 3)``.
        groups: ``(M,)`` group of each marker.
        pairs: the ``(a, b)`` group pairs.
        alpha: distance penalty weight, or a decreasing sequence of weights solved one after the other,
            each starting from the previous solution (so a large first weight places the joint along any
            direction the motion leaves free, and a tiny last one removes its bias elsewhere).
        frames: frames to use (None: all).
        max_iterations: Levenberg–Marquardt iterations at most.

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
    width = max(len(members[a]) + len(members[b]) for a, b in pairs)
    points, seen, valid, index = _pair_arrays(positions, members, pairs, width)
    n_a = np.array([len(members[a]) for a, _ in pairs])
    c0, d0 = _initial_guess(points, seen, valid, n_a)
    solve = jax.vmap(partial(_solve_pair, max_iterations=max_iterations), in_axes=(0, 0, 0, 0, 0, None))
    points, seen, valid = jnp.asarray(points), jnp.asarray(seen), jnp.asarray(valid)
    c, d = jnp.asarray(c0), jnp.asarray(d0)
    for a in np.atleast_1d(np.asarray(alpha, dtype=np.float64)):
        c, d, cost, done = solve(points, seen, valid, c, d, float(a))
    rms, schur, determined = jax.vmap(_diagnostics)(c, d, points, seen, valid)
    null = _free_directions(schur, valid)
    c, d, cost, done = (np.asarray(x) for x in (c, d, cost, done))
    rms, determined = np.asarray(rms), np.asarray(determined)
    out = []
    for i, (a, b) in enumerate(pairs):
        k = len(members[a]) + len(members[b])
        pos = np.where(determined[i][:, None], c[i], np.nan)
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
            )
        )
    return out


def joint_cost_matrix(
    trajectories: MarkerTrajectories,
    groups: np.ndarray,
    *,
    alpha: float = 1e-3,
    max_frames: int = 200,
    max_iterations: int = 60,
    dof_corrected: bool = True,
) -> tuple[np.ndarray, list[JointSolution]]:
    """Joint cost ``Q_ab`` for every pair of groups, on at most ``max_frames`` evenly spaced frames.

    Pairs with fewer than three markers between them cannot fix a joint; their cost is ``inf`` (with a
    warning naming the groups).

    With ``dof_corrected`` each pair's cost is multiplied by ``K / (K − 3)`` (``K`` markers in the pair),
    the correction of a residual variance for the fitted parameters: each frame's joint position takes 3
    of its ``K`` distances, so two small groups fit a joint between them far better than the same motion
    lets two large ones (two 2-marker thigh groups of a real Plug-in Gait walk: 5.3e-5 m² against 1.1e-4
    to the 15-marker trunk, whose hips the topology then missed). ``K = 3`` fits exactly and is weighed
    as ``K − 3 = ½``. The paper's ``Q`` is ``dof_corrected=False``.

    Returns:
        ``(G, G)`` symmetric costs (diagonal ``inf``) and the per-pair solutions (uncorrected costs).
    """
    groups = np.asarray(groups)
    num = int(groups.max()) + 1
    sizes = np.bincount(groups, minlength=num)
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
    sols = solve_joints(trajectories, groups, pairs, alpha=alpha, frames=frames, max_iterations=max_iterations)
    q = np.full((num, num), np.inf)
    for s in sols:
        a, b = s.groups
        k = sizes[a] + sizes[b]
        q[a, b] = q[b, a] = s.cost * (k / max(k - 3, 0.5) if dof_corrected else 1.0)
    return q, sols


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
