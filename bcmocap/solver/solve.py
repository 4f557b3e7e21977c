"""Whole-sequence solve by overlapping sliding windows (§4.3 of the paper).

Windows have a fixed length (one compilation serves them all; the last window is shifted back to end
at the last frame). Each window starts from the current estimate, holds the frame just before it fixed
so pair terms (smoothness, homography) connect across the seam, and hands its last ``overlap`` frames
to the next window, which solves them again with more future context. Memory is that of one window,
whatever the sequence length; the problem's data is sliced (or generated) one window at a time.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Protocol

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..kinematics.rig import Rig
from ..kinematics.skeleton import Motion, Skeleton
from ..residuals.base import Term
from ..precision import require_float64
from .levenberg_marquardt import FINITE, NON_FINITE_MESSAGES, Convergence, levenberg_marquardt
from .model_parameters import MODEL, ModelParameters, reaxis
from .program_cache import cached_call
from .window import (WindowProblem, frame_layout, make_window_problem, model_motion, normal_equations, residuals,
                     static_values, window_history)


class SequenceProblem(Protocol):
    """What the sliding-window solver needs: a model and terms it can cut into windows."""

    skeleton: Skeleton
    rig: Rig | None

    @property
    def num_frames(self) -> int: ...

    def window(self, start: int, stop: int) -> Sequence[Term]: ...


@dataclasses.dataclass
class Problem:
    """Eq. (1) for a whole sequence: a skeleton, its rig and residual terms over ``num_frames`` frames.

    Attributes:
        skeleton: the kinematic tree (fixed during the solve).
        rig: cameras on the segments, or None if no term needs cameras.
        terms: residual terms whose data cover all frames.
    """

    skeleton: Skeleton
    rig: Rig | None
    terms: Sequence[Term]

    def __post_init__(self):
        self.terms = tuple(self.terms)
        if not self.terms:
            raise ValueError("Problem: no residual terms")
        counts = {t.label: t.num_frames() for t in self.terms}
        if len(set(counts.values())) != 1:
            raise ValueError(f"Problem: terms cover different numbers of frames: {counts}")
        uses_cameras = any(t.per_camera for t in self.terms)
        if uses_cameras and self.rig is None:
            raise ValueError("Problem: camera terms need a rig")
        if self.rig is not None:
            self.rig.check(self.skeleton)
        num_cameras = self.rig.num_cameras if self.rig is not None else 0
        for term in self.terms:
            term.check(self.num_frames, num_cameras)

    @property
    def num_frames(self) -> int:
        return self.terms[0].num_frames()

    def window(self, start: int, stop: int) -> tuple[Term, ...]:
        return tuple(t.window(start, stop) for t in self.terms)


@dataclasses.dataclass(frozen=True)
class SolverOptions:
    """Sliding-window Levenberg–Marquardt settings.

    Attributes:
        window: frames per window (the whole sequence if it is shorter).
        overlap: frames each window hands to the next to solve again.
        max_steps: LM iterations per window (accepted or rejected).
        rtol, atol: stopping tolerances: stop after an accepted step that changes the variables by less
            than ``atol + rtol·|y|`` (RMS over the window; rad, m) and the cost by less than
            ``atol + rtol·cost``. Gauss–Newton converges quadratically from registered cameras: once a
            step is below 1e-4 rad / 0.1 mm the cost is within ~1e-11 of its minimum.
        damping_scale: initial Levenberg–Marquardt damping relative to the Marquardt diagonal.
    """

    window: int = 60
    overlap: int = 10
    max_steps: int = 40
    rtol: float = 1e-4
    atol: float = 1e-4
    damping_scale: float = 1e-3

    def __post_init__(self):
        if self.window < 1:
            raise ValueError(f"SolverOptions: window must be ≥ 1, got {self.window}")
        if not 0 <= self.overlap < self.window:
            raise ValueError(f"SolverOptions: overlap must be in [0, window), got {self.overlap} with window {self.window}")
        if self.max_steps < 1:
            raise ValueError(f"SolverOptions: max_steps must be ≥ 1, got {self.max_steps}")


@dataclasses.dataclass(frozen=True)
class WindowReport:
    """How one window's solve went (costs are ½ Σ r² of Eq. 1 over the window)."""

    start: int
    stop: int
    initial_cost: float
    final_cost: float
    num_steps: int
    num_accepted_steps: int
    converged: bool
    seconds: float

    @classmethod
    def from_convergence(cls, start: int, stop: int, lm: Convergence, seconds: float) -> WindowReport:
        return cls(start, stop, float(lm.initial_cost), float(lm.final_cost), int(lm.num_steps),
                   int(lm.num_accepted_steps), bool(lm.converged), seconds)


@dataclasses.dataclass
class Solution:
    """Result of :func:`solve`: the motion over all frames, one report per window, the static variables the
    terms declared (``{name: value}``, the last window's estimate) and their per-frame variables
    (``{name: (T, …)}``); both empty without any."""

    motion: Motion
    reports: list[WindowReport]
    statics: dict = dataclasses.field(default_factory=dict)
    frame_variables: dict = dataclasses.field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return all(r.converged for r in self.reports)


def window_starts(num_frames: int, window: int, overlap: int) -> list[int]:
    """First frame of each window; all windows have length ``min(window, num_frames)``."""
    window = min(window, num_frames)
    starts, start = [0], 0
    while start + window < num_frames:
        start = min(start + window - overlap, num_frames - window)
        starts.append(start)
    return starts


def _system(problem: WindowProblem, v) -> jax.Array:
    """The normal equations at the solver's variables: ``y``, or ``(y, z)`` with static variables."""
    return normal_equations(problem, *v) if isinstance(v, tuple) else normal_equations(problem, v)


def _solve_window(problem: WindowProblem, options: SolverOptions):
    """The compiled solve of one window (through :func:`~bcmocap.solver.program_cache.cached_call`)."""
    w, d, n_static = problem.num_frames, problem.frame_size, problem.num_statics
    fn = lambda v, args: residuals(args, *v) if isinstance(v, tuple) else residuals(args, v)
    v0 = (jnp.zeros((w, d)), jnp.zeros(n_static)) if n_static else jnp.zeros((w, d))
    value, report = levenberg_marquardt(fn, eqx.Partial(_system, problem), v0, problem, rtol=options.rtol,
                                        atol=options.atol, damping_scale=options.damping_scale, max_steps=options.max_steps)
    y, z = value if n_static else (value, None)
    statics = static_values(problem, z)
    motion, frame_values = model_motion(problem, y, statics)
    return motion, statics, frame_values, report


def _non_finite_window(wp: WindowProblem, start: int, stop: int) -> str:
    """Why window ``[start, stop)`` went non-finite: the terms whose residuals are already non-finite at its
    initial motion, or else the steps."""
    blocks = residuals(wp, jnp.zeros((stop - start, wp.frame_size)))
    bad = [t.label for t, b in zip(wp.terms, blocks) if not np.all(np.isfinite(np.asarray(b)))]
    why = (f"term(s) {', '.join(repr(b) for b in bad)} are non-finite at its initial motion" if bad
           else "its terms are finite at its initial motion, so the Levenberg–Marquardt steps diverged")
    return f"solve: window of frames [{start}, {stop}) has a non-finite cost or motion: {why}; nothing was kept"


def solve(
    problem: SequenceProblem,
    initial_motion: Motion,
    options: SolverOptions = SolverOptions(),
    *,
    progress: bool | Callable[[WindowReport], None] = False,
    skip_windows: int = 0,
    checkpoint: Callable[[int, WindowReport, Solution], None] | None = None,
    model_parameters: ModelParameters | None = None,
    initial_statics: dict | None = None,
    initial_frame_variables: dict | None = None,
) -> Solution:
    """Minimise Eq. (1) over a whole sequence with overlapping windows.

    Args:
        problem: a :class:`Problem` (or anything with ``skeleton``, ``rig``, ``num_frames`` and
            ``window(start, stop)``).
        initial_motion: ``(T, ...)`` starting motion, e.g. from registered camera poses.
        options: window length, overlap, iteration limits.
        progress: True for a progress bar, or a callable receiving each :class:`WindowReport`.
        skip_windows: resume: the first ``skip_windows`` windows are taken as solved already (their
            frames in ``initial_motion`` and ``initial_frame_variables``, and ``initial_statics``, hold a
            previous run's :class:`Solution` so far; the next window starts from them exactly as the
            uninterrupted run did).
        checkpoint: called after each window with its index, its report and the :class:`Solution` so far
            (solved frames up to the window's end, the initial values after), e.g. to save it.
        model_parameters: also solve for the skeleton and rig (static variables ``"model"``, with their
            prior; ``problem.skeleton`` and ``rig`` and ``initial_motion`` must be the model at
            ``model_parameters.start()``). Each window starts from the previous window's estimate, so
            the estimate uses all frames only with one window over the sequence
            (:func:`bcmocap.solver.refine_skeleton_and_rig`). ``Solution.statics["model"]`` holds it.
        initial_statics: ``{name: value}`` the static variables the first window starts from (missing: the
            blocks' start values, 0 or identity).
        initial_frame_variables: ``{name: (T, …)}`` the per-frame variables' starting values (missing: start
            values).

    Returns:
        The solved motion and per-window reports.

    Raises:
        ValueError: mismatched shapes, NaN/inf, or a window without any usable observation.
        FloatingPointError: a window's cost or motion became non-finite (naming the window and the terms that
            are non-finite at its initial motion), or its Gauss–Newton system did at a point of finite cost
            (found inside the compiled solve: ``Convergence.non_finite``).
    """
    # statics are carried window to window; frame_values are (T, …) each
    starts, window, root, rotations, statics, frame_values = prepare_sequence(
        problem, initial_motion, options, initial_statics, initial_frame_variables, "bcmocap.solve")
    num_frames = problem.num_frames
    reports: list[WindowReport] = []
    bar = None
    if progress is True:
        from tqdm.auto import tqdm

        bar = tqdm(total=num_frames, desc="solving", unit="frame")
    if not 0 <= skip_windows <= len(starts):
        raise ValueError(f"solve: skip_windows must be in [0, {len(starts)}], got {skip_windows}")
    done = starts[skip_windows - 1] + window if skip_windows else 0
    if bar is not None and done:
        bar.update(done)
    reader = ThreadPoolExecutor(max_workers=1, thread_name_prefix="bcmocap-window-terms")
    upcoming = reader.submit(window_terms, problem, starts[skip_windows], starts[skip_windows] + window) \
        if skip_windows < len(starts) else None
    try:
        for index, start in enumerate(starts[skip_windows:], start=skip_windows):
            stop = start + window
            t0 = time.perf_counter()
            terms = upcoming.result()
            if index + 1 < len(starts):  # read while this window solves (the compiled solve releases the GIL)
                upcoming = reader.submit(window_terms, problem, starts[index + 1], starts[index + 1] + window)
            frame_values = with_start_values(frame_values, terms, num_frames)
            solved = solve_window_span(problem, terms, start, stop, root, rotations, frame_values, statics, options,
                                       model_parameters)
            new_statics, lm = solved.statics, solved.convergence
            root[start:stop], rotations[start:stop] = solved.root_position, solved.rotations
            for name, value in solved.frame_values.items():
                frame_values[name][start:stop] = value
            if model_parameters is not None:  # later frames keep their hinge angles about the moved axes
                old_axes = model_parameters.model(solved.problem.statics[MODEL])[0].hinge_axes
                new_axes = model_parameters.model(jnp.asarray(new_statics[MODEL]))[0].hinge_axes
                rotations[stop:] = np.asarray(reaxis(model_parameters.layout, Motion(root[stop:], rotations[stop:]),
                                                     old_axes, new_axes).rotations)
            statics = new_statics  # the next window starts from this window's estimate
            report = WindowReport.from_convergence(start, stop, lm, time.perf_counter() - t0)
            reports.append(report)
            if bar is not None:
                bar.update(stop - done)
                bar.set_postfix(cost=f"{report.final_cost:.4g}")
            elif callable(progress):
                progress(report)
            if checkpoint is not None:
                checkpoint(index, report, Solution(Motion(root.copy(), rotations.copy()), list(reports), dict(statics),
                                                   {k: v.copy() for k, v in frame_values.items()}))
            done = stop
    finally:
        reader.shutdown(cancel_futures=True)
        if bar is not None:  # also when a window fails: the error's line then starts on a line of its own
            bar.close()
    return Solution(Motion(root, rotations), reports, statics, frame_values)


def prepare_sequence(problem: SequenceProblem, initial_motion: Motion, options: SolverOptions,
                     initial_statics: dict | None, initial_frame_variables: dict | None, what: str):
    """Checked inputs of a whole-sequence solve as numpy: ``(starts, window, root, rotations, statics,
    frame_values)`` (window start frames, the window length, copies of the starting estimates)."""
    require_float64(what)
    num_frames = problem.num_frames
    initial_motion.check(problem.skeleton, "initial_motion")
    if initial_motion.num_frames != num_frames:
        raise ValueError(f"initial_motion has {initial_motion.num_frames} frames, the problem has {num_frames}")
    window = min(options.window, num_frames)
    starts = window_starts(num_frames, window, min(options.overlap, window - 1))
    root = np.array(initial_motion.root_position, dtype=np.float64)
    rotations = np.array(initial_motion.rotations, dtype=np.float64)
    statics = {k: np.asarray(v, np.float64) for k, v in (initial_statics or {}).items()}
    frame_values = {k: np.array(v, np.float64) for k, v in (initial_frame_variables or {}).items()}
    for name, value in frame_values.items():
        if value.shape[:1] != (num_frames,):
            raise ValueError(f"initial_frame_variables[{name!r}] has shape {value.shape}; expected {num_frames} frames first")
    return starts, window, root, rotations, statics, frame_values


def window_terms(problem: SequenceProblem, start: int, stop: int) -> tuple[Term, ...]:
    """The problem's terms cut to frames ``[start, stop)``.

    Raises:
        ValueError: no camera term of the window has a usable observation.
    """
    terms = tuple(problem.window(start, stop))
    _check_window_has_observations(terms, start, stop)
    return terms


def with_start_values(frame_values: dict, terms: Sequence[Term], num_frames: int) -> dict:
    """``frame_values`` (``{name: (T, …)}``) with every per-frame block the terms declare and it lacks at the
    block's start value (the same dict when it lacks none)."""
    missing = [(name, variable) for name, variable in frame_layout(terms) if name not in frame_values]
    if not missing:
        return frame_values
    return {**frame_values, **{name: np.array(np.broadcast_to(variable.start(), (num_frames, *variable.value_shape)))
                               for name, variable in missing}}


@dataclasses.dataclass(frozen=True)
class SolvedSpan:
    """One window's solve (:func:`solve_window_span`): its motion ``(w, …)``, static values, per-frame values
    ``{name: (w, …)}`` (numpy), the solver's convergence record and the window's problem."""

    root_position: np.ndarray
    rotations: np.ndarray
    statics: dict
    frame_values: dict
    convergence: Convergence
    problem: WindowProblem


def solve_window_span(
    problem: SequenceProblem,
    terms: Sequence[Term],
    start: int,
    stop: int,
    root: np.ndarray,
    rotations: np.ndarray,
    frame_values: dict,
    statics: dict,
    options: SolverOptions,
    model_parameters: ModelParameters | None = None,
) -> SolvedSpan:
    """Solve the window of frames ``[start, stop)`` (its ``terms``, from :func:`window_terms`) starting from the
    whole-sequence estimates ``root`` ``(T, 3)``, ``rotations`` ``(T, J, 4)`` and ``frame_values``
    (``{name: (T, …)}``) and from ``statics``; the :func:`window_history` frames before ``start`` are held
    fixed at those estimates. This is the one implementation of a window's solve: :func:`solve` runs it
    window after window, :mod:`bcmocap.solver.parallel` on windows independently. Nothing is modified.

    Raises:
        FloatingPointError: the window's cost, motion or variables became non-finite (naming the window).
    """
    history = window_history(terms)
    before = np.maximum(np.arange(start - history, start), 0)  # the fixed frames (repeats of 0 at the start)
    extended = np.concatenate([before, np.arange(start, stop)])
    reference = Motion(root[extended], rotations[extended])
    wp = make_window_problem(problem.skeleton, problem.rig, terms, reference, min(start, history), statics,
                             model_parameters, {name: value[extended] for name, value in frame_values.items()})
    motion, new_statics, new_frame_values, lm = cached_call(_solve_window, wp, options)
    if int(lm.non_finite) != FINITE:  # checked inside the compiled solve
        why = NON_FINITE_MESSAGES[int(lm.non_finite)]
        raise FloatingPointError(f"solve: window of frames [{start}, {stop}): {why}; nothing was kept")
    new_root, new_rot = np.asarray(motion.root_position), np.asarray(motion.rotations)
    new_statics = {k: np.asarray(v) for k, v in new_statics.items()}
    new_frame_values = {k: np.asarray(v) for k, v in new_frame_values.items()}
    finite = [new_root, new_rot, np.asarray(lm.initial_cost), np.asarray(lm.final_cost), *new_statics.values(),
              *new_frame_values.values()]
    if not all(np.all(np.isfinite(a)) for a in finite):
        raise FloatingPointError(_non_finite_window(wp, start, stop))
    return SolvedSpan(new_root, new_rot, new_statics, new_frame_values, lm, wp)


@eqx.filter_jit
def _frame_costs(wp: WindowProblem) -> jax.Array:
    """``(W,)``: ½ Σ r² of each frame of the window at its reference (pair terms counted at their later frame)."""
    blocks = residuals(wp, jnp.zeros((wp.num_frames, wp.frame_size)))
    return 0.5 * sum(jnp.sum((r * r).reshape(r.shape[0], -1), axis=1) for r in blocks)


def sequence_cost(
    problem: SequenceProblem,
    motion: Motion,
    *,
    statics: dict | None = None,
    frame_variables: dict | None = None,
    chunk: int = 60,
) -> float:
    """Eq. (1), ½ Σ r² over the whole sequence, at ``motion`` (and the static and per-frame variables' values;
    missing: their start values), e.g. to compare solutions whose windows' costs overlap.

    Evaluated in chunks of ``chunk`` frames (one compiled program; the last chunk shifted back to end at the last
    frame, its frames already counted dropped), each with the frames before it fixed at ``motion``, so every
    frame term and every pair or span of frames is counted once, exactly as a single window over all frames
    would count it.
    """
    require_float64("bcmocap.sequence_cost")
    num_frames = problem.num_frames
    motion.check(problem.skeleton, "motion")
    if motion.num_frames != num_frames:
        raise ValueError(f"motion has {motion.num_frames} frames, the problem has {num_frames}")
    chunk = min(chunk, num_frames)
    root, rotations = np.asarray(motion.root_position, np.float64), np.asarray(motion.rotations, np.float64)
    values = {k: np.asarray(v, np.float64) for k, v in (frame_variables or {}).items()}
    total, counted = 0.0, 0
    while counted < num_frames:
        start = min(counted, num_frames - chunk)
        stop = start + chunk
        terms = tuple(problem.window(start, stop))
        values = with_start_values(values, terms, num_frames)
        history = window_history(terms)
        extended = np.concatenate([np.maximum(np.arange(start - history, start), 0), np.arange(start, stop)])
        wp = make_window_problem(problem.skeleton, problem.rig, terms, Motion(root[extended], rotations[extended]),
                                 min(start, history), statics, None, {k: v[extended] for k, v in values.items()})
        total += float(np.sum(np.asarray(_frame_costs(wp))[counted - start:]))
        counted = stop
    return total


def _check_window_has_observations(terms: Sequence[Term], start: int, stop: int) -> None:
    camera_terms = [t for t in terms if t.per_camera]
    if not camera_terms:
        return
    total = 0.0
    for term in camera_terms:
        weights = term.data.get("weights") if isinstance(term.data, dict) else None
        total += float(jnp.sum(weights)) if weights is not None else 1.0
    if total <= 0.0:
        names = ", ".join(t.label for t in camera_terms)
        raise ValueError(f"no usable observation in the window of frames [{start}, {stop}) ({names} all have zero weight)")


def whole_sequence_residual_function(problem: SequenceProblem, initial_motion: Motion) -> Callable[[np.ndarray], np.ndarray]:
    """The residual vector of the whole sequence as one window, ``y (T·(D + E) + S,) ↦ r``, for reference solvers.

    ``y`` holds each frame's tangent offset from ``initial_motion`` and from the start values of the ``E``
    per-frame variables (so ``y = 0`` is the initial guess), followed by the tangents of the ``S`` static
    variables the terms declare at their start values (none of either for the paper's terms); the residuals
    are exactly those the windowed solver minimises.
    """
    skeleton = problem.skeleton
    n = problem.num_frames
    terms = tuple(problem.window(0, n))
    before = np.zeros(window_history(terms), int)
    reference = Motion(
        np.concatenate([np.asarray(initial_motion.root_position)[before], np.asarray(initial_motion.root_position)]),
        np.concatenate([np.asarray(initial_motion.rotations)[before], np.asarray(initial_motion.rotations)]),
    )
    wp = make_window_problem(skeleton, problem.rig, terms, reference, 0)
    d = wp.frame_size
    size = n * d

    @jax.jit
    def fn(y_flat):
        r = residuals(wp, y_flat[:size].reshape(n, d), y_flat[size:] if wp.num_statics else None)
        return jnp.concatenate([a.reshape(-1) for a in r])

    return fn


def motion_from_tangent(problem: SequenceProblem, initial_motion: Motion, y_flat: np.ndarray) -> Motion:
    """The motion at the variables ``y`` of :func:`whole_sequence_residual_function` (inverse of its variables)."""
    n, d = initial_motion.num_frames, problem.skeleton.num_dofs
    frame_size = d + sum(v.size for _, v in frame_layout(problem.window(0, n)))
    y = jnp.asarray(y_flat)[: n * frame_size].reshape(n, frame_size)[:, :d]
    return problem.skeleton.retract(initial_motion, y)
