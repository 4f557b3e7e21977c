"""Tests for bcmocap.solver.block_banded against dense numpy linear algebra."""

import jax
import numpy as np
import pytest

from bcmocap.solver.block_banded import block_banded_dense, block_banded_matvec
from bcmocap.solver.block_banded import solve_block_banded as _solve

solve_block_banded = jax.jit(_solve)


def random_banded_spd(rng, w, d, bandwidth, ridge=0.1):
    """``(diag, bands, dense)`` of ``A = L Lᵀ + ridge I`` with ``L`` block lower-banded of bandwidth ``bandwidth``."""
    n = w * d
    lower = np.zeros((n, n))
    for t in range(w):
        for k in range(bandwidth + 1):
            if t - k >= 0:
                lower[t * d : (t + 1) * d, (t - k) * d : (t - k + 1) * d] = rng.normal(size=(d, d))
    dense = lower @ lower.T + ridge * np.eye(n)
    block = lambda t, s: dense[t * d : (t + 1) * d, s * d : (s + 1) * d]
    diag = np.stack([block(t, t) for t in range(w)])
    bands = tuple(np.array([block(t, t + k) for t in range(w - k)]).reshape(max(w - k, 0), d, d)
                  for k in range(1, bandwidth + 1))
    for t in range(w):  # outside the band the matrix really is zero
        for s in range(w):
            if abs(t - s) > bandwidth:
                assert not block(t, s).any()
    return diag, bands, dense


@pytest.mark.parametrize("w, bandwidth", [(1, 2), (2, 2), (6, 2), (7, 2), (7, 3), (9, 4), (5, 1), (5, 0), (1, 0)])
def test_solve_matches_dense_solve(w, bandwidth):
    """Windows that are and are not multiples of the bandwidth (identity padding), and bandwidth 1."""
    rng = np.random.default_rng(10 * w + bandwidth)
    d = 3
    diag, bands, dense = random_banded_spd(rng, w, d, bandwidth)
    rhs = rng.normal(size=(w, d))
    x = np.asarray(solve_block_banded(diag, bands, rhs))
    np.testing.assert_allclose(x.reshape(-1), np.linalg.solve(dense, rhs.reshape(-1)), rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("bandwidth", [0, 1, 3])
def test_matvec_and_dense_agree(bandwidth):
    rng = np.random.default_rng(bandwidth)
    w, d = 8, 2
    diag, bands, dense = random_banded_spd(rng, w, d, bandwidth)
    x = rng.normal(size=(w, d))
    np.testing.assert_allclose(np.asarray(block_banded_dense(diag, bands)), dense, atol=1e-12)
    np.testing.assert_allclose(np.asarray(block_banded_matvec(diag, bands, x)).reshape(-1), dense @ x.reshape(-1), atol=1e-10)


@pytest.mark.parametrize("bandwidth", [0, 2])
def test_indefinite_system_gives_nan(bandwidth):
    rng = np.random.default_rng(0)
    diag, bands, _ = random_banded_spd(rng, 6, 2, bandwidth)
    diag = diag.copy()
    diag[3] = -np.eye(2) * 100.0
    assert np.isnan(np.asarray(solve_block_banded(diag, bands, np.ones((6, 2))))).any()


@pytest.mark.parametrize("bandwidth", [0, 1, 2])
def test_several_right_hand_sides_share_one_solve(bandwidth):
    rng = np.random.default_rng(20 + bandwidth)
    diag, bands, dense = random_banded_spd(rng, 7, 3, bandwidth)
    rhs = rng.normal(size=(7, 3, 4))
    x = np.asarray(solve_block_banded(diag, bands, rhs))
    np.testing.assert_allclose(x.reshape(21, 4), np.linalg.solve(dense, rhs.reshape(21, 4)), rtol=1e-9, atol=1e-10)
