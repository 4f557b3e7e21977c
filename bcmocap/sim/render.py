"""Ray-cast rendering of a :class:`~bcmocap.sim.scene.TexturedScene` through any camera model.

Every pixel's ray is computed once per camera with the model's own ``unproject`` (FOV, OpenCV fisheye,
pinhole: whatever :mod:`bcmocap.cameras` offers), since intrinsics are fixed. A frame then rotates the
rays into the world and intersects them with the scene's analytic surfaces (the inside of the room box,
boxes by the slab test, pillars as vertical cylinders) and with the body's capsules, keeps the nearest
hit and looks up the surface's procedural texture at the pixel's footprint (analytic anti-aliasing,
:func:`~bcmocap.sim.scene.surface_texture`). All of it is a few float32 vector operations per pixel,
jitted once per image size: a batch of frames is rendered band of rows by band of rows, each band
testing only the boxes and body capsules whose bounding spheres meet its cone of rays.

Performance notes (XLA:CPU). The intersection loop carries the nearest hit as one packed int32
(distance bits with the surface id in the low bits), ends in a division by a runtime 1 so that XLA
stores it instead of recomputing the loop inside every consumer, and the colour is packed into one
uint32 per pixel; carrying several arrays, or ``lax.optimization_barrier``, made XLA recompute the whole
loop per output (10x slower). Several samples per pixel (motion blur's sub-exposures, several rays) are
summed by a ``fori_loop`` whose step stores each sample's scalar shade (:func:`_shade_sum`): unrolled into
one fused loop, the samples' textures made a loop LLVM no longer vectorised (4 sub-exposures cost 20-25
plain renders instead of 4).

Time. A frame's pose is the pose at its timestamp. With ``motion_blur`` the image averages
``blur_samples`` renders spread over ``exposure_frames`` centred on the timestamp; with
``rolling_shutter`` row ``r`` of ``H`` is exposed at ``(r / (H - 1) - 1/2) * readout_frames`` frame
periods from the timestamp (the middle row at the timestamp), its camera pose interpolated between
frames (slerp and linear). The body's capsules follow the blur sub-samples but not the rows.

Sensor. A pixel's value (8-bit levels, linear in light) is the rendered radiance times ``vignetting``'s
fall-off (``1 − vignetting · (θ / θ_max)²`` with θ the ray's angle off the optical axis and θ_max the
largest in the image), times the frame's per-channel ``gains`` (exposure and white balance, see
:mod:`bcmocap.sim.exposure`), plus noise of standard deviation ``sqrt(noise_dn² + value · 255 /
full_scale_electrons)`` levels: read noise and photon shot noise of a sensor that collects
``full_scale_electrons`` electrons at level 255; then rounded and clipped to [0, 255].

Conventions: camera frame as OpenCV (x right, y down, z forward), world Z up, metres; images are
``(H, W, 3)`` uint8 RGB with pixel ``(u, v)`` at ``image[v, u]`` (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..cameras import CameraModel
from ..geometry import matrix_from_quat, slerp
from .observe import Capsule
from .scene import TexturedScene, TextureParams, finished_texture, surface_texture

__all__ = [
    "CameraRays",
    "RenderOptions",
    "Renderer",
    "camera_rays",
    "capsule_colors",
    "interpolate_poses",
    "vignette_map",
]

_F32 = jnp.float32
_FAR = np.float32(1e30)
_CONE_MARGIN = 0.02  # rad added to band cones: the pose changes a little within a rolling-shutter band
_ONE = np.int32(1)  # see _materialize
_BAND_PIXELS = 8192  # pixels per band of rows rendered in one pass (cache-sized intermediates)


@dataclasses.dataclass(frozen=True)
class RenderOptions:
    """How frames are rendered.

    Attributes:
        samples_per_pixel: rays per pixel, 1, 2 (diagonal pair) or 4 (rotated grid), averaged; geometric
            edges get smoother at proportional cost (textures are anti-aliased analytically anyway).
        motion_blur: average ``blur_samples`` renders over the exposure.
        blur_samples: sub-exposures per frame when ``motion_blur``.
        exposure_frames: shutter time as a fraction of the frame period (motion blur only).
        rolling_shutter: expose rows at successive times (see the module docstring).
        readout_frames: time from the first to the last row, in frame periods.
        noise_dn: standard deviation of the read noise in 8-bit levels (hash-based, deterministic).
        full_scale_electrons: electrons a pixel collects at level 255; > 0 adds photon shot noise (variance
            ``value · 255 / full_scale_electrons`` levels²); 0: none.
        vignetting: share of light lost at the image's most oblique ray (0: none; see the module docstring).
        light: direction towards the light (world frame), normalised; ambient: its complement's share.
    """

    samples_per_pixel: int = 1
    motion_blur: bool = False
    blur_samples: int = 4
    exposure_frames: float = 0.5
    rolling_shutter: bool = False
    readout_frames: float = 0.8
    noise_dn: float = 1.0
    full_scale_electrons: float = 0.0
    vignetting: float = 0.0
    light: tuple[float, float, float] = (0.35, 0.25, 0.9)
    ambient: float = 0.55

    def __post_init__(self):
        if self.samples_per_pixel not in (1, 2, 4):
            raise ValueError(f"RenderOptions.samples_per_pixel must be 1, 2 or 4, got {self.samples_per_pixel}")
        if self.blur_samples < 1:
            raise ValueError(f"RenderOptions.blur_samples must be >= 1, got {self.blur_samples}")
        if not 0.0 <= self.exposure_frames <= 1.0 or not 0.0 <= self.readout_frames <= 1.0:
            raise ValueError("RenderOptions.exposure_frames and readout_frames must lie in [0, 1] (frame periods)")
        if not self.noise_dn >= 0 or not self.full_scale_electrons >= 0:  # also refuses NaN
            raise ValueError(f"RenderOptions.noise_dn and full_scale_electrons must be >= 0, got {self.noise_dn} and "
                             f"{self.full_scale_electrons}")
        if not 0.0 <= self.vignetting < 1.0:
            raise ValueError(f"RenderOptions.vignetting must lie in [0, 1), got {self.vignetting}")

    @property
    def num_time_samples(self) -> int:
        return self.blur_samples if self.motion_blur else 1

    def time_offsets(self, height: int) -> np.ndarray:
        """``(S, R)`` offsets from the frame timestamp (frame periods) per sub-exposure and row.

        ``R`` is ``height`` with a rolling shutter and 1 otherwise (all rows at once).
        """
        s = self.num_time_samples
        blur = (np.arange(s) + 0.5) / s - 0.5 if s > 1 else np.zeros(1)
        blur = blur * self.exposure_frames
        if self.rolling_shutter:
            rows = (np.arange(height) / max(height - 1, 1) - 0.5) * self.readout_frames
        else:
            rows = np.zeros(1)
        return blur[:, None] + rows[None, :]


@dataclasses.dataclass(frozen=True)
class CameraRays:
    """A camera's pixel rays, computed once (intrinsics are fixed).

    Attributes:
        directions: ``(N, 3, H, W)`` float32 unit rays in the camera frame, ``N`` rays per pixel.
        pixel_angle: ``(H, W)`` float32 angle (rad) between a pixel's ray and its neighbours' (its size).
        valid: ``(H, W)`` bool, False where the pixel lies outside the model's image (rendered black).
        max_angle: largest angle (rad) between a valid ray and the optical axis.
    """

    directions: np.ndarray
    pixel_angle: np.ndarray
    valid: np.ndarray
    max_angle: float

    @property
    def height(self) -> int:
        return self.directions.shape[2]

    @property
    def width(self) -> int:
        return self.directions.shape[3]


_SUBPIXEL = {  # offsets (px) of the rays of a pixel: centre, diagonal pair, rotated grid
    1: [(0.0, 0.0)],
    2: [(-0.25, -0.25), (0.25, 0.25)],
    4: [(-0.375, -0.125), (0.125, -0.375), (0.375, 0.125), (-0.125, 0.375)],
}


def camera_rays(camera: CameraModel, samples_per_pixel: int = 1) -> CameraRays:
    """Rays of every pixel of a single camera (any model of :mod:`bcmocap.cameras`), via ``unproject``."""
    if camera.batch_shape != ():
        raise ValueError(f"camera_rays: expected a single camera, got batch shape {camera.batch_shape}")
    if samples_per_pixel not in _SUBPIXEL:
        raise ValueError(f"camera_rays: samples_per_pixel must be 1, 2 or 4, got {samples_per_pixel}")
    h, w = camera.height, camera.width
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    uv = np.stack([u, v], axis=-1)
    centre = np.asarray(camera.unproject(uv))
    back, ok = camera.project(centre)
    valid = np.asarray(ok) & (np.linalg.norm(np.asarray(back) - uv, axis=-1) < 1e-3)
    du = np.asarray(camera.unproject(uv + np.array([0.5, 0.0]))) - np.asarray(camera.unproject(uv - np.array([0.5, 0.0])))
    dv = np.asarray(camera.unproject(uv + np.array([0.0, 0.5]))) - np.asarray(camera.unproject(uv - np.array([0.0, 0.5])))
    pixel_angle = np.maximum(np.linalg.norm(du, axis=-1), np.linalg.norm(dv, axis=-1))
    dirs = [centre if (a, b) == (0.0, 0.0) else np.asarray(camera.unproject(uv + np.array([a, b])))
            for a, b in _SUBPIXEL[samples_per_pixel]]
    directions = np.stack([np.moveaxis(d, -1, 0) for d in dirs]).astype(np.float32)
    max_angle = float(np.arccos(np.clip(centre[..., 2][valid].min(), -1.0, 1.0))) if valid.any() else 0.0
    return CameraRays(directions, pixel_angle.astype(np.float32), valid, max_angle)


# ---------------------------------------------------------------------------------------------
# What the compiled renderer takes, grouped (made from a RenderOptions, a CameraRays and a batch of poses by
# Renderer). Fields marked static are part of the compiled code (a new value compiles again); the others are
# traced (any value runs the same compiled code).


@dataclasses.dataclass(frozen=True)
class _Appearance:
    """How surfaces look (static, hashable: an argument of the jitted :func:`_render_batch`).

    Attributes:
        texture: the scene's procedural texture (:attr:`~bcmocap.sim.scene.TexturedScene.texture`).
        light: unit direction towards the light, world frame (:attr:`RenderOptions.light` normalised).
        ambient: share of the light that comes from everywhere, in [0, 1] (:attr:`RenderOptions.ambient`).
    """

    texture: TextureParams
    light: tuple[float, float, float]
    ambient: float


class _Shader(eqx.Module):
    """Everything a ray's colour depends on besides the ray and the body (built inside the jitted functions).

    Attributes:
        scene: the scene's float32 arrays (:func:`_scene_arrays`: room bounds and boxes in m, pillars
            ``(x, y, radius)`` in m, material colours RGB in [0, 1]; with finishes ``finishes`` ``(M, 7)``: kind,
            gain, tile width, height, row shift, joint, faces: :func:`~bcmocap.sim.scene.finished_texture`).
        light: ``(3,)`` float32 unit direction towards the light (world frame).
        one: a runtime int32 1 (see :func:`_materialize`).
        texture: static: the procedural texture; ambient: static: the ambient share of the light, in [0, 1].
    """

    scene: dict
    light: jax.Array
    one: jax.Array
    texture: TextureParams = eqx.field(static=True)
    ambient: float = eqx.field(static=True)


class _Body(eqx.Module):
    """The body's capsules at one sub-exposure.

    Attributes:
        capsules: ``(K, 2, 3)`` end points (m, world frame); radii: ``(K,)`` m; colors: ``(K, 3)`` RGB in [0, 1].
    """

    capsules: jax.Array
    radii: jax.Array
    colors: jax.Array


class _Frames(eqx.Module):
    """A batch of frames to render (arguments of :func:`_render_batch`), or one frame of it (:func:`_render_rows`:
    the per-frame fields without their leading ``F`` axis).

    Attributes:
        rotations: ``(F, S, R, 3, 3)`` float32 ``world_from_camera`` rotations per frame, sub-exposure and row
            (``R`` = 1: all rows at once, or one per row).
        origins: ``(F, S, R, 3)`` float32 camera centres (m, world frame).
        capsules: ``(F, S, K, 2, 3)`` float32 body capsule end points (m, world frame).
        radii: ``(K,)`` float32 capsule radii (m); colors: ``(K, 3)`` float32 RGB in [0, 1] (shared by the frames).
        keys: ``(F,)`` uint32 seeds of each frame's sensor noise.
        gains: ``(F, 3)`` float32 per-channel gains (exposure times white balance; used when
            :attr:`_Sensor.photometric`).
    """

    rotations: jax.Array
    origins: jax.Array
    capsules: jax.Array
    radii: jax.Array
    colors: jax.Array
    keys: jax.Array
    gains: jax.Array


class _Sensor(eqx.Module):
    """How radiance becomes 8-bit levels (made from :class:`RenderOptions`; see the module docstring's Sensor).

    Attributes:
        noise_dn: float32 standard deviation of the read noise (8-bit levels); traced (one compilation for any
            level; zero adds exactly 0).
        shot_scale: float32 ``255 / full_scale_electrons``: the photon shot noise's variance per level
            (levels² per level); traced.
        photometric: static: apply the vignetting map and the frames' gains. Without it the code is the plain
            render's (the same bytes as before these existed).
        shot: static: add shot noise.
    """

    noise_dn: jax.Array
    shot_scale: jax.Array
    photometric: bool = eqx.field(static=True)
    shot: bool = eqx.field(static=True)


class _CameraPixels(eqx.Module):
    """A camera's per-pixel arrays, padded to ``Hp`` rows (a multiple of ``rows``), on the device once.

    Attributes:
        rays: ``(N, 3, Hp, W)`` float32 unit rays (camera frame), ``N`` per pixel.
        pixel_angle: ``(Hp, W)`` float32 size of a pixel (rad); valid: ``(Hp, W)`` bool, False outside the image.
        vignette: ``(Hp, W)`` float32 share of light reaching each pixel (:func:`vignette_map`).
        cones: ``(Hp / rows, 4)`` float32 per band of rows, the cone holding its rays (unit axis, camera frame;
            half angle, rad).
        rows: static: rows per band (the image is rendered band by band).
    """

    rays: jax.Array
    pixel_angle: jax.Array
    valid: jax.Array
    vignette: jax.Array
    cones: jax.Array
    rows: int = eqx.field(static=True)


class _Band(eqx.Module):
    """One band of ``h`` rows of a camera's pixels, and what its rays may meet in the frames of a batch.

    Attributes:
        rays: ``(N, 3, h, W)``; pixel_angle, valid, vignette: ``(h, W)`` (as in :class:`_CameraPixels`).
        row0: int32, its first row in the image.
        box_active, capsule_active: ``(B,)``, ``(K,)`` bool: the boxes and capsules to test (see :func:`_band_flags`).
    """

    rays: jax.Array
    pixel_angle: jax.Array
    valid: jax.Array
    vignette: jax.Array
    row0: jax.Array
    box_active: jax.Array
    capsule_active: jax.Array


# ---------------------------------------------------------------------------------------------
# Ray casting (float32, one sub-exposure of one frame; origins and rotations per row: (R, ...) with
# R = 1 or H, broadcast against the (H, W) pixel arrays).


def _scene_arrays(scene: TexturedScene) -> dict:
    arrays = {
        "lower": jnp.asarray(scene.lower, _F32),
        "upper": jnp.asarray(scene.upper, _F32),
        "boxes": jnp.asarray(scene.boxes, _F32).reshape(-1, 2, 3),
        "pillars": jnp.asarray(scene.pillars, _F32).reshape(-1, 3),
        "colors": jnp.asarray(scene.colors, _F32).reshape(-1, 3),
    }
    if scene.has_finishes:  # a key of its own: a scene without finishes compiles (and renders) as before them
        arrays["finishes"] = jnp.asarray(np.column_stack([scene.finish_kinds, scene.finish_gains, scene.tiles]), _F32)
    return arrays


def _world_rays(rays: jax.Array, rotation: jax.Array) -> tuple[jax.Array, ...]:
    """World directions (3 arrays (H, W)) of camera rays (3, H, W) under per-row rotations (R, 3, 3)."""
    r = [[rotation[:, i, j][:, None] for j in range(3)] for i in range(3)]
    return tuple(r[i][0] * rays[0] + r[i][1] * rays[1] + r[i][2] * rays[2] for i in range(3))


def _pack(t: jax.Array, ident, bits: int) -> jax.Array:
    """Distance and identity in one int32 whose order is the order of ``t`` (for ``t > 0``).

    The ``bits`` low mantissa bits of ``t`` give way to ``ident``: the nearest hit is then one integer
    ``min``, so the whole intersection loop is a single fused chain with one output. (Carrying distance,
    surface and normal as separate arrays made XLA recompute the chain once per output, 10x slower.)
    """
    return (jax.lax.bitcast_convert_type(t, jnp.int32) & jnp.int32(~((1 << bits) - 1))) | jnp.asarray(ident, jnp.int32)


def _unpack(key: jax.Array, bits: int) -> tuple[jax.Array, jax.Array]:
    """Inverse of :func:`_pack`: ``(t, ident)`` (``t`` to 2^-(23 - bits) relative precision)."""
    mask = (1 << bits) - 1
    return jax.lax.bitcast_convert_type(key & jnp.int32(~mask), _F32), key & jnp.int32(mask)


def _scene_bits(num_materials: int) -> int:
    bits = max(1, math.ceil(math.log2(4 * num_materials)))
    if bits > 10:
        raise ValueError(f"the renderer supports up to 256 materials (room, boxes, pillars); the scene has {num_materials}")
    return bits


def _trace_scene(scene: dict, d: tuple, o: tuple, box_active: jax.Array | None = None) -> jax.Array:
    """Nearest scene hit as a packed key of ``t`` and ``4 * material + kind``.

    ``kind`` is 0, 1 or 2 for a face whose normal lies along x, y or z and 3 for a pillar.
    ``box_active`` ``(B,)`` skips boxes (a real branch outside vmap).
    """
    boxes, pillars = scene["boxes"], scene["pillars"]
    bits = _scene_bits(6 + boxes.shape[0] + pillars.shape[0])
    inv = [1.0 / jnp.where(jnp.abs(c) < 1e-12, jnp.where(c < 0, _F32(-1e-12), _F32(1e-12)), c) for c in d]
    key = None
    # Inside the room box: the exit distance along each axis; the nearest is the wall, floor or ceiling hit.
    # Room materials: floor 0, ceiling 1, walls 2 + 2 * axis + (hit on the upper side).
    for i in range(3):
        exit_ = jnp.maximum(jnp.maximum((scene["lower"][i] - o[i]) * inv[i], (scene["upper"][i] - o[i]) * inv[i]), 1e-6)
        upper = (d[i] > 0).astype(jnp.int32)
        material = upper if i == 2 else 2 + 2 * i + upper
        k = _pack(exit_, 4 * material + i, bits)
        key = k if key is None else jnp.minimum(key, k)
    def box(b, key):
        near, far = [], []
        for i in range(3):
            t1 = (boxes[b, 0, i] - o[i]) * inv[i]
            t2 = (boxes[b, 1, i] - o[i]) * inv[i]
            near.append(jnp.minimum(t1, t2))
            far.append(jnp.maximum(t1, t2))
        t_in = jnp.maximum(jnp.maximum(near[0], near[1]), near[2])
        t_out = jnp.minimum(jnp.minimum(far[0], far[1]), far[2])
        axis = jnp.where(near[0] >= jnp.maximum(near[1], near[2]), 0, jnp.where(near[1] >= near[2], 1, 2))
        hit = (t_in > 0) & (t_in <= t_out)
        return jnp.where(hit, jnp.minimum(key, _pack(t_in, 4 * (6 + b) + axis, bits)), key)

    for b in range(boxes.shape[0]):
        key = box(b, key) if box_active is None else jax.lax.cond(box_active[b], functools.partial(box, b), lambda x: x, key)
    a = d[0] * d[0] + d[1] * d[1]
    inv_a = 1.0 / jnp.maximum(a, 1e-12)
    for p in range(pillars.shape[0]):
        ox, oy = o[0] - pillars[p, 0], o[1] - pillars[p, 1]
        half_b = ox * d[0] + oy * d[1]
        c = ox * ox + oy * oy - pillars[p, 2] ** 2
        disc = half_b * half_b - a * c
        t_hit = (-half_b - jnp.sqrt(jnp.maximum(disc, 0.0))) * inv_a
        hit = (disc > 0) & (t_hit > 0)
        key = jnp.where(hit, jnp.minimum(key, _pack(t_hit, 4 * (6 + boxes.shape[0] + p) + 3, bits)), key)
    return key


def _capsule_bits(num_capsules: int) -> int:
    return max(1, math.ceil(math.log2(max(num_capsules, 2))))


def _trace_capsules(capsules: jax.Array, radii: jax.Array, d: tuple, o: tuple, active: jax.Array | None = None) -> jax.Array:
    """Nearest capsule entry as a packed key of ``t`` and the capsule index (Quilez's ray-capsule test).

    Where no capsule is hit ``t`` is 1e30. A ray starting inside a capsule (a camera on its own
    segment's surface) does not hit it. ``active`` ``(K,)`` skips capsules (a real branch outside vmap).
    """
    bits = _capsule_bits(capsules.shape[0])
    key = jnp.full(jnp.broadcast_shapes(d[0].shape, o[0].shape), _pack(jnp.asarray(_FAR), 0, bits), jnp.int32)

    def dot(v):
        return d[0] * v[0] + d[1] * v[1] + d[2] * v[2]

    def test(k, key):
        a, b, r = capsules[k, 0], capsules[k, 1], radii[k]
        ba = [b[i] - a[i] for i in range(3)]
        oa = [o[i] - a[i] for i in range(3)]
        ob = [o[i] - b[i] for i in range(3)]
        baba = ba[0] * ba[0] + ba[1] * ba[1] + ba[2] * ba[2]
        baoa = ba[0] * oa[0] + ba[1] * oa[1] + ba[2] * oa[2]
        oaoa = oa[0] * oa[0] + oa[1] * oa[1] + oa[2] * oa[2]
        obob = ob[0] * ob[0] + ob[1] * ob[1] + ob[2] * ob[2]
        bard, rdoa, rdob = dot(ba), dot(oa), dot(ob)
        qa = baba - bard * bard
        qb = baba * rdoa - baoa * bard
        qc = baba * oaoa - baoa * baoa - r * r * baba
        h = qb * qb - qa * qc
        t_side = (-qb - jnp.sqrt(jnp.maximum(h, 0.0))) / jnp.maximum(qa, 1e-12)
        y = baoa + t_side * bard
        low = y <= 0
        rdoc = jnp.where(low, rdoa, rdob)
        hc = rdoc * rdoc - (jnp.where(low, oaoa, obob) - r * r)
        t_cap = -rdoc - jnp.sqrt(jnp.maximum(hc, 0.0))
        t_hit = jnp.where((y > 0) & (y < baba), t_side, jnp.where(hc > 0, t_cap, -1.0))
        hit = (h >= 0) & (t_hit > 0)
        return jnp.where(hit, jnp.minimum(key, _pack(t_hit, k, bits)), key)

    for k in range(capsules.shape[0]):
        key = test(k, key) if active is None else jax.lax.cond(active[k], functools.partial(test, k), lambda x: x, key)
    return key


def _materialize(key: jax.Array, one: jax.Array) -> jax.Array:
    """``key`` unchanged, computed once and stored rather than re-derived inside each consumer.

    XLA:CPU fuses cheap element-wise chains into every consumer (the intersection loop would run once
    per use of its result) but stores the result of an operation it deems expensive when it has several
    users. Integer division is one (float division by a runtime 1.0 is rewritten as a multiplication,
    and ``lax.optimization_barrier`` did not survive the CPU pipeline), so divide by a runtime 1.
    """
    return jax.lax.div(key, one)


def _select(index: jax.Array, table: jax.Array) -> list[jax.Array]:
    """``table[index]`` column by column, as a chain of selects (a gather would end the fused loop)."""
    out = [jnp.full(index.shape, table[0, c]) for c in range(table.shape[1])]
    for k in range(1, table.shape[0]):
        hit = index == k
        out = [jnp.where(hit, table[k, c], out[c]) for c in range(table.shape[1])]
    return out


def _shade_terms(shader: _Shader, d, o, pixel_angle, body: _Body, box_active=None, capsule_active=None) -> tuple:
    """The pieces of a pixel's colour, each ``(H, W)``: ``(material, shade, t, body)``.

    ``d``, ``o``: the rays' world directions and origins (3 arrays each); ``pixel_angle`` ``(H, W)`` rad;
    ``box_active``, ``capsule_active``: the boxes and capsules to test (None: all).

    ``material`` indexes the scene's colours and ``shade`` scales it, ``t`` is the distance to the scene;
    ``body`` is None without capsules, else ``(hit, k, body_shade, t_body)``: where ``hit`` the pixel shows
    capsule ``k``'s colour times ``body_shade`` at distance ``t_body``. Both intersection keys are stored
    (:func:`_materialize`): ``material``, ``t``, ``k``, ``t_body`` are cheap to re-derive from them.
    """
    scene, texture, light, ambient, one = shader.scene, shader.texture, shader.light, shader.ambient, shader.one
    capsules, radii = body.capsules, body.radii
    num_boxes, num_pillars = scene["boxes"].shape[0], scene["pillars"].shape[0]
    t, ident = _unpack(_materialize(_trace_scene(scene, d, o, box_active), one), _scene_bits(6 + num_boxes + num_pillars))
    material, kind = ident >> 2, ident & 3
    p = [o[i] + t * d[i] for i in range(3)]
    is_pillar = kind == 3
    if num_pillars:
        cx, cy, radius = _select(jnp.clip(material - 6 - num_boxes, 0, num_pillars - 1), scene["pillars"])
    else:
        cx, cy, radius = jnp.zeros_like(t), jnp.zeros_like(t), jnp.ones_like(t)
    # Normals facing the camera: -sign(d) along the face axis; radial on pillars.
    nx = jnp.where(is_pillar, (p[0] - cx) / radius, jnp.where(kind == 0, -jnp.sign(d[0]), 0.0))
    ny = jnp.where(is_pillar, (p[1] - cy) / radius, jnp.where(kind == 1, -jnp.sign(d[1]), 0.0))
    nz = jnp.where(kind == 2, -jnp.sign(d[2]), 0.0)
    cos_view = jnp.abs(nx * d[0] + ny * d[1] + nz * d[2])
    lit = ambient + (1.0 - ambient) * jnp.maximum(nx * light[0] + ny * light[1] + nz * light[2], 0.0)
    u = jnp.where(kind == 0, p[1], jnp.where(is_pillar, jnp.arctan2(p[1] - cy, p[0] - cx) * radius, p[0]))
    v = jnp.where(kind == 2, p[1], p[2])
    footprint = t * pixel_angle / jnp.sqrt(jnp.maximum(cos_view, 0.05))
    if "finishes" in scene:  # (M, 7): kind, gain, tile width, height, row shift, joint, faces
        finish = _select(material, scene["finishes"])
        grey = finished_texture(u, v, material, footprint, texture, finish[0], finish[1], tuple(finish[2:]))
    else:
        grey = surface_texture(u, v, material, footprint, texture)
    shade = (0.15 + 0.85 * grey) * lit
    if not capsules.shape[0]:
        return material, shade, t, None
    t_body, k = _unpack(_materialize(_trace_capsules(capsules, radii, d, o, capsule_active), one),
                        _capsule_bits(capsules.shape[0]))
    body = t_body < t
    q = [o[i] + t_body * d[i] for i in range(3)]
    ends = jnp.concatenate([capsules[:, 0], capsules[:, 1] - capsules[:, 0]], axis=1)  # (K, 6)
    sel = _select(k, ends)
    a, ab = sel[0:3], sel[3:6]
    s = sum((q[i] - a[i]) * ab[i] for i in range(3)) / jnp.maximum(sum(ab[i] * ab[i] for i in range(3)), 1e-12)
    s = jnp.clip(s, 0.0, 1.0)
    n = [q[i] - a[i] - s * ab[i] for i in range(3)]
    n_len = jnp.sqrt(jnp.maximum(n[0] * n[0] + n[1] * n[1] + n[2] * n[2], 1e-12))
    facing = jnp.abs(n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) / n_len
    body_shade = 0.35 + 0.65 * facing
    return material, shade, t, (body, k, body_shade, t_body)


def _shade(shader: _Shader, d, o, pixel_angle, body: _Body, box_active=None,
           capsule_active=None) -> tuple[list[jax.Array], jax.Array]:
    """``([r, g, b], depth)``: colour in [0, 1] and distance along the ray, each ``(H, W)``, one ray per pixel
    (arguments as :func:`_shade_terms`'s).

    Written as one chain of element-wise operations from rays to colour, with no gather or reduction,
    so that XLA compiles it into a single loop over pixels (every intermediate computed once).
    """
    material, shade, t, hit_body = _shade_terms(shader, d, o, pixel_angle, body, box_active, capsule_active)
    rgb = [c * shade for c in _select(material, shader.scene["colors"])]
    depth = t
    if hit_body is not None:
        hit, k, body_shade, t_body = hit_body
        color = _select(k, body.colors)
        rgb = [jnp.where(hit, color[c] * body_shade, rgb[c]) for c in range(3)]
        depth = jnp.where(hit, t_body, t)
    return rgb, depth


def _materialize_f32(x: jax.Array, one: jax.Array) -> jax.Array:
    """:func:`_materialize` for float32 (through its bits: the same value, stored)."""
    return jax.lax.bitcast_convert_type(_materialize(jax.lax.bitcast_convert_type(x, jnp.int32), one), _F32)


def _shade_sum(shader: _Shader, band: _Band, frame: _Frames) -> list[jax.Array]:
    """Sum of the colours ``[r, g, b]`` ``(h, W)`` of all the band's rays (``(N, 3, h, W)``) at all sub-exposures
    of one frame.

    Sub-exposure ``s`` and ray ``n`` are summed in the order ``s * N + n`` (the order of a plain double
    loop), by a ``fori_loop``. One step stores the intersection keys and the pixel's scalar shade (surface
    or body), then adds its colour (a table entry) times that shade: each colour is the same product as
    in :func:`_shade` and the sums the same, so the images are those of unrolled loops (up to float
    rounding: about 1e-5 of the bytes differ by a level), but XLA compiles one small vectorised step instead
    of a fused loop holding every sample's texture (5-8x slower per sample, and a long compilation).
    """
    rays, pixel_angle, box_active, capsule_active = band.rays, band.pixel_angle, band.box_active, band.capsule_active
    rotations, origins, capsules = frame.rotations, frame.origins, frame.capsules
    num_rays = rays.shape[0]
    num_samples = rotations.shape[0] * num_rays

    def step(i, acc):
        s, n = i // num_rays, i % num_rays
        o = tuple(jax.lax.dynamic_index_in_dim(origins, s, keepdims=False)[:, j][:, None] for j in range(3))
        rot = jax.lax.dynamic_index_in_dim(rotations, s, keepdims=False)
        ray = rays[0] if num_rays == 1 else jax.lax.dynamic_index_in_dim(rays, n, keepdims=False)
        caps = jax.lax.dynamic_index_in_dim(capsules, s, keepdims=False)
        d = _world_rays(ray, rot)
        material, shade, _, body = _shade_terms(shader, d, o, pixel_angle, _Body(caps, frame.radii, frame.colors),
                                                box_active, capsule_active)
        color = _select(material, shader.scene["colors"])
        if body is not None:
            hit, k, body_shade, _ = body
            shade = jnp.where(hit, body_shade, shade)
            color = [jnp.where(hit, a, b) for a, b in zip(_select(k, frame.colors), color)]
        shade = _materialize_f32(shade, shader.one)
        return tuple(acc[c] + color[c] * shade for c in range(3))

    zero = jnp.zeros(pixel_angle.shape, _F32)
    return list(jax.lax.fori_loop(0, num_samples, step, (zero, zero, zero)))


def _in_cone(centres: jax.Array, bounds: jax.Array, rotation: jax.Array, origin: jax.Array, axis: jax.Array,
             half_angle: jax.Array) -> jax.Array:
    """Which spheres (centres ``(N, 3)``, radii ``(N,)``, world) may meet a cone of camera rays.

    The cone has its apex at the camera centre ``origin``, axis ``axis`` (camera frame) and half angle
    ``half_angle`` (rad); ``rotation`` is world_from_camera.
    """
    rel = (centres - origin) @ rotation  # camera frame
    dist = jnp.sqrt(jnp.sum(rel * rel, axis=-1))
    safe = jnp.maximum(dist, 1e-6)
    angle = jnp.arccos(jnp.clip(rel @ axis / safe, -1.0, 1.0))
    return (dist <= bounds) | (angle <= half_angle + jnp.arcsin(jnp.clip(bounds / safe, 0.0, 1.0)) + _CONE_MARGIN)


def _band_flags(scene, cone, rotations, origins, capsules, radii):
    """``(box_active (B,), capsule_active (K,))``: which boxes and capsules may be seen in a band.

    Args:
        cone: ``(4,)`` axis (camera frame) and half angle of the band's rays.
        rotations: ``(F, S, r, 3, 3)``, origins ``(F, S, r, 3)``, capsules ``(F, S, K, 2, 3)`` for the
            frames of a batch; the union over frames and sub-exposures is returned.
    """
    middle = rotations.shape[2] // 2
    rot = rotations[:, :, middle].reshape(-1, 3, 3)
    org = origins[:, :, middle].reshape(-1, 3)
    box_centre = 0.5 * (scene["boxes"][:, 0] + scene["boxes"][:, 1])
    box_bound = 0.5 * jnp.sqrt(jnp.sum((scene["boxes"][:, 1] - scene["boxes"][:, 0]) ** 2, axis=-1))
    caps = capsules.reshape(capsules.shape[0] * capsules.shape[1], *capsules.shape[2:])
    cap_centre = 0.5 * (caps[:, :, 0] + caps[:, :, 1])
    cap_bound = 0.5 * jnp.sqrt(jnp.sum((caps[:, :, 1] - caps[:, :, 0]) ** 2, axis=-1)) + radii
    boxes = jax.vmap(lambda r, o: _in_cone(box_centre, box_bound, r, o, cone[:3], cone[3]))(rot, org)
    capsules_seen = jax.vmap(lambda r, o, c, b: _in_cone(c, b, r, o, cone[:3], cone[3]))(rot, org, cap_centre, cap_bound)
    return boxes.any(axis=0), capsules_seen.any(axis=0)


def _render_rows(shader: _Shader, sensor: _Sensor, band: _Band, frame: _Frames) -> jax.Array:
    """A band of rows of one frame → uint8 ``(h, W, 3)``.

    Args:
        shader: the scene and its lighting; sensor: noise, and whether to apply the band's ``vignette`` and the
            frame's ``gains``.
        band: the band's rays and pixel arrays, its first row and the boxes and capsules to test.
        frame: one frame: rotations ``(S, r, 3, 3)``, origins ``(S, r, 3)`` with ``r`` = 1 (all rows) or ``h``
            (per row), capsules ``(S, K, 2, 3)``, its noise ``keys`` (a scalar) and ``gains`` ``(3,)``.

    The channels are packed into one uint32 per pixel so that the band is one fused loop.
    """
    rays, pixel_angle, rotations, origins = band.rays, band.pixel_angle, frame.rotations, frame.origins
    noise_dn, shot_scale, photometric, shot = sensor.noise_dn, sensor.shot_scale, sensor.photometric, sensor.shot
    valid, vignette, row0, key, gains = band.valid, band.vignette, band.row0, frame.keys, frame.gains
    width = rays.shape[-1]
    if rotations.shape[0] * rays.shape[0] == 1:  # one ray per pixel, one exposure: a single fused loop
        o = tuple(origins[0, :, i][:, None] for i in range(3))
        acc, _ = _shade(shader, _world_rays(rays[0], rotations[0]), o, pixel_angle,
                        _Body(frame.capsules[0], frame.radii, frame.colors), band.box_active, band.capsule_active)
    else:
        acc = _shade_sum(shader, band, frame)
    scale = 255.0 / (rotations.shape[0] * rays.shape[0])
    h = pixel_angle.shape[0]
    packed = jnp.zeros(pixel_angle.shape, jnp.uint32)
    for c in range(3):
        value = acc[c] * scale
        if photometric:
            value = value * (vignette * gains[c])
        # Sensor noise: noise_dn is traced (one compilation for any level); zero adds exactly 0.
        row = jnp.arange(h, dtype=jnp.uint32)[:, None] + row0.astype(jnp.uint32)
        idx = (row * jnp.uint32(width) + jnp.arange(width, dtype=jnp.uint32)[None, :]) * jnp.uint32(3) + jnp.uint32(c)
        n1 = _hash_uniform(idx, key)
        n2 = _hash_uniform(idx, key ^ jnp.uint32(0x68E31DA4))
        sigma = jnp.sqrt(noise_dn * noise_dn + jnp.maximum(value, 0.0) * shot_scale) if shot else noise_dn
        value = value + (n1 + n2 - 1.0) * (sigma * math.sqrt(6.0))
        value = jnp.where(valid, jnp.clip(jnp.round(value), 0.0, 255.0), 0.0)
        packed = packed | (value.astype(jnp.uint32) << jnp.uint32(8 * c))
    return jax.lax.bitcast_convert_type(packed, jnp.uint8)[..., :3]


def _hash_uniform(idx: jax.Array, key: jax.Array) -> jax.Array:
    h = idx * jnp.uint32(0x9E3779B1) + key * jnp.uint32(0x85EBCA77)
    h = h ^ (h >> 16)
    h = h * jnp.uint32(0x7FEB352D)
    h = h ^ (h >> 15)
    h = h * jnp.uint32(0x846CA68B)
    h = h ^ (h >> 16)
    return (h >> 8).astype(_F32) * _F32(1.0 / (1 << 24))


@functools.partial(jax.jit, static_argnames=("appearance",))
def _render_batch(scene: dict, one, pixels: _CameraPixels, frames: _Frames, sensor: _Sensor, *,
                  appearance: _Appearance):
    """Frames ``(F, Hp, W, 3)`` uint8 from a camera's pixels padded to ``Hp`` rows, a multiple of ``pixels.rows``.

    ``scene``: :func:`_scene_arrays`; ``one``: a runtime int32 1 (:func:`_materialize`).

    The image is rendered band by band of ``rows`` rows (``lax.map``), all frames of the batch at once
    (``vmap``): the few arrays XLA stores between its fused loops stay in cache, and a band skips the
    boxes and capsules outside its cone of rays (``pixels.cones`` ``(bands, 4)``) in every frame of the batch
    (a real branch: the flags are shared by the vmapped frames).
    """
    shader = _Shader(scene, jnp.asarray(appearance.light, _F32), one, appearance.texture, appearance.ambient)
    rays, pixel_angle, valid, vignette, cones, rows = (pixels.rays, pixels.pixel_angle, pixels.valid, pixels.vignette,
                                                       pixels.cones, pixels.rows)
    rotations, origins, capsules, radii = frames.rotations, frames.origins, frames.capsules, frames.radii
    n, _, hp, w = rays.shape
    bands = hp // rows
    per_row = rotations.shape[2] != 1
    band_rays = rays.reshape(n, 3, bands, rows, w).transpose(2, 0, 1, 3, 4)
    band_angle = pixel_angle.reshape(bands, rows, w)
    band_valid = valid.reshape(bands, rows, w)
    band_vignette = vignette.reshape(bands, rows, w)
    row0 = jnp.arange(bands, dtype=jnp.int32) * rows
    if per_row:
        f, s_ = rotations.shape[:2]
        band_rot = rotations.reshape(f, s_, bands, rows, 3, 3).transpose(2, 0, 1, 3, 4, 5)
        band_org = origins.reshape(f, s_, bands, rows, 3).transpose(2, 0, 1, 3, 4)
    else:
        band_rot = jnp.broadcast_to(rotations, (bands, *rotations.shape))
        band_org = jnp.broadcast_to(origins, (bands, *origins.shape))

    def band(args):
        b_rays, b_angle, b_valid, b_vignette, b_row0, cone, rot, org = args
        box_active, capsule_active = _band_flags(scene, cone, rot, org, capsules, radii)
        strip = _Band(b_rays, b_angle, b_valid, b_vignette, b_row0, box_active, capsule_active)
        return jax.vmap(lambda r, o, c, k, g: _render_rows(shader, sensor, strip,
                                                           _Frames(r, o, c, radii, frames.colors, k, g)))(
            rot, org, capsules, frames.keys, frames.gains)

    out = jax.lax.map(band, (band_rays, band_angle, band_valid, band_vignette, row0, cones, band_rot, band_org))
    return out.transpose(1, 0, 2, 3, 4).reshape(-1, hp, w, 3)


@jax.jit
def _depth(scene, rays, rotation, origin, capsules, radii, one):
    o = tuple(origin[i][None, None] for i in range(3))
    d = _world_rays(rays, rotation[None])
    shader = _Shader(scene, jnp.zeros(3, _F32), one, TextureParams(octaves=1), 1.0)
    _, depth = _shade(shader, d, o, jnp.ones(rays.shape[1:], _F32),
                      _Body(capsules, radii, jnp.ones((capsules.shape[0], 3), _F32)))
    if capsules.shape[0]:
        t_body, _ = _unpack(_trace_capsules(capsules, radii, d, o), _capsule_bits(capsules.shape[0]))
        return depth, t_body <= depth
    return depth, jnp.zeros(depth.shape, bool)


# ---------------------------------------------------------------------------------------------
# Poses over time (numpy, float64).


def _matrix(q: np.ndarray) -> np.ndarray:
    return np.asarray(matrix_from_quat(q))


def interpolate_poses(wxyz_xyz: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses at fractional frame indices, held at the first and last frame.

    Args:
        wxyz_xyz: ``(T, 7)`` poses (``world_from_camera``) at integer frames.
        times: ``(...)`` fractional frame indices.

    Returns:
        ``(rotations (..., 3, 3), translations (..., 3))`` (slerp and linear interpolation).
    """
    poses = np.asarray(wxyz_xyz, np.float64)
    n = poses.shape[0]
    tau = np.clip(np.asarray(times, np.float64), 0.0, n - 1)
    k0 = np.minimum(np.floor(tau).astype(int), n - 1)
    k1 = np.minimum(k0 + 1, n - 1)
    a = tau - k0
    q = slerp(poses[k0, :4], poses[k1, :4], a)
    x = poses[k0, 4:] * (1 - a[..., None]) + poses[k1, 4:] * a[..., None]
    return _matrix(q), x


def _interpolate_points(points: np.ndarray, times: np.ndarray) -> np.ndarray:
    """``points`` ``(T, ...)`` linearly interpolated at fractional frames ``times`` ``(...)``."""
    n = points.shape[0]
    tau = np.clip(np.asarray(times, np.float64), 0.0, n - 1)
    k0 = np.minimum(np.floor(tau).astype(int), n - 1)
    k1 = np.minimum(k0 + 1, n - 1)
    a = (tau - k0).reshape(tau.shape + (1,) * (points.ndim - 1))
    return points[k0] * (1 - a) + points[k1] * a


#: The subject's skin, trousers and shirt (RGB in [0, 1]).
SUBJECT_PALETTE = ((0.80, 0.62, 0.50), (0.22, 0.24, 0.30), (0.30, 0.42, 0.62))


def capsule_colors(capsules: tuple[Capsule, ...], names: tuple[str, ...],
                   palette: tuple = SUBJECT_PALETTE) -> np.ndarray:
    """``(K, 3)`` RGB clothing colours: skin for head and hands, a shirt on the trunk and arms, trousers.

    ``palette``: the skin, trousers and shirt colours (RGB in [0, 1]; default :data:`SUBJECT_PALETTE`).
    """
    skin, trousers, shirt = palette
    out = []
    for c in capsules:
        name = names[c.segment]
        if name == "head" or name.endswith("hand"):
            out.append(skin)
        elif name.endswith(("thigh", "shin", "foot")) or name == "pelvis":
            out.append(trousers)
        else:
            out.append(shirt)
    return np.asarray(out, np.float64)


def vignette_map(rays: CameraRays, vignetting: float) -> np.ndarray:
    """``(H, W)`` float32 share of light reaching each pixel: ``1 − vignetting · (θ / θ_max)²`` (1 outside the image).

    θ is the angle between the pixel's ray and the optical axis, θ_max the largest one in the image.
    """
    z = np.clip(np.asarray(rays.directions[0, 2], np.float64), -1.0, 1.0)
    theta = np.arccos(z) / max(rays.max_angle, 1e-9)
    return np.where(rays.valid, 1.0 - vignetting * np.minimum(theta, 1.0) ** 2, 1.0).astype(np.float32)


def _band_cones(rays: CameraRays, rows: int) -> np.ndarray:
    """``(bands, 4)``: per band of ``rows`` rows, a cone (unit axis, half angle in rad) holding its rays."""
    dirs = np.asarray(rays.directions, np.float64)  # (N, 3, H, W)
    h = rays.height
    out = []
    for first in range(0, h + (-h % rows), rows):
        band = dirs[:, :, first: min(first + rows, h)].transpose(1, 0, 2, 3).reshape(3, -1)
        valid = rays.valid[first: min(first + rows, h)]
        ok = np.broadcast_to(valid, dirs.shape[:1] + valid.shape).ravel()
        if band.shape[1] == 0 or not ok.any():
            out.append([0.0, 0.0, 1.0, -1.0])  # no ray: nothing can be seen
            continue
        band = band[:, ok]
        axis = band.sum(axis=1)
        axis = axis / max(np.linalg.norm(axis), 1e-12)
        half = np.arccos(np.clip(axis @ band, -1.0, 1.0)).max() + float(rays.pixel_angle.max())
        out.append([*axis, half])
    return np.asarray(out, np.float32)


class Renderer:
    """Renders frames of one camera (its rays are computed once).

    Args:
        scene: the textured scene.
        camera: a single camera model (FOV, OpenCV fisheye, pinhole).
        options: sampling, motion blur, rolling shutter, noise.
    """

    def __init__(self, scene: TexturedScene, camera: CameraModel, options: RenderOptions = RenderOptions()):
        self.scene, self.camera, self.options = scene, camera, options
        self.rays = camera_rays(camera, options.samples_per_pixel)
        self._scene = _scene_arrays(scene)
        h, w = self.rays.height, self.rays.width
        self._rows = max(1, min(h, _BAND_PIXELS // w))
        pad = -h % self._rows
        edge = ((0, 0),) * 2 + ((0, pad), (0, 0))
        self.vignette = vignette_map(self.rays, options.vignetting)
        self._pixels = _CameraPixels(
            rays=jnp.asarray(np.pad(self.rays.directions, edge, mode="edge")),
            pixel_angle=jnp.asarray(np.pad(self.rays.pixel_angle, ((0, pad), (0, 0)), mode="edge")),
            valid=jnp.asarray(np.pad(self.rays.valid, ((0, pad), (0, 0)))),
            vignette=jnp.asarray(np.pad(self.vignette, ((0, pad), (0, 0)), mode="edge")),
            cones=jnp.asarray(_band_cones(self.rays, self._rows)),
            rows=self._rows,
        )
        self._dev_rays_first = jnp.asarray(self.rays.directions[0])
        self._pad = pad

    def poses_at(self, world_from_camera: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per sub-exposure and row poses of ``frames`` ``(B,)``: rotations ``(B, S, R, 3, 3)``, origins ``(B, S, R, 3)``."""
        times = np.asarray(frames, np.float64)[:, None, None] + self.options.time_offsets(self.rays.height)[None]
        return interpolate_poses(world_from_camera, times)

    def capsules_at(self, capsule_ends: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Capsule end points ``(B, S, K, 2, 3)`` at the sub-exposures of ``frames`` (from ``(T, K, 2, 3)``)."""
        offsets = self.options.time_offsets(self.rays.height)[:, :1]  # capsules follow sub-exposures only
        times = np.asarray(frames, np.float64)[:, None] + offsets[None, :, 0]
        return _interpolate_points(np.asarray(capsule_ends, np.float64), times)

    def render(self, rotations: np.ndarray, origins: np.ndarray, capsules: np.ndarray | None = None,
               radii: np.ndarray | None = None, colors: np.ndarray | None = None, keys: np.ndarray | None = None,
               gains: np.ndarray | None = None) -> np.ndarray:
        """Render a batch of frames.

        Args:
            rotations: ``(B, S, R, 3, 3)`` ``world_from_camera`` rotations per frame, sub-exposure and row
                (``R`` = 1 or H); origins ``(B, S, R, 3)`` camera centres (m).
            capsules: ``(B, S, K, 2, 3)`` body capsule end points (m) or None for no body; radii ``(K,)`` m;
                colors ``(K, 3)`` RGB in [0, 1].
            keys: ``(B,)`` integers seeding each frame's sensor noise (default: zeros).
            gains: ``(B, 3)`` per-frame RGB gains (exposure times white balance; default: none).

        Returns:
            ``(B, H, W, 3)`` uint8 RGB images.
        """
        rotations = np.asarray(rotations, np.float32)
        origins = np.asarray(origins, np.float32)
        b, s, rows = rotations.shape[:3]
        if rotations.shape[3:] != (3, 3) or origins.shape != (b, s, rows, 3) or rows not in (1, self.rays.height):
            raise ValueError(
                f"Renderer.render: expected rotations (B, S, R, 3, 3) and origins (B, S, R, 3) with R = 1 or "
                f"{self.rays.height}; got {rotations.shape} and {origins.shape}"
            )
        if capsules is None or np.shape(capsules)[2] == 0:
            caps = np.zeros((b, s, 0, 2, 3), np.float32)
            radii = np.zeros(0, np.float32)
            colors = np.zeros((0, 3), np.float32)
        else:
            caps = np.asarray(capsules, np.float32)
            if caps.shape[:2] != (b, s) or caps.shape[3:] != (2, 3):
                raise ValueError(f"Renderer.render: capsules must have shape ({b}, {s}, K, 2, 3), got {caps.shape}")
            radii = np.asarray(radii, np.float32)
            colors = np.full((caps.shape[2], 3), 0.5, np.float32) if colors is None else np.asarray(colors, np.float32)
        keys = np.zeros(b, np.uint32) if keys is None else (np.asarray(keys, np.int64) & 0xFFFFFFFF).astype(np.uint32)
        photometric = gains is not None or self.options.vignetting > 0
        gains = np.ones((b, 3), np.float32) if gains is None else np.asarray(gains, np.float32)
        if gains.shape != (b, 3):
            raise ValueError(f"Renderer.render: gains must have shape ({b}, 3), got {gains.shape}")
        if rows > 1 and self._pad:
            rotations = np.pad(rotations, ((0, 0), (0, 0), (0, self._pad), (0, 0), (0, 0)), mode="edge")
            origins = np.pad(origins, ((0, 0), (0, 0), (0, self._pad), (0, 0)), mode="edge")
        opt = self.options
        shot = opt.full_scale_electrons > 0
        sensor = _Sensor(np.float32(opt.noise_dn), np.float32(255.0 / opt.full_scale_electrons if shot else 0.0),
                         photometric=photometric, shot=shot)
        appearance = _Appearance(self.scene.texture,
                                 tuple(float(x) for x in np.asarray(opt.light) / np.linalg.norm(opt.light)),
                                 float(opt.ambient))
        frames = _Frames(rotations, origins, caps, radii, colors, keys, gains)
        out = _render_batch(self._scene, _ONE, self._pixels, frames, sensor, appearance=appearance)
        return np.asarray(out)[:, : self.rays.height]

    def depth(self, rotation: np.ndarray, origin: np.ndarray, capsules: np.ndarray | None = None,
              radii: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Distance along each pixel's (first) ray to the nearest surface ``(H, W)`` and the body mask ``(H, W)``.

        Args:
            rotation: ``(3, 3)`` ``world_from_camera`` rotation; origin ``(3,)`` camera centre (m).
            capsules: ``(K, 2, 3)`` body capsules or None; radii ``(K,)``.
        """
        caps = np.zeros((0, 2, 3), np.float32) if capsules is None else np.asarray(capsules, np.float32)
        rad = np.zeros(0, np.float32) if radii is None else np.asarray(radii, np.float32)
        t, body = _depth(self._scene, self._dev_rays_first, jnp.asarray(rotation, _F32), jnp.asarray(origin, _F32),
                         jnp.asarray(caps), jnp.asarray(rad), _ONE)
        return np.asarray(t), np.asarray(body)
