"""Tests for bcmocap.solver.levenberg_marquardt, the one Levenberg–Marquardt, on small problems with their
structure (one dense block; frames bordered by static variables) against scipy.optimize.least_squares."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import least_squares

from bcmocap.solver.levenberg_marquardt import NormalEquations, levenberg_marquardt


def _curve_residual(y, data):
    """``a·exp(b x) + c − v`` for ``y = [[a, b, c]]`` (one frame of three variables)."""
    a, b, c = y[0]
    x, v = data
    return a * jnp.exp(b * x) + c - v


def _dense_system(data, y):
    jac = jax.jacfwd(_curve_residual)(y, data)[:, 0]
    r = _curve_residual(y, data)
    return NormalEquations.dense(jac.T @ jac, jac.T @ r)


def _curve_data(seed):
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 2.0, 40)
    v = 1.5 * np.exp(-1.2 * x) + 0.3 + 0.01 * rng.normal(size=x.shape)
    return jnp.asarray(x), jnp.asarray(v)


@jax.jit
def _fit_curve(data, y0):
    return levenberg_marquardt(_curve_residual, eqx.Partial(_dense_system, data), y0, data, rtol=1e-10, atol=1e-12)


def _scipy_curve(data, y0):
    x, v = (np.asarray(a) for a in data)
    fun = lambda p: p[0] * np.exp(p[1] * x) + p[2] - v  # noqa: E731
    return least_squares(fun, np.asarray(y0)[0], xtol=1e-14, ftol=1e-14, gtol=1e-14).x


def test_dense_problem_reaches_scipys_minimum_and_reports_convergence():
    data, y0 = _curve_data(0), jnp.array([[1.0, -0.5, 0.0]])
    y, report = _fit_curve(data, y0)
    np.testing.assert_allclose(np.asarray(y)[0], _scipy_curve(data, y0), rtol=1e-7, atol=1e-9)
    assert bool(report.converged)
    assert float(report.final_cost) < float(report.initial_cost)
    assert 0 < int(report.num_accepted_steps) <= int(report.num_steps) < 100


def test_vmapped_problems_each_reach_their_own_minimum():
    datasets = [_curve_data(s) for s in range(4)]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *datasets)
    y0 = jnp.tile(jnp.array([[[1.0, -0.5, 0.0]]]), (4, 1, 1))
    y, report = jax.vmap(_fit_curve)(stacked, y0)
    assert np.all(np.asarray(report.converged))
    for k, data in enumerate(datasets):
        np.testing.assert_allclose(np.asarray(y)[k, 0], _scipy_curve(data, y0[k]), rtol=1e-7, atol=1e-9)


def test_starting_at_the_minimum_stops_at_once_instead_of_shrinking_the_trust_region_to_max_steps():
    """At the minimum every step's decrease is rounding: the solver must say converged, not run out of steps."""
    data = _curve_data(1)
    best = jnp.asarray(_scipy_curve(data, jnp.array([[1.0, -0.5, 0.0]])))[None]
    y, report = levenberg_marquardt(_curve_residual, eqx.Partial(_dense_system, data), best, data, rtol=1e-14, atol=1e-16,
                                    max_steps=50)
    assert bool(report.converged)
    assert int(report.num_steps) < 10
    np.testing.assert_allclose(np.asarray(y), np.asarray(best), atol=1e-10)


def test_max_steps_is_reported_as_not_converged():
    data = _curve_data(2)
    _, report = levenberg_marquardt(_curve_residual, eqx.Partial(_dense_system, data), jnp.array([[0.1, 1.0, 2.0]]), data,
                                    rtol=1e-12, atol=1e-14, max_steps=2)
    assert not bool(report.converged)
    assert int(report.num_steps) == 2


# ---- frames bordered by static variables: per-frame u_t, shared z = (k, o) --------------------------------


def _per_frame(u_t, z, obs_t):
    """``[u_t − a_t, exp(k·u_t) + o − b_t]``: ``u_t`` ``(1,)``, ``z`` ``(2,)``, ``obs_t = (a_t, b_t)``."""
    return jnp.concatenate([u_t - obs_t[:1], jnp.exp(z[0] * u_t) + z[1] - obs_t[1:]])


def _arrow_residual(v, obs):
    (u, z) = v
    return jax.vmap(_per_frame, in_axes=(0, None, 0))(u, z, obs)


def _arrow_system(obs, v):
    u, z = v
    r = _arrow_residual(v, obs)  # (W, 2)
    ju = jax.vmap(jax.jacfwd(_per_frame), in_axes=(0, None, 0))(u, z, obs)  # (W, 2, 1)
    jz = jax.vmap(jax.jacfwd(_per_frame, argnums=1), in_axes=(0, None, 0))(u, z, obs)  # (W, 2, 2)
    return NormalEquations(
        jnp.einsum("tri,trj->tij", ju, ju), (), jnp.einsum("tri,tr->ti", ju, r),
        jnp.einsum("tri,trs->tis", ju, jz), jnp.einsum("trs,tru->su", jz, jz), jnp.einsum("trs,tr->s", jz, r),
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_frames_with_static_variables_reach_scipys_joint_minimum(seed):
    rng = np.random.default_rng(seed)
    w = 12
    u_true = rng.uniform(-1.0, 1.0, w)
    obs = jnp.asarray(np.stack([u_true, np.exp(0.8 * u_true) - 0.3], axis=1) + 0.05 * rng.normal(size=(w, 2)))
    v0 = (jnp.zeros((w, 1)), jnp.array([0.0, 0.0]))
    (u, z), report = levenberg_marquardt(_arrow_residual, eqx.Partial(_arrow_system, obs), v0, obs, rtol=1e-10, atol=1e-12)
    flat = lambda p: np.asarray(_arrow_residual((p[:w, None], p[w:]), obs)).reshape(-1)  # noqa: E731
    ref = least_squares(flat, np.zeros(w + 2), xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    assert bool(report.converged)
    np.testing.assert_allclose(np.asarray(u)[:, 0], ref[:w], atol=1e-8)
    np.testing.assert_allclose(np.asarray(z), ref[w:], atol=1e-8)


def test_vmapped_bordered_problems_each_keep_their_own_damping_and_minimum():
    """Frames with no bands bordered by static variables, several problems under ``jax.vmap`` (as the re-fit of
    registered poses solves its cameras): each reaches scipy's joint minimum of its own problem, with its own
    number of accepted steps."""
    rng = np.random.default_rng(3)
    w, k = 10, 3
    u_true = rng.uniform(-1.0, 1.0, (k, w))
    scale = np.array([0.8, 0.2, 1.5])[:, None]
    obs = jnp.asarray(np.stack([u_true, np.exp(scale * u_true) - 0.3], axis=2) + 0.05 * rng.normal(size=(k, w, 2)))
    v0 = (jnp.zeros((k, w, 1)), jnp.zeros((k, 2)))
    solve = lambda o, v: levenberg_marquardt(_arrow_residual, eqx.Partial(_arrow_system, o), v, o, rtol=1e-10, atol=1e-12)
    (u, z), report = jax.jit(jax.vmap(solve))(obs, v0)
    assert np.all(np.asarray(report.converged))
    for i in range(k):
        flat = lambda p, i=i: np.asarray(_arrow_residual((p[:w, None], p[w:]), obs[i])).reshape(-1)
        ref = least_squares(flat, np.zeros(w + 2), xtol=1e-15, ftol=1e-15, gtol=1e-15).x
        np.testing.assert_allclose(np.asarray(u)[i, :, 0], ref[:w], atol=1e-8)
        np.testing.assert_allclose(np.asarray(z)[i], ref[w:], atol=1e-8)
