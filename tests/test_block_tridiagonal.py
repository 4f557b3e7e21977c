"""Tests for bcmocap.solver.block_tridiagonal against dense numpy linear algebra."""

import jax
import numpy as np
import pytest

from bcmocap.solver.block_tridiagonal import block_tridiagonal_matvec
from bcmocap.solver.block_tridiagonal import solve_block_tridiagonal as _solve

# One compilation per shape, shared by the tests (eager scans would compile on every call).
solve_block_tridiagonal = jax.jit(_solve)


def random_spd_blocks(rng, w, d, ridge=0.1):
    """``(diag, upper, dense)`` of ``A = L Lᵀ + ridge I`` with ``L`` block lower bidiagonal (so A is block tridiagonal)."""
    n = w * d
    lower = np.zeros((n, n))
    for t in range(w):
        lower[t * d : (t + 1) * d, t * d : (t + 1) * d] = rng.normal(size=(d, d))
        if t > 0:
            lower[t * d : (t + 1) * d, (t - 1) * d : t * d] = rng.normal(size=(d, d))
    dense = lower @ lower.T + ridge * np.eye(n)
    diag = np.stack([dense[t * d : (t + 1) * d, t * d : (t + 1) * d] for t in range(w)])
    upper = np.array([dense[t * d : (t + 1) * d, (t + 1) * d : (t + 2) * d] for t in range(w - 1)]).reshape(w - 1, d, d)
    # Outside the tridiagonal band the matrix really is zero.
    for t in range(w):
        for s in range(w):
            if abs(t - s) > 1:
                assert not dense[t * d : (t + 1) * d, s * d : (s + 1) * d].any()
    return diag, upper, dense


@pytest.mark.parametrize("w", [1, 2, 5])
def test_solve_matches_dense_solve(w):
    rng = np.random.default_rng(w)
    d = 3
    diag, upper, dense = random_spd_blocks(rng, w, d)
    rhs = rng.normal(size=(w, d))
    x = np.asarray(solve_block_tridiagonal(diag, upper, rhs))
    assert x.shape == (w, d)
    ref = np.linalg.solve(dense, rhs.reshape(-1)).reshape(w, d)
    scale = np.linalg.cond(dense) * np.abs(ref).max()
    np.testing.assert_allclose(x, ref, atol=1e-13 * scale)
    np.testing.assert_allclose(dense @ x.reshape(-1), rhs.reshape(-1), atol=1e-10)


@pytest.mark.parametrize("w", [1, 2, 5])
def test_matvec_matches_dense_product_and_inverts_solve(w):
    rng = np.random.default_rng(10 + w)
    d = 3
    diag, upper, dense = random_spd_blocks(rng, w, d)
    x = rng.normal(size=(w, d))
    ax = np.asarray(block_tridiagonal_matvec(diag, upper, x))
    np.testing.assert_allclose(ax.reshape(-1), dense @ x.reshape(-1), atol=1e-12)
    np.testing.assert_allclose(solve_block_tridiagonal(diag, upper, ax), x, atol=1e-9)


def test_solve_is_accurate_on_an_ill_conditioned_system():
    # Strong coupling between frames (as smoothness terms with large weights give): κ ~ 1e8.
    rng = np.random.default_rng(20)
    w, d = 5, 3
    diag, upper, dense = random_spd_blocks(rng, w, d, ridge=1e-6)
    rhs = rng.normal(size=(w, d))
    x = np.asarray(solve_block_tridiagonal(diag, upper, rhs))
    residual = np.linalg.norm(dense @ x.reshape(-1) - rhs.reshape(-1)) / np.linalg.norm(rhs)
    assert residual < 1e-8


def test_indefinite_pivot_gives_nan_not_an_exception():
    w, d = 5, 3
    diag = np.tile(np.eye(3), (w, 1, 1))
    diag[2] = -np.eye(3)
    upper = np.zeros((w - 1, d, d))
    x = np.asarray(solve_block_tridiagonal(diag, upper, np.ones((w, d))))
    assert np.isnan(x).any()
