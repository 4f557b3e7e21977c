"""A static synthetic scene as 3D feature points: ground, room walls and clutter (boxes, pillars)."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class World:
    """Scene points and the box that bounds the room.

    Attributes:
        points: ``(P, 3)`` world coordinates of features (m), Z up, ground at z = 0.
        lower, upper: ``(3,)`` corners of the room.
    """

    points: np.ndarray
    lower: np.ndarray
    upper: np.ndarray


def make_world(
    path_xy: np.ndarray,
    *,
    seed: int = 0,
    margin_m: float = 6.0,
    wall_height_m: float = 4.0,
    density_per_m2: float = 3.0,
    num_pillars: int = 8,
    num_boxes: int = 10,
) -> World:
    """A room around a walking path, with features on every surface.

    Args:
        path_xy: ``(T, 2)`` horizontal positions the subject visits; the room encloses them with ``margin_m``.
        seed: random seed (the same seed gives the same world).
        density_per_m2: features per square metre on every surface.
        num_pillars, num_boxes: clutter placed off the path (≥ 1.5 m from it).
    """
    rng = np.random.default_rng(seed)
    path_xy = np.asarray(path_xy, dtype=np.float64).reshape(-1, 2)
    lo = path_xy.min(axis=0) - margin_m
    hi = path_xy.max(axis=0) + margin_m
    parts = []

    def surface(origin, u, v, area_scale=1.0):
        area = np.linalg.norm(u) * np.linalg.norm(v)
        n = rng.poisson(density_per_m2 * area * area_scale)
        st = rng.random((n, 2))
        parts.append(origin + st[:, :1] * u + st[:, 1:] * v)

    z = np.array([0.0, 0.0, wall_height_m])
    surface(np.array([lo[0], lo[1], 0.0]), np.array([hi[0] - lo[0], 0, 0]), np.array([0, hi[1] - lo[1], 0]))
    corners = [np.array([lo[0], lo[1], 0]), np.array([hi[0], lo[1], 0]), np.array([hi[0], hi[1], 0]), np.array([lo[0], hi[1], 0])]
    for a, b in zip(corners, corners[1:] + corners[:1]):
        surface(a, b - a, z, area_scale=1.5)
    surface(np.array([lo[0], lo[1], wall_height_m]), np.array([hi[0] - lo[0], 0, 0]), np.array([0, hi[1] - lo[1], 0]), 0.5)

    def away_from_path(count):
        out = []
        while len(out) < count:
            c = lo + 1.0 + rng.random(2) * (hi - lo - 2.0)
            if np.min(np.linalg.norm(path_xy - c, axis=1)) > 1.5:
                out.append(c)
        return out

    for c in away_from_path(num_pillars):
        radius, height = rng.uniform(0.2, 0.4), wall_height_m
        n = rng.poisson(density_per_m2 * 2 * np.pi * radius * height * 2)
        ang, hz = rng.random(n) * 2 * np.pi, rng.random(n) * height
        parts.append(np.stack([c[0] + radius * np.cos(ang), c[1] + radius * np.sin(ang), hz], axis=1))
    for c in away_from_path(num_boxes):
        size = rng.uniform(0.4, 1.2, 3)
        base = np.array([c[0] - size[0] / 2, c[1] - size[1] / 2, 0.0])
        ex, ey, ez = np.diag(size)
        for origin, u, v in ((base, ex, ez), (base + ey, ex, ez), (base, ey, ez), (base + ex, ey, ez), (base + ez, ex, ey)):
            surface(origin, u, v, area_scale=2.0)
    return World(np.concatenate(parts).astype(np.float64), np.array([lo[0], lo[1], 0.0]), np.array([hi[0], hi[1], wall_height_m]))
