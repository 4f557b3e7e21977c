"""Solve symmetric positive-definite block-tridiagonal systems by a block Cholesky scan.

Frames of a window are coupled only through pair terms (smoothness, homography transfer), so the
Gauss–Newton matrix JᵀJ is block tridiagonal with one ``D × D`` block per frame: a scan over frames
solves it in O(W D³) instead of O((W D)³).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve


def solve_block_tridiagonal(diag: jax.Array, upper: jax.Array, rhs: jax.Array) -> jax.Array:
    """Solve ``A x = b`` for SPD block-tridiagonal ``A``.

    Args:
        diag: ``(W, D, D)`` diagonal blocks ``A[t, t]``.
        upper: ``(W-1, D, D)`` super-diagonal blocks ``A[t, t+1]`` (``A[t+1, t] = upper[t]ᵀ``).
        rhs: ``(W, D)``, or ``(W, D, K)`` for ``K`` right-hand sides sharing one factorisation.

    Returns:
        The solution, shaped as ``rhs``; NaN if a pivot block is not positive definite.
    """
    if rhs.shape[0] == 1:
        return cho_solve((jnp.linalg.cholesky(diag[0]), True), rhs[0])[None]
    def forward(carry, inputs):
        prev_chol, prev_z = carry
        a_tt, b_prev, rhs_t = inputs
        # Schur complement S_t = A_tt − B_{t−1}ᵀ S_{t−1}⁻¹ B_{t−1}; z_t = b_t − B_{t−1}ᵀ S_{t−1}⁻¹ z_{t−1}.
        s_inv_b = cho_solve((prev_chol, True), b_prev)
        s_inv_z = cho_solve((prev_chol, True), prev_z)
        schur = a_tt - b_prev.T @ s_inv_b
        chol = jnp.linalg.cholesky(0.5 * (schur + schur.T))
        z = rhs_t - b_prev.T @ s_inv_z
        return (chol, z), (chol, z)

    first_chol = jnp.linalg.cholesky(diag[0])
    _, (chols, zs) = jax.lax.scan(forward, (first_chol, rhs[0]), (diag[1:], upper, rhs[1:]))
    chols = jnp.concatenate([first_chol[None], chols], axis=0)
    zs = jnp.concatenate([rhs[:1], zs], axis=0)

    def backward(x_next, inputs):
        chol, z, b_t = inputs  # b_t = A[t, t+1]
        x = cho_solve((chol, True), z - b_t @ x_next)
        return x, x

    x_last = cho_solve((chols[-1], True), zs[-1])
    _, xs = jax.lax.scan(backward, x_last, (chols[:-1], zs[:-1], upper), reverse=True)
    return jnp.concatenate([xs, x_last[None]], axis=0)


def block_tridiagonal_matvec(diag: jax.Array, upper: jax.Array, x: jax.Array) -> jax.Array:
    """``A x`` for the block-tridiagonal ``A`` of :func:`solve_block_tridiagonal` (for tests and models)."""
    out = jnp.einsum("tij,tj->ti", diag, x)
    out = out.at[:-1].add(jnp.einsum("tij,tj->ti", upper, x[1:]))
    return out.at[1:].add(jnp.einsum("tji,tj->ti", upper, x[:-1]))
