"""3-D errors of monocular reconstructions: the paper's 3DPE (after rigid alignment) and MPJPE (Eq. 26)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..geometry import rotation_from_covariance

__all__ = ["aligned_joint_distances", "aligned_joint_errors", "joint_errors"]


def _check(estimate, truth):
    estimate, truth = jnp.asarray(estimate), jnp.asarray(truth)
    if estimate.shape != truth.shape or estimate.ndim < 2 or estimate.shape[-1] != 3:
        raise ValueError(f"expected estimate and truth of one shape (..., J, 3), got {estimate.shape} and {truth.shape}")
    return estimate, truth


def joint_errors(estimate, truth) -> jax.Array:
    """``(...)`` MPJPE (Eq. 26): mean joint distance after matching centroids (no rotation), per pose.

    Use it on poses expressed in the same frame (e.g. camera-frame reconstructions against camera-frame
    truth): weak perspective loses the absolute depth, hence the centroid alignment.
    """
    estimate, truth = _check(estimate, truth)
    e = estimate - estimate.mean(axis=-2, keepdims=True)
    t = truth - truth.mean(axis=-2, keepdims=True)
    return jnp.linalg.norm(e - t, axis=-1).mean(axis=-1)


def aligned_joint_distances(estimate, truth, scale: bool = False) -> jax.Array:
    """``(..., J)`` distance of each joint after the best rigid alignment of each pose to the truth.

    Args:
        estimate: ``(..., J, 3)`` poses.
        truth: ``(..., J, 3)`` ground truth, same shape.
        scale: also fit a scale (similarity alignment) instead of a rigid one.
    """
    estimate, truth = _check(estimate, truth)
    e = estimate - estimate.mean(axis=-2, keepdims=True)
    t = truth - truth.mean(axis=-2, keepdims=True)
    m = jnp.swapaxes(t, -1, -2) @ e  # Σ t eᵀ, (..., 3, 3)
    r = rotation_from_covariance(m)  # truth_from_estimate
    aligned = e @ jnp.swapaxes(r, -1, -2)
    if scale:
        k = jnp.trace(jnp.swapaxes(r, -1, -2) @ m, axis1=-2, axis2=-1) / jnp.maximum(jnp.sum(e * e, axis=(-1, -2)), 1e-300)
        aligned = aligned * k[..., None, None]
    return jnp.linalg.norm(aligned - t, axis=-1)


def aligned_joint_errors(estimate, truth, scale: bool = False) -> jax.Array:
    """``(...)`` 3DPE: mean joint distance after the best rigid alignment of each pose to the truth
    (the mean over joints of :func:`aligned_joint_distances`; same arguments)."""
    return aligned_joint_distances(estimate, truth, scale).mean(axis=-1)
