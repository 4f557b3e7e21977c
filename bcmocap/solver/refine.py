"""Refine the skeleton and camera mounts shared by all frames (issue 3, item 6; beyond the paper).

The paper keeps the skeleton and the mounts of the range-of-motion trial fixed in the final
optimisation (Eq. 1, skeleton as a hard constraint). Here they are refined from the capture itself,
by alternating two steps (:func:`solve_with_refinement`):

(a) the motion with the current skeleton and rig: the windowed solver, unchanged (:func:`solve`);
(b) the shared parameters θ of :mod:`bcmocap.solver.model_parameters` — offset corrections, 6-DOF mount
    corrections and hinge-axis tilts — together with the motion, on the same objective as (a) (the
    paper's terms and any user terms) plus a prior ``½ Σ (θ/σ)²`` towards the range-of-motion values
    (:func:`refine_skeleton_and_rig`).

Step (b) is the windowed solver itself with one window over the whole sequence and θ as its static
variables (:class:`~bcmocap.solver.model_parameters.ModelParameters`): every term sees the skeleton and
rig at θ, the Gauss–Newton matrix is block banded in the motion and bordered by θ, and each step of the
one Levenberg–Marquardt eliminates the motion (Schur complement), so the step in θ already accounts for
how the motion re-fits and the motion moves with it. With the motion held fixed instead, it would have
compensated the wrong skeleton and pinned θ near its old value; eliminated, one round does nearly all
of it. Memory is that of a window as long as the sequence (camera-pose Jacobians ``T × C × 6 × (D + P)``).

Gauge. With the motion free, several directions of θ are not observable from the capture at all:
where the root's origin sits among its cameras (any shift is absorbed by the root position); the
orientation of each segment frame (absorbed by the joint angles: it is the rest pose of the trial;
for a hinge, parent and child frames turn together with the axis); a hinge's centre along its
axis. Refining freely, the first two drift wherever the prior's metric sends them, and joint angles
drift with the frames although the fit is the same. So they are held by construction, as the
range-of-motion estimate defines them: the mean correction of the ``root_origin`` children's
offsets is zero (the root stays at the same joint, the convention of
:func:`~bcmocap.kinematics.skeleton_from_range_of_motion`), and so is the mean rotation correction
of the cameras of each FREE or BALL segment (``hold_segment_frames``: cameras of one segment may
still turn relative to each other; a hinge segment's frame follows its parent's through the refined
axis). What is left weak in a given motion (a joint flexed about one axis in a walk, a hinge's
centre along its axis) is decided by the prior ``(θ/σ)²``, in the same χ² units as the whitened
pixel residuals, with σ about the accuracy of the range-of-motion estimate: the trial's values stay
where the capture is silent and the two are weighed where both speak. The report counts the
directions the prior decides (eigenvalues of the prior-whitened data matrix below 1).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..correspondences import Correspondences
from ..geometry import SE3
from ..kinematics.rig import Rig, camera_poses
from ..kinematics.skeleton import Motion, Skeleton
from ..residuals import CameraView, Reprojection
from ..precision import require_float64
from .levenberg_marquardt import static_schur_complement
from .model_parameters import MODEL, ModelParameters, parameter_changes, parameter_difference, parameter_layout
from .objective import ObjectiveWeights, TermFactory, paper_problem
from .solve import Problem, SequenceProblem, Solution, SolverOptions, solve
from .window import make_window_problem, normal_equations, window_history


@dataclasses.dataclass(frozen=True)
class RefineOptions:
    """Settings of :func:`refine_skeleton_and_rig`.

    Attributes:
        offset_sigma_m: prior σ of each offset coordinate around the prior skeleton (m).
        mount_translation_sigma_m, mount_rotation_sigma_deg: prior σ of each mount's translation
            (m, segment frame) and rotation (°, per axis) around the prior rig.
        hinge_axis_sigma_deg: prior σ of each hinge axis's tilt (°, per perpendicular direction).
        refine_offsets, refine_mounts, refine_hinge_axes: which shared parameters move.
        hold_segment_frames: keep the mean rotation correction of the cameras of every FREE or
            BALL segment at zero, so segment frames (hence joint angles) stay those of the trial's
            rest pose; a hinge segment's cameras turn freely (its frame follows its parent's
            through the refined axis). Without it, only the prior holds these directions.
        root_origin: children of the root whose mean joint is the root's origin (held); default:
            the root's children with a zero offset if there are any, else all of them.
        max_steps: Levenberg–Marquardt iterations (accepted or rejected).
        xtol, ftol: stop after an accepted step that changes the variables (motion tangents and θ) by
            less than ``xtol + ftol |v|`` in RMS (m and rad) and the cost by less than ``xtol + ftol · cost``
            (the ``atol`` and ``rtol`` of :func:`~bcmocap.solver.levenberg_marquardt`).
        damping_scale: initial damping relative to the Marquardt diagonal.
    """

    offset_sigma_m: float = 0.005
    mount_translation_sigma_m: float = 0.005
    mount_rotation_sigma_deg: float = 0.3
    hinge_axis_sigma_deg: float = 0.5
    refine_offsets: bool = True
    refine_mounts: bool = True
    refine_hinge_axes: bool = True
    hold_segment_frames: bool = True
    root_origin: tuple[str, ...] | None = None
    max_steps: int = 15
    xtol: float = 1e-5
    ftol: float = 1e-10
    damping_scale: float = 1e-4

    def __post_init__(self):
        for name in ("offset_sigma_m", "mount_translation_sigma_m", "mount_rotation_sigma_deg", "hinge_axis_sigma_deg"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RefineOptions: {name} must be positive, got {getattr(self, name)}")
        if not (self.refine_offsets or self.refine_mounts or self.refine_hinge_axes):
            raise ValueError("RefineOptions: nothing to refine (refine_offsets, refine_mounts and refine_hinge_axes are all False)")
        if self.max_steps < 1:
            raise ValueError(f"RefineOptions: max_steps must be ≥ 1, got {self.max_steps}")


@dataclasses.dataclass(frozen=True)
class RefineReport:
    """How one refinement went.

    Attributes:
        initial_cost, final_cost: the objective ``½ Σ λρ`` of all terms plus the prior, before and after.
        initial_reprojection_cost, final_reprojection_cost: the reprojection part alone (None from
            :func:`refine_model`).
        num_steps, num_accepted_steps, converged: from the solver's
            :class:`~bcmocap.solver.Convergence` (converged: stopped by the tolerances, not by ``max_steps``).
        offset_change_m: largest change of an offset vector (norm, m) against the input.
        mount_translation_change_m, mount_rotation_change_deg: largest change of a mount.
        hinge_axis_change_deg: largest change of a hinge axis.
        prior_directions: directions of θ that the prior, not the data, determines (eigenvalues of the
            prior-whitened data matrix, the motion eliminated, below 1; the held means are not counted).
        num_parameters: size of θ; frames: frames used; seconds: wall time.
    """

    initial_cost: float
    final_cost: float
    initial_reprojection_cost: float | None
    final_reprojection_cost: float | None
    num_steps: int
    num_accepted_steps: int
    converged: bool
    offset_change_m: float
    mount_translation_change_m: float
    mount_rotation_change_deg: float
    hinge_axis_change_deg: float
    prior_directions: int
    num_parameters: int
    frames: int
    seconds: float


@dataclasses.dataclass
class Refinement:
    """Result of :func:`refine_skeleton_and_rig`.

    Attributes:
        skeleton, rig: the refined model (same topology, cameras and intrinsics as the input).
        motion: the motion solved with the parameters, a starting point for the next solve.
        report: costs, steps and parameter changes.
    """

    skeleton: Skeleton
    rig: Rig
    motion: Motion
    report: RefineReport


@dataclasses.dataclass(frozen=True)
class RoundReport:
    """One round of :func:`solve_with_refinement`: refinement (None in round 0), then a solve.

    ``reprojection_cost`` is the robust reprojection cost over all frames after the round's solve.
    """

    round: int
    refinement: RefineReport | None
    reprojection_cost: float
    solve_seconds: float


@dataclasses.dataclass
class RefinedSolution:
    """Result of :func:`solve_with_refinement`: the last solve, its model, and one report per round."""

    solution: Solution
    skeleton: Skeleton
    rig: Rig
    rounds: list[RoundReport]

    @property
    def motion(self) -> Motion:
        return self.solution.motion


# ---- parameters ---------------------------------------------------------------------------------


# ---- linearisation -------------------------------------------------------------------------------


def _checked_problem(correspondences: Correspondences, skeleton: Skeleton, rig: Rig, motion: Motion, prior,
                     weights: ObjectiveWeights, extra_terms: Sequence[TermFactory] = ()) -> Problem:
    """The objective of :func:`paper_problem` (which checks the measurements against the rig), after checking
    the motion and the prior model against it."""
    problem = paper_problem(correspondences, skeleton, rig, weights, extra_terms=extra_terms)
    motion.check(skeleton, "refine_skeleton_and_rig: motion")
    if motion.num_frames != correspondences.num_frames:
        raise ValueError(
            f"refine_skeleton_and_rig: the motion has {motion.num_frames} frames, the correspondences {correspondences.num_frames}"
        )
    if prior is not None:
        p_skel, p_rig = prior
        same = p_skel.names == skeleton.names and p_skel.parents == skeleton.parents
        if not (same and p_rig.names == rig.names and p_rig.segments == rig.segments):
            raise ValueError("refine_skeleton_and_rig: the prior model has other segments or cameras than the skeleton and rig")
    return problem


def _reprojection(problem: Problem) -> Reprojection:
    return next(t for t in problem.terms if isinstance(t, Reprojection))


def model_parameters(skeleton: Skeleton, rig: Rig, options: RefineOptions = RefineOptions(), *,
                     prior: tuple[Skeleton, Rig] | None = None) -> ModelParameters:
    """The skeleton and rig as variables starting at ``(skeleton, rig)``, with the prior and gauge of
    ``options`` around ``prior`` (default: the same model)."""
    base_skeleton, base_rig = prior if prior is not None else (skeleton, rig)
    layout = parameter_layout(base_skeleton, base_rig, offsets=options.refine_offsets, mounts=options.refine_mounts,
                              hinge_axes=options.refine_hinge_axes, hold_segment_frames=options.hold_segment_frames,
                              root_origin=options.root_origin)
    sigmas = layout.sigmas(options.offset_sigma_m, options.mount_translation_sigma_m, options.mount_rotation_sigma_deg,
                           options.hinge_axis_sigma_deg)[np.asarray(layout.active)]
    theta = parameter_difference(layout, base_skeleton, base_rig, skeleton, rig)
    return ModelParameters(base_skeleton, base_rig, jnp.asarray(theta), jnp.asarray(1.0 / sigmas), layout)


def refine_skeleton_and_rig(
    correspondences: Correspondences,
    skeleton: Skeleton,
    rig: Rig,
    motion: Motion,
    options: RefineOptions = RefineOptions(),
    *,
    weights: ObjectiveWeights = ObjectiveWeights(),
    prior: tuple[Skeleton, Rig] | None = None,
    extra_terms: Sequence[TermFactory] = (),
) -> Refinement:
    """Refine bone offsets, camera mounts and hinge axes with the motion, from the capture's objective.

    Args:
        correspondences: the capture's measurements (``T`` frames, ``C`` cameras).
        skeleton, rig: the current model, e.g. from a range-of-motion trial.
        motion: ``(T, J)`` the motion solved with that model (the starting point).
        options: priors, what moves, iterations.
        weights, extra_terms: the objective, as in :func:`paper_problem` (the paper's terms and user terms).
        prior: the model the prior pulls towards (the range-of-motion estimate); default: the input.
            Pass the first model in every round of an alternation so the gauge stays where it was.

    Returns:
        The refined skeleton and rig, the motion solved with them, and a :class:`RefineReport`.

    Raises:
        ValueError: measurements, motion or prior that do not fit the model; unknown ``root_origin``.
    """
    require_float64("bcmocap.solver.refine_skeleton_and_rig")
    problem = _checked_problem(correspondences, skeleton, rig, motion, prior, weights, extra_terms)
    refinement = refine_model(problem, motion, options, prior=prior)
    term = _reprojection(problem)
    report = dataclasses.replace(
        refinement.report,
        initial_reprojection_cost=_reprojection_cost(term, skeleton, rig, motion),
        final_reprojection_cost=_reprojection_cost(term, refinement.skeleton, refinement.rig, refinement.motion),
    )
    return dataclasses.replace(refinement, report=report)


def refine_model(problem: SequenceProblem, motion: Motion, options: RefineOptions = RefineOptions(), *,
                 prior: tuple[Skeleton, Rig] | None = None) -> Refinement:
    """Refine the model of any problem (its ``skeleton`` and ``rig``, e.g. a
    :class:`~bcmocap.solver.objective.StoredProblem` of ``bcmocap run``) with the motion, on its own terms.

    As :func:`refine_skeleton_and_rig`, whose measurements are in memory; here the report's reprojection
    costs are None (the problem's terms may not include a reprojection term one could single out).

    Raises:
        ValueError: a motion of another length or skeleton than the problem's; unknown ``root_origin``.
    """
    require_float64("bcmocap.solver.refine_model")
    start_time = time.perf_counter()
    motion.check(problem.skeleton, "refine: motion")
    if motion.num_frames != problem.num_frames:
        raise ValueError(f"refine: the motion has {motion.num_frames} frames, the problem {problem.num_frames}")
    parameters = model_parameters(problem.skeleton, problem.rig, options, prior=prior)
    solver = SolverOptions(window=motion.num_frames, overlap=0, max_steps=options.max_steps, rtol=options.ftol,
                           atol=options.xtol, damping_scale=options.damping_scale)
    solution = solve(problem, motion, solver, model_parameters=parameters)
    values = jnp.asarray(solution.statics[MODEL])
    new_skeleton, new_rig = parameters.model(values)
    lm = solution.reports[0]
    theta_in, theta = np.asarray(parameters.theta), np.asarray(parameters.full(values))
    report = RefineReport(
        lm.initial_cost, lm.final_cost, None, None, lm.num_steps, lm.num_accepted_steps, lm.converged,
        *parameter_changes(parameters.layout, theta_in, theta), _prior_directions(problem, solution.motion, parameters, values),
        parameters.size, motion.num_frames, time.perf_counter() - start_time,
    )
    return Refinement(new_skeleton, new_rig, solution.motion, report)


def _prior_directions(problem, motion: Motion, parameters: ModelParameters, values: jax.Array) -> int:
    """Directions of θ the prior decides: eigenvalues below 1 of the prior-whitened data matrix with the
    motion eliminated, ``C − Bᵀ A⁻¹ B`` at the solution (the held means, zero by construction, not counted)."""
    terms = tuple(problem.window(0, motion.num_frames))
    before = np.zeros(window_history(terms), int)
    reference = Motion(*(np.concatenate([np.asarray(a)[before], np.asarray(a)]) for a in (motion.root_position, motion.rotations)))
    wp = make_window_problem(problem.skeleton, problem.rig, terms, reference, 0, {MODEL: values}, parameters)
    data = _data_matrix(wp, parameters)
    whitened = np.asarray(data) / np.outer(parameters.sqrt_precision, parameters.sqrt_precision)
    count = int(np.sum(np.linalg.eigvalsh(0.5 * (whitened + whitened.T)) < 1.0))
    layout = parameters.layout
    offsets = any(i < layout.num_offsets for i in layout.active)
    mounts = any(layout.num_offsets <= i < layout.num_offsets + layout.num_mounts for i in layout.active)
    return count - 3 * (bool(layout.origin_children) * offsets + len(layout.held_frames) * mounts)


@eqx.filter_jit
def _data_matrix(wp, parameters: ModelParameters) -> jax.Array:
    """The model's block of the static Schur complement at the window's reference, without the prior."""
    block = slice(wp.num_statics - parameters.size, None)
    schur = static_schur_complement(normal_equations(wp, jnp.zeros((wp.num_frames, wp.frame_size))))
    return schur[block, block] - jnp.diag(parameters.sqrt_precision**2)


def reprojection_cost(
    correspondences: Correspondences, skeleton: Skeleton, rig: Rig, motion: Motion, *, weights: ObjectiveWeights = ObjectiveWeights()
) -> float:
    """Robust reprojection cost ``½ Σ λρ(‖r‖²)`` of a motion over all frames (as in :func:`paper_problem`)."""
    return _reprojection_cost(_reprojection(_checked_problem(correspondences, skeleton, rig, motion, None, weights)),
                              skeleton, rig, motion)


def _reprojection_cost(term: Reprojection, skeleton: Skeleton, rig: Rig, motion: Motion) -> float:
    total, chunk = 0.0, 64
    for start in range(0, motion.num_frames, chunk):
        window = term.window(start, min(start + chunk, motion.num_frames))
        total += float(_chunk_cost(skeleton, rig, eqx.tree_at(lambda t: t.data, window, {}), motion[start : start + chunk],
                                   window.data))
    return total


@eqx.filter_jit
def _chunk_cost(skeleton: Skeleton, rig: Rig, term: Reprojection, motion: Motion, data):
    cam_from_world = camera_poses(skeleton, rig, motion).inverse()  # (F, C)
    one = lambda p, cam, dt: term.finish(*term.residual(CameraView(SE3(p), cam), dt, {}))  # noqa: E731
    per_camera = jax.vmap(jax.vmap(one, in_axes=(0, 0, 0)), in_axes=(0, None, 0))
    return 0.5 * jnp.sum(per_camera(cam_from_world.wxyz_xyz, rig.intrinsics, data) ** 2)


def solve_with_refinement(
    correspondences: Correspondences,
    skeleton: Skeleton,
    rig: Rig,
    initial_motion: Motion,
    *,
    rounds: int = 1,
    solver_options: SolverOptions = SolverOptions(),
    refine_options: RefineOptions = RefineOptions(),
    weights: ObjectiveWeights = ObjectiveWeights(),
    min_change_m: float = 1e-4,
    callback: Callable[[int, Skeleton, Rig, Solution], None] | None = None,
    extra_terms: Sequence[TermFactory] = (),
) -> RefinedSolution:
    """Eq. (1) with the skeleton and mounts refined: solve, then ``rounds`` × (refine, solve).

    Args:
        correspondences: the capture's measurements.
        skeleton, rig: the starting model (its values are the prior of every refinement).
        initial_motion: ``(T, J)`` starting motion for the first solve.
        rounds: refinements (each followed by a solve); 0 is the plain solve. With the motion
            eliminated one round does nearly all of it (on the walk benchmark a second round moved
            nothing by more than a micrometre).
        solver_options, refine_options, weights, extra_terms: as in :func:`solve`,
            :func:`refine_skeleton_and_rig`, :func:`paper_problem`; solve and refinement minimise the same
            objective (the paper's terms and the user terms of ``extra_terms``).
        min_change_m: stop early after a refinement that moved no offset or mount by more than this
            (m; rotations in rad at 1 m).
        callback: called after every solve with ``(round, skeleton, rig, solution)``.

    Returns:
        The last solution with its model and one :class:`RoundReport` per round (round 0: no refinement).
    """
    if rounds < 0:
        raise ValueError(f"solve_with_refinement: rounds must be ≥ 0, got {rounds}")
    prior = (skeleton, rig)
    history: list[RoundReport] = []
    motion, refinement = initial_motion, None
    for k in range(rounds + 1):
        if k:
            refinement = refine_skeleton_and_rig(
                correspondences, skeleton, rig, solution.motion, refine_options, weights=weights, prior=prior,
                extra_terms=extra_terms,
            )
            skeleton, rig, motion = refinement.skeleton, refinement.rig, refinement.motion
        start = time.perf_counter()
        solution = solve(paper_problem(correspondences, skeleton, rig, weights, extra_terms=extra_terms), motion, solver_options)
        seconds = time.perf_counter() - start
        cost = reprojection_cost(correspondences, skeleton, rig, solution.motion, weights=weights)
        history.append(RoundReport(k, None if refinement is None else refinement.report, cost, seconds))
        if callback is not None:
            callback(k, skeleton, rig, solution)
        if refinement is not None:
            r = refinement.report
            rotation = np.deg2rad(max(r.mount_rotation_change_deg, r.hinge_axis_change_deg))
            if max(r.offset_change_m, r.mount_translation_change_m, rotation) < min_change_m:
                break
    return RefinedSolution(solution, skeleton, rig, history)
