"""Marker identities (Kirk et al. §4): merge the labels a passive system produces into physical markers.

A passive optical system gives a marker a new label whenever it loses and finds it again, so it reports
many more labels than markers were worn. The paper takes the number of physical markers ``n'`` as the
largest number of labels seen in one frame; with heavy occlusion no frame may see every marker, so here
``n'`` is the largest number of labels whose spans (first to last frame seen) cover one frame
(:func:`concurrent_labels`): the labels of one physical marker follow one another, so they never
overlap, and a labelled capture (every label spanning the trial, gaps inside) needs no merging at all.
Two labels seen in the same frame are different markers. For two labels ``i``
and ``j`` never seen together, the paper's distance is

    D_ij = min over frames a (i seen), b (j seen) of ‖m_{i,a} − A_ab m_{j,b}‖

where ``A_ab`` is the rigid motion that best aligns frame ``b`` onto frame ``a`` using the labels seen in
both: when the body passes through a similar configuration again, the same physical marker lands on itself.
Here the alignment is *local*: the common labels are weighted by their closeness to ``m_{i,a}``
(Gaussian, ``radius_m``), so only the body part around the marker has to repeat its configuration, not
the whole pose; and the alignment's own weighted RMS misfit is added (in quadrature) to the distance, so
that a minimum over many poor alignments does not bring a wrong marker close by chance. Frames are sampled at a constant interval, as in the paper (its final search of all
frame pairs around the best samples is not done). The labels are then clustered into ``n'`` markers by
spectral clustering with affinity ``exp(−D²/2σ²)`` and, for labels seen together, zero affinity and a
repulsion (Yu & Shi); a last pass moves any label that still shares a frame with a cluster-mate to the
closest cluster where it shares none (``method="spectral"``).

The default clustering (``method="linkage"``) uses the same distances and the same cannot-link rule in a
constrained single linkage: the two closest clusters that never share a frame are joined until ``n'``
remain. On simulated full-body data (45 markers, ~100 labels) it merged the labels better than spectral
clustering (k-means in a 45-dimensional embedding), which got 92–96 % right; see
``benchmarks/markers_fullbody.py`` for both figures. The locality radius (8 cm, about one segment) was
chosen on that simulation: at 15 cm the neighbourhood spans joints and its misfit blurs the distances.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..geometry import rotation_from_covariance
from .preprocess import MarkerTrajectories
from .spectral import spectral_clustering

__all__ = ["IdentityMerge", "concurrent_labels", "label_distances", "merge_identities"]


@dataclasses.dataclass(frozen=True)
class IdentityMerge:
    """Labels merged into physical markers.

    Attributes:
        marker_of_label: ``(L,)`` physical marker of each input label, in ``[0, num_markers)``.
        num_markers: markers after merging: ``n'``, or more when some labels could not be compared with
            any cluster they could join (they are kept as markers of their own).
        distances: ``(L, L)`` pose-invariant distances ``D`` (m; inf where not comparable or seen together).
        overlap: ``(L, L)`` True where two labels are seen in the same frame.
        conflicts_fixed: labels moved by the last pass.
    """

    marker_of_label: np.ndarray
    num_markers: int
    distances: np.ndarray
    overlap: np.ndarray
    conflicts_fixed: int


def concurrent_labels(visible: np.ndarray) -> int:
    """The largest number of labels whose spans (first to last frame seen) cover one frame (``visible`` ``(F, L)``).

    The labels of one physical marker follow one another in time, so this is at most the number of
    physical markers, and at least the largest number seen in one frame.
    """
    visible = np.asarray(visible, bool)
    num_frames = visible.shape[0]
    seen = visible.any(0)
    first = np.argmax(visible, axis=0)[seen]
    last = num_frames - 1 - np.argmax(visible[::-1], axis=0)[seen]
    change = np.zeros(num_frames + 1, int)
    np.add.at(change, first, 1)
    np.add.at(change, last + 1, -1)
    return int(np.cumsum(change)[:num_frames].max()) if seen.any() else 0


def label_distances(
    positions: np.ndarray,
    frames: np.ndarray,
    *,
    radius_m: float = 0.08,
    min_common: int = 3,
) -> np.ndarray:
    """``(L, L)`` distances ``D_ij`` over the sampled ``frames`` (see the module docstring).

    Args:
        positions: ``(F, L, 3)`` positions per label (NaN where the label has no data).
        frames: the sampled frame indices.
        radius_m: scale of the locality weights of the alignment.
        min_common: alignments need this many common labels with non-negligible weight.
    """
    p = positions[frames]  # (S, L, 3)
    vis = np.isfinite(p[..., 0])
    p0 = np.where(vis[..., None], p, 0.0)
    norm2 = np.sum(p0 * p0, -1)  # (S, L)
    num_labels = p.shape[1]
    out = np.full((num_labels, num_labels), np.inf)
    for i in range(num_labels):
        a_idx = np.flatnonzero(vis[:, i])
        if len(a_idx) == 0:
            continue
        centre = p0[a_idx, i]  # (A, 3)
        w = vis[a_idx] * np.exp(-0.5 * np.sum((p0[a_idx] - centre[:, None]) ** 2, -1) / radius_m**2)
        w[:, i] = 0.0
        weights = w[:, None, :] * vis[None, :, :]  # (A, S, L)
        weights[:, :, i] = 0.0
        total = weights.sum(-1)
        enough = (weights > 1e-3).sum(-1) >= min_common
        tot = np.where(total > 0, total, 1.0)
        mu_a = np.einsum("abk,aki->abi", weights, p0[a_idx]) / tot[..., None]
        mu_b = np.einsum("abk,bki->abi", weights, p0) / tot[..., None]
        h = np.einsum("abk,bki,akj->abij", weights, p0, p0[a_idx], optimize=True) - total[..., None, None] * mu_b[..., :, None] * mu_a[..., None, :]
        rot = rotation_from_covariance(np.swapaxes(h, -1, -2))  # frame b → frame a
        # How well the neighbourhood itself lines up: a poor alignment (a different local pose) can
        # carry a wrong marker onto m_{i,a} by chance, so its misfit is added to the distance. Both from
        # moments, without moving every label (|R x| = |x|): the weighted misfit is
        # Σ w |x_a|² + Σ w |x_b|² − 2 tr(R hᵀ) for the centred points x, and a label k at frame b lands at
        # squared distance |x_bk|² + |μ_a − m_{i,a}|² + 2 (Rᵀ (μ_a − m_{i,a}))·x_bk from m_{i,a}.
        spread_a = np.einsum("abk,ak->ab", weights, norm2[a_idx]) - total * np.sum(mu_a**2, -1)
        spread_b = np.einsum("abk,bk->ab", weights, norm2) - total * np.sum(mu_b**2, -1)
        misfit = np.maximum(spread_a + spread_b - 2.0 * np.einsum("abij,abji->ab", rot, h), 0.0) / tot
        offset = mu_a - centre[:, None, :]
        v = np.einsum("abji,abj->abi", rot, offset)
        dist2 = (norm2[None] + np.einsum("abi,bki->abk", 2.0 * (v - mu_b), p0)
                 + (np.sum(mu_b**2, -1) + np.sum(offset**2, -1) - 2.0 * np.sum(v * mu_b, -1))[..., None])
        dist = np.sqrt(np.maximum(dist2, 0.0) + misfit[..., None])  # (A, S, L)
        dist = np.where(vis[None] & enough[..., None], dist, np.inf)
        out[i] = dist.min(axis=(0, 1))
    out = np.minimum(out, out.T)
    np.fill_diagonal(out, 0.0)
    return out


def merge_identities(
    trajectories: MarkerTrajectories,
    num_markers: int | None = None,
    *,
    sample_interval_s: float = 0.1,
    max_samples: int = 150,
    radius_m: float = 0.08,
    scale_m: float | None = None,
    method: str = "linkage",
    seed: int = 0,
) -> tuple[MarkerTrajectories, IdentityMerge]:
    """Merge labels into physical markers (§4).

    Args:
        trajectories: labelled fragments ``(F, L, 3)``, preprocessed (no ghosts).
        num_markers: ``n'``; None takes :func:`concurrent_labels`.
        sample_interval_s: spacing of the sampled frames (widened to keep at most ``max_samples``).
        radius_m: locality of the alignments.
        scale_m: σ of the affinity ``exp(−D²/2σ²)`` (m); None: twice the median over labels of the
            distance to their nearest label.
        method: "linkage" (constrained single linkage, the default) or "spectral" (the paper's
            spectral clustering with repulsion).
        seed: random seed of k-means.

    Returns:
        Trajectories of the ``n'`` merged markers (each labelled by its first label) and an
        :class:`IdentityMerge`.

    Raises:
        ValueError: ``num_markers`` is smaller than the number of labels seen in one frame, or larger
            than the number of labels.
    """
    vis = trajectories.visible
    num_labels = trajectories.num_markers
    most = int(vis.sum(1).max())
    n = concurrent_labels(vis) if num_markers is None else int(num_markers)
    if n < most:
        frame = int(np.argmax(vis.sum(1)))
        raise ValueError(f"merge_identities: {most} labels are seen together at frame {frame}, more than num_markers={n}")
    if n > num_labels:
        raise ValueError(f"merge_identities: num_markers={n} but there are only {num_labels} labels")
    overlap = (vis.T.astype(np.int32) @ vis.astype(np.int32)) > 0
    np.fill_diagonal(overlap, False)
    if n == num_labels:
        ident = IdentityMerge(np.arange(n), n, np.zeros((n, n)), overlap, 0)
        return trajectories, ident
    step = max(1, int(round(sample_interval_s * trajectories.fps)), int(np.ceil(trajectories.num_frames / max_samples)))
    frames = np.arange(0, trajectories.num_frames, step)
    dist = label_distances(trajectories.positions, frames, radius_m=radius_m)
    dist[overlap] = np.inf
    if scale_m is None:
        nearest = np.min(np.where(np.eye(num_labels, dtype=bool), np.inf, dist), axis=1)
        nearest = nearest[np.isfinite(nearest)]
        scale_m = float(2.0 * np.median(nearest)) if len(nearest) else 0.02
    affinity = np.where(np.isfinite(dist), np.exp(-0.5 * (np.where(np.isfinite(dist), dist, 0.0) / scale_m) ** 2), 0.0)
    np.fill_diagonal(affinity, 0.0)
    if method == "spectral":
        repulsion = overlap.astype(float) * max(float(affinity.max()), 1e-12)
        labels = spectral_clustering(affinity, n, np.random.default_rng(seed), repulsion=repulsion)
        labels, moved = _fix_conflicts(labels, overlap, affinity, n)
    elif method == "linkage":
        labels, moved = _constrained_linkage(dist, vis, n), 0
    else:
        raise ValueError(f"merge_identities: method must be 'linkage' or 'spectral', got {method!r}")

    # Labels no distance links to any compatible cluster stay markers of their own.
    n = int(labels.max()) + 1
    positions = np.full((trajectories.num_frames, n, 3), np.nan)
    names = []
    for k in range(n):
        members = np.flatnonzero(labels == k)
        for m in members:
            seen = vis[:, m]
            positions[seen, k] = trajectories.positions[seen, m]
        names.append(trajectories.labels[members[0]] if len(members) else f"marker{k}")
    merged = MarkerTrajectories(positions, tuple(names), trajectories.fps)
    return merged, IdentityMerge(labels, n, dist, overlap, moved)


def _constrained_linkage(dist: np.ndarray, visible: np.ndarray, n: int) -> np.ndarray:
    """Single linkage with cannot-links: join the closest two clusters whose labels never share a frame."""
    num = len(dist)
    parent = np.arange(num)
    frames = visible.T.copy()  # (L, F): frames each cluster (by its root) occupies
    clusters = num
    flat = np.argsort(dist, axis=None)
    for i, j in zip(*np.unravel_index(flat, dist.shape)):
        if clusters <= n or not np.isfinite(dist[i, j]):
            break
        if i >= j:
            continue
        a, b = parent[i], parent[j]
        if a == b or (frames[a] & frames[b]).any():
            continue
        frames[a] |= frames[b]
        parent[parent == b] = a
        clusters -= 1
    return np.unique(parent, return_inverse=True)[1]


def _fix_conflicts(labels: np.ndarray, overlap: np.ndarray, affinity: np.ndarray, n: int) -> tuple[np.ndarray, int]:
    """Move labels that share a frame with a cluster-mate to the best cluster where they share none."""
    labels = labels.copy()
    moved = 0
    for _ in range(len(labels)):
        bad = None
        for k in range(n):
            members = np.flatnonzero(labels == k)
            sub = overlap[np.ix_(members, members)]
            if sub.any():
                # the member with the most conflicts, then the least attached to its cluster
                score = sub.sum(1) * 1e6 - affinity[np.ix_(members, members)].sum(1)
                bad = members[int(np.argmax(score))]
                break
        if bad is None:
            break
        best, best_aff = None, -1.0
        for k in range(n):
            members = np.flatnonzero(labels == k)
            members = members[members != bad]
            if overlap[bad, members].any():
                continue
            aff = affinity[bad, members].sum() if len(members) else 0.0
            if aff > best_aff:
                best, best_aff = k, aff
        if best is None or best == labels[bad]:
            break  # no cluster can take it: leave the conflict (reported by the caller's checks)
        labels[bad] = best
        moved += 1
    return labels, moved
