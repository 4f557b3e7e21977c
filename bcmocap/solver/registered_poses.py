"""Registered camera poses re-fitted under the solver's camera model (beyond the paper).

Registration fits each frame as a global-shutter image through the intrinsics the user gave. Where the
solver models the camera better — a rolling shutter (:mod:`bcmocap.residuals.rolling_shutter`), intrinsics off
by a calibration error (:mod:`bcmocap.residuals.self_calibration`) — those poses are biased, and the bias
reaches the result whatever the solver models: the skeleton is estimated from the range-of-motion trial's
registered poses, and the solve starts from (and is held near) the capture's. On the realism benchmark's
rolling-shutter capture (15 ms readout) the registered camera centres are 0.5 cm off while the camera turns
slower than 5°/s, 6 cm off at 120–240°/s and 21 cm above 240°/s.

:func:`refine_registered_poses` re-fits them with the scene points held fixed: a camera-only bundle adjustment
of each registered frame's pose ``T_t`` (``cam_from_world``) and, with ``calibrate``, of each camera's
intrinsics correction ``k_c`` (log focal scale, principal point shift in px; as
:func:`~bcmocap.residuals.self_calibration.corrected_camera`, held near zero by a Gaussian prior). A measurement
``x`` of point ``X`` in image row ``y`` is predicted by the solver's rolling-shutter projection
(:func:`~bcmocap.residuals.rolling_shutter.rolling_shutter_projection`),

    π_{k_c}( exp(s · readout · v_t) · T_t · X ),   s = y / (H − 1) − ½,

with ``v_t`` the camera's velocity at frame ``t`` (a left increment of ``cam_from_world`` per frame period): half
the increment from frame ``t − 1`` to ``t + 1`` when both are registered, else the one-sided increment, else
zero (:func:`camera_velocities`). The loss is the solver's Cauchy loss (:class:`~bcmocap.residuals.losses.CauchyLoss`)
at ``loss_scale`` px on each measurement's inverse-variance weighted error.

Given the velocities, every camera is a problem of its own — its frames (of all trials, end to end) are independent
given its correction ``k_c``, which no other camera sees — with the structure of the solver's normal equations
(:class:`~bcmocap.solver.levenberg_marquardt.NormalEquations`): ``(T, 6, 6)`` pose blocks, no bands, bordered by
the 3 variables of ``k_c``. Each camera is therefore solved by the one Levenberg–Marquardt
(:func:`~bcmocap.solver.levenberg_marquardt.levenberg_marquardt`, ``jax.vmap`` over cameras: one damping and one
trust region per camera, i.e. block-diagonal damping), the velocities held fixed, for at most ``max_steps`` steps
(by default two Gauss–Newton steps). Then the velocities are taken from the new poses and the cameras solved
again, until no pose moves more than ``tolerance`` over a round (or every camera's solve converges from its
start). The fixed point is the poses whose every frame best explains its image given its neighbours' velocity:
the same as that of refreshing the velocities after every Gauss–Newton step, as this module did before it used
the one Levenberg–Marquardt (at the fixed point a refresh changes nothing and every solve's gradient is zero).
Rounds are short because stale velocities and the IRLS model of the Cauchy loss both cost a few-fold contraction
a step: solving each round to convergence took 30 steps where short rounds take 17 (60 frames × 18 cameras).
Without a readout the velocities are zero and the rounds only continue the one solve.

Memory: a group of cameras is solved at once, holding those cameras' whole sequences (every trial): per camera
``T × N`` measurements (``T`` frames of all trials, ``N`` the most measurements one of its re-fitted frames
has) of about 100 bytes, and the Jacobians (2 × 9 per measurement) of ``block_frames`` frames at a time. The
group is as many cameras as ``memory`` bytes allow, at least one, so memory grows with one camera's ``T × N``;
the measurements are read from a :class:`~bcmocap.correspondence_store.CorrespondenceStore` a block of frames at
a time, once per group (or taken from in-memory :class:`~bcmocap.correspondences.Correspondences`; a short
trial's blocks are kept in memory).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..cameras import CameraModel
from ..correspondence_store import CorrespondenceStore
from ..geometry import SE3
from ..residuals.losses import CauchyLoss, RobustLoss
from ..residuals.rolling_shutter import (
    rolling_shutter_motion,
    rolling_shutter_projection,
)
from ..residuals.self_calibration import corrected_camera, corrected_cameras
from .levenberg_marquardt import NormalEquations, levenberg_marquardt

__all__ = [
    "CameraSequence",
    "PoseRefinement",
    "PoseRefinementOptions",
    "camera_velocities",
    "refine_registered_poses",
    "refine_trials",
    "sequence_normal_equations",
    "sequence_residuals",
]

#: Relative tolerance of each Levenberg–Marquardt solve (the absolute one is ``PoseRefinementOptions.tolerance``).
_RTOL = 1e-4
_DAMPING = 1e-3
#: Bytes held per measurement of a group of cameras (points, pixels, weights, residuals and the solve's copies).
_BYTES_PER_MEASUREMENT = 100


@dataclasses.dataclass(frozen=True)
class PoseRefinementOptions:
    """Settings of :func:`refine_registered_poses`.

    Attributes:
        readout: rolling-shutter readout, first row to last, in frame periods of the trial's frames (readout
            seconds × the trial's frames per second); 0: global shutter.
        calibrate: also estimate each camera's intrinsics correction.
        intrinsics_sigma: the correction's prior σ: (log focal scale, principal point px).
        loss_scale: Cauchy loss scale (px).
        max_iterations: rounds at most (each one Levenberg–Marquardt solve per camera with the velocities held,
            then the velocities taken from the new poses).
        max_steps: Levenberg–Marquardt steps at most in one round (the first evaluates the start: 3 is two
            Gauss–Newton steps between velocity refreshes).
        tolerance: a round's solve stops when no pose (nor, with ``calibrate``, correction) moves more than this
            in a step, the rounds when none moves more than this over a round (the poses' units and rad; log focal
            scale and px).
        min_measurements: a registered frame with fewer measurements keeps its pose (it still gives its
            neighbours their velocity): too few to fit a pose (the frontend registered it through points the
            measurements do not hold).
        block_frames: frames read from the source at once, and linearised at once (the Jacobians of
            ``block_frames × slots`` measurements of 2 × 9 per camera solved together).
        memory: bytes of measurements to hold at once; sets how many cameras are solved together (at least one).
    """

    readout: float = 0.0
    calibrate: bool = False
    intrinsics_sigma: tuple[float, float] = (0.01, 5.0)
    loss_scale: float = 2.0
    max_iterations: int = 12
    max_steps: int = 3
    tolerance: float = 1e-4
    min_measurements: int = 20
    block_frames: int = 32
    memory: float = 1e9

    def __post_init__(self):
        if not (np.isfinite(self.readout) and 0.0 <= self.readout <= 2.0):
            raise ValueError(f"PoseRefinementOptions.readout must lie in [0, 2] frame periods, got {self.readout}")
        if not (len(self.intrinsics_sigma) == 2 and all(np.isfinite(s) and s > 0 for s in self.intrinsics_sigma)):
            raise ValueError(f"PoseRefinementOptions.intrinsics_sigma must be two positive numbers, got {self.intrinsics_sigma}")
        if not (self.loss_scale > 0 and self.max_iterations >= 1 and self.max_steps >= 1 and self.tolerance > 0
                and self.block_frames >= 1 and self.min_measurements >= 6 and self.memory > 0):
            raise ValueError("PoseRefinementOptions: loss_scale, tolerance and memory must be > 0, max_iterations, "
                             "max_steps and block_frames >= 1, min_measurements >= 6")


@dataclasses.dataclass(frozen=True)
class PoseRefinement:
    """What :func:`refine_registered_poses` found.

    Attributes:
        world_from_camera: ``(T, C, 7)`` refined poses (wxyz_xyz); unregistered rows as given.
        intrinsics_correction: ``(C, 3)`` per camera (log focal scale, Δcx px, Δcy px); zeros without ``calibrate``.
        rms_px: ``(C, 2)`` per camera, root mean square reprojection error of its measurements before and after
            (inverse-variance weighted, px; measurements within 5 loss scales, NaN for a camera without any).
        iterations: Levenberg–Marquardt steps taken (over all rounds; the most of any camera).
        moved_m, moved_deg: ``(T, C)`` how far each pose's centre moved (m) and its orientation turned (deg).
        refined: ``(T, C)`` the registered frames re-fitted (enough measurements); the others are as given.
    """

    world_from_camera: np.ndarray
    intrinsics_correction: np.ndarray
    rms_px: np.ndarray
    iterations: int
    moved_m: np.ndarray
    moved_deg: np.ndarray
    refined: np.ndarray

    def corrected_cameras(self, cameras: CameraModel) -> CameraModel:
        """The stacked ``cameras`` with :attr:`intrinsics_correction` applied."""
        return corrected_cameras(cameras, self.intrinsics_correction)


def camera_velocities(cam_from_world: np.ndarray, registered: np.ndarray) -> np.ndarray:
    """``(T, C, 6)`` each frame's velocity (SE(3) tangent of a left increment of ``cam_from_world`` per frame
    period): half the increment from ``t − 1`` to ``t + 1`` when both are registered, else the one-sided one, else
    zero (and zero at unregistered frames)."""
    poses = SE3(jnp.asarray(cam_from_world))
    step = np.asarray((SE3(poses.wxyz_xyz[1:]) @ SE3(poses.wxyz_xyz[:-1]).inverse()).log())  # t-1 → t, (T-1, C, 6)
    both = registered[1:] & registered[:-1]
    step = np.where(both[..., None], step, 0.0)
    zero = np.zeros_like(step[:1])
    back, ahead = np.concatenate([zero, step]), np.concatenate([step, zero])  # t-1 → t, t → t+1
    has_back = np.concatenate([np.zeros_like(both[:1]), both])
    has_ahead = np.concatenate([both, np.zeros_like(both[:1])])
    count = has_back.astype(float) + has_ahead.astype(float)
    velocity = (back + ahead) / np.maximum(count, 1.0)[..., None]
    # with both neighbours, the centred estimate of the step t-1 → t+1: half of log(T_{t+1} T_{t-1}^-1)
    centred = np.asarray((SE3(poses.wxyz_xyz[2:]) @ SE3(poses.wxyz_xyz[:-2]).inverse()).log()) / 2.0
    velocity[1:-1] = np.where((has_back & has_ahead)[1:-1, :, None], centred, velocity[1:-1])
    return np.where(registered[..., None], velocity, 0.0)


class CameraSequence(eqx.Module):
    """One camera's frames to re-fit (those of every trial, end to end), the velocities held: one
    Levenberg–Marquardt problem. Its variables ``y``: the ``(T, 6)`` left increments of the poses, and with
    ``calibrate`` the ``(3,)`` intrinsics correction with them (the pair ``(increments, correction)``).

    Attributes:
        camera: the camera's intrinsics as given.
        cam_from_world: ``(T, 7)`` the poses the increments move; velocity: ``(T, 6)`` held fixed; readout:
            ``(T,)`` of each frame's trial (frame periods).
        points: ``(T, N, 3)`` world points; pixels: ``(T, N, 2)``; weights: ``(T, N)`` inverse variances (0: a
            padding slot or a frame that keeps its pose).
        correction: ``(3,)`` the intrinsics correction (without ``calibrate``: held; with: where the solve starts).
        prior: ``(3,)`` ``1 / σ`` of the correction's Gaussian prior.
        loss: the robust loss of each measurement's weighted squared error.
        calibrate: estimate the correction; block_frames: frames linearised at once.
    """

    camera: CameraModel
    cam_from_world: jax.Array
    velocity: jax.Array
    readout: jax.Array
    points: jax.Array
    pixels: jax.Array
    weights: jax.Array
    correction: jax.Array
    prior: jax.Array
    loss: RobustLoss
    calibrate: bool = eqx.field(static=True, default=False)
    block_frames: int = eqx.field(static=True, default=32)

    def split(self, y) -> tuple[jax.Array, jax.Array]:
        """``(T, 6)`` increments and ``(3,)`` correction of the variables ``y``."""
        return y if self.calibrate else (y, self.correction)

    def frame_data(self) -> tuple[jax.Array, ...]:
        return self.cam_from_world, self.velocity, self.readout, self.points, self.pixels, self.weights


def _frame_residuals(camera: CameraModel, correction: jax.Array, delta: jax.Array, cam_from_world: jax.Array,
                     velocity: jax.Array, readout: jax.Array, points: jax.Array, pixels: jax.Array,
                     weights: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One frame's ``(N, 2)`` weighted residuals (px × √weight; 0 where not valid) at the pose increment ``delta``
    ``(6,)`` and intrinsics correction ``correction``, and their ``(N,)`` validity."""
    pose = SE3.exp(delta) @ SE3(cam_from_world)
    predicted, valid = rolling_shutter_projection(corrected_camera(camera, correction), pose, velocity, readout,
                                                  points, pixels[:, 1])
    ok = valid & (weights > 0)
    return jnp.where(ok[:, None], (predicted - pixels) * jnp.sqrt(weights)[:, None], 0.0), ok


def _over_frames(fn):
    """``fn(camera, correction, delta, *frame_data)`` mapped over the frames (camera and correction shared)."""
    return jax.vmap(fn, in_axes=(None, None, 0, 0, 0, 0, 0, 0, 0))


def sequence_residuals(y, problem: CameraSequence):
    """The residuals whose squared sum is twice the cost of ``problem`` at ``y``: each measurement's weighted
    residual scaled by its robust loss, and with ``calibrate`` the correction's prior ``correction / σ``."""
    delta, correction = problem.split(y)
    r, _ = _over_frames(_frame_residuals)(problem.camera, correction, delta, *problem.frame_data())
    r = problem.loss.scale_residual(r)
    return (r, correction * problem.prior) if problem.calibrate else r


def sequence_normal_equations(problem: CameraSequence, y) -> NormalEquations:
    """The Gauss–Newton system of :func:`sequence_residuals` at ``y`` (IRLS model of the robust loss, exact
    gradient): ``(T, 6, 6)`` pose blocks, no bands, with ``calibrate`` bordered by the correction (its prior
    included)."""
    delta, correction = problem.split(y)
    h, g = jax.lax.map(lambda inputs: _frame_system(problem, correction, *inputs), (delta, *problem.frame_data()),
                       batch_size=problem.block_frames)
    if not problem.calibrate:
        return NormalEquations(h, (), g, jnp.zeros(h.shape[:2] + (0,)), jnp.zeros((0, 0)), jnp.zeros(0))
    p2 = problem.prior ** 2
    return NormalEquations(h[:, :6, :6], (), g[:, :6], h[:, :6, 6:], h[:, 6:, 6:].sum(0) + jnp.diag(p2),
                           g[:, 6:].sum(0) + p2 * correction)


def _frame_system(problem: CameraSequence, correction, delta, cam_from_world, velocity, readout, points, pixels, weights):
    """One frame's ``Σ ρ' JᵀJ`` and ``Σ ρ' Jᵀr`` (``(6 [+ 3],)`` columns: the pose increment, with ``calibrate`` the
    correction): :func:`~bcmocap.residuals.rolling_shutter.rolling_shutter_projection` differentiated by the chain
    rule. With ``q = exp(δ) · T · X`` and ``M`` the row's motion
    (:func:`~bcmocap.residuals.rolling_shutter.rolling_shutter_motion`), the prediction is ``π_k(M · q)``: forward
    mode differentiates ``π_k`` along 6 directions (the point in the camera, the correction), and
    ``∂(M · q)/∂δ = R(M) · ∂q/∂δ`` with ``∂q/∂δ = ∂R(exp(δ))/∂δ · T X + ∂t(exp(δ))/∂δ`` (one ``(3, 4, 6)`` per frame)."""
    motion = rolling_shutter_motion(problem.camera, velocity, readout, pixels[:, 1])  # (N,)
    in_pose = SE3(cam_from_world).apply(points)  # T · X, (N, 3)
    q = SE3.exp(delta).apply(in_pose)
    project = lambda pk: corrected_camera(problem.camera, pk[3:]).project(pk[:3])
    pk = jnp.concatenate([motion.apply(q), jnp.broadcast_to(correction, q.shape)], axis=-1)  # (N, 6)
    predicted, valid = jax.vmap(project)(pk)
    jac = jax.vmap(jax.jacfwd(lambda x: project(x)[0]))(pk)  # (N, 2, 6)
    increment = jax.jacfwd(lambda d: SE3.exp(d).as_matrix()[:3])(delta)  # (3, 4, 6): ∂[R | t]/∂δ
    dq = jnp.einsum("ijk,nj->nik", increment[:, :3], in_pose) + increment[:, 3]  # (N, 3, 6)
    j_delta = jnp.einsum("nri,nij,njk->nrk", jac[..., :3], motion.rotation().as_matrix(), dq)
    jac = jnp.concatenate([j_delta, jac[..., 3:]], axis=-1) if problem.calibrate else j_delta
    root = jnp.where(valid & (weights > 0), jnp.sqrt(weights), 0.0)[:, None]  # as _frame_residuals
    r, jac = (predicted - pixels) * root, jac * root[..., None]
    w = problem.loss.derivative(jnp.sum(r * r, axis=-1))  # ρ'(s): the IRLS weight of each measurement
    return jnp.einsum("n,nri,nrj->ij", w, jac, jac), jnp.einsum("n,nri,nr->i", w, jac, r)


@eqx.filter_jit
def _solve_sequences(problems: CameraSequence, y0, tolerance: float, max_steps: int):
    """One Levenberg–Marquardt solve per camera (``problems`` and ``y0`` stacked over cameras)."""

    def one(problem, y):
        return levenberg_marquardt(sequence_residuals, eqx.Partial(sequence_normal_equations, problem), y, problem,
                                   rtol=_RTOL, atol=tolerance, max_steps=max_steps, norm=optx.max_norm,
                                   damping_scale=_DAMPING)

    return jax.vmap(one)(problems, y0)


@eqx.filter_jit
def _sequence_errors(problems: CameraSequence, inlier_bound: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(G, T)`` weighted squared error and count of each camera-frame's valid measurements whose weighted squared
    error is below ``inlier_bound``, at zero increments and the problems' corrections."""

    def one(problem):
        zero = jnp.zeros(problem.cam_from_world.shape[:1] + (6,))
        r, ok = _over_frames(_frame_residuals)(problem.camera, problem.correction, zero, *problem.frame_data())
        e = jnp.sum(r * r, axis=-1)
        inlier = ok & (e < inlier_bound)
        return jnp.sum(jnp.where(inlier, e, 0.0), axis=-1), jnp.sum(inlier, axis=-1)

    return jax.vmap(one)(problems)


class _BlockReader:
    """Iterates over :func:`_blocks` of ``source``; keeps them in memory when they take less than ``budget`` bytes
    (a short trial: the refinement reads it once to count, then once per group of cameras), else reads them again
    each time (memory of a block)."""

    def __init__(self, source, block_frames: int, budget: float = 1e9):
        self.source, self.block_frames, self.kept = source, block_frames, None
        slots = source.slots if isinstance(source, CorrespondenceStore) else source.point_ids.shape[-1]
        if 48.0 * (source.num_frames + block_frames) * source.num_cameras * slots < budget:  # 6 float64 per slot
            self.kept = list(_blocks(source, block_frames))

    def __iter__(self):
        return iter(self.kept) if self.kept is not None else _blocks(self.source, self.block_frames)


def _blocks(source, block_frames: int):
    """``(start, stop, points (B, C, N, 3), pixels, weights)`` per block of frames of ``source`` (a store or
    in-memory correspondences), padded to ``block_frames`` frames (padding has weight 0)."""
    for start in range(0, source.num_frames, block_frames):
        stop = min(start + block_frames, source.num_frames)
        part = source.frames(start, stop)  # a store's: only the points these frames measure
        ids, pixels, weights, points = part.point_ids, part.pixels, part.weights, part.points
        xyz = np.asarray(points)[np.clip(ids, 0, max(len(points) - 1, 0))] if len(points) else np.zeros(ids.shape + (3,))
        weights = np.where(ids >= 0, weights, 0.0)
        pad = block_frames - (stop - start)
        if pad:
            xyz, pixels, weights = (np.concatenate([a, np.zeros((pad,) + a.shape[1:], a.dtype)]) for a in (xyz, pixels, weights))
        yield start, stop, xyz.astype(np.float64), np.asarray(pixels, np.float64), np.asarray(weights, np.float64)


def refine_registered_poses(source, cameras: CameraModel, options: PoseRefinementOptions = PoseRefinementOptions(),
                            *, world_from_camera: np.ndarray | None = None, registered: np.ndarray | None = None,
                            progress: Callable[[str], None] | None = None) -> PoseRefinement:
    """Re-fit a trial's registered camera poses (and, with ``options.calibrate``, each camera's intrinsics
    correction) under the rolling-shutter and corrected-intrinsics projection (see the module's notes).

    Args:
        source: the trial's measurements and registration: a
            :class:`~bcmocap.correspondence_store.CorrespondenceStore` or
            :class:`~bcmocap.correspondences.Correspondences` (``point_ids`` ``(T, C, N)``, ``pixels``, ``weights``,
            ``points`` ``(P, 3)`` held fixed, ``world_from_camera`` ``(T, C, 7)``, ``registered`` ``(T, C)``).
        cameras: the rig's ``C`` intrinsics as given (stacked).
        world_from_camera, registered: start from these instead of the source's.
        progress: receives one line per round.

    Returns:
        A :class:`PoseRefinement`.
    """
    start = None if world_from_camera is None and registered is None else (world_from_camera, registered)
    return refine_trials([source], cameras, options, starts=[start], progress=progress)[0]


def refine_trials(sources, cameras: CameraModel, options: PoseRefinementOptions = PoseRefinementOptions(), *,
                  starts=None, readouts=None, progress: Callable[[str], None] | None = None) -> list[PoseRefinement]:
    """:func:`refine_registered_poses` of several trials of one rig at once: with ``options.calibrate`` they share
    each camera's intrinsics correction (a camera with too few measurements in one trial is calibrated by the
    others). ``starts``: per trial None or ``(world_from_camera, registered)`` to start from (None of the pair:
    the source's); ``readouts``: per trial the readout in its frame periods (trials at different frame rates;
    default ``options.readout``). Returns one :class:`PoseRefinement` per trial, all with the same correction."""
    o = options
    starts = [None] * len(sources) if starts is None else list(starts)
    readouts = [o.readout] * len(sources) if readouts is None else [float(r) for r in readouts]
    if not (len(starts) == len(readouts) == len(sources)):
        raise ValueError(f"refine_trials: {len(sources)} trials, {len(starts)} starts and {len(readouts)} readouts")
    trials = [_Trial(source, cameras, dataclasses.replace(o, readout=readout), *(start or (None, None)))
              for source, start, readout in zip(sources, starts, readouts)]
    num_cameras, frames = cameras.batch_shape[0], sum(t.num_frames for t in trials)
    width = -(-max(int(t.counts[t.free].max(initial=0)) for t in trials) // 8) * 8  # slots of a camera-frame
    per_camera = frames * width * _BYTES_PER_MEASUREMENT + min(o.block_frames, frames) * width * 2 * 9 * 8
    group = int(np.clip(o.memory // max(per_camera, 1), 1, num_cameras))
    cam_from_world = np.concatenate([t.cam_from_world for t in trials])  # (T, C, 7): all trials end to end
    correction = np.zeros((num_cameras, 3))
    errors = np.zeros((2, 2, frames, num_cameras))  # (before, after), (squared, count)
    iterations = 0
    for first in range(0, num_cameras, group) if width else ():
        cams = np.arange(first, first + group)
        real = cams < num_cameras
        cams = np.minimum(cams, num_cameras - 1)  # the last group padded with copies that measure nothing
        poses, k, error, steps = _refine_cameras(trials, cameras, cams, real, width, progress)
        cam_from_world[:, cams[real]], correction[cams[real]] = poses[:, real], k[real]
        errors[..., cams[real]] = error[..., real]
        iterations = max(iterations, steps)
    out, offset = [], 0
    for t in trials:
        t.cam_from_world = np.where(t.free[..., None], cam_from_world[offset:offset + t.num_frames], t.cam_from_world)
        squared, count = errors[:, :, offset:offset + t.num_frames].sum(2).transpose(1, 0, 2)
        rms = np.sqrt(squared / np.where(count > 0, count, np.nan))  # (2, C)
        out.append(t.result(correction, rms[0], rms[1], iterations))
        offset += t.num_frames
    return out


def _refine_cameras(trials: list[_Trial], cameras: CameraModel, cams: np.ndarray, real: np.ndarray, width: int,
                    progress: Callable[[str], None] | None):
    """Rounds of :func:`_solve_sequences` for the cameras ``cams`` (``real``: not a padding copy) of all ``trials``.

    Returns ``(T, G, 7)`` poses, ``(G, 3)`` corrections, ``(2, 2, T, G)`` (before, after) × (squared error, count)
    of the inliers, and the Levenberg–Marquardt steps taken."""
    o = trials[0].options
    points, pixels, weights = _camera_measurements(trials, cams, width)
    weights[~real] = 0.0
    free = np.concatenate([t.free[:, cams] for t in trials]) & real  # (T, G)
    poses = np.concatenate([t.cam_from_world[:, cams] for t in trials])
    readout = np.concatenate([np.full(t.num_frames, t.options.readout) for t in trials])
    group = len(cams)
    sigma = np.array([o.intrinsics_sigma[0], o.intrinsics_sigma[1], o.intrinsics_sigma[1]])
    fixed = {"camera": jax.tree.map(lambda a: a[cams], cameras), "readout": jnp.asarray(np.tile(readout, (group, 1))),
             "points": jnp.asarray(points), "pixels": jnp.asarray(pixels), "weights": jnp.asarray(weights),
             "prior": jnp.asarray(np.tile(1.0 / sigma, (group, 1))), "loss": CauchyLoss(jnp.full(group, o.loss_scale)),
             "calibrate": o.calibrate, "block_frames": o.block_frames}

    def problems(poses: np.ndarray, correction: np.ndarray) -> CameraSequence:
        velocity = np.concatenate([_velocities(t, poses[offset:offset + t.num_frames], cams)
                                   for t, offset in zip(trials, np.cumsum([0] + [t.num_frames for t in trials]))])
        return CameraSequence(cam_from_world=jnp.asarray(poses.swapaxes(0, 1)), velocity=jnp.asarray(velocity.swapaxes(0, 1)),
                              correction=jnp.asarray(correction), **fixed)

    inlier_bound = jnp.asarray(25.0 * o.loss_scale ** 2)
    correction = np.zeros((group, 3))
    before = _sequence_errors(problems(poses, correction), inlier_bound)
    steps = 0
    for round_ in range(1, o.max_iterations + 1):
        delta = jnp.zeros(weights.shape[:2] + (6,))
        y, report = _solve_sequences(problems(poses, correction), (delta, jnp.asarray(correction)) if o.calibrate else delta,
                                     o.tolerance, o.max_steps)
        delta, k = (np.asarray(a) for a in y) if o.calibrate else (np.asarray(y), correction)
        delta = np.where(free.T[..., None], delta, 0.0)
        moved = max(np.abs(delta).max(initial=0.0), np.abs(k - correction).max(initial=0.0))
        poses = np.where(free[..., None], np.asarray((SE3.exp(jnp.asarray(delta.swapaxes(0, 1))) @ SE3(jnp.asarray(poses))).wxyz_xyz),
                         poses)
        correction = k
        steps += int(np.max(report.num_steps))
        if progress:
            progress(f"pose refinement of cameras {cams[real].min()}–{cams[real].max()}, round {round_}: cost "
                     f"{np.sum(np.asarray(report.initial_cost)[real]):.6g} → {np.sum(np.asarray(report.final_cost)[real]):.6g} in "
                     f"{int(np.max(report.num_steps))} steps, largest move {moved:.2e}")
        settled = np.asarray(report.converged) & (np.asarray(report.num_steps) <= 2)  # converged from the start
        if moved < o.tolerance or np.all(settled) or (not readout.any() and np.all(np.asarray(report.converged))):
            break  # (without a readout the velocities stay zero: nothing changes for another round)
    after = _sequence_errors(problems(poses, correction), inlier_bound)
    error = np.stack([np.stack([np.asarray(a).T for a in before]), np.stack([np.asarray(a).T for a in after])])
    return poses, correction, error, steps


def _velocities(trial: _Trial, cam_from_world: np.ndarray, cams: np.ndarray) -> np.ndarray:
    """``(T, G, 6)`` the cameras ``cams``' velocities in ``trial`` at its poses ``cam_from_world`` ``(T, G, 7)``."""
    if trial.options.readout <= 0:
        return np.zeros(cam_from_world.shape[:2] + (6,))
    return camera_velocities(cam_from_world, trial.registered[:, cams])


def _camera_measurements(trials: list[_Trial], cams: np.ndarray, width: int):
    """``(G, T, width, 3)`` points, ``(G, T, width, 2)`` pixels and ``(G, T, width)`` weights of the cameras ``cams``
    over all ``trials`` (end to end): each camera-frame's weighted measurements first (zero weight at frames that
    keep their pose)."""
    frames = sum(t.num_frames for t in trials)
    group = len(cams)
    points, pixels = np.zeros((group, frames, width, 3)), np.zeros((group, frames, width, 2))
    weights = np.zeros((group, frames, width))
    offset = 0
    for t in trials:
        for start, stop, xyz, px, w in t.blocks:
            n = stop - start
            w = np.where(t.free[start:stop, cams, None], w[:n, cams], 0.0)  # (n, G, S)
            order = np.argsort(w <= 0, axis=-1, kind="stable")[..., :width]  # (n, G, ≤ width)
            rows, used = slice(offset + start, offset + stop), order.shape[-1]
            points[:, rows, :used], pixels[:, rows, :used], weights[:, rows, :used] = (
                _slots(a, order) for a in (xyz[:n, cams], px[:n, cams], w))
        offset += t.num_frames
    return points, pixels, weights


def _slots(a: np.ndarray, order: np.ndarray) -> np.ndarray:
    """``a`` ``(n, G, S, ...)`` at the slots ``order`` ``(n, G, K)``, as ``(G, n, K, ...)``."""
    return np.take_along_axis(a, order.reshape(order.shape + (1,) * (a.ndim - 3)), axis=2).swapaxes(0, 1)


class _Trial:
    """One trial's state in :func:`refine_trials`: its measurements (read a block at a time), registered and
    re-fitted frames and current ``cam_from_world`` poses."""

    def __init__(self, source, cameras: CameraModel, options: PoseRefinementOptions, world_from_camera=None,
                 registered=None):
        self.poses0 = np.asarray(source.world_from_camera if world_from_camera is None else world_from_camera, np.float64)
        self.registered = np.asarray(source.registered if registered is None else registered, bool)
        self.num_frames, num_cameras = self.registered.shape
        if cameras.batch_shape != (num_cameras,):
            raise ValueError(f"refine_registered_poses: {num_cameras} cameras registered, intrinsics for "
                             f"{cameras.batch_shape}")
        if self.poses0.shape != (self.num_frames, num_cameras, 7):
            raise ValueError(f"refine_registered_poses: world_from_camera has shape {self.poses0.shape}, expected "
                             f"({self.num_frames}, {num_cameras}, 7)")
        self.options = options
        self.blocks = _BlockReader(source, min(options.block_frames, self.num_frames))
        self.counts = np.zeros((self.num_frames, num_cameras), int)
        for start, stop, _, _, weights in self.blocks:
            self.counts[start:stop] = (weights[: stop - start] > 0).sum(-1)
        self.free = self.registered & (self.counts >= options.min_measurements)
        self.safe = np.where(self.registered[..., None], self.poses0, np.array([1.0, 0, 0, 0, 0, 0, 0]))
        self.cam_from_world = np.asarray(SE3(jnp.asarray(self.safe)).inverse().wxyz_xyz)

    def result(self, correction: np.ndarray, rms_before: np.ndarray, rms_after: np.ndarray, iterations: int) -> PoseRefinement:
        refined = np.asarray(SE3(jnp.asarray(self.cam_from_world)).inverse().wxyz_xyz)
        refined = np.where(self.free[..., None], refined, self.poses0)
        moved_m = np.where(self.registered, np.linalg.norm(refined[..., 4:] - self.safe[..., 4:], axis=-1), 0.0)
        turn = np.abs(np.sum(refined[..., :4] * self.safe[..., :4], axis=-1)).clip(0.0, 1.0)
        moved_deg = np.where(self.registered, np.degrees(2 * np.arccos(turn)), 0.0)
        return PoseRefinement(refined, correction, np.stack([rms_before, rms_after], axis=-1), iterations, moved_m,
                              moved_deg, self.free)
