"""Marker segmentation (Kirk et al. §3.1): which markers move together as one rigid segment.

Markers on one rigid body keep their mutual distances, so the standard deviation over time of the
distance between two markers, ``A_ij``, is (near) zero within a segment and larger across a joint. ``A`` is
computed over a jittered uniform sampling of frames (every half second, ± a few thirtieths of a second)
and the markers are split into ``n`` groups by spectral clustering of the affinity
``exp(−A² / 2σ²)``; ``n`` is given, or chosen at the largest eigengap. As in the paper's RANSAC-like
variant, several samplings are clustered and the clustering with the smallest normalised within-group
cost ``Σ_groups Σ_{i<j in group} A_ij / |group|`` is kept; here every candidate is scored on the same
matrix, the element-wise median of ``A`` over the samplings, which a sporadic jump in one sampling does not
move.

Gaps (not in the paper, whose data had "only occasional gaps"): real occlusion hides a marker for long
stretches exactly when its limb moves (behind the body in a crouch or a roll). ``A_ij`` uses only the
frames where both markers are seen, and is trusted only if those frames show the motion around the pair:
a pair seen together only while the joint between them is still keeps its distance and would look rigid.
For every pair the *coverage* (:func:`pair_statistics`) compares how much the distances from ``i`` and
from ``j`` to the markers around them vary over the frames where ``i`` and ``j`` are seen together with
how much they vary over all the frames. A pair seen together in fewer than ``min_common`` sampled frames,
or with coverage below ``min_coverage``, is *unknown*: neither rigid nor not — it has no affinity and no
say in the within-group cost or in the rigidity check (``distance_std`` holds NaN there). A known pair's
affinity is weighed by its coverage. A marker with no rigid partner the spectral embedding can see (its
strongest link in the normalised affinity under :data:`WEAK_LINK`) would be placed there at random, lumped
with unrelated markers; instead it joins the group of its most rigid known partner if the two are within
the rigidity tolerance, becomes a segment of its own if enough of its pairs are known (it is simply not
rigid with anything it is seen with), and is otherwise left out (group ``-1``: the caller drops it and
says so).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from .preprocess import MarkerTrajectories
from .spectral import eigengap, spectral_clustering

#: A marker whose strongest link in the normalised affinity ``W_ij / √(d_i d_j)`` is below this has no rigid
#: partner the spectral embedding can see (real files: 0–0.007 for lone shoulder and finger markers of an
#: HDM05 trial, 0.02 for a loose pelvis marker, 0.06 and up for markers with a partner).
WEAK_LINK = 0.05

__all__ = [
    "WEAK_LINK",
    "PairStatistics",
    "Segmentation",
    "distance_std",
    "jittered_samples",
    "least_rigid",
    "pair_statistics",
    "segment_markers",
    "within_group_cost",
]


@dataclasses.dataclass(frozen=True)
class Segmentation:
    """Markers grouped into rigid segments.

    Attributes:
        groups: ``(M,)`` group index of each marker, in ``[0, num_groups)``; ``-1`` for a marker left out
            (too few pairs known to place it).
        num_groups: number of groups.
        cost: normalised within-group cost of the kept clustering (m).
        distance_std: ``(M, M)`` median over samplings of the std of pairwise distances (m; NaN for
            unknown pairs: never or rarely seen together, or only while still).
        scale_m: σ of the affinity.
        eigenvalues: eigenvalues of the normalised affinity, descending.
        chosen_by: "given" or "eigengap".
        candidate_costs: cost of the clustering from each sampling.
        coverage: ``(M, M)`` share of the motion around each pair that its frames seen together show.
        known: ``(M, M)`` pairs whose distance statistics are trusted.
    """

    groups: np.ndarray
    num_groups: int
    cost: float
    distance_std: np.ndarray
    scale_m: float
    eigenvalues: np.ndarray
    chosen_by: str
    candidate_costs: tuple[float, ...]
    coverage: np.ndarray | None = None
    known: np.ndarray | None = None

    def members(self, group: int) -> np.ndarray:
        """Indices of the markers in ``group``."""
        return np.flatnonzero(self.groups == group)

    @property
    def left_out(self) -> np.ndarray:
        """Indices of the markers in no group."""
        return np.flatnonzero(self.groups < 0)


def jittered_samples(
    num_frames: int,
    fps: float,
    rng: np.random.Generator,
    interval_s: float = 0.5,
    jitter_s: float = 2.0 / 30.0,
    min_samples: int = 120,
) -> np.ndarray:
    """Frame indices on a uniform grid with random jitter (sorted, unique).

    The grid step is ``interval_s`` or less, so that at least ``min_samples`` frames are drawn from a
    short capture; each grid frame moves by up to ``± jitter_s`` (at least one frame) so that periodic
    errors do not line up with the sampling.
    """
    step = max(1, min(int(round(interval_s * fps)), num_frames // max(min_samples, 1)))
    jitter = max(1, int(round(jitter_s * fps)))
    grid = np.arange(int(rng.integers(0, step)), num_frames, step)
    frames = np.clip(grid + rng.integers(-jitter, jitter + 1, size=len(grid)), 0, num_frames - 1)
    return np.unique(frames)


def _distances(p: np.ndarray) -> np.ndarray:
    """``(S, M, M)`` distances between every two markers per frame, NaN where either is not seen.

    From the Gram matrix of each frame's positions about their mean (one batched matrix product)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # frames with no marker seen
        centred = p - np.nanmean(p, axis=1, keepdims=True)
    gram = centred @ np.swapaxes(centred, 1, 2)
    sq = np.einsum("smm->sm", gram)
    return np.sqrt(np.maximum(sq[:, :, None] + sq[:, None, :] - 2.0 * gram, 0.0))


def distance_std(positions: np.ndarray, frames: np.ndarray | None = None, min_common: int = 5, *,
                 distances: np.ndarray | None = None) -> np.ndarray:
    """``(M, M)`` standard deviation of the distance between every two markers over ``frames`` (m).

    Only frames where both markers are seen count; pairs seen together fewer than ``min_common`` times
    get NaN. The diagonal is 0. ``distances``: the ``(S, M, M)`` distances at ``frames``, if already known.
    """
    if distances is None:
        distances = _distances(positions if frames is None else positions[frames])
    dist = distances  # (S, M, M), NaN where either is missing
    seen = np.isfinite(dist)
    count = seen.sum(0)
    d0 = np.where(seen, dist, 0.0)
    mean = d0.sum(0) / np.maximum(count, 1)
    var = np.where(seen, (dist - mean) ** 2, 0.0).sum(0) / np.maximum(count - 1, 1)
    out = np.sqrt(var)
    out[count < min_common] = np.nan
    np.fill_diagonal(out, 0.0)
    return out


@dataclasses.dataclass(frozen=True)
class PairStatistics:
    """What the frames where two markers are seen together say about them (see :func:`pair_statistics`).

    Attributes:
        std: ``(M, M)`` std of the distance over those frames (m; NaN if fewer than ``min_common``).
        count: ``(M, M)`` number of those frames.
        coverage: ``(M, M)`` share in ``[0, 1]`` of the motion around the pair that they show.
    """

    std: np.ndarray
    count: np.ndarray
    coverage: np.ndarray


def pair_statistics(
    positions: np.ndarray,
    frames: np.ndarray | None = None,
    *,
    min_common: int = 10,
    neighbours: int = 8,
    still_m: float = 0.005,
    distances: np.ndarray | None = None,
) -> PairStatistics:
    """Distance statistics of every pair of markers over the frames where both are seen, and their coverage.

    The coverage of pair ``(i, j)`` asks whether the frames ``C_ij`` where both are seen show the motion
    around them. The markers ``k`` around the pair are the ``neighbours`` nearest to ``i`` and to ``j`` (by
    mean distance) whose distance to ``i`` (or ``j``) varies by more than ``still_m`` (std) over all the
    frames where the two are seen: those that move relative to ``i`` (or ``j``), across the joints nearby.
    The coverage is ``Σ_k var_{C_ij}(d_ik) + var_{C_ij}(d_jk)`` over ``Σ_k var(d_ik) + var(d_jk)``, each
    variance over the frames where its two markers (and, for the first, ``i`` and ``j``) are seen: about 1
    when ``C_ij`` samples the motion like the whole capture does, near 0 when the pair is seen together
    only while the limbs around it are still. A pair with nothing moving around it has coverage 1.

    Args:
        positions: ``(F, M, 3)`` marker positions (NaN gaps).
        frames: frames to use (None: all).
        min_common: pairs seen together in fewer frames get a NaN ``std`` and coverage 0.
        neighbours: markers around each marker that the coverage looks at.
        still_m: a distance varying less than this (std) does not count as motion.
        distances: the ``(S, M, M)`` distances at ``frames``, if already known.
    """
    p = positions if frames is None else positions[frames]
    num_frames, m, _ = p.shape
    vis = np.isfinite(p[..., 0]).astype(np.float64)  # (S, M)
    dist = _distances(p) if distances is None else distances
    seen = np.isfinite(dist)
    x = np.where(seen, dist, 0.0)
    both = seen.astype(np.float64)
    count = both.sum(0)
    mean = x.sum(0) / np.maximum(count, 1)
    var = np.maximum((x * x).sum(0) / np.maximum(count, 1) - mean**2, 0.0) * count / np.maximum(count - 1, 1)
    std = np.sqrt(var)
    std[count < min_common] = np.nan
    np.fill_diagonal(std, 0.0)
    # Over the frames where i, j and k are all seen: n[j, i, k], s1, s2 of d_ik (one matrix product each).
    n3 = (vis.T @ both.reshape(num_frames, m * m)).reshape(m, m, m)
    s1 = (vis.T @ x.reshape(num_frames, m * m)).reshape(m, m, m)
    s2 = (vis.T @ (x * x).reshape(num_frames, m * m)).reshape(m, m, m)
    with np.errstate(invalid="ignore", divide="ignore"):
        var3 = np.maximum(s2 / np.maximum(n3, 1) - (s1 / np.maximum(n3, 1)) ** 2, 0.0) * n3 / np.maximum(n3 - 1, 1)
    var3 = np.where(n3 >= 2, var3, 0.0)  # var3[j, i, k]: variance of d_ik while j is seen too
    # The markers around each one: nearest by mean distance, moving relative to it.
    far = np.where(count >= min_common, mean, np.inf)
    np.fill_diagonal(far, np.inf)
    order = np.argsort(far, axis=1)[:, :neighbours]
    near = np.zeros((m, m), bool)
    near[np.arange(m)[:, None], order] = True
    near &= np.isfinite(far)
    moving = (var > still_m**2) & (count >= min_common)  # moving[i, k]
    # around[i, j, k]: k counts for pair (i, j) on i's side
    around = (near[:, None, :] | near[None, :, :]) & moving[:, None, :]
    idx = np.arange(m)
    around[idx, :, idx] = False  # k ≠ i
    around[:, idx, idx] = False  # k ≠ j
    seen_part = np.einsum("ijk,jik->ij", around, var3)  # Σ_k var of d_ik over frames with j seen
    total = np.einsum("ijk,ik->ij", around, var)
    shown = seen_part + seen_part.T
    total = total + total.T
    coverage = np.where(total > 0, np.minimum(shown / np.where(total > 0, total, 1.0), 1.0), 1.0)
    coverage[count < min_common] = 0.0
    np.fill_diagonal(coverage, 1.0)
    return PairStatistics(std, count.astype(int), coverage)


def within_group_cost(a: np.ndarray, groups: np.ndarray) -> float:
    """``Σ_g Σ_{i<j ∈ g} A_ij / |g|``; unknown pairs (NaN) count as 0; markers left out (group −1) do not count."""
    a = np.where(np.isfinite(a), a, 0.0)
    total = 0.0
    for g in np.unique(groups[groups >= 0]):
        idx = np.flatnonzero(groups == g)
        total += np.triu(a[np.ix_(idx, idx)], 1).sum() / len(idx)
    return float(total)


def least_rigid_pair(a: np.ndarray, members: np.ndarray) -> tuple[float, int, int]:
    """``(std, i, j)``: the pair of ``members`` (marker indices) whose distance varies most, by ``A`` (m);
    ``(0, i, i)`` for a single marker or pairs never seen together."""
    block = a[np.ix_(members, members)]
    if not np.isfinite(block).any():
        return 0.0, int(members[0]), int(members[0])
    i, j = np.unravel_index(np.nanargmax(block), block.shape)
    return float(block[i, j]), int(members[i]), int(members[j])


def least_rigid(a: np.ndarray, groups: np.ndarray) -> float:
    """The largest within-group entry of ``A`` (m): how much the least rigid pair of one group varies."""
    return max(least_rigid_pair(a, np.flatnonzero(groups == g))[0] for g in np.unique(groups[groups >= 0]))


def split_named_conflicts(groups: np.ndarray, label_weights: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``groups`` with each group that holds two markers the names put on different bones (``label_weights`` below
    1) split so that none does: its markers, those with the most such pairs first, each join the part of the group
    it is most rigid with (mean distance std over ``reference``) among those holding none of its conflicts, or start
    a new part (a new group number after the last)."""
    out = groups.copy()
    following = int(groups.max()) + 1
    for g in np.unique(groups[groups >= 0]):
        members = np.flatnonzero(groups == g)
        conflict = label_weights[np.ix_(members, members)] < 1.0
        if not conflict.any():
            continue
        parts: list[list[int]] = []
        for m in members[np.argsort(-conflict.sum(1), kind="stable")]:
            fits = [p for p in parts if (label_weights[m, p] >= 1.0).all()]
            if fits:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    rigid = [np.nanmean(reference[m, p]) for p in fits]
                fits[int(np.argmin(np.nan_to_num(rigid, nan=np.inf)))].append(int(m))
            else:
                parts.append([int(m)])
        for part in parts[1:]:
            out[part] = following
            following += 1
    return out


def merge_named_singles(groups: np.ndarray, label_weights: np.ndarray, reference: np.ndarray,
                        tolerance_m: float) -> np.ndarray:
    """``groups`` with each named marker alone on its segment (one the names keep apart from some other: a row of
    ``label_weights`` below 1) moved into the group it is most rigid with (mean distance std) among those holding no
    marker the names keep apart from it (unnamed markers allow it), where it stays rigid with all of them (std at
    most ``tolerance_m``); the groups numbered again from 0 in order. A thigh's lone marker joins the thigh and knee
    markers rather than hang as a segment of its own."""
    out = groups.copy()
    named = (label_weights < 1.0).any(axis=1)
    for g in np.unique(groups[groups >= 0]):
        members = np.flatnonzero(out == g)
        if len(members) != 1 or not named[members[0]]:
            continue
        m = members[0]
        best, best_std = None, np.inf
        for h in np.unique(out[(out >= 0) & (out != g)]):
            others = np.flatnonzero(out == h)
            stds = reference[m, others]
            if (label_weights[m, others] < 1.0).any() or not np.isfinite(stds).all() or stds.max() > tolerance_m:
                continue
            if stds.mean() < best_std:
                best, best_std = h, float(stds.mean())
        if best is not None:
            out[m] = best
    kept = np.unique(out[out >= 0])
    return np.where(out >= 0, np.searchsorted(kept, out), -1)


def _affinity(a: np.ndarray, scale: float, weight: np.ndarray | None = None) -> np.ndarray:
    w = np.exp(-0.5 * (np.nan_to_num(a, nan=np.inf) / scale) ** 2)
    if weight is not None:
        w = w * weight
    np.fill_diagonal(w, 0.0)
    return w


def _auto_scale(a: np.ndarray) -> float:
    """σ from the data: twice the median, over markers, of the std to their most rigid partner (≥ 1 mm)."""
    off = np.where(np.eye(len(a), dtype=bool), np.nan, a)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        nearest = np.nanmin(off, axis=1)
    nearest = nearest[np.isfinite(nearest)]
    return float(max(2.0 * np.median(nearest), 1e-3)) if len(nearest) else 1e-2


def _lone_markers(reference: np.ndarray, known: np.ndarray, w: np.ndarray, label_weights: np.ndarray | None,
                  rigid_tolerance_m: float | None, min_known: int) -> tuple[np.ndarray, ...]:
    """Markers the spectral embedding cannot place, and where they go.

    Args:
        reference: ``(M, M)`` distance std (m); known: ``(M, M)`` pairs seen together long enough;
        w: ``(M, M)`` affinity; the others as in :func:`segment_markers`.

    Returns:
        ``rest`` (markers clustered), ``partner`` ``(M,)`` (each marker's most rigid partner in ``rest``),
        ``attach`` (lone markers joining their partner's group) and ``single`` (lone markers that are segments
        of their own); the lone markers in neither are left out.
    """
    m = len(reference)
    root_degree = np.sqrt(np.maximum(w.sum(1), 1e-300))
    alone = (w / root_degree[:, None] / root_degree[None, :]).max(1) < WEAK_LINK
    rest = np.flatnonzero(~alone)
    if len(rest) == 0:
        raise ValueError("segment_markers: no marker has a rigid partner it is seen with long enough")
    partner_std = np.where(known[:, rest], reference[:, rest], np.inf)
    ranked = partner_std if label_weights is None else partner_std / label_weights[:, rest]
    partner = rest[np.argmin(ranked, axis=1)]
    best_std = partner_std[np.arange(m), np.searchsorted(rest, partner)]
    tolerance = np.inf if rigid_tolerance_m is None else rigid_tolerance_m
    attach = np.flatnonzero(alone & np.isfinite(best_std) & (best_std <= tolerance))
    single = np.flatnonzero(alone & ~np.isin(np.arange(m), attach) & (known.sum(1) - 1 >= min_known))
    return rest, partner, attach, single


def _refine_by_names(labels: np.ndarray, label_weights: np.ndarray, reference: np.ndarray,
                     rigid_tolerance_m: float | None) -> tuple[np.ndarray, str]:
    """Split groups the names put on two bones, then move lone named markers to their bone's segment.

    Returns the new ``(M,)`` labels and a note for ``chosen_by`` (empty when nothing changed).
    """
    note = ""
    split = split_named_conflicts(labels, label_weights, reference)
    if split.max() > labels.max():
        note += f"; {split.max() - labels.max()} split where the markers' names put them on two bones"
    merged = merge_named_singles(split, label_weights, reference, 2.0 * (rigid_tolerance_m or 0.015))
    if merged.max() < split.max():
        note += f"; {split.max() - merged.max()} lone named marker(s) moved to the segment of their bone"
    return merged, note


def segment_markers(
    trajectories: MarkerTrajectories,
    num_groups: int | None = None,
    *,
    num_samplings: int = 8,
    interval_s: float = 0.5,
    jitter_s: float = 2.0 / 30.0,
    min_samples: int = 120,
    scale_m: float | None = None,
    max_groups: int = 20,
    rigid_tolerance_m: float | None = None,
    min_common: int = 10,
    min_coverage: float = 0.3,
    min_known: int = 3,
    coverage_frames: int = 600,
    label_weights: np.ndarray | None = None,
    seed: int = 0,
) -> Segmentation:
    """Group markers into rigid segments (§3.1), gaps handled as in the module docstring.

    Args:
        trajectories: preprocessed marker trajectories ``(F, M, 3)``.
        num_groups: number of segments, or None to choose it at the largest eigengap (2 … ``max_groups``).
        num_samplings: jittered frame samplings clustered; the best clustering is kept.
        interval_s, jitter_s, min_samples: the sampling (see :func:`jittered_samples`).
        scale_m: σ of the affinity ``exp(−A²/2σ²)`` (m); None picks it from the data.
        rigid_tolerance_m: with the eigengap, raise the count one at a time (up to ``max_groups``)
            while a group has two markers whose distance varies more than this (std): such a group spans a joint.
            A group holding two markers the names put on different bones (``label_weights`` below 1) is then split
            (:func:`split_named_conflicts`). The eigengap alone merges whole limbs on short real trials (a CMU file:
            10 groups, one of them a whole arm whose markers vary by 53 mm; 15 rigid ones).
        min_common: a pair seen together in fewer of the frames the statistics use is unknown.
        min_coverage: a pair whose frames together show less of the motion around it is unknown.
        min_known: a marker with no rigid partner is a segment of its own with at least this many known
            pairs, and left out with fewer.
        coverage_frames: evenly spaced frames (at most) for the pairs' counts and coverage.
        label_weights: ``(M, M)`` multipliers of the affinities from the markers' names
            (:func:`~bcmocap.markers.label_hints.marker_label_weights`; None: none); a lone marker's partner is
            chosen by its distance std divided by them.
        seed: random seed of the samplings and k-means.

    Raises:
        ValueError: fewer markers than groups, or fewer than two markers.
    """
    m = trajectories.num_markers
    if num_groups is not None and not 1 <= num_groups <= m:
        raise ValueError(
            f"segment_markers: cannot split {m} markers into {num_groups} groups (fewer markers than groups): "
            f"{list(trajectories.labels)}"
        )
    if m < 2:
        raise ValueError(f"segment_markers: at least two markers are needed, got {list(trajectories.labels)}")
    rng = np.random.default_rng(seed)
    samplings = [jittered_samples(trajectories.num_frames, trajectories.fps, rng, interval_s, jitter_s, min_samples)
                 for _ in range(max(1, num_samplings))]
    union = np.unique(np.concatenate(samplings))
    dist = _distances(trajectories.positions[union])  # every sampled frame's distances, once
    pooled = np.arange(len(union))
    if len(pooled) > coverage_frames:
        pooled = np.unique(np.linspace(0, len(pooled) - 1, coverage_frames).round().astype(int))
    stats = pair_statistics(trajectories.positions, union[pooled], min_common=min_common, distances=dist[pooled])
    known = (stats.count >= min_common) & (stats.coverage >= min_coverage)
    np.fill_diagonal(known, True)
    if not known[~np.eye(m, dtype=bool)].any():
        raise ValueError("segment_markers: no two markers are seen together long enough to compare them")
    stds = [np.where(known, distance_std(trajectories.positions, min_common=2, distances=dist[np.searchsorted(union, s)]), np.nan)
            for s in samplings]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        reference = np.where(known, np.nanmedian(np.stack(stds), axis=0), np.nan)
    np.fill_diagonal(reference, 0.0)
    scale = float(scale_m) if scale_m is not None else _auto_scale(reference)
    weight = np.where(known, stats.coverage, 0.0)
    if label_weights is not None:
        weight = weight * label_weights
    # Markers with no rigid partner the spectral embedding can see: in the normalised affinity
    # W_ij / √(d_i d_j) their strongest link is weak (their partners belong to tighter groups; markers only
    # loosely rigid with each other but with nothing else still link strongly), and the embedding would
    # place them at random. Each joins the group of its most rigid partner among the others if it is rigid
    # enough with it (``rigid_tolerance_m``), else it is a segment of its own, or left out with too few
    # pairs known.
    rest, partner, attach, single = _lone_markers(reference, known, _affinity(reference, scale, weight), label_weights,
                                                  rigid_tolerance_m, min_known)
    fixed = len(single)
    sub = np.ix_(rest, rest)
    r = len(rest)
    if num_groups is not None:
        n_rest = num_groups - fixed
        if not 1 <= n_rest <= r:
            raise ValueError(f"segment_markers: {num_groups} groups asked, but {fixed} markers are segments of their own "
                             f"({[trajectories.labels[k] for k in single]}) and {r} markers are left for the other "
                             f"{n_rest}")
    eig_n, eigenvalues = eigengap(_affinity(reference[sub], scale, weight[sub]), min(max_groups - fixed, r - 1) if r > 2 else 1,
                                  min_groups=2 if r > 2 else 1)
    chosen_by = "given" if num_groups is not None else "eigengap"
    n = n_rest if num_groups is not None else eig_n

    def full(labels: np.ndarray) -> np.ndarray:
        out = np.full(m, -1)
        out[rest] = labels
        out[attach] = out[partner[attach]]
        out[single] = labels.max() + 1 + np.arange(fixed)
        return out

    def best_clustering(n: int) -> tuple[np.ndarray, list[float]]:
        candidates, costs = [], []
        for a in stds:
            filled = np.where(np.isfinite(a), a, reference)
            labels = spectral_clustering(_affinity(filled[sub], scale, weight[sub]), n, rng)
            candidates.append(labels)
            costs.append(within_group_cost(reference, full(labels)))
        return candidates[int(np.argmin(costs))], costs

    labels, costs = best_clustering(n)
    if num_groups is None and rigid_tolerance_m is not None:
        limit = min(max_groups - fixed, r - 1)
        while n < limit and least_rigid(reference, full(labels)) > rigid_tolerance_m:  # attached markers count
            n += 1
            labels, costs = best_clustering(n)
        if n > eig_n:
            chosen_by = f"eigengap {eig_n + fixed}, raised for rigid groups (tolerance {rigid_tolerance_m * 1000:.0f} mm)"
    labels = full(labels)
    cost = min(costs)
    if num_groups is None and label_weights is not None:
        named, note = _refine_by_names(labels, label_weights, reference, rigid_tolerance_m)
        chosen_by += note
        if (named != labels).any():
            n += int(named.max() - labels.max())
            labels, cost = named, within_group_cost(reference, named)
    return Segmentation(
        groups=labels,
        num_groups=n + fixed,
        cost=cost,
        distance_std=reference,
        scale_m=scale,
        eigenvalues=eigenvalues,
        chosen_by=chosen_by,
        candidate_costs=tuple(costs),
        coverage=stats.coverage,
        known=known,
    )
