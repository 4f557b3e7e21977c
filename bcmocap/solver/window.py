"""One time window of Eq. (1): its residuals and its structured Gauss–Newton normal equations.

A window holds ``W`` frames of variables plus, first in its reference motion, the ``H`` frames just
before it (solved by the previous window and held fixed) so that terms over several frames connect
across the seam: ``H = 1`` for the paper's pair terms, ``span − 1`` for a :class:`MultiFrameTerm`.
Variables are tangent vectors ``y`` ``(W, D + E)`` relative to the reference motion (see
:meth:`Skeleton.retract`) and to the reference values of the ``E`` per-frame variables the terms declare,
so the solver always steps in the tangent space of the current pose; static variables ``z`` ``(S,)`` are
tangents at their blocks' values likewise. Indices below called *extended* count those ``H`` fixed frames
first.
"""

from __future__ import annotations

import math
from math import prod
from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp

from ..geometry import SE3, transform_points
from ..kinematics.fk import forward_kinematics
from ..kinematics.rig import Rig
from ..kinematics.skeleton import Motion, Skeleton
from .levenberg_marquardt import NormalEquations
from .model_parameters import MODEL, ModelParameters, reaxis
from ..residuals.base import CameraTerm, CameraView, FrameState, StackedFrames, Term, declared_statics, slot_cameras, stacked
from ..residuals.variables import CAMERA_OFFSETS, Euclidean, PerCamera, Variable, as_variable, retract_blocks


class WindowProblem(eqx.Module):
    """Everything a window's solve needs, as one pytree.

    Attributes:
        skeleton, rig: the model (rig may be None for problems without cameras).
        terms: residual terms restricted to the window (data leading axis ``W``).
        reference: motion with ``H + W`` frames: the ``H`` fixed frames before the window
            (:func:`window_history`), then the window's frames.
        num_previous: scalar int, how many of those ``H`` frames exist (fewer at the start of a
            sequence; terms reaching further back are dropped at the window's first frames).
        statics: the static variables' values the window starts from, ``{name: value}`` for every block of
            :func:`problem_static_layout` (the solver's variables ``z`` are tangents at them).
        model_parameters: the skeleton and rig as static variables (block ``"model"``), or None: every
            term sees the model at those variables, and their prior joins the objective.
        frame_values: the per-frame variables' reference values, ``{name: (H + W, *value_shape)}`` for every
            block of :func:`frame_layout` (the last ``E`` entries of each row of ``y`` are tangents at them).
    """

    skeleton: Skeleton
    rig: Rig | None
    terms: tuple[Term, ...]
    reference: Motion
    num_previous: jax.Array = eqx.field(converter=lambda n: jnp.asarray(n, jnp.int32))
    statics: dict = eqx.field(default_factory=dict)
    model_parameters: ModelParameters | None = None
    frame_values: dict = eqx.field(default_factory=dict)

    @property
    def history(self) -> int:
        return window_history(self.terms)

    @property
    def num_statics(self) -> int:
        """``S``: the length of the static variables' vector ``z``."""
        return sum(variable.size for _, variable in problem_static_layout(self))

    @property
    def num_frames(self) -> int:
        return self.reference.root_position.shape[0] - self.history

    @property
    def frame_size(self) -> int:
        """``D + E``: the variables of one frame (the motion's tangent, then the per-frame blocks')."""
        return self.skeleton.num_dofs + sum(v.size for _, v in frame_layout(self.terms))

    def extended_reference(self) -> tuple[Motion, dict]:
        """``(motion, frame_values)`` of the ``H + W`` extended frames, indexed together."""
        return self.reference, self.frame_values


def window_history(terms: Sequence[Term]) -> int:
    """``H``: fixed frames a window needs before its first (1, or ``span − 1`` of the widest multi-frame term).

    It is also the bandwidth of the normal equations: frames up to ``H`` apart are coupled.
    """
    return max([2, *(t.span for t in terms)]) - 1


def _declared_layout(terms: Sequence[Term], declared, kind: str) -> tuple[tuple[str, Variable], ...]:
    """``((name, Variable), …)`` sorted by name, of the blocks ``declared(term)`` gives for every term.

    Raises:
        ValueError: two terms declare one name differently.
    """
    blocks: dict[str, tuple[Variable, str]] = {}
    for term in terms:
        for name, value in declared(term).items():
            variable = as_variable(value, f"{term.label}: {kind} variable {name!r}")
            if name in blocks and blocks[name][0] != variable:
                raise ValueError(f"{kind} variable {name!r}: {blocks[name][1]} declares {blocks[name][0]}, "
                                 f"{term.label} declares {variable}")
            blocks[name] = (variable, term.label)
    return tuple((name, blocks[name][0]) for name in sorted(blocks))


def static_layout(terms: Sequence[Term]) -> tuple[tuple[str, Variable], ...]:
    """The static variable blocks the terms declare, ``((name, Variable), …)`` sorted by name; ``z`` stacks their
    tangents.

    Raises:
        ValueError: two terms declare one name differently.
    """
    return _declared_layout(terms, lambda t: t.static_variables(), "static")


def frame_layout(terms: Sequence[Term]) -> tuple[tuple[str, Variable], ...]:
    """The per-frame variable blocks the terms declare, ``((name, Variable), …)`` sorted by name; each frame's
    variables are its motion tangent followed by their tangents.

    Raises:
        ValueError: two terms declare one name differently, or a camera term declares any.
    """
    for term in terms:
        if term.per_camera and term.frame_variables():
            raise ValueError(f"{term.label}: camera terms cannot declare per-frame variables; they see "
                             f"{CAMERA_OFFSETS!r} through the camera poses")
    return _declared_layout(terms, lambda t: t.frame_variables(), "per-frame")


def problem_static_layout(problem: WindowProblem) -> tuple[tuple[str, Variable], ...]:
    """The terms' static blocks (:func:`static_layout`), then the model's (``"model"``) if it is variable."""
    blocks = static_layout(problem.terms)
    if problem.model_parameters is None:
        return blocks
    return (*blocks, (MODEL, Euclidean(problem.model_parameters.size)))


def _static_offsets(problem: WindowProblem) -> dict[str, int]:
    """Where each static block's tangent starts in ``z``."""
    offsets, at = {}, 0
    for name, variable in problem_static_layout(problem):
        offsets[name], at = at, at + variable.size
    return offsets


def _model_block(problem: WindowProblem) -> slice:
    """Where the model's variables sit in ``z``."""
    start = _static_offsets(problem)[MODEL]
    return slice(start, start + problem.model_parameters.size)


def static_values(problem: WindowProblem, z: jax.Array | None) -> dict:
    """``{name: value}``: the window's static variables moved by tangents ``z`` ``(S,)`` (None: at the start)."""
    return retract_blocks(problem_static_layout(problem), problem.statics, z)


@eqx.filter_jit  # traced once per shape: the solve's tracing calls it ~25 times
def frame_state(skeleton: Skeleton, rig: Rig | None, reference: Motion, y: jax.Array, statics: dict | None = None,
                variables: dict | None = None) -> FrameState:
    """State of frames with batch shape ``S`` from motion tangents ``(*S, D)``, static variables (repeated) and
    the frames' own ``variables`` (``{name: (*S, …)}``; :data:`CAMERA_OFFSETS` moves the cameras)."""
    motion = skeleton.retract(reference, y)
    world_from_segment = forward_kinematics(skeleton, motion)
    variables = dict(variables or {})
    if rig is None:
        world_from_camera = SE3.identity(batch_axes=(*y.shape[:-1], 0))
    else:
        world_from_camera = rig.world_from_camera(world_from_segment)
        if CAMERA_OFFSETS in variables:  # each camera moved on its mount: world_from_camera · exp(offset)
            world_from_camera = world_from_camera @ SE3.exp(variables[CAMERA_OFFSETS])
    batch = y.shape[:-1]
    statics = {k: jnp.broadcast_to(v, (*batch, *jnp.shape(v))) for k, v in (statics or {}).items()}
    return FrameState(motion, world_from_segment, world_from_camera, statics, variables)


def _model_at(problem: WindowProblem, reference: Motion, statics: dict) -> tuple[Skeleton, Rig | None, Motion]:
    """The skeleton, rig and reference motion at the static values: with variable model parameters, the model
    at ``statics["model"]`` and the reference's hinge angles kept about the axes that moved."""
    if problem.model_parameters is None:
        return problem.skeleton, problem.rig, reference
    parameters = problem.model_parameters
    skeleton, rig = parameters.model(statics[MODEL])
    start_axes = parameters.model(problem.statics[MODEL])[0].hinge_axes  # the reference motion's axes
    return skeleton, rig, reaxis(parameters.layout, reference, start_axes, skeleton.hinge_axes)


def model_state(problem: WindowProblem, reference: tuple[Motion, dict], y: jax.Array, statics: dict) -> FrameState:
    """:func:`frame_state` of the window's model at the static values (see :func:`_model_at`), at frame variables
    ``y`` ``(..., D + E)`` from ``reference`` = (motion, per-frame values) with the same batch shape."""
    motion, values = reference
    skeleton, rig, motion = _model_at(problem, motion, statics)
    d = skeleton.num_dofs
    variables = retract_blocks(frame_layout(problem.terms), values, y[..., d:])
    return frame_state(skeleton, rig, motion, y[..., :d], statics, variables)


def model_motion(problem: WindowProblem, y: jax.Array, statics: dict) -> tuple[Motion, dict]:
    """The window's motion and per-frame values ``{name: (W, …)}`` at frame variables ``y`` ``(W, D + E)``, in the
    model at the static values."""
    h = problem.history
    skeleton, _, reference = _model_at(problem, problem.reference[h:], statics)
    d = skeleton.num_dofs
    values = {k: v[h:] for k, v in problem.frame_values.items()}
    return skeleton.retract(reference, y[:, :d]), retract_blocks(frame_layout(problem.terms), values, y[:, d:])


def _extended(problem: WindowProblem, y: jax.Array) -> jax.Array:
    return jnp.concatenate([jnp.zeros((problem.history, y.shape[1]), y.dtype), y], axis=0)


def _span_ok(problem: WindowProblem, span: int) -> jax.Array:
    """``(W,)``: whether the frames ``t − span + 1 … t`` all exist (the fixed ones included)."""
    return jnp.arange(problem.num_frames) - (span - 1) >= -problem.num_previous


def _span_index(problem: WindowProblem, span: int) -> jax.Array:
    """``(W, span)`` extended indices of frames ``t − span + 1 … t`` (oldest first)."""
    w, h = problem.num_frames, problem.history
    return h + jnp.arange(w)[:, None] + jnp.arange(span)[None, :] - (span - 1)


def _pair_valid(problem: WindowProblem, valid: jax.Array) -> jax.Array:
    """Drop the pair (previous, first) when there is no previous frame."""
    return valid & _span_ok(problem, 2).reshape(-1, *([1] * (valid.ndim - 1)))


def _slot_gather(term: Term, per_camera: jax.Array) -> jax.Array:
    """``(W, C, ...)`` per-camera values → ``(W, K, ...)`` per data slot of a term with camera slots."""
    index = slot_cameras(term.data)
    if index is None:
        return per_camera
    return jnp.take_along_axis(per_camera, index.reshape(*index.shape, *([1] * (per_camera.ndim - 2))), axis=1)


def _slot_intrinsics(term: Term, rig: Rig):
    """Intrinsics to vmap over frames: ``(C, ...)`` shared by all frames (axis None) or ``(W, K, ...)`` per slot."""
    index = slot_cameras(term.data)
    if index is None:
        return rig.intrinsics, None
    return jax.tree.map(lambda a: a[index], rig.intrinsics), 0


def _camera_indices(problem: WindowProblem, term: Term) -> jax.Array:
    """``(W, K)``: the camera of each data slot of a camera term (``K = C`` without slots)."""
    index = slot_cameras(term.data)
    if index is None:
        return jnp.broadcast_to(jnp.arange(problem.rig.num_cameras), (problem.num_frames, problem.rig.num_cameras))
    return index


class _CameraTermStatics(eqx.Module):
    """The static blocks a camera term reads, per frame and data slot: its own blocks ``((name, Variable), …)``
    (a :class:`PerCamera` block's per-camera block), their start values ``{name: (W, K, …)}`` (the slot's
    camera's copy) and the columns of ``z`` their tangents are, ``(W, K, k)``."""

    layout: tuple = eqx.field(static=True)
    values: dict
    columns: jax.Array

    @property
    def size(self) -> int:
        return sum(variable.size for _, variable in self.layout)

    def at(self, values: dict, z_own: jax.Array) -> dict:
        """One camera-frame's static values at its own tangents ``z_own`` ``(k,)`` (``values`` sliced to it)."""
        return retract_blocks(self.layout, values, z_own)


def _camera_term_statics(problem: WindowProblem, term: Term) -> _CameraTermStatics | None:
    """What a camera term reads of the static variables (None if it declares none)."""
    if not term.static_variables():
        return None
    layout, offsets = dict(problem_static_layout(problem)), _static_offsets(problem)
    cameras = _camera_indices(problem, term)
    own, values, columns = [], {}, []
    for name in sorted(term.static_variables()):
        variable, value = layout[name], problem.statics[name]
        if isinstance(variable, PerCamera):
            size = variable.block.size
            own.append((name, variable.block))
            values[name] = value[cameras]
            columns.append(offsets[name] + cameras[..., None] * size + jnp.arange(size))
        else:
            own.append((name, variable))
            values[name] = jnp.broadcast_to(value, (*cameras.shape, *jnp.shape(value)))
            columns.append(jnp.broadcast_to(offsets[name] + jnp.arange(variable.size), (*cameras.shape, variable.size)))
    return _CameraTermStatics(tuple(own), values, jnp.concatenate(columns, axis=-1))


def _camera_statics_args(own: _CameraTermStatics | None, z: jax.Array) -> tuple:
    """Per frame and slot: the start values and own tangents ``z[columns]`` of a camera term's statics (or Nones)."""
    return (None, None) if own is None else (own.values, z[own.columns])


def _own_statics(own: _CameraTermStatics | None, values: dict | None, z_own: jax.Array | None) -> dict:
    """The ``variables`` argument of a camera term's residual: its static values ({} if it declares none)."""
    return {} if own is None else own.at(values, z_own)


def _span_statics(term: Term, states: FrameState) -> dict:
    """The ``variables`` argument of a multi-frame term's residual (the statics are the same at every frame)."""
    return declared_statics(term, jax.tree.map(lambda a: a[0], states.statics))


def cost(problem: WindowProblem, y: jax.Array) -> jax.Array:
    """½ Σ of all finished squared residuals."""
    return 0.5 * sum(jnp.sum(r * r) for r in residuals(problem, y))


def _log_near_identity(matrix: jax.Array) -> jax.Array:
    """``(..., 6)`` (translation, rotation) of 4×4 transforms, with the derivative of SE(3) log at the identity.

    Jacobians are only ever taken at the identity, where this linear map and ``SE3.log`` agree to first
    order; it avoids differentiating jaxlie's log (branches for small angles) for every camera and DOF.
    """
    rot = matrix[..., :3, :3]
    skew = 0.5 * (rot - jnp.swapaxes(rot, -1, -2))
    omega = jnp.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], axis=-1)
    return jnp.concatenate([matrix[..., :3, 3], omega], axis=-1)


def _camera_pose_jacobians(problem: WindowProblem, y_ext: jax.Array, z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``cam_from_world`` ``(H+W, C, 7)`` and its Jacobian ``(H+W, C, 6, D + E)`` w.r.t. each frame's variables,
    ``(H+W, C, 6, D + E + S)`` w.r.t. them and the static variables ``z`` when the model is variable.

    The camera tangent is a left perturbation: ``cam_from_world(y') = exp(ξ) · cam_from_world(y)``.
    """
    d = y_ext.shape[1]
    with_model = problem.model_parameters is not None

    def per_frame(reference: tuple[Motion, dict], y_t: jax.Array):
        def pose(v):
            at = static_values(problem, v[d:] if with_model else z)
            return model_state(problem, reference, v[:d], at).world_from_camera.inverse()

        v0 = jnp.concatenate([y_t, z]) if with_model else y_t
        current = jax.lax.stop_gradient(pose(v0))
        tangent = lambda v: _log_near_identity((pose(v) @ current.inverse()).as_matrix())
        return current.wxyz_xyz, jax.jacfwd(tangent)(v0)

    return jax.vmap(per_frame)(problem.extended_reference(), y_ext)


def _camera_measurement_jacobians(residual_fn, poses: tuple[jax.Array, ...], rotation_only: bool = False,
                                  static_size: int = 0):
    """Residual blocks ``(n, k)`` and their Jacobian ``(n, k, 6·len(poses) + static_size)`` w.r.t. left pose
    perturbations (and, with ``static_size``, the tangent of the term's static blocks, ``residual_fn``'s last
    argument).

    With ``rotation_only`` the residual is declared independent of the translations: only the rotation
    tangents are differentiated and the translation columns are zero.
    """
    per_pose, num = (3 if rotation_only else 6), len(poses)

    def perturbed(xi):
        tangents = [xi[per_pose * i : per_pose * (i + 1)] for i in range(num)]
        if rotation_only:
            tangents = [jnp.concatenate([jnp.zeros(3), t]) for t in tangents]
        moved = [SE3.exp(t) @ SE3(p) for t, p in zip(tangents, poses)]
        return residual_fn(*moved, xi[per_pose * num :]) if static_size else residual_fn(*moved)

    zero = jnp.zeros(per_pose * num + static_size)
    r, jac = perturbed(zero), jax.jacfwd(perturbed)(zero)
    if rotation_only:  # back to (translation, rotation) blocks of 6 per pose
        pose_jac = jac[..., : per_pose * num].reshape(*jac.shape[:-1], num, 3)
        pose_jac = jnp.concatenate([jnp.zeros_like(pose_jac), pose_jac], axis=-1).reshape(*jac.shape[:-1], 6 * num)
        jac = jnp.concatenate([pose_jac, jac[..., per_pose * num :]], axis=-1)
    return r, jac


class _StaticBlocks(eqx.Module):
    """Accumulators of the static variables' blocks: coupling ``(H + W, D, S)`` (extended), matrix ``(S, S)``,
    grad ``(S,)``."""

    coupling: jax.Array
    matrix: jax.Array
    grad: jax.Array


def residuals(problem: WindowProblem, y: jax.Array, z: jax.Array | None = None) -> tuple[jax.Array, ...]:
    """All finished residual blocks of the window, one array per term (shapes ``(W, ..., k)``), at frame
    variables ``y`` ``(W, D + E)`` and static-variable tangents ``z`` ``(S,)`` (None: 0)."""
    at = static_values(problem, z)
    point = _Point(problem, y, jnp.zeros(problem.num_statics) if z is None else z, at)
    out = []
    for term in problem.terms:
        r, v = term_kind(term).residuals(problem, term, point)
        out.append(term.finish(r, v))
    if problem.model_parameters is not None:  # the prior on the skeleton and rig
        out.append(problem.model_parameters.prior_residual(at[MODEL]))
    return tuple(out)


class _Point:
    """What every kind's residuals read at one point ``(y, z)`` of a window: the extended frames' states, those of
    the pairs ``(t − 1, t)``, the cameras' ``cam_from_world`` and the static tangents ``z``."""

    def __init__(self, problem: WindowProblem, y: jax.Array, z: jax.Array, statics: dict):
        h = problem.history
        self.z = z
        self.states = model_state(problem, problem.extended_reference(), _extended(problem, y), statics)
        self.prev_states = jax.tree.map(lambda a: a[h - 1 : -1], self.states)
        self.curr_states = jax.tree.map(lambda a: a[h:], self.states)
        self.cam_from_world = self.states.world_from_camera.inverse() if problem.rig is not None else None


class _System:
    """The normal equations being assembled (extended arrays, the ``H`` fixed frames first) and what every kind's
    linearisation reads: frame variables ``y``, their extended ``y_ext``, static tangents ``z``, and (when a term
    needs them) the cameras' poses and their Jacobians w.r.t. the frames' variables."""

    def __init__(self, problem: WindowProblem, y: jax.Array, z: jax.Array):
        self.w, self.d = y.shape
        self.h, self.n_static = problem.history, problem.num_statics
        self.y, self.z = y, z
        self.y_ext = _extended(problem, y)
        self.reference = problem.extended_reference()
        h, d, n_static = self.h, self.d, self.n_static
        self.diag = jnp.zeros((h + self.w, d, d))
        self.bands = [jnp.zeros((h + self.w, d, d)) for _ in range(h)]  # bands[k-1][u] couples frames u and u+k
        self.grad = jnp.zeros((h + self.w, d))
        self.statics = _StaticBlocks(jnp.zeros((h + self.w, d, n_static)), jnp.zeros((n_static, n_static)),
                                     jnp.zeros(n_static))
        if any(t.per_camera for t in problem.terms):
            self.cam_poses, self.pose_jac = _camera_pose_jacobians(problem, self.y_ext, z)  # (H+W, C, 6, D [+ S])

    def frames(self, index):
        """The reference (motion, per-frame values) of some extended frames."""
        return jax.tree.map(lambda a: a[index], self.reference)

    def with_z(self, v: jax.Array) -> jax.Array:
        """``(W, n)`` → ``(W, n + S)``: each row followed by the static tangents."""
        return jnp.concatenate([v, jnp.broadcast_to(self.z, (v.shape[0], self.n_static))], axis=1)

    def add_span_rows(self, r, jy, jz) -> None:
        """Add IRLS rows of frames ``t − N + 1 … t`` (:func:`_add_span_blocks`)."""
        self.diag, self.bands, self.grad, self.statics = _add_span_blocks(self.diag, self.bands, self.grad,
                                                                          self.statics, r, jy, jz, self.h)


def normal_equations(problem: WindowProblem, y: jax.Array, z: jax.Array | None = None) -> NormalEquations:
    """Assemble the block-banded Gauss–Newton system of the window at frame variables ``y`` ``(W, D + E)`` and
    static-variable tangents ``z`` ``(S,)`` (None: 0).

    ``grad`` is the exact gradient of the window's cost; ``diag``/``bands`` are the IRLS Gauss–Newton
    matrix ``Σ λ ρ'(s) JᵀJ`` (exactly ``JᵀJ`` of the residuals when no robust loss is used). The
    bandwidth is the window's history ``H`` (1 unless a multi-frame term spans more than two frames).
    Each term is linearised by the adapter of its kind (:func:`term_kind`); the kinds that share one
    differentiation of the frame state (frame terms, pair terms) are linearised together, first.
    """
    system = _System(problem, y, jnp.zeros(problem.num_statics) if z is None else z)
    kinds = [term_kind(t) for t in problem.terms]
    for kind in _GROUPED:
        group = [t for t, k in zip(problem.terms, kinds) if k is kind]
        if group:
            kind.linearise(problem, group, system)
    for term, kind in zip(problem.terms, kinds):
        if kind not in _GROUPED:
            kind.linearise(problem, [term], system)
    statics = system.statics
    if problem.model_parameters is not None:  # the prior ½ Σ (θ/σ)² on the model's variables
        block = _model_block(problem)
        precision = problem.model_parameters.sqrt_precision ** 2
        values = static_values(problem, system.z)[MODEL]
        statics = _StaticBlocks(statics.coupling, statics.matrix.at[block, block].add(jnp.diag(precision)),
                                statics.grad.at[block].add(precision * values))
    h, w = system.h, system.w
    return NormalEquations(system.diag[h:], tuple(band[h : h + w - k] for k, band in enumerate(system.bands, start=1)),
                           system.grad[h:], statics.coupling[h:], statics.matrix, statics.grad)


# ---- the five kinds of term: one adapter each ------------------------------------------------------------------


class _TermKind:
    """How the solver evaluates and linearises the terms of one kind (their footprint: see
    :mod:`bcmocap.residuals.base`). ``residuals`` gives a term's raw blocks ``(r (W, …, k), valid)``; ``linearise``
    adds the terms' IRLS Gauss–Newton blocks to the system."""

    def residuals(self, problem: WindowProblem, term: Term, point: _Point) -> tuple[jax.Array, jax.Array]:
        raise NotImplementedError

    def linearise(self, problem: WindowProblem, terms: list[Term], system: _System) -> None:
        raise NotImplementedError


class _FrameKind(_TermKind):
    """One frame's state: ``term.residual(state, data[t])``."""

    def residuals(self, problem, term, point):
        return jax.vmap(lambda x, data: term.residual(x, data, declared_statics(term, x.statics)))(
            point.curr_states, term.data)

    def linearise(self, problem, terms, system):  # one differentiation of the frame state serves every frame term
        d, h = system.d, system.h

        def frame_residuals(v, ref_t, data):
            state = model_state(problem, ref_t, v[:d], static_values(problem, v[d:]))
            return tuple(t.masked(*t.residual(state, dt, declared_statics(t, state.statics))) for t, dt in zip(terms, data))

        args = (system.with_z(system.y), system.frames(slice(h, None)), tuple(t.data for t in terms))
        rs, jacs = jax.vmap(frame_residuals)(*args), jax.vmap(_jacobian(frame_residuals, args))(*args)
        for term, r, jac in zip(terms, rs, jacs):
            r, jac = _irls_rows(term, r, jac)  # jac: (W, m, D + S)
            system.add_span_rows(r, jac[..., None, :d], jac[..., d:])


class _PairKind(_TermKind):
    """Consecutive frames: ``term.residual(prev, curr, data[t])``; the pair before a sequence's first frame is dropped."""

    def residuals(self, problem, term, point):
        r, v = jax.vmap(lambda prev, curr, data: term.residual(StackedFrames(prev, curr), data, declared_statics(term, prev.statics)))(
            point.prev_states, point.curr_states, term.data)
        return r, _pair_valid(problem, v)

    def linearise(self, problem, terms, system):  # likewise one differentiation of both frames of each pair
        d, h = system.d, system.h

        def pair_residuals(v, ref_prev, ref_curr, data, ok):
            at = static_values(problem, v[2 * d :])
            prev = model_state(problem, ref_prev, v[:d], at)
            curr = model_state(problem, ref_curr, v[d : 2 * d], at)
            return tuple(t.masked(*_and_valid(t.residual(StackedFrames(prev, curr), dt, declared_statics(t, prev.statics)), ok))
                         for t, dt in zip(terms, data))

        pairs = jnp.concatenate([system.y_ext[h - 1 : -1], system.y_ext[h:]], axis=1)  # (W, 2D)
        args = (system.with_z(pairs), system.frames(slice(h - 1, -1)), system.frames(slice(h, None)),
                tuple(t.data for t in terms), _span_ok(problem, 2))
        rs, jacs = jax.vmap(pair_residuals)(*args), jax.vmap(_jacobian(pair_residuals, args))(*args)
        for term, r, jac in zip(terms, rs, jacs):  # jac: (W, n, k, 2D + S)
            r, jac = _irls_rows(term, r, jac)
            jy = jac[..., : 2 * d].reshape(*jac.shape[:2], 2, d)
            system.add_span_rows(r, jy, jac[..., 2 * d :])


class _SpanKind(_TermKind):
    """Frames ``t − span + 1 … t``: ``term.residual(states, data[t])`` with states of leading axis ``span``."""

    def residuals(self, problem, term, point):
        spans = jax.tree.map(lambda a: a[_span_index(problem, term.span)], point.states)
        r, v = jax.vmap(lambda x, data: term.residual(x, data, _span_statics(term, x)))(spans, term.data)
        return r, v & _span_ok(problem, term.span).reshape(-1, *([1] * (v.ndim - 1)))

    def linearise(self, problem, terms, system):
        (term,) = terms
        d, w, span = system.d, system.w, term.span

        def span_residuals(v, ref_span, data, ok):
            states = model_state(problem, ref_span, v[: span * d].reshape(span, d), static_values(problem, v[span * d :]))
            return term.masked(*_and_valid(term.residual(states, data, _span_statics(term, states)), ok))

        index = _span_index(problem, span)
        args = (system.with_z(system.y_ext[index].reshape(w, span * d)), system.frames(index), term.data,
                _span_ok(problem, span))
        r, jac = jax.vmap(span_residuals)(*args), jax.vmap(_jacobian(span_residuals, args))(*args)
        r, jac = _irls_rows(term, r, jac)  # jac: (W, n, k, span·D + S) → (W, m, span·D + S)
        jy = jac[..., : span * d].reshape(*jac.shape[:2], span, d)
        system.add_span_rows(r, jy, jac[..., span * d :])


class _CameraKind(_TermKind):
    """One camera at one frame: ``term.residual(cam_from_world, camera, data[t, c][, statics])``, differentiated
    w.r.t. the camera's pose (and its own static blocks), then chained with the pose's Jacobian."""

    def residuals(self, problem, term, point):
        h = problem.history
        own = _camera_term_statics(problem, term)
        fn = lambda pose, cam, data, values, z_own: term.residual(CameraView(SE3(pose), cam), data,
                                                                  _own_statics(own, values, z_own))
        cams, cam_axis = _slot_intrinsics(term, problem.rig)
        return jax.vmap(jax.vmap(fn, in_axes=(0, 0, 0, 0, 0)), in_axes=(0, cam_axis, 0, 0, 0))(
            _slot_gather(term, point.cam_from_world.wxyz_xyz[h:]), cams, term.data, *_camera_statics_args(own, point.z))

    def linearise(self, problem, terms, system):
        (term,) = terms
        d, h, n_static = system.d, system.h, system.n_static
        own = _camera_term_statics(problem, term)
        own_size = 0 if own is None else own.size

        def cam_blocks(pose, cam, data, values, z_own):
            if own is not None:
                fn = lambda p, delta: term.masked(*term.residual(CameraView(p, cam), data, own.at(values, z_own + delta)))
                r, jac = _irls_rows(term, *_camera_measurement_jacobians(fn, (pose,), static_size=own.size))
            elif term.world_points(data) is None:
                fn = lambda p: term.masked(*term.residual(CameraView(p, cam), data, {}))
                r, jac = _irls_rows(term, *_camera_measurement_jacobians(fn, (pose,)))
            else:
                r, jac = _irls_rows(term, *_point_measurement_jacobians(term, SE3(pose), cam, data))
            return jac.T @ jac, jac.T @ r

        cams, cam_axis = _slot_intrinsics(term, problem.rig)
        hess, g = jax.vmap(jax.vmap(cam_blocks, in_axes=(0, 0, 0, 0, 0)), in_axes=(0, cam_axis, 0, 0, 0))(
            _slot_gather(term, system.cam_poses[h:]), cams, term.data, *_camera_statics_args(own, system.z)
        )  # (W, C, 6 + k, 6 + k), (W, C, 6 + k) (C: cameras or slots; k: the term's own static tangents)
        jp = _slot_gather(term, system.pose_jac[h:])
        jy = jp[..., :d]
        system.diag = system.diag.at[h:].add(jnp.einsum("tcai,tcab,tcbj->tij", jy, hess[..., :6, :6], jy))
        system.grad = system.grad.at[h:].add(jnp.einsum("tcai,tca->ti", jy, g[..., :6]))
        if jp.shape[-1] > d or own_size:  # the poses depend on z (variable model), or the term reads z itself
            jz = _camera_static_jacobian(jp[..., d:], own, n_static)
            system.statics = _add_camera_statics(system.statics, [(h, _with_zero_rows(jy, own_size))], jz, hess, g)


class _CameraPairKind(_TermKind):
    """One camera at frames ``t − 1`` and ``t``: ``term.residual(prev, curr, camera, data[t, c][, statics])``,
    differentiated w.r.t. both poses (their rotations only, for a ``rotation_only`` term)."""

    def residuals(self, problem, term, point):
        h = problem.history
        own = _camera_term_statics(problem, term)
        fn = lambda prev, pose, cam, data, values, z_own: term.residual(
            CameraView(SE3(jnp.stack([prev, pose])), cam), data, _own_statics(own, values, z_own))
        cams, cam_axis = _slot_intrinsics(term, problem.rig)
        poses = point.cam_from_world.wxyz_xyz
        r, v = jax.vmap(jax.vmap(fn, in_axes=(0, 0, 0, 0, 0, 0)), in_axes=(0, 0, cam_axis, 0, 0, 0))(
            _slot_gather(term, poses[h - 1 : -1]), _slot_gather(term, poses[h:]), cams, term.data,
            *_camera_statics_args(own, point.z),
        )
        return r, _pair_valid(problem, v)

    def linearise(self, problem, terms, system):
        (term,) = terms
        d, h, n_static = system.d, system.h, system.n_static
        own = _camera_term_statics(problem, term)
        own_size = 0 if own is None else own.size

        def cam_pair_blocks(prev, pose, cam, data, values, z_own, ok):
            if own is not None:
                fn = lambda p0, p1, delta: term.masked(*_and_valid(
                    term.residual(CameraView(stacked(p0, p1), cam), data, own.at(values, z_own + delta)), ok))
            else:
                fn = lambda p0, p1: term.masked(*_and_valid(term.residual(CameraView(stacked(p0, p1), cam), data, {}), ok))
            r, jac = _irls_rows(term, *_camera_measurement_jacobians(fn, (prev, pose), term.rotation_only, own_size))
            return jac.T @ jac, jac.T @ r

        cams, cam_axis = _slot_intrinsics(term, problem.rig)
        hess, g = jax.vmap(jax.vmap(cam_pair_blocks, in_axes=(0, 0, 0, 0, 0, 0, None)),
                           in_axes=(0, 0, cam_axis, 0, 0, 0, 0))(
            _slot_gather(term, system.cam_poses[h - 1 : -1]), _slot_gather(term, system.cam_poses[h:]), cams, term.data,
            *_camera_statics_args(own, system.z), _span_ok(problem, 2),
        )  # (W, C, 12 + k, 12 + k), (W, C, 12 + k) (C: cameras or slots)
        jp_prev, jp_curr = _slot_gather(term, system.pose_jac[h - 1 : -1]), _slot_gather(term, system.pose_jac[h:])
        if jp_curr.shape[-1] > d or own_size:  # the poses depend on z (variable model), or the term reads z itself
            jz = _camera_static_jacobian(jnp.concatenate([jp_prev[..., d:], jp_curr[..., d:]], axis=2), own,
                                         n_static)  # (W, C, 12 + k, S)
            zero = jnp.zeros_like(jp_curr[..., :d])
            blocks = [(h - 1, _with_zero_rows(jnp.concatenate([jp_prev[..., :d], zero], axis=2), own_size)),
                      (h, _with_zero_rows(jnp.concatenate([zero, jp_curr[..., :d]], axis=2), own_size))]
            system.statics = _add_camera_statics(system.statics, blocks, jz, hess, g)
            jp_prev, jp_curr = jp_prev[..., :d], jp_curr[..., :d]
        h00 = jnp.einsum("tcai,tcab,tcbj->tij", jp_prev, hess[:, :, :6, :6], jp_prev)
        h11 = jnp.einsum("tcai,tcab,tcbj->tij", jp_curr, hess[:, :, 6:12, 6:12], jp_curr)
        h01 = jnp.einsum("tcai,tcab,tcbj->tij", jp_prev, hess[:, :, :6, 6:12], jp_curr)
        system.diag = system.diag.at[h - 1 : -1].add(h00).at[h:].add(h11)
        system.bands[0] = system.bands[0].at[h - 1 : -1].add(h01)
        system.grad = system.grad.at[h - 1 : -1].add(jnp.einsum("tcai,tca->ti", jp_prev, g[:, :, :6]))
        system.grad = system.grad.at[h:].add(jnp.einsum("tcai,tca->ti", jp_curr, g[:, :, 6:12]))


_KINDS = {"frame": _FrameKind(), "pair": _PairKind(), "span": _SpanKind(), "camera": _CameraKind(),
          "camera_pair": _CameraPairKind()}
#: Kinds whose terms are linearised together (one differentiation of the frame state serves them all), first.
_GROUPED = (_KINDS["frame"], _KINDS["pair"])


def term_kind(term: Term) -> _TermKind:
    """The solver's adapter for ``term``'s kind (``term.kind``: see :mod:`bcmocap.residuals.base`).

    Raises:
        TypeError: a term that is none of the five kinds.
    """
    kind = _KINDS.get(getattr(term, "kind", None))
    if kind is None:
        raise TypeError(f"{getattr(term, 'label', type(term).__name__)}: a term must subclass FrameTerm, PairTerm, "
                        "MultiFrameTerm, CameraTerm or CameraPairTerm (or be made by bcmocap.residuals.residual_term)")
    return kind


def _jacobian(fn, batched_args):
    """``jacfwd`` or ``jacrev`` of ``fn`` w.r.t. its first argument, whichever needs fewer passes.

    ``batched_args`` carry a leading frame axis (the caller vmaps). Smoothness pairs have 2·D
    tangents but fewer residual rows, where reverse mode is several times cheaper.
    """
    one = jax.tree.map(lambda a: a[0], batched_args)
    rows = sum(int(prod(o.shape)) for o in jax.tree.leaves(jax.eval_shape(fn, *one)))
    tangents = int(prod(one[0].shape))
    return jax.jacrev(fn) if rows < tangents else jax.jacfwd(fn)


def _point_measurement_jacobians(term: CameraTerm, cam_from_world: SE3, camera, data):
    """Residual blocks ``(n, k)`` and Jacobians ``(n, k, 6)`` of a term that acts on camera-frame points.

    Block i depends on point i only, so one 3-tangent JVP shared by all points gives every per-point
    Jacobian ∂r_i/∂p_i at once; it is chained with ∂p_i/∂ξ of the left perturbation ``exp(ξ) · p``.
    """
    points = transform_points(cam_from_world, term.world_points(data))
    residual = lambda shift: term.masked(*term.residual_in_camera(points + shift, camera, data))
    r, d_point = residual(jnp.zeros(3)), jax.jacfwd(residual)(jnp.zeros(3))  # (n, k), (n, k, 3)
    d_action = jax.jacfwd(lambda xi: transform_points(SE3.exp(xi), points))(jnp.zeros(6))  # (n, 3, 6)
    return r, jnp.einsum("nkj,nji->nki", d_point, d_action)


def _irls_rows(term: Term, r: jax.Array, jac: jax.Array) -> tuple[jax.Array, jax.Array]:
    """IRLS-weighted rows: blocks ``(..., n, k)`` and Jacobians ``(..., n, k, P)`` → ``(..., n·k)``, ``(..., n·k, P)``.

    Each block is scaled by ``sqrt(λ ρ'(‖r‖²))``, so ``JᵀJ = Σ λρ' JᵀJ`` and ``Jᵀr`` is the exact gradient
    of ``λ ½ Σ ρ``.
    """
    scale = term.irls_sqrt_weights(r)[..., None]
    r, jac = r * scale, jac * scale[..., None]
    return r.reshape(*r.shape[:-2], -1), jac.reshape(*jac.shape[:-3], -1, jac.shape[-1])


def _add_camera_statics(statics: _StaticBlocks, frames, jz, hess, g) -> _StaticBlocks:
    """Add camera blocks ``hess`` ``(W, C, K, K)``, ``g`` ``(W, C, K)`` whose poses' Jacobian w.r.t. ``z`` is ``jz``
    ``(W, C, K, S)`` to the static blocks; ``frames``: ``(first extended index, Jacobian (W, C, K, D) w.r.t.
    those frames' variables)`` for the frames the poses depend on."""
    coupling = statics.coupling
    hz = jnp.einsum("tcab,tcbs->tcas", hess, jz)
    for first, jy in frames:
        coupling = coupling.at[first : first + jy.shape[0]].add(jnp.einsum("tcai,tcas->tis", jy, hz))
    return _StaticBlocks(coupling, statics.matrix + jnp.einsum("tcas,tcau->su", jz, hz),
                         statics.grad + jnp.einsum("tcas,tca->s", jz, g))


def _camera_static_jacobian(pose_z: jax.Array, own: _CameraTermStatics | None, num_static: int) -> jax.Array:
    """``(W, C, P + k, S)``: how a camera term's ``P`` pose tangents (``pose_z`` ``(W, C, P, S')``, ``S' = S`` with a
    variable model, else 0) and its own ``k`` static tangents (columns ``own.columns`` of ``z``) move with ``z``."""
    w, c, p = pose_z.shape[:3]
    if pose_z.shape[-1] != num_static:
        pose_z = jnp.zeros((w, c, p, num_static))
    if own is None:
        return pose_z
    return jnp.concatenate([pose_z, jax.nn.one_hot(own.columns, num_static, dtype=pose_z.dtype)], axis=2)


def _with_zero_rows(jac: jax.Array, rows: int) -> jax.Array:
    """``(W, C, P, D)`` → ``(W, C, P + rows, D)``: a camera term's own static tangents do not move the frames."""
    return jnp.concatenate([jac, jnp.zeros((*jac.shape[:2], rows, jac.shape[3]), jac.dtype)], axis=2) if rows else jac


def _and_valid(result, ok):
    r, v = result
    return r, v & ok


def _add_span_blocks(diag, bands, grad, statics, r, jy, jz, history):
    """Add a term's IRLS rows ``r`` ``(W, m)`` with Jacobians ``jy`` ``(W, m, N, D)`` w.r.t. frames ``t − N + 1 … t``
    and ``jz`` ``(W, m, S)`` w.r.t. the static variables to the banded system (extended arrays of a window with
    ``history`` fixed frames) and the static blocks."""
    w, span = jy.shape[0], jy.shape[2]
    bands = list(bands)
    coupling = statics.coupling
    for i in range(span):
        rows = slice(history - (span - 1) + i, history - (span - 1) + i + w)  # extended index of frame t − N + 1 + i
        grad = grad.at[rows].add(jnp.einsum("tri,tr->ti", jy[:, :, i], r))
        for j in range(i, span):
            block = jnp.einsum("tri,trj->tij", jy[:, :, i], jy[:, :, j])
            if i == j:
                diag = diag.at[rows].add(block)
            else:
                bands[j - i - 1] = bands[j - i - 1].at[rows].add(block)
        if jz.shape[-1]:
            coupling = coupling.at[rows].add(jnp.einsum("tri,trs->tis", jy[:, :, i], jz))
    if jz.shape[-1]:
        statics = _StaticBlocks(coupling, statics.matrix + jnp.einsum("trs,tru->su", jz, jz),
                                statics.grad + jnp.einsum("trs,tr->s", jz, r))
    return diag, bands, grad, statics


def make_window_problem(
    skeleton: Skeleton,
    rig: Rig | None,
    terms: Sequence[Term],
    reference: Motion,
    num_previous: int | bool,
    statics: dict | None = None,
    model_parameters: ModelParameters | None = None,
    frame_values: dict | None = None,
) -> WindowProblem:
    """A :class:`WindowProblem`; ``reference`` holds :func:`window_history` fixed frames first, of which
    ``num_previous`` exist (a bool for the paper's terms: whether the frame before the window exists);
    ``statics`` the static variables' starting values (missing blocks start at their start value; the
    model's at ``model_parameters.start()``), the reference motion being expressed in the model at those
    values; ``frame_values`` the per-frame variables' values ``{name: (H + W, …)}`` (missing: start values).

    Raises:
        ValueError: a term declares a static variable named ``"model"`` while the model is variable, a
            :class:`PerCamera` block's camera count is not the rig's, or a given value has the wrong shape.
    """
    num_cameras = rig.num_cameras if rig is not None else 0
    layout = static_layout(terms)
    frames = frame_layout(terms)
    for name, variable in (*layout, *frames):
        if isinstance(variable, PerCamera) and variable.num_cameras != num_cameras:
            raise ValueError(f"variable {name!r} is declared for {variable.num_cameras} cameras; the rig has {num_cameras}")
    if CAMERA_OFFSETS in dict(frames) and dict(frames)[CAMERA_OFFSETS] != PerCamera(Euclidean(6), num_cameras):
        raise ValueError(f"{CAMERA_OFFSETS!r} must be declared as PerCamera(Euclidean(6), {num_cameras})")
    statics = dict(statics or {})
    if model_parameters is not None:
        if MODEL in dict(layout):
            raise ValueError(f"static variable {MODEL!r} is the model's; a term may not declare it")
        layout = (*layout, (MODEL, Euclidean(model_parameters.size)))
        statics.setdefault(MODEL, model_parameters.start())
    statics = {name: _block_value(statics.get(name), variable, (), f"static variable {name!r}") for name, variable in layout}
    length = reference.root_position.shape[0]
    given = dict(frame_values or {})
    values = {name: _block_value(given.get(name), variable, (length,), f"per-frame variable {name!r}")
              for name, variable in frames}
    return WindowProblem(skeleton, rig, tuple(terms), reference, int(num_previous), statics, model_parameters, values)


def _block_value(value, variable: Variable, batch: tuple[int, ...], what: str) -> jax.Array:
    """``value`` (None: the block's start) as float64 of shape ``(*batch, *variable.value_shape)``."""
    shape = (*batch, *variable.value_shape)
    if value is None:
        return jnp.broadcast_to(jnp.asarray(variable.start(), jnp.float64), shape)
    value = jnp.asarray(value, jnp.float64)
    if value.size != math.prod(shape):
        raise ValueError(f"{what}: value of shape {value.shape}; expected {shape}")
    return value.reshape(shape)
