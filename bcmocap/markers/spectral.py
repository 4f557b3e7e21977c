"""Spectral clustering (Ng, Jordan & Weiss 2002), with optional repulsion (Yu & Shi 2001), and the eigengap.

Both marker segmentation (§3.1) and marker identity merging (§4) of Kirk et al. cluster this way. With an
attraction matrix ``W`` (affinities ≥ 0) and a repulsion matrix ``R`` (≥ 0, for pairs that must not share
a cluster), Yu & Shi's generalised normalised cut uses ``W − R + D_R`` with degrees ``D_W + D_R``; with
``R = 0`` it is Ng–Jordan–Weiss: the top ``k`` eigenvectors of ``D^{-1/2} W D^{-1/2}``, rows normalised
to unit length, then k-means.
"""

from __future__ import annotations

import numpy as np

__all__ = ["eigengap", "kmeans", "spectral_clustering", "spectral_embedding"]


def _normalised(affinity: np.ndarray, repulsion: np.ndarray | None) -> np.ndarray:
    w = np.asarray(affinity, dtype=np.float64)
    if w.ndim != 2 or w.shape[0] != w.shape[1]:
        raise ValueError(f"affinity must be a square matrix, got {w.shape}")
    if not np.all(np.isfinite(w)) or (w < 0).any():
        raise ValueError("affinity must be finite and non-negative")
    w = 0.5 * (w + w.T)
    np.fill_diagonal(w, 0.0)
    degree = w.sum(1)
    if repulsion is not None:
        r = 0.5 * (np.asarray(repulsion, dtype=np.float64) + np.asarray(repulsion, dtype=np.float64).T)
        np.fill_diagonal(r, 0.0)
        dr = r.sum(1)
        w = w - r + np.diag(dr)
        degree = degree + dr
    # A point with no affinity to anything stays its own cluster; keep the division finite.
    degree = np.maximum(degree, 1e-12 * max(degree.max(), 1e-300))
    inv = 1.0 / np.sqrt(degree)
    return inv[:, None] * w * inv[None, :]


def spectral_embedding(affinity: np.ndarray, k: int, repulsion: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the top-``k`` eigenvectors, normalised to unit length, and all eigenvalues (descending).

    Returns:
        ``(N, k)`` embedding and ``(N,)`` eigenvalues of the normalised affinity.
    """
    m = _normalised(affinity, repulsion)
    values, vectors = np.linalg.eigh(m)
    order = np.argsort(values)[::-1]
    values, vectors = values[order], vectors[:, order]
    emb = vectors[:, :k]
    norm = np.linalg.norm(emb, axis=1, keepdims=True)
    emb = emb / np.where(norm > 1e-12, norm, 1.0)
    return emb, values


def eigengap(affinity: np.ndarray, max_groups: int, min_groups: int = 2, repulsion: np.ndarray | None = None) -> tuple[int, np.ndarray]:
    """Number of clusters at the largest gap between consecutive eigenvalues of the normalised affinity.

    Returns:
        ``k`` in ``[min_groups, max_groups]`` maximising ``λ_k − λ_{k+1}`` (eigenvalues descending), and
        the eigenvalues.
    """
    _, values = spectral_embedding(affinity, 1, repulsion)
    n = len(values)
    hi = min(max_groups, n - 1)
    if hi < min_groups:
        return min(n, max(1, min_groups)), values
    gaps = values[min_groups - 1 : hi] - values[min_groups : hi + 1]
    return int(min_groups + np.argmax(gaps)), values


def kmeans(points: np.ndarray, k: int, rng: np.random.Generator, restarts: int = 10, iterations: int = 100) -> np.ndarray:
    """Lloyd's k-means with k-means++ seeding, best of ``restarts``; returns ``(N,)`` labels in ``[0, k)``."""
    x = np.asarray(points, dtype=np.float64)
    n = len(x)
    if not 1 <= k <= n:
        raise ValueError(f"kmeans: cannot make {k} clusters of {n} points")
    best, best_cost = None, np.inf
    for _ in range(restarts):
        centres = [x[rng.integers(n)]]
        for _ in range(1, k):
            d2 = np.min(((x[:, None] - np.asarray(centres)[None]) ** 2).sum(-1), axis=1)
            p = d2 / d2.sum() if d2.sum() > 0 else np.full(n, 1.0 / n)
            centres.append(x[rng.choice(n, p=p)])
        c = np.asarray(centres)
        labels = np.zeros(n, int)
        for it in range(iterations):
            d2 = ((x[:, None] - c[None]) ** 2).sum(-1)
            new = np.argmin(d2, axis=1)
            if it > 0 and np.array_equal(new, labels):
                break
            labels = new
            for j in range(k):
                members = x[labels == j]
                # An emptied cluster takes the point worst served by its centre.
                c[j] = members.mean(0) if len(members) else x[np.argmax(d2[np.arange(n), labels])]
        cost = ((x - c[labels]) ** 2).sum()
        if cost < best_cost:
            best, best_cost = labels.copy(), cost
    return _relabel(best)


def _relabel(labels: np.ndarray) -> np.ndarray:
    """Cluster ids renumbered in order of first appearance (a canonical form)."""
    _, first = np.unique(labels, return_index=True)
    order = np.argsort(first)
    mapping = np.empty(len(order), int)
    mapping[order] = np.arange(len(order))
    return mapping[np.unique(labels, return_inverse=True)[1]]


def spectral_clustering(
    affinity: np.ndarray,
    k: int,
    rng: np.random.Generator,
    repulsion: np.ndarray | None = None,
    restarts: int = 10,
) -> np.ndarray:
    """Cluster ``N`` items into ``k`` groups; returns ``(N,)`` labels (first item in cluster 0, …)."""
    emb, _ = spectral_embedding(affinity, k, repulsion)
    return kmeans(emb, k, rng, restarts=restarts)
