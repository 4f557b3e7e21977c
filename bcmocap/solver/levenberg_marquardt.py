"""Levenberg–Marquardt over a time window with optimistix in charge of the iteration.

optimistix keeps the loop, the trust-region update (:class:`optimistix.ClassicalTrustRegion`), the
stopping rule, ``max_steps`` and result codes. Its stock linear solvers would materialise the dense
Jacobian of the window; instead :class:`StructuredDampedNewtonDescent` assembles the block-tridiagonal
normal equations (:func:`bcmocap.solver.window.normal_equations`) once per accepted step and solves
the damped system ``(H + μ diag(H)) δ = −g`` (Marquardt scaling, μ = 1/step size) by a block
Cholesky scan at every trial step.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from .block_tridiagonal import solve_block_tridiagonal
from .window import NormalEquations


class _DescentState(eqx.Module):
    system: NormalEquations


class StructuredDampedNewtonDescent(optx.AbstractDescent):
    """Damped Gauss–Newton step from structured normal equations.

    Attributes:
        build: ``y ↦ NormalEquations`` (an ``eqx.Partial`` closing over the window problem).
        damping_scale: μ = damping_scale / step size; optimistix's trust region starts at step size 1.
            A good initial guess (registered cameras) deserves a nearly undamped first step.
        min_diagonal: floor on the Marquardt scaling so that variables no term sees stay put.
    """

    build: Callable
    damping_scale: float = 1e-3
    min_diagonal: float = 1e-9

    def init(self, y, f_info_struct):
        del f_info_struct
        shapes = jax.eval_shape(self.build, y)
        return _DescentState(jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes))

    def query(self, y, f_info, state):
        del f_info, state
        return _DescentState(self.build(y))

    def step(self, step_size, state):
        system = state.system
        mu = self.damping_scale / step_size
        d = jnp.diagonal(system.diag, axis1=-2, axis2=-1)
        floor = self.min_diagonal * jnp.maximum(jnp.max(d), 1.0)
        damping = mu * jnp.maximum(d, floor)
        damped = system.diag + jax.vmap(jnp.diag)(damping)
        delta = -solve_block_tridiagonal(damped, system.upper, system.grad)
        ok = jnp.all(jnp.isfinite(delta))
        delta = jnp.where(ok, delta, 0.0)
        result = optx.RESULTS.where(ok, optx.RESULTS.successful, optx.RESULTS.singular)
        return delta, result


class StructuredLevenbergMarquardt(optx.AbstractGaussNewton):
    """optimistix Levenberg–Marquardt whose step comes from :class:`StructuredDampedNewtonDescent`."""

    rtol: float
    atol: float
    norm: Callable
    descent: StructuredDampedNewtonDescent
    search: optx.ClassicalTrustRegion
    verbose: Callable

    def __init__(
        self,
        build: Callable,
        rtol: float = 1e-4,
        atol: float = 1e-4,
        norm: Callable = optx.rms_norm,
        damping_scale: float = 1e-3,
    ):
        self.rtol = rtol
        self.atol = atol
        self.norm = norm
        self.descent = StructuredDampedNewtonDescent(build, damping_scale)
        self.search = optx.ClassicalTrustRegion()
        self.verbose = lambda **kwargs: None
