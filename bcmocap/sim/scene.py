"""A textured static scene for rendering: a room with clutter, made of a handful of analytic surfaces.

The room of :func:`bcmocap.sim.world.make_world` (same bounds from the subject's path: the path's
bounding box grown by ``margin_m``, floor at z = 0, a ceiling at ``wall_height_m``), as surfaces a ray
can hit in a few vector operations: the inside of the room box (floor, ceiling, four walls), axis-aligned
boxes standing on the floor and vertical cylindrical pillars from floor to ceiling.

Every surface carries a procedural, non-repeating, multi-scale texture (value noise summed over octaves
from 2 m down to 4 mm, each octave rotated and seeded per surface). A texture is a function of the
surface coordinates ``(u, v)`` (metres) and of the pixel footprint on the surface: octaves finer than
about two footprints fade out, which anti-aliases the texture analytically at any distance (frequency
clamping), so one ray per pixel gives images SIFT can track.

Surface coordinates: a face whose normal is along x uses ``(y, z)``, along y ``(x, z)``, along z
``(x, y)``; a pillar uses ``(radius * azimuth, z)``. Materials are numbered: 0 floor, 1 ceiling, 2..5
the walls at x = lower, x = upper, y = lower, y = upper, then one per box, then one per pillar.

Finishes. A scene may also give each material a finish (:class:`TexturedScene`'s ``finish_kinds``,
``finish_gains`` and ``tiles``; :func:`finished_texture`): ``NOISE`` (the texture above, its contrast times
a gain), ``TILED`` (tiles, bricks or windows: the noise of one tile repeated, exactly for sizes that are powers of
two and to float32's rounding otherwise, every tile alike or each showing one of a few faces, with darker joints
between them, box-filtered over the pixel footprint) or ``BLANK`` (uniform grey: nothing to track). A scene
without finishes is rendered by the plain texture's code, so it keeps its pixels.
:func:`make_room` builds the studio's rooms: "textured" (:func:`make_textured_scene`), "sparse" (painted,
weakly textured surfaces, one blank wall, less clutter) and "repeated" (a floor of tiles of a few faces, a
ceiling of identical panels, a wall of identical bricks, a wall of identical windows).
"""

from __future__ import annotations

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np

from .world import World, make_world

__all__ = ["BLANK", "NOISE", "ROOM_STYLES", "TILED", "TextureParams", "TexturedScene", "finished_texture",
           "make_room", "make_textured_scene", "surface_texture"]

ROOM_MATERIALS = 6  # floor, ceiling, walls x-, x+, y-, y+
NOISE, TILED, BLANK = 0, 1, 2  # finishes of a material (module docstring)
ROOM_STYLES = ("textured", "sparse", "repeated")  # what make_room builds
_JOINT_GREY = 0.2  # grey level of the joints between tiles
_FACE_SEED_STEP = 4096  # a tile face's noise is seeded as material + face × this (no scene has as many materials)


@dataclasses.dataclass(frozen=True)
class TextureParams:
    """Procedural texture of every surface (static: changing it recompiles the renderer).

    Attributes:
        coarsest_m: lattice spacing of the coarsest octave (m).
        octaves: number of octaves; each halves the spacing (10 octaves: 2 m down to 4 mm).
        persistence: amplitude ratio of an octave to the previous one (close to 1 keeps fine contrast).
        contrast: gain of the summed noise around mid-grey.
        fade_footprints: an octave is fully present when its spacing is at least twice this many pixel
            footprints and gone at this many.
        seed: base seed of the lattice hashes.
    """

    coarsest_m: float = 2.0
    octaves: int = 10
    persistence: float = 0.95
    contrast: float = 1.8
    fade_footprints: float = 1.0
    seed: int = 0


def _hash01(ix: jax.Array, iy: jax.Array, seed: jax.Array) -> jax.Array:
    """A float32 in [0, 1) per integer lattice point (uint32 inputs; a murmur-like integer mix)."""
    h = ix * jnp.uint32(0x8DA6B343) + iy * jnp.uint32(0xD8163841) + seed
    h = h ^ (h >> 15)
    h = h * jnp.uint32(0x2C1B3C6D)
    h = h ^ (h >> 12)
    h = h * jnp.uint32(0x297A2D39)
    h = h ^ (h >> 15)
    return (h >> 8).astype(jnp.float32) * jnp.float32(1.0 / (1 << 24))


def _lattice(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    f = jnp.floor(x)
    return jax.lax.bitcast_convert_type(f.astype(jnp.int32), jnp.uint32), x - f


def surface_texture(u: jax.Array, v: jax.Array, material: jax.Array, footprint_m: jax.Array, params: TextureParams) -> jax.Array:
    """Grey level in [0, 1] of the procedural texture at surface coordinates (float32, any shape).

    Args:
        u, v: surface coordinates (m), see the module docstring.
        material: integer material index (selects an independent texture).
        footprint_m: size of a pixel on the surface (m); octaves below it fade out (anti-aliasing).
        params: the texture.
    """
    total, norm = _octave_sum(u, v, material, footprint_m, params)
    return jnp.clip(0.5 + params.contrast * total / norm, 0.0, 1.0)


def _octave_sum(u, v, material, footprint_m, params: TextureParams,
                largest_m: jax.Array | None = None) -> tuple[jax.Array, float]:
    """``(sum, norm)``: the octaves of value noise in [-1/2, 1/2] summed with their weights (float32, shapes
    broadcast), and the root of the sum of their squared weights (arguments as :func:`surface_texture`'s;
    ``largest_m``: leave out the octaves whose spacing exceeds it, m)."""
    u = jnp.asarray(u, jnp.float32)
    v = jnp.asarray(v, jnp.float32)
    # One reciprocal shared by all octaves (a division per octave would each be a separate XLA loop).
    inv_foot = 1.0 / (params.fade_footprints * jnp.maximum(jnp.asarray(footprint_m, jnp.float32), 1e-6))
    seed = jnp.asarray(material).astype(jnp.uint32) * jnp.uint32(0x9E3779B1) + jnp.uint32(params.seed * 0x85EBCA77 & 0xFFFFFFFF)
    total = jnp.zeros(jnp.broadcast_shapes(u.shape, v.shape, inv_foot.shape), jnp.float32)
    for k in range(params.octaves):
        spacing = params.coarsest_m * 0.5**k
        # A different rotation and offset per octave: no lattice axis or period is shared between octaves.
        angle = 2.399963 * k + 0.3
        c, s = math.cos(angle) / spacing, math.sin(angle) / spacing
        ix, fx = _lattice(c * u - s * v + 37.1 * k)
        iy, fy = _lattice(s * u + c * v + 11.7 * k)
        sd = seed + jnp.uint32((k * 0x632BE5AB) & 0xFFFFFFFF)
        h00, h10 = _hash01(ix, iy, sd), _hash01(ix + 1, iy, sd)
        h01, h11 = _hash01(ix, iy + 1, sd), _hash01(ix + 1, iy + 1, sd)
        fx = fx * fx * (3.0 - 2.0 * fx)
        fy = fy * fy * (3.0 - 2.0 * fy)
        bottom = h00 + (h10 - h00) * fx
        top = h01 + (h11 - h01) * fx
        value = bottom + (top - bottom) * fy - 0.5
        weight = jnp.clip(spacing * inv_foot - 1.0, 0.0, 1.0)
        if largest_m is not None:
            weight = jnp.where(spacing <= largest_m, weight, 0.0)
        total = total + (params.persistence**k) * weight * value
    norm = sum(params.persistence**k for k in range(params.octaves)) ** 0.5
    return total, norm


def _joint_coverage(distance_m: jax.Array, joint_m: jax.Array, footprint_m: jax.Array) -> jax.Array:
    """Share of a pixel (a box of width ``footprint_m``) covered by a joint of width ``joint_m`` centred
    ``distance_m`` away (m, ``distance_m >= 0``)."""
    half_joint, half_pixel = 0.5 * joint_m, 0.5 * footprint_m
    overlap = jnp.minimum(distance_m + half_pixel, half_joint) - jnp.maximum(distance_m - half_pixel, -half_joint)
    return jnp.clip(overlap / footprint_m, 0.0, 1.0)


def finished_texture(u: jax.Array, v: jax.Array, material: jax.Array, footprint_m: jax.Array, params: TextureParams,
                     kind: jax.Array, gain: jax.Array, tile: tuple) -> jax.Array:
    """Grey level in [0, 1] of a material with a finish (module docstring; float32, shapes broadcast).

    Args:
        u, v, material, footprint_m, params: as :func:`surface_texture`'s.
        kind: ``NOISE``, ``TILED`` or ``BLANK``; gain: the noise's contrast relative to ``params.contrast``.
        tile: ``(width, height, row_shift, joint, faces)``: a tile's size along u and v (m), the share of a width
            every other row is shifted by (0: a grid, 0.5: bricks), the joints' width (m) and how many different
            faces the tiles have (1: every tile alike; k: each tile shows one of k, drawn per tile, as printed
            porcelain tiles come in a handful of faces). With one face exactly periodic, in float32 too, when
            width and height are powers of two (period ``width`` along u; ``height`` along v, or twice it with a
            row shift).
    """
    u = jnp.asarray(u, jnp.float32)
    v = jnp.asarray(v, jnp.float32)
    footprint_m = jnp.maximum(jnp.asarray(footprint_m, jnp.float32), 1e-6)
    width, height, row_shift, joint, faces = tile
    row = jnp.floor(v / height)
    shifted = u + row_shift * width * (row - 2.0 * jnp.floor(0.5 * row))
    column = jnp.floor(shifted / width)
    tile_u = shifted - width * column  # in [0, width): exact for a power-of-two width
    tile_v = v - height * row
    tiled = kind == TILED
    # Each tile shows one of `faces` noises, drawn per tile (one face: every tile alike), each seeded as a
    # material of its own.
    ix, _ = _lattice(column)
    iy, _ = _lattice(row)
    material = jnp.asarray(material).astype(jnp.uint32)
    face = jnp.floor(_hash01(ix, iy, material + jnp.uint32(0x7F4A7C15)) * faces).astype(jnp.uint32)
    noise_material = jnp.where(tiled & (faces > 1), material + _FACE_SEED_STEP * face, material)
    # A tile holds the octaves no larger than itself (larger ones would shade every tile as one ramp).
    total, norm = _octave_sum(jnp.where(tiled, tile_u, u), jnp.where(tiled, tile_v, v), noise_material, footprint_m,
                              params, jnp.where(tiled, jnp.minimum(width, height), jnp.float32(np.inf)))
    grey = jnp.clip(0.5 + (params.contrast * gain) * total / norm, 0.0, 1.0)
    # Joints, box-filtered; where a pixel spans most of a tile, their mean share instead (no aliasing).
    across_u = _joint_coverage(jnp.minimum(tile_u, width - tile_u), joint, footprint_m)
    across_v = _joint_coverage(jnp.minimum(tile_v, height - tile_v), joint, footprint_m)
    fade = jnp.clip(2.0 * footprint_m / jnp.minimum(width, height) - 0.5, 0.0, 1.0)
    across_u = across_u + fade * (joint / width - across_u)
    across_v = across_v + fade * (joint / height - across_v)
    in_joint = 1.0 - (1.0 - across_u) * (1.0 - across_v)
    grey = jnp.where(tiled, grey + in_joint * (_JOINT_GREY - grey), grey)
    return jnp.where(kind == BLANK, jnp.float32(0.5), grey)


@dataclasses.dataclass(frozen=True)
class TexturedScene:
    """The room, its clutter and their materials (numpy float64; the renderer casts to float32).

    Attributes:
        lower, upper: ``(3,)`` corners of the room box (m); the floor is at ``lower[2] = 0``.
        boxes: ``(B, 2, 3)`` lower and upper corners of axis-aligned boxes standing on the floor (m).
        pillars: ``(P, 3)`` centre x, centre y and radius of vertical pillars from floor to ceiling (m).
        colors: ``(6 + B + P, 3)`` RGB albedo in [0, 1] per material (order in the module docstring).
        texture: the procedural texture.
        finish_kinds: None (every material ``NOISE`` at gain 1, the plain texture's code) or ``(6 + B + P,)``
            int ``NOISE``, ``TILED`` or ``BLANK`` per material (:func:`finished_texture`); then also
            finish_gains: ``(6 + B + P,)`` contrast of each material's noise relative to ``texture.contrast``;
            tiles: ``(6 + B + P, 4)`` width, height (m), row shift (share of a width) and joint width (m) of
            each material's tiles (used where ``TILED``; width and height > 0 everywhere).
    """

    lower: np.ndarray
    upper: np.ndarray
    boxes: np.ndarray
    pillars: np.ndarray
    colors: np.ndarray
    texture: TextureParams = TextureParams()
    finish_kinds: np.ndarray | None = None
    finish_gains: np.ndarray | None = None
    tiles: np.ndarray | None = None

    def __post_init__(self):
        for name, shape in (("lower", (3,)), ("upper", (3,))):
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"TexturedScene.{name} must have shape {shape}, got {np.shape(getattr(self, name))}")
        if np.ndim(self.boxes) != 3 or np.shape(self.boxes)[1:] != (2, 3):
            raise ValueError(f"TexturedScene.boxes must have shape (B, 2, 3), got {np.shape(self.boxes)}")
        if np.ndim(self.pillars) != 2 or np.shape(self.pillars)[1] != 3:
            raise ValueError(f"TexturedScene.pillars must have shape (P, 3), got {np.shape(self.pillars)}")
        if np.shape(self.colors) != (self.num_materials, 3):
            raise ValueError(f"TexturedScene.colors must have shape ({self.num_materials}, 3), got {np.shape(self.colors)}")
        if not np.all(np.asarray(self.upper) > np.asarray(self.lower)):
            raise ValueError(f"TexturedScene: upper {self.upper} must exceed lower {self.lower} on every axis")
        self._check_finishes()

    def _check_finishes(self) -> None:
        given = [self.finish_kinds is not None, self.finish_gains is not None, self.tiles is not None]
        if not any(given):
            return
        if not all(given):
            raise ValueError("TexturedScene: finish_kinds, finish_gains and tiles must be given together (or none)")
        m = self.num_materials
        for name, shape in (("finish_kinds", (m,)), ("finish_gains", (m,)), ("tiles", (m, 5))):
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"TexturedScene.{name} must have shape {shape}, got {np.shape(getattr(self, name))}")
        if not np.isin(self.finish_kinds, (NOISE, TILED, BLANK)).all():
            raise ValueError(f"TexturedScene.finish_kinds must be {NOISE} (noise), {TILED} (tiled) or {BLANK} (blank), "
                             f"got {np.unique(self.finish_kinds).tolist()}")
        if not (np.all(np.isfinite(self.finish_gains)) and np.all(np.asarray(self.finish_gains) >= 0)):
            raise ValueError("TexturedScene.finish_gains must be finite and >= 0")
        tiles = np.asarray(self.tiles, float)
        if not (np.all(np.isfinite(tiles)) and np.all(tiles[:, :2] > 0) and np.all(tiles[:, 3] >= 0)
                and np.all(tiles[:, 4] >= 1) and np.all(tiles[:, 4] == np.round(tiles[:, 4]))):
            raise ValueError("TexturedScene.tiles must be finite, with widths and heights > 0, joints >= 0 (m) and "
                             "a whole number of faces >= 1")

    @property
    def has_finishes(self) -> bool:
        """Whether the materials have finishes (else every one is the plain texture)."""
        return self.finish_kinds is not None

    @property
    def num_materials(self) -> int:
        return ROOM_MATERIALS + len(self.boxes) + len(self.pillars)

    def inside_clutter(self, points: np.ndarray, margin_m: float = 1e-6) -> np.ndarray:
        """``(N,)`` True for points ``(N, 3)`` strictly inside a box or a pillar."""
        p = np.asarray(points, dtype=np.float64)
        inside = np.zeros(len(p), bool)
        for lo, hi in self.boxes:
            inside |= np.all((p > lo + margin_m) & (p < hi - margin_m), axis=1)
        for cx, cy, r in self.pillars:
            inside |= np.hypot(p[:, 0] - cx, p[:, 1] - cy) < r - margin_m
        return inside

    def sample_points(self, density_per_m2: float = 3.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Random points on every visible surface, as the scene's ground-truth 3D structure.

        Returns:
            ``(points (N, 3), materials (N,))``: world coordinates (m) and the material of each point.
            Points hidden inside a box or pillar (floor under a box, wall behind a pillar) are dropped.
        """
        rng = np.random.default_rng(seed)
        pts, mats = [], []

        def rectangle(origin, u, v, material):
            n = rng.poisson(density_per_m2 * np.linalg.norm(u) * np.linalg.norm(v))
            st = rng.random((n, 2))
            pts.append(origin + st[:, :1] * u + st[:, 1:] * v)
            mats.append(np.full(n, material))

        lo, hi = np.asarray(self.lower, float), np.asarray(self.upper, float)
        ex, ey, ez = np.diag(hi - lo)
        rectangle(lo, ex, ey, 0)
        rectangle(lo + ez, ex, ey, 1)
        rectangle(lo, ey, ez, 2)
        rectangle(lo + ex, ey, ez, 3)
        rectangle(lo, ex, ez, 4)
        rectangle(lo + ey, ex, ez, 5)
        for b, (blo, bhi) in enumerate(np.asarray(self.boxes, float)):
            bx, by, bz = np.diag(bhi - blo)
            m = ROOM_MATERIALS + b
            for origin, u, v in ((blo, bx, bz), (blo + by, bx, bz), (blo, by, bz), (blo + bx, by, bz), (blo + bz, bx, by)):
                rectangle(origin, u, v, m)
        height = hi[2] - lo[2]
        for p, (cx, cy, r) in enumerate(np.asarray(self.pillars, float)):
            n = rng.poisson(density_per_m2 * 2 * np.pi * r * height)
            ang, z = rng.random(n) * 2 * np.pi, lo[2] + rng.random(n) * height
            pts.append(np.stack([cx + r * np.cos(ang), cy + r * np.sin(ang), z], axis=1))
            mats.append(np.full(n, ROOM_MATERIALS + len(self.boxes) + p))
        points, materials = np.concatenate(pts), np.concatenate(mats)
        keep = ~self.inside_clutter(points)
        return points[keep], materials[keep]

    def world(self, density_per_m2: float = 3.0, seed: int = 0) -> World:
        """The scene as a :class:`~bcmocap.sim.world.World` of surface points (for the point simulator)."""
        points, _ = self.sample_points(density_per_m2, seed)
        return World(points, np.asarray(self.lower, float), np.asarray(self.upper, float))

    def to_dict(self) -> dict:
        """JSON-ready description (metres, RGB in [0, 1]; the finishes only where given)."""
        out = {
            "lower": np.asarray(self.lower).tolist(),
            "upper": np.asarray(self.upper).tolist(),
            "boxes": np.asarray(self.boxes).tolist(),
            "pillars": np.asarray(self.pillars).tolist(),
            "colors": np.asarray(self.colors).tolist(),
            "texture": dataclasses.asdict(self.texture),
            "materials": "0 floor, 1 ceiling, 2-5 walls x-, x+, y-, y+, then one per box, then one per pillar",
        }
        if self.has_finishes:
            out["finish_kinds"] = np.asarray(self.finish_kinds).tolist()
            out["finish_gains"] = np.asarray(self.finish_gains).tolist()
            out["tiles"] = np.asarray(self.tiles).tolist()
            out["finishes"] = (f"{NOISE} noise, {TILED} tiled, {BLANK} blank; "
                               "tiles: width, height (m), row shift, joint (m), faces")
        return out

    @classmethod
    def from_dict(cls, data: dict, where: str = "scene") -> TexturedScene:
        """Inverse of :meth:`to_dict` (``where`` names the file in error messages)."""
        try:
            return cls(
                lower=np.asarray(data["lower"], float),
                upper=np.asarray(data["upper"], float),
                boxes=np.asarray(data["boxes"], float).reshape(-1, 2, 3),
                pillars=np.asarray(data["pillars"], float).reshape(-1, 3),
                colors=np.asarray(data["colors"], float).reshape(-1, 3),
                texture=TextureParams(**data.get("texture", {})),
                finish_kinds=None if "finish_kinds" not in data else np.asarray(data["finish_kinds"], np.int64),
                finish_gains=None if "finish_gains" not in data else np.asarray(data["finish_gains"], float),
                tiles=None if "tiles" not in data else _tiles_with_faces(np.asarray(data["tiles"], float)),
            )
        except KeyError as err:
            raise ValueError(f"{where}: missing field {err}") from None
        except (TypeError, ValueError) as err:
            raise ValueError(f"{where}: {err}") from None

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)


def _hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    k = (np.array([5.0, 3.0, 1.0]) + h[:, None] * 6.0) % 6.0
    return v[:, None] - v[:, None] * s[:, None] * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def make_textured_scene(
    path_xy: np.ndarray,
    *,
    seed: int = 0,
    margin_m: float = 6.0,
    wall_height_m: float = 4.0,
    num_pillars: int = 8,
    num_boxes: int = 10,
    clearance_m: float = 1.5,
    texture: TextureParams | None = None,
) -> TexturedScene:
    """A textured room around a path, with boxes and pillars off the path (as :func:`make_world`).

    Args:
        path_xy: ``(T, 2)`` horizontal positions the subject (and the photographer) visit (m).
        seed: the same seed gives the same scene.
        margin_m, wall_height_m: room bounds, computed by :func:`make_world` itself so both agree.
        num_pillars, num_boxes: clutter, placed at least ``clearance_m`` from the path.
        texture: texture parameters (default: :class:`TextureParams` with ``seed``).
    """
    path_xy = np.asarray(path_xy, dtype=np.float64).reshape(-1, 2)
    bounds = make_world(path_xy, seed=seed, margin_m=margin_m, wall_height_m=wall_height_m, density_per_m2=0.0,
                        num_pillars=0, num_boxes=0)
    lo, hi = bounds.lower, bounds.upper
    rng = np.random.default_rng([seed, 0x5CE4E])

    def away_from_path(count: int) -> list[np.ndarray]:
        out = []
        for _ in range(1000 * max(count, 1)):
            if len(out) == count:
                break
            c = lo[:2] + 1.0 + rng.random(2) * (hi[:2] - lo[:2] - 2.0)
            if np.min(np.linalg.norm(path_xy - c, axis=1)) > clearance_m:
                out.append(c)
        return out

    boxes = []
    for c in away_from_path(num_boxes):
        size = rng.uniform(0.4, 1.2, 3)
        boxes.append([[c[0] - size[0] / 2, c[1] - size[1] / 2, 0.0], [c[0] + size[0] / 2, c[1] + size[1] / 2, size[2]]])
    pillars = [[c[0], c[1], rng.uniform(0.2, 0.4)] for c in away_from_path(num_pillars)]
    n = ROOM_MATERIALS + len(boxes) + len(pillars)
    hue = rng.random(n)
    sat = rng.uniform(0.15, 0.55, n)
    val = rng.uniform(0.65, 0.95, n)
    colors = _hsv_to_rgb(hue, sat, val)
    return TexturedScene(
        lower=np.asarray(lo, float),
        upper=np.asarray(hi, float),
        boxes=np.asarray(boxes, float).reshape(-1, 2, 3),
        pillars=np.asarray(pillars, float).reshape(-1, 3),
        colors=colors,
        texture=texture if texture is not None else TextureParams(seed=seed),
    )


def make_room(style: str, path_xy: np.ndarray, *, seed: int = 0, margin_m: float = 6.0,
              wall_height_m: float = 4.0) -> TexturedScene:
    """One of the studio's rooms around a path (the same style and seed give the same room).

    Args:
        style: "textured" (:func:`make_textured_scene` as it is), "sparse" (painted walls, ceiling and pillars
            of weak texture, the wall the path heads for blank, a grey concrete floor, 4 boxes and 2 pillars) or "repeated" (the textured room with a floor of 0.6 m tiles of 8 faces laid at
            random, a ceiling of identical 0.6 × 1.2 m panels, identical bricks on the wall the path heads for and
            a wall of identical 1.25 × 1.5 m windows behind: see :func:`finished_texture`).
        path_xy, seed, margin_m, wall_height_m: as :func:`make_textured_scene`'s.
    """
    if style not in ROOM_STYLES:
        raise ValueError(f"make_room: style must be one of {list(ROOM_STYLES)}, got {style!r}")
    bounds = {"seed": seed, "margin_m": margin_m, "wall_height_m": wall_height_m}
    if style == "textured":
        return make_textured_scene(path_xy, **bounds)
    ahead = _wall_ahead(np.asarray(path_xy, dtype=np.float64).reshape(-1, 2))
    if style == "sparse":
        # The texture's fine octaves stay (paint is weak by its gain, not blurred): with the texture cut to 6 cm and
        # coarser, as this room had before, the boxes lost their detail too and the reference photos verified 13
        # of 276 pairs, fewer than SfM needs in any room a user would film in.
        scene = make_textured_scene(path_xy, **bounds, num_pillars=2, num_boxes=4, texture=TextureParams(seed=seed))
        rng = np.random.default_rng([seed, 0x5BA125E])
        colors = np.array(scene.colors)
        paint = slice(0, ROOM_MATERIALS)
        colors[paint] = _hsv_to_rgb(rng.random(ROOM_MATERIALS), rng.uniform(0.03, 0.15, ROOM_MATERIALS),
                                    rng.uniform(0.8, 0.95, ROOM_MATERIALS))
        gains = np.ones(scene.num_materials)
        gains[paint] = [0.8, 0.15, 0.2, 0.2, 0.2, 0.2]  # a concrete floor; ceiling and walls: plaster and paint
        gains[ROOM_MATERIALS + len(scene.boxes):] = 0.4  # painted pillars; the boxes keep their texture
        kinds = np.full(scene.num_materials, NOISE)
        kinds[ahead] = BLANK
        tiles = np.tile([1.0, 1.0, 0.0, 0.0, 1.0], (scene.num_materials, 1))
        return dataclasses.replace(scene, colors=colors, finish_kinds=kinds, finish_gains=gains, tiles=tiles)
    scene = make_textured_scene(path_xy, **bounds)
    tiles = np.tile([1.0, 1.0, 0.0, 0.0, 1.0], (scene.num_materials, 1))
    # Sizes of real ones, so that no two surfaces share a lattice of periods (with the 0.5 m floor and ceiling
    # tiles, bricks and windows of powers of two this room had before, moving a camera 1 m along a wall mapped
    # every repeated surface onto itself, and fewer than 1 in 10 of the reference photos' verified pairs was
    # right); the floor's tiles come in faces, as printed porcelain does.
    tiles[0] = [0.6, 0.6, 0.0, 0.003, 8.0]  # porcelain floor tiles: 8 faces, laid at random
    tiles[1] = [0.6, 1.2, 0.0, 0.025, 1.0]  # ceiling panels in their grid, all alike
    tiles[ahead] = [0.225, 0.075, 0.5, 0.01, 1.0]  # brick bond (a brick and its mortar), all alike
    tiles[ahead ^ 1] = [1.25, 1.5, 0.0, 0.08, 1.0]  # windows in their frames, all alike
    kinds = np.full(scene.num_materials, NOISE)
    kinds[[0, 1, ahead, ahead ^ 1]] = TILED
    colors = np.array(scene.colors)
    colors[ahead] = [0.72, 0.40, 0.31]  # brick
    return dataclasses.replace(scene, colors=colors, finish_kinds=kinds, finish_gains=np.ones(scene.num_materials),
                               tiles=tiles)


def _tiles_with_faces(tiles: np.ndarray) -> np.ndarray:
    """``(M, 5)`` tiles from a scene file's rows (rows of 4, written before tiles had faces, have one face)."""
    tiles = tiles.reshape(len(tiles), -1) if tiles.size else tiles.reshape(0, 5)
    return np.column_stack([tiles, np.ones(len(tiles))]) if tiles.shape[1] == 4 else tiles


def _wall_ahead(path_xy: np.ndarray) -> int:
    """Material of the wall a path heads for (along its larger net displacement; the x+ wall for no displacement)."""
    step = path_xy[-1] - path_xy[0]
    axis = int(np.argmax(np.abs(step))) if np.abs(step).max() > 0.5 else 0
    return 2 + 2 * axis + int(step[axis] >= 0 or np.abs(step).max() <= 0.5)
