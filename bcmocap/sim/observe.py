"""Simulated feature measurements: what each body camera sees of the scene, frame by frame.

Visibility by the lens's field of view, the image bounds, range, and occlusion by the body (capsules
around the segments). Then 2D noise, outliers, unregistered camera-frames (whose point measurements are
replaced by 2D–2D matches with the previous frame, as the homography step of §4.1 leaves them), and
SfM-like noisy poses for the registered ones. Every frame draws its randomness from ``(seed, frame)``,
so any range of frames can be generated alone and always comes out the same.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import SE3, SO3, transform_points
from ..kinematics.fk import forward_kinematics
from ..kinematics.rig import Rig
from ..kinematics.skeleton import Motion, Skeleton


@dataclasses.dataclass(frozen=True)
class NoiseModel:
    """How measurements depart from the truth (defaults: the standard synthetic capture).

    Attributes:
        pixel_sigma: 2D noise σ (px). outlier_fraction: share of point measurements replaced by random pixels.
        unregistered_fraction: share of camera-frames registration misses (homography-only).
        rotation_sigma_deg, position_sigma_m: noise of registered camera poses (SfM-like).
        max_observations: point slots per camera-frame (N). max_matches: homography slots (M).
        min_range_m, max_range_m: distances at which features are detected.
    """

    pixel_sigma: float = 1.0
    outlier_fraction: float = 0.1
    unregistered_fraction: float = 0.05
    rotation_sigma_deg: float = 1.0
    position_sigma_m: float = 0.02
    max_observations: int = 330
    max_matches: int = 64
    min_range_m: float = 0.3
    max_range_m: float = 25.0


@dataclasses.dataclass(frozen=True)
class Capsule:
    """A body part for occlusion: a segment-fixed line from ``a`` to ``b`` (m) with a radius."""

    segment: int
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    radius: float


def body_capsules(skeleton: Skeleton) -> tuple[Capsule, ...]:
    """Capsules around the camera skeleton's segments (names of :data:`bcmocap.sim.motions.BODY_SEGMENTS`)."""
    radii = {"torso": 0.14, "head": 0.11, "upper_arm": 0.05, "forearm": 0.045, "hand": 0.04,
             "thigh": 0.08, "shin": 0.06, "foot": 0.05}
    caps = []
    idx = skeleton.index
    pelvis = idx("pelvis")
    caps.append(Capsule(pelvis, tuple(np.asarray(skeleton.offsets[idx("left_thigh")])),
                        tuple(np.asarray(skeleton.offsets[idx("right_thigh")])), 0.12))
    for j in range(1, skeleton.num_segments):
        name = skeleton.names[j]
        kind = name.split("_", 1)[-1] if "_" in name else name
        kids = skeleton.children(j)
        if kids:
            end = np.asarray(skeleton.offsets[kids[0]])
        elif kind == "head":
            end = np.array([0.0, 0.0, 0.22])
        elif kind == "hand":
            d = np.asarray(skeleton.offsets[j])
            end = 0.15 * d / max(np.linalg.norm(d), 1e-9)
        else:  # foot: toward the toes, roughly forward and down
            end = np.array([0.0, 0.0, -0.05])
        caps.append(Capsule(j, (0.0, 0.0, 0.0), tuple(end), radii.get(kind, 0.05)))
    return tuple(caps)


def segment_distance_squared(p1, q1, p2, q2):
    """Squared shortest distance between line segments ``[p1, q1]`` and ``[p2, q2]``.

    Args:
        p1, q1, p2, q2: ``(..., 3)`` end points (JAX or numpy; leading axes broadcast). A degenerate
            segment (equal ends) counts as its point.

    Returns:
        ``(...)`` squared distances (JAX array), e.g. to test a ray against a capsule of radius ``r``
        by ``d² < r²``.
    """
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = jnp.sum(d1 * d1, -1)
    e = jnp.maximum(jnp.sum(d2 * d2, -1), 1e-12)
    f = jnp.sum(d2 * r, -1)
    c = jnp.sum(d1 * r, -1)
    b = jnp.sum(d1 * d2, -1)
    denom = a * e - b * b
    s = jnp.where(denom > 1e-12, jnp.clip((b * f - c * e) / jnp.where(denom > 1e-12, denom, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / e
    a_safe = jnp.maximum(a, 1e-12)
    s = jnp.where(t < 0.0, jnp.clip(-c / a_safe, 0.0, 1.0), jnp.where(t > 1.0, jnp.clip((b - c) / a_safe, 0.0, 1.0), s))
    t = jnp.clip(t, 0.0, 1.0)
    diff = (p1 + d1 * s[..., None]) - (p2 + d2 * t[..., None])
    return jnp.sum(diff * diff, -1)


def _visibility(rig: Rig, points, cam_from_world, capsule_ends, radii, noise: NoiseModel):
    """Per camera: pixels ``(C, P, 2)`` and visibility ``(C, P)`` of all scene points at one frame.

    ``capsule_ends`` may have zero capsules: visibility by lens, image and range only.
    """
    p_cam = jax.vmap(lambda pose: transform_points(SE3(pose), points))(cam_from_world)  # (C, P, 3)
    uv, valid = jax.vmap(lambda cam, p: cam.project(p))(rig.intrinsics, p_cam)
    inside = jax.vmap(lambda cam, x: cam.in_image(x))(rig.intrinsics, uv)
    dist = jnp.linalg.norm(p_cam, axis=-1)
    visible = valid & inside & (dist > noise.min_range_m) & (dist < noise.max_range_m)
    centers = SE3(cam_from_world).inverse().translation()  # (C, 3)
    direction = (points[None] - centers[:, None]) / jnp.maximum(dist, 1e-9)[..., None]
    start = centers[:, None] + 0.05 * direction  # skip the camera's own mount surface
    occluded = jnp.zeros(visible.shape, bool)
    for k in range(capsule_ends.shape[0]):
        d2 = segment_distance_squared(start, points[None], capsule_ends[k, 0], capsule_ends[k, 1])
        occluded = occluded | (d2 < radii[k] ** 2)
    return uv, visible & ~occluded


class ObservationSimulator:
    """Generates :class:`~bcmocap.correspondences.Correspondences` rows for any range of frames.

    Args:
        skeleton, rig, motion: the ground truth (``motion`` over all T frames).
        points: ``(P, 3)`` scene points.
        noise: the measurement model.
        seed: base seed; frame t uses ``(seed, t)``.
    """

    def __init__(self, skeleton: Skeleton, rig: Rig, motion: Motion, points: np.ndarray, noise: NoiseModel, seed: int):
        self.skeleton, self.rig, self.motion, self.noise, self.seed = skeleton, rig, motion, noise, seed
        self.points = jnp.asarray(points)
        caps = body_capsules(skeleton)
        self._cap_segments = np.array([c.segment for c in caps])
        self._cap_local = jnp.asarray(np.array([[c.a, c.b] for c in caps]))
        self._radii = np.array([c.radius for c in caps])
        self._frames_fn = jax.jit(jax.vmap(self._frame))

    #: frames simulated per vectorised call (the last chunk is padded, so one compilation serves all)
    chunk = 16

    def _frame(self, frame_index, rotations, root_position):
        """Observations of frame t given the truth at frames (t−1, t) (arrays of shape (2, ...))."""
        noise, rig = self.noise, self.rig
        pose = Motion(root_position, rotations)
        world_from_segment = forward_kinematics(self.skeleton, pose)  # (2, J)
        world_from_camera = rig.world_from_camera(world_from_segment)  # (2, C)
        cam_from_world = world_from_camera.inverse().wxyz_xyz
        seg = SE3(world_from_segment.wxyz_xyz[1][self._cap_segments])
        ends = jnp.stack([seg @ self._cap_local[:, 0], seg @ self._cap_local[:, 1]], axis=1)  # (K, 2, 3)
        uv, visible = _visibility(rig, self.points, cam_from_world[1], ends, self._radii, noise)
        # Homography matches must also be seen at t-1; body occlusion is taken from frame t (it barely
        # changes in one frame, and the capsule test is the simulator's most expensive step).
        prev_uv, prev_visible = _visibility(rig, self.points, cam_from_world[0], ends[:0], self._radii[:0], noise)

        key = jax.random.fold_in(jax.random.PRNGKey(self.seed), frame_index)
        k_pick, k_noise, k_out, k_outpix, k_reg, k_rot, k_pos, k_hnoise = jax.random.split(key, 8)
        c, p = visible.shape
        n, m = noise.max_observations, noise.max_matches
        score = visible + 0.5 * jax.random.uniform(k_pick, (c, p))
        _, ids = jax.lax.top_k(score, n)  # (C, N): visible points first, in random order
        slot_visible = jnp.take_along_axis(visible, ids, axis=1)
        pix = jnp.take_along_axis(uv, ids[..., None], axis=1) + noise.pixel_sigma * jax.random.normal(k_noise, (c, n, 2))
        size = jnp.array([rig.intrinsics.width, rig.intrinsics.height], dtype=jnp.float64) - 1.0
        outlier = jax.random.uniform(k_out, (c, n)) < noise.outlier_fraction
        pix = jnp.where(outlier[..., None], jax.random.uniform(k_outpix, (c, n, 2)) * size, pix)
        registered = jax.random.uniform(k_reg, (c,)) >= noise.unregistered_fraction
        registered = registered | (frame_index == 0)  # frame 0 has no previous frame to match
        inside = jax.vmap(lambda cam, x: cam.in_image(x))(rig.intrinsics, pix)  # noise may push a few out
        use = slot_visible & inside & registered[:, None]
        point_ids = jnp.where(use, ids, -1).astype(jnp.int32)
        weights = jnp.where(use, 1.0 / noise.pixel_sigma**2, 0.0)
        pix = jnp.where(use[..., None], pix, 0.0)

        both = slot_visible & jnp.take_along_axis(prev_visible, ids, axis=1)
        order = jnp.argsort(~both, axis=1, stable=True)[:, :m]  # matched slots first
        h_ids = jnp.take_along_axis(ids, order, axis=1)
        h_ok = jnp.take_along_axis(both, order, axis=1) & ~registered[:, None]
        h_noise = noise.pixel_sigma * jax.random.normal(k_hnoise, (2, c, m, 2))
        h_pix = jnp.where(h_ok[..., None], jnp.take_along_axis(uv, h_ids[..., None], axis=1) + h_noise[0], 0.0)
        h_prev = jnp.where(h_ok[..., None], jnp.take_along_axis(prev_uv, h_ids[..., None], axis=1) + h_noise[1], 0.0)
        h_w = jnp.where(h_ok, 1.0 / noise.pixel_sigma**2, 0.0)

        rot_noise = jnp.deg2rad(noise.rotation_sigma_deg) * jax.random.normal(k_rot, (c, 3))
        pos_noise = noise.position_sigma_m * jax.random.normal(k_pos, (c, 3))
        true = SE3(world_from_camera.wxyz_xyz[1])
        noisy = SE3.from_rotation_and_translation(true.rotation() @ SO3.exp(rot_noise), true.translation() + pos_noise)
        return point_ids, pix, weights, h_pix, h_prev, h_w, noisy.wxyz_xyz, registered

    def frames(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Correspondence arrays for frames ``[start, stop)`` (keys as :class:`Correspondences` fields)."""
        if not 0 <= start < stop <= self.motion.num_frames:
            raise ValueError(f"frames [{start}, {stop}) outside the capture's {self.motion.num_frames} frames")
        rot = np.asarray(self.motion.rotations)
        pos = np.asarray(self.motion.root_position)
        keys = ("point_ids", "pixels", "weights", "homography_pixels", "homography_pixels_prev",
                "homography_weights", "world_from_camera", "registered")
        parts = []
        for first in range(start, stop, self.chunk):
            frames = np.minimum(np.arange(first, first + self.chunk), stop - 1)  # pad with the last frame
            pairs = np.stack([np.maximum(frames - 1, 0), frames], axis=1)  # (chunk, 2): frames t-1, t
            out = self._frames_fn(jnp.asarray(frames), jnp.asarray(rot[pairs]), jnp.asarray(pos[pairs]))
            parts.append([np.asarray(a)[: min(self.chunk, stop - first)] for a in out])
        return {k: np.concatenate([p[i] for p in parts]) for i, k in enumerate(keys)}
