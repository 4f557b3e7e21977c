"""The sliding windows of :func:`~bcmocap.solver.solve` solved independently (e.g. on a cluster), then joined.

Why. :func:`~bcmocap.solver.solve` solves its overlapping windows one after the other: each starts from the
previous window's result (its frames, the fixed frame before it, the static and per-frame variables). That
chain is what makes a long sequence take ``windows × one window's time`` whatever the number of machines.
Here every window starts from the *initial* motion instead (the fixed history frames before it too), so
all windows are independent: they go through any ``map(fn, iterable)`` (the builtin, a process pool's, a
Dask client's ``lambda f, xs: client.gather(client.map(f, list(xs)))``) and come back as small picklable
:class:`WindowSolution` records of numpy arrays. This module imports no cluster library; the caller brings
the ``map``. (With a plain Dask ``client.map`` the scheduler unpickles ``fn`` and its JAX arrays: one started
without float64 JAX (``JAX_ENABLE_X64=1``) hands them to the workers as float32. ``Executor.map`` of
:mod:`bcmocap.pipeline.cluster` sends them as bytes, unpickled on the worker in float64.)

Joining (:func:`join_windows`). Consecutive windows are blended across the frames they share, with weights
that ramp linearly from one window to the next (window ``k`` from 1 down, ``k + 1`` from 0 up, summing to
1 at every frame; a frame shared by three windows, possible where the last window is shifted back, has
its weights renormalised). Both windows are at their weakest there (the earlier one lacks future frames
at its end, the later one starts from a fixed initial-motion frame), so the blend is smooth but not as
accurate as the sequential solve, where the later window re-solves those frames starting from the earlier
one's. Frames no window covers keep ``initial_motion``.

- Rotations are unit quaternions (w, x, y, z) per segment (:class:`~bcmocap.kinematics.Motion`: the root's
  ``world_from_root`` and each joint's ``parent_from_child``). They are blended by normalised linear
  interpolation: each window's quaternion is flipped to the hemisphere of the one with the largest weight
  at that frame, the weighted sum is normalised. For two windows this is the chordal (projected
  Euclidean) mean, within O(θ³) of slerp for the angle θ between them — windows agree to a fraction of a
  degree — and it keeps every joint where the skeleton allows: a hinge's quaternions are all
  ``(cos, sin·axis)`` about its one axis, and so is any combination of them; a fixed joint stays identity.
  Root positions and Euclidean per-frame variables are blended linearly, :class:`~bcmocap.residuals.
  variables.Rotation` ones (also inside :class:`~bcmocap.residuals.variables.PerCamera`) like the joints;
  a per-frame block of any other manifold, which this module cannot average, takes the value of the window
  with the largest weight at each frame (a switch at the middle of the overlap).
- Static variables (one value per window, e.g. a sensor bias) are combined into one by a weighted mean in
  which each window counts with the number of frames it contributes to the joined motion (the sum of its
  blend weights), so a window counts as much as the part of the sequence it decides: Euclidean blocks by
  the weighted mean, rotations by the weighted chordal mean as above, other manifolds by the value of the
  window that contributes most frames. (The sequential solve keeps its last window's estimate, which has
  started from all the earlier ones'.)

Seam pass (:func:`solve_windows_independently` with ``seam_pass=True``). After the join, one window of the
same length (so the one compiled window solve serves everything) is centred on each seam — the middle of
the frames two consecutive windows share — started from the joined motion, statics and per-frame values
(its fixed history frame is then a well-solved joined frame), solved through ``map`` as well, and blended
back: weight 1 over the shared frames (and one frame either side), ramping linearly to 0 towards the
middle between this seam and the neighbouring ones (or the seam window's ends). Seam windows of the full
length overlap each other by about ``overlap`` frames; that is harmless, since each starts from the same
joined estimate and is solved alone, and the blend supports are cut at the midpoints between seams so no
frame takes two seam windows (with ``overlap ≥ window / 2`` the seams are closer than the shared frames
and each seam window then decides only the frames nearer its own seam). The seam windows re-solve the
shared frames with the whole window of context around them, as the sequential solve's later window does.

Cost: ``windows`` window-solves, plus ``windows − 1`` with the seam pass, i.e. about twice the sequential
solve's work, in two rounds of independent solves (wall time ≈ 2 × one window's with enough workers).

Not supported: solving the skeleton and rig (:class:`~bcmocap.solver.ModelParameters`), whose windows' motions
would be expressed in different models; use :func:`~bcmocap.solver.solve`.
"""

from __future__ import annotations

import builtins
import dataclasses
import functools
import time
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from ..kinematics.skeleton import Motion
from ..residuals.variables import Euclidean, PerCamera, Rotation, Variable
from .solve import (SequenceProblem, Solution, SolverOptions, WindowReport, prepare_sequence, solve_window_span,
                    window_terms, with_start_values)
from .window import frame_layout, static_layout

#: How a block is averaged: linearly, as unit quaternions (last axis), or not at all (largest weight wins).
EUCLIDEAN, ROTATION, OTHER = "euclidean", "rotation", "other"

Map = Callable[[Callable, Iterable], Iterable]


@dataclasses.dataclass(frozen=True, eq=False)
class WindowSolution:
    """One window solved on its own (:func:`solve_window`): plain numpy arrays and Python scalars, cheap to
    pickle to and from a worker.

    Attributes:
        start, stop: the window's frames ``[start, stop)``.
        root_position: ``(w, 3)`` (m).
        rotations: ``(w, J, 4)`` unit quaternions (w, x, y, z), as in :class:`~bcmocap.kinematics.Motion`.
        statics: ``{name: value}`` the window's estimate of each static variable the terms declare.
        frame_values: ``{name: (w, …)}`` its per-frame variables.
        report: how the solve went.
        static_kinds, frame_kinds: ``{name: "euclidean" | "rotation" | "other"}``, how each block is averaged
            when windows are joined.
        frame_starts: ``{name: value}`` each per-frame block's start value (for frames no window covers).
    """

    start: int
    stop: int
    root_position: np.ndarray
    rotations: np.ndarray
    statics: dict
    frame_values: dict
    report: WindowReport
    static_kinds: dict = dataclasses.field(default_factory=dict)
    frame_kinds: dict = dataclasses.field(default_factory=dict)
    frame_starts: dict = dataclasses.field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return self.stop - self.start


def _kind(variable: Variable) -> str:
    if isinstance(variable, PerCamera):
        return _kind(variable.block)
    if isinstance(variable, Euclidean):
        return EUCLIDEAN
    if isinstance(variable, Rotation):
        return ROTATION
    return OTHER


def _solve_at(problem: SequenceProblem, root: np.ndarray, rotations: np.ndarray, frame_values: dict, statics: dict,
              options: SolverOptions, window: int, start: int) -> WindowSolution:
    """The window of ``window`` frames from ``start``, from the whole-sequence estimates given (a module-level
    function, so that ``functools.partial`` of it pickles to a worker)."""
    stop = start + window
    t0 = time.perf_counter()
    terms = window_terms(problem, start, stop)
    frame_values = with_start_values(frame_values, terms, problem.num_frames)
    solved = solve_window_span(problem, terms, start, stop, root, rotations, frame_values, statics, options)
    report = WindowReport.from_convergence(start, stop, solved.convergence, time.perf_counter() - t0)
    frames = frame_layout(terms)
    return WindowSolution(
        start, stop, solved.root_position, solved.rotations, solved.statics, solved.frame_values, report,
        static_kinds={name: _kind(v) for name, v in static_layout(terms)},
        frame_kinds={name: _kind(v) for name, v in frames},
        frame_starts={name: np.asarray(v.start(), np.float64) for name, v in frames},
    )


def solve_window(
    problem: SequenceProblem,
    initial_motion: Motion,
    options: SolverOptions,
    index: int,
    *,
    initial_statics: dict | None = None,
    initial_frame_variables: dict | None = None,
) -> WindowSolution:
    """Solve window ``index`` of ``window_starts(num_frames, min(window, T), overlap)`` on its own, starting from
    ``initial_motion`` (the fixed frames before it too), ``initial_statics`` and ``initial_frame_variables``
    (missing: the blocks' start values), exactly as :func:`~bcmocap.solver.solve` solves a window (the same
    code; window 0 gives :func:`solve`'s first window bit for bit).

    Raises:
        ValueError: ``index`` out of range, mismatched shapes, NaN/inf, a window without any usable
            observation.
        FloatingPointError: the window's cost, motion or variables became non-finite (naming the window).
    """
    starts, window, root, rotations, statics, frame_values = prepare_sequence(
        problem, initial_motion, options, initial_statics, initial_frame_variables, "bcmocap.solve_window")
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < len(starts):
        raise ValueError(f"solve_window: index must be in [0, {len(starts)}) ({len(starts)} windows), got {index!r}")
    return _solve_at(problem, root, rotations, frame_values, statics, options, window, starts[int(index)])


# ---- blending ---------------------------------------------------------------------------------------------------


def _align(values: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Quaternions (last axis) flipped to the hemisphere of ``reference``."""
    return np.where(np.sum(values * reference, axis=-1, keepdims=True) < 0.0, -values, values)


def _expand(weights: np.ndarray, ndim: int) -> np.ndarray:
    return weights.reshape(weights.shape + (1,) * (ndim - weights.ndim))


def _blend(base: np.ndarray, base_weight: np.ndarray, pieces: Sequence[tuple[int, np.ndarray, np.ndarray]],
           kind: str) -> np.ndarray:
    """``(T, …)``: at each frame the weighted mean of ``base`` (weight ``base_weight`` ``(T,)``) and the pieces
    ``(start, values (w, …), weights (w,))`` covering it; weights at a frame sum to 1. A frame with a single
    contributor takes its value unchanged."""
    best_weight = np.array(base_weight, np.float64)
    reference = np.array(base, np.float64)  # the heaviest contributor's value at each frame
    total = np.array(base_weight, np.float64)
    for start, values, weights in pieces:
        span = slice(start, start + len(values))
        heavier = weights > best_weight[span]
        reference[span][heavier] = values[heavier]
        best_weight[span] = np.maximum(best_weight[span], weights)
        total[span] += weights
    if kind == OTHER:
        return reference
    align = (lambda v, ref: _align(v, ref)) if kind == ROTATION else (lambda v, ref: v)
    acc = _expand(base_weight, base.ndim) * align(np.asarray(base, np.float64), reference)
    for start, values, weights in pieces:
        span = slice(start, start + len(values))
        acc[span] += _expand(weights, values.ndim) * align(np.asarray(values, np.float64), reference[span])
    if kind == ROTATION:
        mixed = acc / np.linalg.norm(acc, axis=-1, keepdims=True)
    else:
        mixed = acc / _expand(np.where(total > 0, total, 1.0), acc.ndim)
    single = best_weight == total  # one contributor: its value exactly
    return np.where(_expand(single, base.ndim), reference, mixed)


def _mean(values: Sequence[np.ndarray], weights: Sequence[float], kind: str) -> np.ndarray:
    """Weighted mean of one static block's estimates (see the module docstring)."""
    heaviest = int(np.argmax(weights))
    if kind == OTHER or len(values) == 1:
        return np.asarray(values[heaviest])
    w = np.asarray(weights, np.float64) / np.sum(weights)
    if kind == ROTATION:
        ref = np.asarray(values[heaviest], np.float64)
        acc = sum(wi * _align(np.asarray(v, np.float64), ref) for wi, v in zip(w, values))
        return acc / np.linalg.norm(acc, axis=-1, keepdims=True)
    return sum(wi * np.asarray(v, np.float64) for wi, v in zip(w, values))


def _ramp_weights(spans: Sequence[tuple[int, int]], num_frames: int) -> list[np.ndarray]:
    """Each window's weight per frame (sorted windows): linear ramps across the frames it shares with its
    neighbours, normalised so the weights of the windows covering a frame sum to 1."""
    weights, coverage = [], np.zeros(num_frames)
    for k, (start, stop) in enumerate(spans):
        t = np.arange(start, stop)
        shared_before = max(0, spans[k - 1][1] - start) if k > 0 else 0
        shared_after = max(0, stop - spans[k + 1][0]) if k + 1 < len(spans) else 0
        rise = np.minimum(1.0, (t - start + 1) / (shared_before + 1))
        fall = np.minimum(1.0, (stop - t) / (shared_after + 1))
        weights.append(np.minimum(rise, fall))
        coverage[start:stop] += weights[-1]
    return [w / coverage[start:stop] for w, (start, stop) in zip(weights, spans)]


def _check_solutions(initial_motion: Motion, solutions: Sequence[WindowSolution]) -> list[WindowSolution]:
    solutions = sorted(solutions, key=lambda s: s.start)
    if not solutions:
        raise ValueError("join_windows: no window solutions")
    num_frames = initial_motion.num_frames
    for a, b in zip(solutions, solutions[1:]):
        if a.start == b.start:
            raise ValueError(f"join_windows: two solutions of the window starting at frame {a.start}")
    for s in solutions:
        if not 0 <= s.start < s.stop <= num_frames or len(s.root_position) != s.num_frames:
            raise ValueError(f"join_windows: window [{s.start}, {s.stop}) with {len(s.root_position)} frames does not "
                             f"fit the {num_frames} frames of initial_motion")
    return solutions


def _join(root: np.ndarray, rotations: np.ndarray, frame_values: dict, base_weight: np.ndarray, statics: dict,
          solutions: Sequence[WindowSolution], weights: Sequence[np.ndarray]):
    """Blend ``solutions`` (their ``weights`` per frame) onto the base estimates; statics by frames contributed
    (the base's static estimate, if any, counting with its own remaining weight)."""
    pieces = lambda get: [(s.start, get(s), w) for s, w in zip(solutions, weights)]  # noqa: E731
    new_root = _blend(root, base_weight, pieces(lambda s: s.root_position), EUCLIDEAN)
    new_rotations = _blend(rotations, base_weight, pieces(lambda s: s.rotations), ROTATION)
    kinds = {k: v for s in solutions for k, v in s.frame_kinds.items()}
    starts = {k: v for s in solutions for k, v in s.frame_starts.items()}
    num_frames = len(root)
    new_values = {}
    for name in sorted(set(frame_values) | {k for s in solutions for k in s.frame_values}):
        having = [(s, w) for s, w in zip(solutions, weights) if name in s.frame_values]
        if not having:  # a block no window solves: carried unchanged
            new_values[name] = np.array(frame_values[name])
            continue
        if name in frame_values:
            base = frame_values[name]
        else:
            shape = np.shape(starts[name]) if name in starts else having[0][0].frame_values[name].shape[1:]
            base = np.broadcast_to(starts.get(name, np.zeros(shape)), (num_frames, *shape))
        new_values[name] = _blend(base, base_weight, [(s.start, s.frame_values[name], w) for s, w in having],
                                  kinds.get(name, EUCLIDEAN))
    static_kinds = {k: v for s in solutions for k, v in s.static_kinds.items()}
    new_statics = {}
    for name in sorted(set(statics) | {k for s in solutions for k in s.statics}):
        values, counts = [], []
        if name in statics:  # the base's estimate counts with the frames it keeps
            values.append(statics[name])
            counts.append(float(np.sum(base_weight)))
        for s, w in zip(solutions, weights):
            if name in s.statics:
                values.append(s.statics[name])
                counts.append(float(np.sum(w)))
        if sum(counts) <= 0.0:
            counts = [1.0] * len(counts)
        new_statics[name] = _mean(values, counts, static_kinds.get(name, EUCLIDEAN))
    return new_root, new_rotations, new_values, new_statics


def join_windows(
    initial_motion: Motion,
    solutions: Sequence[WindowSolution],
    options: SolverOptions,
    *,
    initial_frame_variables: dict | None = None,
) -> Solution:
    """Join independently solved windows into one :class:`~bcmocap.solver.Solution`.

    Consecutive windows are blended across their shared frames with weights ramping linearly from one to the
    next; rotations by hemisphere-aligned normalised lerp, root positions and per-frame variables likewise
    (see the module docstring); static variables are each window's estimate weighted by the frames it
    contributes. Frames no window covers keep ``initial_motion`` (and ``initial_frame_variables``, else the
    blocks' start values); a frame covered by one window takes it unchanged. Reports are in window order.

    Args:
        initial_motion: ``(T, …)`` the motion the windows started from.
        solutions: :func:`solve_window` results, in any order, at most one per window start.
        options: the options the windows were solved with: every window must have ``min(window, T)`` frames.

    Raises:
        ValueError: no solutions, two of one window, a window outside the sequence or of another length.
    """
    num_frames = initial_motion.num_frames
    solutions = _check_solutions(initial_motion, solutions)
    window = min(options.window, num_frames)
    for s in solutions:
        if s.num_frames != window:
            raise ValueError(f"join_windows: window [{s.start}, {s.stop}) has {s.num_frames} frames; options give {window}")
    weights = _ramp_weights([(s.start, s.stop) for s in solutions], num_frames)
    covered = np.zeros(num_frames, bool)
    for s in solutions:
        covered[s.start:s.stop] = True
    frame_values = {k: np.asarray(v, np.float64) for k, v in (initial_frame_variables or {}).items()}
    root, rotations, values, statics = _join(
        np.asarray(initial_motion.root_position, np.float64), np.asarray(initial_motion.rotations, np.float64),
        frame_values, (~covered).astype(np.float64), {}, solutions, weights)
    return Solution(Motion(root, rotations), [s.report for s in solutions], statics, values)


# ---- the seam pass ----------------------------------------------------------------------------------------------


def seam_windows(starts: Sequence[int], window: int, num_frames: int) -> list[tuple[int, np.ndarray]]:
    """The seam pass's windows: ``(start, weights (window,))`` for the seam between each two consecutive windows
    of ``starts``: a window of the same length centred on the frames they share (shifted to fit the sequence),
    weighted 1 over those frames (and one either side), ramping linearly to 0 towards the midpoints between
    neighbouring seams or the window's ends; no two seam windows weigh the same frame."""
    centres2 = [starts[k + 1] + starts[k] + window for k in range(len(starts) - 1)]  # twice each seam's centre
    out = []
    for k, c2 in enumerate(centres2):
        shared = (starts[k + 1], starts[k] + window)
        start = int(np.clip((c2 - window) // 2, 0, num_frames - window))
        lo, hi = start, start + window
        if k > 0:
            lo = max(lo, -(-(centres2[k - 1] + c2) // 4))  # ceil of the midpoint between the seams
        if k + 1 < len(centres2):
            hi = min(hi, -(-(c2 + centres2[k + 1]) // 4))
        p0, p1 = max(lo, shared[0] - 1), min(hi, shared[1] + 1)
        t = np.arange(start, start + window)
        weights = np.where(t < p0, (t - lo + 1) / (p0 - lo + 1), np.where(t < p1, 1.0, (hi - t) / (hi - p1 + 1)))
        weights[(t < lo) | (t >= hi)] = 0.0
        out.append((start, weights))
    return out


def solve_windows_independently(
    problem: SequenceProblem,
    initial_motion: Motion,
    options: SolverOptions = SolverOptions(),
    *,
    map: Map = builtins.map,
    seam_pass: bool = True,
    initial_statics: dict | None = None,
    initial_frame_variables: dict | None = None,
) -> Solution:
    """Minimise Eq. (1) over a whole sequence with the windows of :func:`~bcmocap.solver.solve` solved
    independently (each from ``initial_motion``) through ``map``, joined (:func:`join_windows`), and, with
    ``seam_pass``, a window centred on every seam re-solved from the joined estimate (through ``map`` too) and
    blended back (:func:`seam_windows`). See the module docstring for the design and its cost
    (``windows`` + ``windows − 1`` window-solves).

    Args:
        problem, initial_motion, options, initial_statics, initial_frame_variables: as for :func:`solve`.
        map: ``map(fn, iterable)`` → results in order: the builtin (sequential, the default), a process pool's
            ``map``, or a cluster's. ``fn`` is a ``functools.partial`` of a module-level function holding the
            problem and the starting estimates (pickled with it), applied to window start frames.
        seam_pass: re-solve the seams (more accurate; about twice the work).

    Returns:
        The joined solution; its reports are the windows' in order, then the seam windows' in order.

    Raises:
        As :func:`solve_window`.
    """
    starts, window, root, rotations, statics, frame_values = prepare_sequence(
        problem, initial_motion, options, initial_statics, initial_frame_variables,
        "bcmocap.solve_windows_independently")
    num_frames = problem.num_frames
    fn = functools.partial(_solve_at, problem, root, rotations, frame_values, statics, options, window)
    solutions = list(map(fn, starts))
    joined = join_windows(initial_motion, solutions, options, initial_frame_variables=frame_values)
    if not seam_pass or len(starts) < 2:
        return joined
    seams = seam_windows(starts, window, num_frames)
    j_root, j_rot = np.asarray(joined.motion.root_position), np.asarray(joined.motion.rotations)
    fn = functools.partial(_solve_at, problem, j_root, j_rot, joined.frame_variables, joined.statics, options, window)
    seam_solutions = list(map(fn, [start for start, _ in seams]))
    weights = [w for _, w in seams]
    base_weight = np.ones(num_frames)
    for (start, w) in seams:
        base_weight[start:start + window] -= w
    base_weight = np.clip(base_weight, 0.0, 1.0)
    root, rotations, values, statics = _join(j_root, j_rot, joined.frame_variables, base_weight, joined.statics,
                                             seam_solutions, weights)
    return Solution(Motion(root, rotations), [*joined.reports, *(s.report for s in seam_solutions)], statics, values)
