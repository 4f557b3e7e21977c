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
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from .preprocess import MarkerTrajectories
from .spectral import eigengap, spectral_clustering

__all__ = ["Segmentation", "distance_std", "jittered_samples", "least_rigid", "segment_markers", "within_group_cost"]


@dataclasses.dataclass(frozen=True)
class Segmentation:
    """Markers grouped into rigid segments.

    Attributes:
        groups: ``(M,)`` group index of each marker, in ``[0, num_groups)``.
        num_groups: number of groups.
        cost: normalised within-group cost of the kept clustering (m).
        distance_std: ``(M, M)`` median over samplings of the std of pairwise distances (m; NaN if never
            seen together).
        scale_m: σ of the affinity.
        eigenvalues: eigenvalues of the normalised affinity, descending.
        chosen_by: "given" or "eigengap".
        candidate_costs: cost of the clustering from each sampling.
    """

    groups: np.ndarray
    num_groups: int
    cost: float
    distance_std: np.ndarray
    scale_m: float
    eigenvalues: np.ndarray
    chosen_by: str
    candidate_costs: tuple[float, ...]

    def members(self, group: int) -> np.ndarray:
        """Indices of the markers in ``group``."""
        return np.flatnonzero(self.groups == group)


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


def distance_std(positions: np.ndarray, frames: np.ndarray | None = None, min_common: int = 5) -> np.ndarray:
    """``(M, M)`` standard deviation of the distance between every two markers over ``frames`` (m).

    Only frames where both markers are seen count; pairs seen together fewer than ``min_common`` times
    get NaN. The diagonal is 0.
    """
    p = positions if frames is None else positions[frames]
    diff = p[:, :, None, :] - p[:, None, :, :]
    dist = np.sqrt(np.sum(diff * diff, axis=-1))  # (S, M, M), NaN where either is missing
    seen = np.isfinite(dist)
    count = seen.sum(0)
    d0 = np.where(seen, dist, 0.0)
    mean = d0.sum(0) / np.maximum(count, 1)
    var = np.where(seen, (dist - mean) ** 2, 0.0).sum(0) / np.maximum(count - 1, 1)
    out = np.sqrt(var)
    out[count < min_common] = np.nan
    np.fill_diagonal(out, 0.0)
    return out


def within_group_cost(a: np.ndarray, groups: np.ndarray) -> float:
    """``Σ_g Σ_{i<j ∈ g} A_ij / |g|``; pairs never seen together count as the largest finite entry."""
    fill = np.nanmax(a) if np.isfinite(a).any() else 0.0
    a = np.where(np.isfinite(a), a, fill)
    total = 0.0
    for g in np.unique(groups):
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
    return max(least_rigid_pair(a, np.flatnonzero(groups == g))[0] for g in np.unique(groups))


def _affinity(a: np.ndarray, scale: float) -> np.ndarray:
    w = np.exp(-0.5 * (np.nan_to_num(a, nan=np.inf) / scale) ** 2)
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
    seed: int = 0,
) -> Segmentation:
    """Group markers into rigid segments (§3.1).

    Args:
        trajectories: preprocessed marker trajectories ``(F, M, 3)``.
        num_groups: number of segments, or None to choose it at the largest eigengap (2 … ``max_groups``).
        num_samplings: jittered frame samplings clustered; the best clustering is kept.
        interval_s, jitter_s, min_samples: the sampling (see :func:`jittered_samples`).
        scale_m: σ of the affinity ``exp(−A²/2σ²)`` (m); None picks it from the data.
        rigid_tolerance_m: with the eigengap, raise the count one at a time (up to ``max_groups``)
            while a group has two markers whose distance varies more than this (std): such a group
            spans a joint. The eigengap alone merges whole limbs on short real trials (a CMU file:
            10 groups, one of them a whole arm whose markers vary by 53 mm; 15 rigid ones).
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
    stds = [
        distance_std(trajectories.positions, jittered_samples(trajectories.num_frames, trajectories.fps, rng, interval_s, jitter_s, min_samples))
        for _ in range(max(1, num_samplings))
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        reference = np.nanmedian(np.stack(stds), axis=0)
    never = [
        (trajectories.labels[i], trajectories.labels[j])
        for i, j in zip(*np.nonzero(np.triu(~np.isfinite(reference), 1)))
    ]
    if never and len(never) == m * (m - 1) // 2:
        raise ValueError("segment_markers: no two markers are ever seen together")
    scale = float(scale_m) if scale_m is not None else _auto_scale(reference)
    eig_n, eigenvalues = eigengap(_affinity(reference, scale), min(max_groups, m - 1) if m > 2 else 1, min_groups=2 if m > 2 else 1)
    chosen_by = "given" if num_groups is not None else "eigengap"
    n = num_groups if num_groups is not None else eig_n

    def best_clustering(n: int) -> tuple[np.ndarray, list[float]]:
        candidates, costs = [], []
        for a in stds:
            filled = np.where(np.isfinite(a), a, reference)
            labels = spectral_clustering(_affinity(filled, scale), n, rng)
            candidates.append(labels)
            costs.append(within_group_cost(reference, labels))
        return candidates[int(np.argmin(costs))], costs

    labels, costs = best_clustering(n)
    if num_groups is None and rigid_tolerance_m is not None:
        limit = min(max_groups, m - 1)
        while n < limit and least_rigid(reference, labels) > rigid_tolerance_m:
            n += 1
            labels, costs = best_clustering(n)
        if n > eig_n:
            chosen_by = f"eigengap {eig_n}, raised for rigid groups (tolerance {rigid_tolerance_m * 1000:.0f} mm)"
    return Segmentation(
        groups=labels,
        num_groups=n,
        cost=min(costs),
        distance_std=reference,
        scale_m=scale,
        eigenvalues=eigenvalues,
        chosen_by=chosen_by,
        candidate_costs=tuple(costs),
    )
