"""Per-frame weak-perspective cameras in the kinematic chain space (§3.3, Eqs. 22–25).

A weak-perspective camera is ``P = s (r₁ r₂)ᵀ`` (2 × 3) with ``r₁ ⊥ r₂`` unit rows: exactly the matrices
that satisfy Eq. 24 (equal row norms) and Eq. 25 (orthogonal rows). We keep it as ``s`` (pixels per model
unit) and the full rotation ``R = (r₁ r₂ r₃)ᵀ`` (``camera_from_model``: its third row is the viewing
direction), so the constraints hold by construction and the depth axis is available.

Eq. 22, ``min_P ‖Y − P B‖_F`` over weak-perspective ``P`` for bones ``Y = X′C`` (2 × b) and ``B`` (3 × b),
has no closed form (it is an orthographic Procrustes problem). We solve it by the classical EM
iteration: complete the missing depth row with the current camera's prediction ``s r₃ B``, solve the
full 3-D similarity Procrustes problem in closed form (SVD), repeat. Each step cannot increase the
reprojection error. Bones are translation-free, so no camera translation is needed.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import rotation_from_covariance

__all__ = ["WeakPerspectiveCameras", "fit_cameras", "initial_cameras", "reprojection_rms"]


class WeakPerspectiveCameras(eqx.Module):
    """Weak-perspective cameras, one per frame.

    Attributes:
        rotation: ``(..., F, 3, 3)`` ``camera_from_model`` rotations (rows r₁, r₂ image axes, r₃ depth).
        scale: ``(..., F)`` image units (pixels) per model unit (metres).
    """

    rotation: jax.Array
    scale: jax.Array

    def matrices(self) -> jax.Array:
        """``(..., F, 2, 3)`` projection matrices ``P = s (r₁ r₂)ᵀ`` (Eq. 23), satisfying Eqs. 24–25."""
        return self.scale[..., None, None] * self.rotation[..., :2, :]


def _procrustes_step(y, w, bones, rotation, scale):
    """One EM step of Eq. 22 for one frame: y (2, b), w (b,), bones (3, b)."""
    depth = scale * rotation[2] @ bones
    target = jnp.concatenate([y, depth[None]], axis=0)
    m = (target * w) @ bones.T
    r = rotation_from_covariance(m)
    rb = r[:2] @ bones
    den = jnp.sum(w * rb * rb)
    s = jnp.sum(w * y * rb) / jnp.where(den > 0, den, 1.0)
    ok = (den > 1e-300) & (s > 0) & (jnp.sum(w) > 0)
    return jnp.where(ok, r, rotation), jnp.where(ok, s, scale)


def _fit_frame(y, w, bones, rotation, scale, iterations: int):
    def body(_, carry):
        return _procrustes_step(y, w, bones, *carry)

    return jax.lax.fori_loop(0, iterations, body, (rotation, scale))


@functools.partial(jax.jit, static_argnames=("iterations",))
def fit_cameras(
    bones_2d: jax.Array,
    weights: jax.Array,
    bones_3d: jax.Array,
    cameras: WeakPerspectiveCameras,
    iterations: int = 20,
) -> WeakPerspectiveCameras:
    """Refine per-frame cameras for Eq. 22 (warm start from ``cameras``).

    Args:
        bones_2d: ``(F, 2, b)`` observed bones ``X′ C`` (pixels).
        weights: ``(F, b)`` 1 for observed bones, 0 for missing ones.
        bones_3d: ``(F, 3, b)`` or ``(3, b)`` model bones ``A S + B0`` (metres).
        cameras: current cameras (``F`` frames).
        iterations: EM steps per frame.

    Returns:
        Cameras with a reprojection error no larger than the input's; a frame without observed bones
        keeps its camera.
    """
    bones_3d = jnp.broadcast_to(bones_3d, (bones_2d.shape[0], 3, bones_2d.shape[-1]))
    fit = jax.vmap(lambda y, w, b, r, s: _fit_frame(y, w, b, r, s, iterations))
    r, s = fit(bones_2d, weights, bones_3d, cameras.rotation, cameras.scale)
    return WeakPerspectiveCameras(r, s)


def _start_rotations() -> np.ndarray:
    """The 24 rotations of the cube group: starting points that cover SO(3) within 62.8°."""
    out = []
    for perm in ((0, 1, 2), (1, 2, 0), (2, 0, 1), (1, 0, 2), (0, 2, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            m = np.zeros((3, 3))
            for row, col in enumerate(perm):
                m[row, col] = 1.0 - 2.0 * signs[row]
            if np.linalg.det(m) > 0:
                out.append(m)
    return np.stack(out)


START_ROTATIONS = _start_rotations()


@functools.partial(jax.jit, static_argnames=("iterations", "start_iterations"))
def initial_cameras(
    bones_2d: jax.Array,
    weights: jax.Array,
    bones_3d: jax.Array,
    iterations: int = 40,
    start_iterations: int = 10,
) -> WeakPerspectiveCameras:
    """Cameras for the initial bone configuration ``B0`` (``A = 0``), from 24 starts per frame.

    Eq. 22 has local minima (a body seen from the front or, mirrored, from the back); each frame runs
    ``start_iterations`` EM steps from each of 24 rotations, keeps the start with the lowest weighted
    reprojection error and refines it by ``iterations`` more steps.

    Args:
        bones_2d: ``(F, 2, b)`` observed bones (pixels).
        weights: ``(F, b)`` bone observation weights.
        bones_3d: ``(3, b)`` initial bone configuration ``B0`` (metres).
        iterations: EM steps for the best start.
        start_iterations: EM steps per start.
    """
    starts = jnp.asarray(START_ROTATIONS)
    f = bones_2d.shape[0]

    def per_start(rot):
        rb = rot[:2] @ bones_3d
        den = jnp.sum(weights[:, None, :] * rb * rb, axis=(1, 2))
        s0 = jnp.sum(weights[:, None, :] * bones_2d * rb, axis=(1, 2)) / jnp.where(den > 0, den, 1.0)
        s0 = jnp.where(s0 > 0, s0, jnp.abs(s0) + 1e-3)
        cams = WeakPerspectiveCameras(jnp.broadcast_to(rot, (f, 3, 3)), s0)
        cams = fit_cameras(bones_2d, weights, bones_3d, cams, start_iterations)
        res = bones_2d - jnp.einsum("fij,jb->fib", cams.matrices(), bones_3d)
        return cams, jnp.sum(weights[:, None, :] * res * res, axis=(1, 2))

    cams, cost = jax.vmap(per_start)(starts)  # leading axis: starts
    best = jnp.argmin(cost, axis=0)  # (F,)
    frames = jnp.arange(f)
    # A frame observing fewer than two bones has no camera of its own: borrow the nearest such frame's.
    valid = jnp.sum(weights > 0, axis=1) >= 2
    before = jax.lax.cummax(jnp.where(valid, frames, -1))
    after = jax.lax.cummin(jnp.where(valid, frames, f), reverse=True)
    use = jnp.where(before < 0, after, jnp.where((after < f) & (after - frames < frames - before), after, before))
    use = jnp.where(valid, frames, jnp.clip(use, 0, f - 1))
    cams = WeakPerspectiveCameras(cams.rotation[best[use], use], cams.scale[best[use], use])
    return fit_cameras(bones_2d, weights, bones_3d, cams, iterations)


def reprojection_rms(bones_2d, weights, bones_3d, cameras: WeakPerspectiveCameras) -> jax.Array:
    """Root-mean-square reprojection error of the observed bones (pixels per coordinate)."""
    bones_3d = jnp.broadcast_to(bones_3d, (bones_2d.shape[0], 3, bones_2d.shape[-1]))
    res = bones_2d - jnp.einsum("fij,fjb->fib", cameras.matrices(), bones_3d)
    n = jnp.maximum(2.0 * jnp.sum(weights), 1.0)
    return jnp.sqrt(jnp.sum(weights[:, None, :] * res * res) / n)
