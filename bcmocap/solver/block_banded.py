"""Symmetric positive-definite block-banded systems: terms over up to ``B + 1`` consecutive frames.

A term that reads frames ``t−B … t`` couples frames up to ``B`` apart, so the Gauss–Newton matrix of a
window has ``D × D`` blocks ``A[t, t+k]`` for ``k ≤ B`` only. Grouping ``B`` consecutive frames into one
super-block of size ``B·D`` makes it block tridiagonal, which :func:`solve_block_tridiagonal` solves by
a Cholesky scan in O(W B² D³); for ``B = 1`` (the paper's terms) nothing is regrouped, and for ``B = 0``
(independent frames, e.g. joint centres or one frame's IK) the blocks are factorised all at once.

The bands are a tuple: ``bands[k-1]`` ``(W-k, D, D)`` holds ``A[t, t+k]``; ``A[t+k, t]`` is its transpose.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve

from .block_tridiagonal import block_tridiagonal_matvec, solve_block_tridiagonal


def solve_block_banded(diag: jax.Array, bands: tuple[jax.Array, ...], rhs: jax.Array) -> jax.Array:
    """Solve ``A x = b`` for SPD block-banded ``A``.

    Args:
        diag: ``(W, D, D)`` diagonal blocks; bands: ``B`` arrays, ``bands[k-1]`` ``(W-k, D, D)`` = ``A[t, t+k]``.
        rhs: ``(W, D)``, or ``(W, D, K)`` for ``K`` right-hand sides sharing one factorisation.

    Returns:
        The solution, shaped as ``rhs``; NaN if a pivot is not positive definite.
    """
    if not bands:  # block diagonal: independent frames
        return _solve_block_diagonal(diag, rhs)
    if len(bands) <= 1:
        upper = bands[0] if bands else jnp.zeros((max(diag.shape[0] - 1, 0), *diag.shape[1:]), diag.dtype)
        return solve_block_tridiagonal(diag, upper, rhs)
    w, d, *k = rhs.shape
    super_diag, super_upper, padded = _super_blocks(diag, bands, len(bands))
    x = solve_block_tridiagonal(super_diag, super_upper, _pad(rhs, padded - w).reshape(-1, len(bands) * d, *k))
    return x.reshape(padded, d, *k)[:w]


def _solve_block_diagonal(diag: jax.Array, rhs: jax.Array) -> jax.Array:
    """``x[t] = diag[t]⁻¹ rhs[t]`` by batched Cholesky; NaN where a block is not positive definite."""
    chol = jnp.linalg.cholesky(diag)
    return jax.vmap(lambda c, b: cho_solve((c, True), b))(chol, rhs)


def block_banded_matvec(diag: jax.Array, bands: tuple[jax.Array, ...], x: jax.Array) -> jax.Array:
    """``A x`` for the block-banded ``A`` of :func:`solve_block_banded`; ``x`` ``(W, D)``."""
    if not bands:
        return jnp.einsum("tij,tj->ti", diag, x)
    if len(bands) == 1:
        return block_tridiagonal_matvec(diag, bands[0], x)
    out = jnp.einsum("tij,tj->ti", diag, x)
    for k, band in enumerate(bands, start=1):
        out = out.at[:-k].add(jnp.einsum("tij,tj->ti", band, x[k:]))
        out = out.at[k:].add(jnp.einsum("tji,tj->ti", band, x[:-k]))
    return out


def block_banded_dense(diag: jax.Array, bands: tuple[jax.Array, ...]) -> jax.Array:
    """The ``(W·D, W·D)`` matrix (for tests and small problems)."""
    w, d, _ = diag.shape
    dense = jnp.zeros((w, d, w, d), diag.dtype)
    t = jnp.arange(w)
    dense = dense.at[t, :, t, :].set(diag)
    for k, band in enumerate(bands, start=1):
        rows = t[: w - k]
        dense = dense.at[rows, :, rows + k, :].set(band)
        dense = dense.at[rows + k, :, rows, :].set(jnp.swapaxes(band, -1, -2))
    return dense.reshape(w * d, w * d)


def _pad(a: jax.Array, count: int, fill: jax.Array | None = None) -> jax.Array:
    """``a`` with ``count`` more rows along axis 0: zeros, or copies of ``fill``."""
    if count <= 0:
        return a
    extra = jnp.zeros((count, *a.shape[1:]), a.dtype) if fill is None else jnp.broadcast_to(fill, (count, *a.shape[1:]))
    return jnp.concatenate([a, extra], axis=0)


def _super_blocks(diag: jax.Array, bands: tuple[jax.Array, ...], b: int):
    """Regroup into ``M = ⌈W/B⌉`` super-blocks of ``B`` frames: ``(M, BD, BD)`` diagonal and ``(M-1, BD, BD)``
    upper blocks of the same matrix, padded with identity frames (whose solution is 0)."""
    w, d, _ = diag.shape
    padded = -(-w // b) * b
    m = padded // b
    diag_p = _pad(diag, padded - w, jnp.eye(d, dtype=diag.dtype)).reshape(m, b, d, d)
    band_p = [_pad(band, padded - band.shape[0]).reshape(m, b, d, d) for band in bands]  # band_p[k-1][m, i] = A[mB+i, mB+i+k]
    zero = jnp.zeros((m, d, d), diag.dtype)
    # Inside super-block m: A[mB+i, mB+j] = bands[j-i-1][mB+i] for j > i.
    inside = [[None] * b for _ in range(b)]
    for i in range(b):
        inside[i][i] = diag_p[:, i]
        for j in range(i + 1, b):
            inside[i][j] = band_p[j - i - 1][:, i]
            inside[j][i] = jnp.swapaxes(band_p[j - i - 1][:, i], -1, -2)
    # Between super-blocks m and m+1: A[mB+i, (m+1)B+j] = bands[B+j-i-1][mB+i] when B+j-i ≤ B, i.e. j ≤ i.
    between = [[band_p[b + j - i - 1][:, i] if j <= i else zero for j in range(b)] for i in range(b)]
    assemble = lambda grid: jnp.concatenate([jnp.concatenate(row, axis=-1) for row in grid], axis=-2)
    return assemble(inside), assemble(between)[:-1], padded
