"""Levenberg–Marquardt over a time window with optimistix in charge of the iteration.

optimistix keeps the loop (``optx.least_squares``: ``max_steps``, ``throw``, result codes) and the
trust-region update (:class:`optimistix.ClassicalTrustRegion`). Its Gauss–Newton solvers would
linearise the residual function at every trial point (a full tangent pass) and its stock linear
solvers would materialise the dense Jacobian of the window. Here instead:

- :class:`StructuredLevenbergMarquardt` evaluates only the residuals at a trial point; when the trust
  region accepts it, it assembles the block-banded normal equations
  (:func:`bcmocap.solver.window.normal_equations`) there, unless the step already satisfies the
  stopping rule (then they would never be used). The model ``f + gᵀδ + ½ δᵀHδ`` is handed to the
  trust region as :class:`optimistix.FunctionInfo.EvalGradHessian` with ``H`` a
  :class:`BlockBandedOperator`, so its predicted reduction costs one block matvec.
- :class:`StructuredDampedNewtonDescent` solves the damped system ``(H + μ diag(H)) δ = −g``
  (Marquardt scaling, μ = damping_scale / step size) by a block Cholesky scan at every trial step
  (block tridiagonal for the paper's terms, block banded for terms over more frames).

With a robust loss, ``g`` is the exact gradient and ``H`` the IRLS Gauss–Newton model (as Ceres), so
the trust region compares the true cost change with the reduction of the model the step minimises.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

from .block_banded import block_banded_dense, block_banded_matvec, solve_block_banded


class NormalEquations(eqx.Module):
    """Gauss–Newton system ``H = JᵀJ`` (block banded over ``W`` frames, bordered by ``S`` static variables)
    and ``g = Jᵀr``: what :class:`StructuredLevenbergMarquardt` steps with.

    Attributes:
        diag: ``(W, D, D)``; bands: ``B`` arrays, ``bands[k-1]`` ``(W-k, D, D)`` = ``H[t, t+k]``
            (``B`` = 1 for the paper's terms); grad: ``(W, D)``.
        coupling: ``(W, D, S)`` = ``H[t, z]``; static_matrix: ``(S, S)`` = ``H[z, z]``; static_grad: ``(S,)``
            (``S`` = 0 without static variables).
    """

    diag: jax.Array
    bands: tuple[jax.Array, ...]
    grad: jax.Array
    coupling: jax.Array
    static_matrix: jax.Array
    static_grad: jax.Array

    @property
    def upper(self) -> jax.Array:
        """``(W-1, D, D)``: ``H[t, t+1]``."""
        return self.bands[0]

    @classmethod
    def dense(cls, hessian: jax.Array, grad: jax.Array) -> NormalEquations:
        """One dense block of ``D`` variables (``hessian`` ``(D, D)``, ``grad`` ``(D,)``): one frame, no static variables."""
        d = grad.shape[0]
        return cls(hessian[None], (), grad[None], jnp.zeros((1, d, 0)), jnp.zeros((0, 0)), jnp.zeros(0))


def static_schur_complement(system: NormalEquations, relative_ridge: float = 1e-9) -> jax.Array:
    """``(S, S)`` ``C − Bᵀ A⁻¹ B``: what the system says about the static variables once every frame's variables
    re-fit (their information matrix). A ridge of ``relative_ridge`` times each block's mean diagonal (plus
    1e-12) keeps variables that no term sees in a frame out of it."""
    d = system.diag.shape[-1]
    ridge = (relative_ridge * jnp.trace(system.diag, axis1=1, axis2=2) / d + 1e-12)[:, None, None] * jnp.eye(d)
    gain = solve_block_banded(system.diag + ridge, system.bands, system.coupling)
    return system.static_matrix - jnp.einsum("tdp,tdq->pq", system.coupling, gain)


class BlockBandedOperator(lx.AbstractLinearOperator):
    """Symmetric block-banded ``(W·D) × (W·D)`` operator on ``(W, D)`` arrays, bordered by ``S`` static
    variables: then on ``(y (W, D), z (S,))`` pairs, ``[[A, B], [Bᵀ, C]]``.

    Attributes:
        diag: ``(W, D, D)`` diagonal blocks; bands: ``bands[k-1]`` ``(W-k, D, D)`` = ``A[t, t+k]``.
        coupling: ``(W, D, S)`` = ``B``; static_matrix: ``(S, S)`` = ``C`` (``S`` = 0: no border).
    """

    diag: jax.Array
    bands: tuple[jax.Array, ...]
    coupling: jax.Array
    static_matrix: jax.Array

    @property
    def has_statics(self) -> bool:
        return self.static_matrix.shape[0] > 0

    def mv(self, vector):
        if not self.has_statics:
            return block_banded_matvec(self.diag, self.bands, vector)
        y, z = vector
        return (block_banded_matvec(self.diag, self.bands, y) + jnp.einsum("tis,s->ti", self.coupling, z),
                jnp.einsum("tis,ti->s", self.coupling, y) + self.static_matrix @ z)

    def as_matrix(self):
        banded = block_banded_dense(self.diag, self.bands)
        if not self.has_statics:
            return banded
        b = self.coupling.reshape(-1, self.coupling.shape[-1])
        return jnp.block([[banded, b], [b.T, self.static_matrix]])

    def transpose(self):
        return self

    def in_structure(self):
        motion = jax.ShapeDtypeStruct(self.diag.shape[:2], self.diag.dtype)
        return (motion, jax.ShapeDtypeStruct(self.static_matrix.shape[:1], self.diag.dtype)) if self.has_statics else motion

    def out_structure(self):
        return self.in_structure()


@lx.is_symmetric.register(BlockBandedOperator)
def _(operator):
    return True


class _DescentState(eqx.Module):
    grad: Any  # (W, D), or ((W, D), (S,)) with static variables
    hessian: BlockBandedOperator


class StructuredDampedNewtonDescent(optx.AbstractDescent):
    """Damped Gauss–Newton step from the block-banded model in ``EvalGradHessian``.

    Attributes:
        damping_scale: μ = damping_scale / step size; optimistix's trust region starts at step size 1.
            A good initial guess (registered cameras) deserves a nearly undamped first step.
        min_diagonal: floor on the Marquardt scaling so that variables no term sees stay put.
    """

    damping_scale: float = 1e-3
    min_diagonal: float = 1e-9

    def init(self, y, f_info_struct):
        zeros = lambda a: jnp.zeros(a.shape, a.dtype)
        return _DescentState(jax.tree.map(zeros, y), jax.tree.map(zeros, f_info_struct.hessian))

    def query(self, y, f_info, state):
        del y, state
        return _DescentState(f_info.grad, f_info.hessian)

    def step(self, step_size, state):
        hessian = state.hessian
        mu = self.damping_scale / step_size
        d = jnp.diagonal(hessian.diag, axis1=-2, axis2=-1)
        floor = self.min_diagonal * jnp.maximum(jnp.max(d), 1.0)
        damped = hessian.diag + jax.vmap(jnp.diag)(mu * jnp.maximum(d, floor))
        if not hessian.has_statics:
            delta = -solve_block_banded(damped, hessian.bands, state.grad)
        else:  # eliminate the motion: Schur complement onto the static variables
            g_y, g_z = state.grad
            c = jnp.diagonal(hessian.static_matrix)
            damped_c = hessian.static_matrix + jnp.diag(mu * jnp.maximum(c, self.min_diagonal * jnp.maximum(jnp.max(c), 1.0)))
            columns = jnp.concatenate([g_y[..., None], hessian.coupling], axis=-1)  # (W, D, 1 + S)
            solved = solve_block_banded(damped, hessian.bands, columns)  # one factorisation, 1 + S columns
            a_inv_g, a_inv_b = solved[..., 0], solved[..., 1:]
            schur = damped_c - jnp.einsum("tis,tiu->su", hessian.coupling, a_inv_b)
            delta_z = -jnp.linalg.solve(schur, g_z - jnp.einsum("tis,ti->s", hessian.coupling, a_inv_g))
            delta = (-(a_inv_g + jnp.einsum("tis,s->ti", a_inv_b, delta_z)), delta_z)
        ok = _all_finite(delta)
        delta = jax.tree.map(lambda x: jnp.where(ok, x, 0.0), delta)
        result = optx.RESULTS.where(ok, optx.RESULTS.successful, optx.RESULTS.singular)
        return delta, result


class _SolverState(eqx.Module):
    first_step: jax.Array
    y_eval: Any  # (W, D), or ((W, D), (S,)) with static variables
    f_info: optx.FunctionInfo.EvalGradHessian  # model at the last accepted point (f: its cost)
    initial_cost: jax.Array  # cost at the starting point
    aux: Any
    search_state: Any
    descent_state: _DescentState
    terminate: jax.Array
    result: optx.RESULTS
    num_accepted_steps: jax.Array
    non_finite: jax.Array  # int: FINITE, or the check that stopped the solve (START_/SYSTEM_NOT_FINITE)


def _model(cost: jax.Array, system: NormalEquations) -> optx.FunctionInfo.EvalGradHessian:
    operator = BlockBandedOperator(system.diag, system.bands, system.coupling, system.static_matrix)
    grad = (system.grad, system.static_grad) if operator.has_statics else system.grad
    return optx.FunctionInfo.EvalGradHessian(cost, grad, operator)


def _predicted_reduction(f_info: optx.FunctionInfo.EvalGradHessian, delta) -> jax.Array:
    """``−(gᵀδ + ½ δᵀHδ)``: the cost decrease the Gauss–Newton model predicts for step ``δ``."""
    dot = lambda a, b: sum(jnp.vdot(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))  # noqa: E731
    return -(dot(f_info.grad, delta) + 0.5 * dot(delta, f_info.hessian.mv(delta)))


NON_FINITE_START = "levenberg_marquardt: the starting point holds NaN or inf"
NON_FINITE_SYSTEM = ("levenberg_marquardt: the Gauss–Newton system is NaN or inf at a point of finite cost "
                     "(a term's Jacobian is not finite there)")
# Codes of Convergence.non_finite: the checks are flags in the loop state, not host callbacks
# (``eqx.error_if``), so that the compiled solve stays pure and is found in the persistent compilation cache.
FINITE, START_NOT_FINITE, SYSTEM_NOT_FINITE = 0, 1, 2
NON_FINITE_MESSAGES = {START_NOT_FINITE: NON_FINITE_START, SYSTEM_NOT_FINITE: NON_FINITE_SYSTEM}


def _all_finite(tree) -> jax.Array:
    return jnp.all(jnp.array([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree)]))


class StructuredLevenbergMarquardt(optx.AbstractLeastSquaresSolver):
    """Levenberg–Marquardt for a window: structured normal equations, optimistix trust region and loop.

    Stops when an accepted step changes ``y`` by less than ``atol + rtol |y|`` (in ``norm``) and the
    cost by less than ``atol + rtol · cost`` (optimistix's Cauchy rule, on the cost), or when the trust
    region rejects a step for which the model predicted a decrease below that cost tolerance (the
    comparison was rounding, and no step can gain more than the tolerance).

    Attributes:
        build: ``y ↦ NormalEquations`` (an ``eqx.Partial`` closing over the window problem).

    A starting point holding NaN or inf ends the solve before its first step, and so do normal equations
    holding NaN or inf at an accepted point of finite cost; ``state.non_finite`` says which
    (:data:`START_NOT_FINITE`, :data:`SYSTEM_NOT_FINITE`).
    """

    rtol: float
    atol: float
    norm: Callable
    build: Callable
    descent: StructuredDampedNewtonDescent
    search: optx.ClassicalTrustRegion

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
        self.build = build
        self.descent = StructuredDampedNewtonDescent(damping_scale)
        self.search = optx.ClassicalTrustRegion()

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del fn, args, options, f_struct, tags
        system = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(self.build, y))
        dtype = jax.tree.leaves(y)[0].dtype
        f_info = _model(jnp.zeros((), dtype), system)
        start_bad = ~_all_finite(y)
        return _SolverState(
            first_step=jnp.array(True),
            y_eval=y,
            f_info=f_info,
            initial_cost=jnp.zeros((), dtype),
            aux=jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), aux_struct),
            search_state=self.search.init(y, f_info),
            descent_state=self.descent.init(y, f_info),
            terminate=start_bad,
            result=optx.RESULTS.successful,
            num_accepted_steps=jnp.array(0),
            non_finite=jnp.where(start_bad, START_NOT_FINITE, FINITE),
        )

    def _cost_tolerance(self, cost):
        return self.atol + self.rtol * jnp.abs(cost)

    def _converged(self, y, y_diff, cost, cost_diff):
        y_small = self.norm(jax.tree.map(lambda a, b: jnp.abs(a) / (self.atol + self.rtol * jnp.abs(b)), y_diff, y)) < 1
        return y_small & (jnp.abs(cost_diff) < self._cost_tolerance(cost))

    def step(self, fn, y, args, options, state, tags):
        del options, tags
        residual, aux_eval = fn(state.y_eval, args)
        cost_eval = 0.5 * sum(jnp.sum(r * r) for r in jax.tree.leaves(residual))
        trial = optx.FunctionInfo.EvalGradHessian(cost_eval, state.f_info.grad, state.f_info.hessian)
        step_size, accept, search_result, search_state = self.search.step(
            state.first_step, y, state.y_eval, state.f_info, trial, state.search_state
        )

        def accepted(_):
            terminate = ~state.first_step & self._converged(
                state.y_eval, jax.tree.map(jnp.subtract, state.y_eval, y), state.f_info.f, cost_eval - state.f_info.f
            )
            # The normal equations at the final point would never be used.
            system = jax.lax.cond(
                terminate,
                lambda yy: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(self.build, yy)),
                lambda yy: self.build(yy),
                state.y_eval,
            )
            bad = jnp.isfinite(cost_eval) & ~_all_finite(system)
            return state.y_eval, _model(cost_eval, system), aux_eval, terminate | bad, bad

        def rejected(_):
            # The model promised less than the cost tolerance for this step, so rounding decided that it
            # failed: there is nothing left to gain here (otherwise the trust region shrinks until max_steps).
            delta = jax.tree.map(jnp.subtract, state.y_eval, y)
            stop = _predicted_reduction(state.f_info, delta) <= self._cost_tolerance(state.f_info.f)
            return y, state.f_info, state.aux, stop, jnp.array(False)

        y, f_info, aux, terminate, bad_system = jax.lax.cond(accept, accepted, rejected, None)
        descent_state = self.descent.query(y, f_info, state.descent_state)
        y_descent, descent_result = self.descent.step(step_size, descent_state)
        result = optx.RESULTS.where(search_result == optx.RESULTS.successful, descent_result, search_result)
        new_state = _SolverState(
            first_step=jnp.array(False),
            y_eval=jax.tree.map(jnp.add, y, y_descent),
            f_info=f_info,
            initial_cost=jnp.where(state.first_step, cost_eval, state.initial_cost),
            aux=aux,
            search_state=search_state,
            descent_state=descent_state,
            terminate=terminate,
            result=result,
            num_accepted_steps=state.num_accepted_steps + jnp.where(accept, 1, 0),
            non_finite=jnp.where(bad_system, SYSTEM_NOT_FINITE, state.non_finite),
        )
        return y, new_state, aux

    def terminate(self, fn, y, args, options, state, tags):
        return state.terminate, state.result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


class Convergence(eqx.Module):
    """How one Levenberg–Marquardt solve went (arrays: one more leading axis per ``vmap``).

    Attributes:
        initial_cost, final_cost: ``½ Σ r²`` at the start and at the returned point.
        num_steps: iterations (accepted or rejected); num_accepted_steps: those the trust region accepted.
        converged: stopped by the tolerances, not by ``max_steps``, a failed step or a non-finite value.
        non_finite: :data:`FINITE` (0), or why the solve stopped: :data:`START_NOT_FINITE` (``y0`` holds NaN
            or inf; no step was taken) or :data:`SYSTEM_NOT_FINITE` (the normal equations at an accepted point
            of finite cost hold NaN or inf: a term's Jacobian is not finite there; ``y`` is that point).
            :data:`NON_FINITE_MESSAGES` words them.
    """

    initial_cost: jax.Array
    final_cost: jax.Array
    num_steps: jax.Array
    num_accepted_steps: jax.Array
    converged: jax.Array
    non_finite: jax.Array


def levenberg_marquardt(
    residual_fn: Callable,
    build: Callable,
    y0,
    args=None,
    *,
    rtol: float = 1e-4,
    atol: float = 1e-4,
    damping_scale: float = 1e-3,
    max_steps: int = 100,
    norm: Callable = optx.rms_norm,
):
    """Minimise ``½ Σ r(y)²`` from ``y0``: the one Levenberg–Marquardt of bcmocap (jit- and vmap-able).

    The windowed motion solve, the skeleton and mount refinement, the joint centres of marker groups,
    marker IK and the re-fit of registered camera poses all step through here; what differs is only
    ``build``, the structure of their Gauss–Newton system (block banded over frames, bordered by static
    variables, or one dense block; no bands: independent frames). Under ``jax.vmap`` each problem keeps
    its own trust region, i.e. its own damping (block-diagonal damping over the mapped problems).

    Args:
        residual_fn: ``(y, args) ↦`` residual pytree (its squared sum is twice the cost).
        build: ``y ↦`` :class:`NormalEquations` of ``residual_fn`` at ``y`` (a pytree such as an
            ``eqx.Partial``, so that compiled callers are not retraced).
        y0: ``(W, D)`` array, or ``((W, D), (S,))`` when the system has ``S`` static variables.
        rtol, atol, norm, damping_scale: see :class:`StructuredLevenbergMarquardt`.
        max_steps: iterations at most (accepted or rejected).

    Returns:
        ``(y, Convergence)``: the last accepted point and how the solve went. A non-finite start or
        Gauss–Newton system stops the solve and is reported in ``Convergence.non_finite`` (a flag, so the
        compiled solve has no host callback); a non-finite cost is left to the caller, who can say which term
        it comes from.
    """
    solver = StructuredLevenbergMarquardt(build, rtol, atol, norm, damping_scale)
    sol = optx.least_squares(residual_fn, solver, y0, args=args, max_steps=max_steps, throw=False)
    report = Convergence(
        sol.state.initial_cost,
        sol.state.f_info.f,  # the cost at the returned point, the last accepted one
        sol.stats["num_steps"],
        sol.state.num_accepted_steps,
        (sol.result == optx.RESULTS.successful) & (sol.state.non_finite == FINITE),
        sol.state.non_finite,
    )
    return sol.value, report
