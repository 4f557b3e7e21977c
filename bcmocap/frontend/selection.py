"""Measurement selection (issue 18, item 3): at most N measurements per camera-frame for the solver.

A registered frame can observe thousands of 3D points, and every camera-frame of a window is padded to the
widest one, so a few rich frames make the whole solve slow. The paper used about 300 inliers per image.
:func:`select_measurements` keeps ``limit`` measurements spread over the image: the image is cut into a
grid of buckets and the buckets are visited round-robin, each giving its best remaining measurement, so a
textured corner cannot crowd out the rest of the view (the spread is what constrains a pose). "Best" is
:func:`measurement_score`: long tracks (seen in many frames: stable, well triangulated points) and low
reprojection error under the frame's registered pose.
"""

from __future__ import annotations

import numpy as np

__all__ = ["measurement_score", "select_measurements"]


def measurement_score(track_length: np.ndarray, error_px: np.ndarray) -> np.ndarray:
    """``(K,)`` higher is better: ``log2(track length) − error / 1 px`` (a point seen in twice as many frames
    is worth one pixel of reprojection error; NaN errors score lowest)."""
    score = np.log2(np.maximum(np.asarray(track_length, np.float64), 1.0)) - np.asarray(error_px, np.float64)
    return np.where(np.isfinite(score), score, -np.inf)


def select_measurements(pixels: np.ndarray, score: np.ndarray, limit: int, width: int, height: int,
                        grid: tuple[int, int] = (8, 6)) -> np.ndarray:
    """Indices of at most ``limit`` measurements spread over the image, best first within each bucket.

    Args:
        pixels: ``(K, 2)`` measurement positions (px, x right, y down) in an image of ``width × height``.
        score: ``(K,)`` higher is better (e.g. :func:`measurement_score`).
        limit: how many to keep (all when ``K ≤ limit``).
        grid: buckets across and down.

    Returns:
        ``(min(K, limit),)`` sorted indices into ``pixels``.
    """
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    score = np.asarray(score, np.float64).reshape(-1)
    if len(score) != len(pixels):
        raise ValueError(f"select_measurements: {len(pixels)} pixels but {len(score)} scores")
    if limit < 0:
        raise ValueError(f"select_measurements: limit must be ≥ 0, got {limit}")
    if len(pixels) <= limit:
        return np.arange(len(pixels))
    gx = np.clip((pixels[:, 0] / width * grid[0]).astype(np.int64), 0, grid[0] - 1)
    gy = np.clip((pixels[:, 1] / height * grid[1]).astype(np.int64), 0, grid[1] - 1)
    bucket = gy * grid[0] + gx
    order = np.lexsort((-score, bucket))  # by bucket, best first within it
    sorted_bucket = bucket[order]
    first = np.searchsorted(sorted_bucket, sorted_bucket, side="left")
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order)) - first  # place of each measurement within its bucket
    # round-robin: every bucket's best, then every bucket's second, … (ties in a round: higher score first)
    pick = np.lexsort((-score, rank))[:limit]
    return np.sort(pick)
