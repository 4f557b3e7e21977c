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
``x`` of point ``X`` in image row ``y`` is predicted as in the solver's rolling-shutter term,

    π_{k_c}( exp(s · readout · v_t) · T_t · X ),   s = y / (H − 1) − ½,

with ``v_t`` the camera's velocity at frame ``t`` (a left increment of ``cam_from_world`` per frame period): half
the increment from frame ``t − 1`` to ``t + 1`` when both are registered, else the one-sided increment, else
zero. The velocities are taken from the current poses and held fixed for one Gauss–Newton step (the frames are
then independent given ``k_c``; the intrinsics are eliminated per camera by a Schur complement), then
recomputed, so the fixed point is the poses whose every frame best explains its image given its neighbours'.
The loss is Cauchy at ``loss_scale`` px; steps are damped (Levenberg–Marquardt, one damping per camera) and a
camera's step is kept only when its cost falls.

The measurements are read a block of frames at a time from a
:class:`~bcmocap.correspondence_store.CorrespondenceStore` (or taken from in-memory
:class:`~bcmocap.correspondences.Correspondences`; a short trial's blocks are kept in memory): the Jacobians are a
block's, the normal equations ``(T, C, 9, 9)`` the whole trial's (about 0.7 kB per camera-frame); each step reads
the trial two to five times (linearisation, then the cost of each damped try).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..cameras import CameraModel
from ..correspondence_store import CorrespondenceStore
from ..geometry import SE3
from ..residuals.self_calibration import corrected_camera, corrected_cameras

__all__ = ["PoseRefinementOptions", "PoseRefinement", "refine_registered_poses", "refine_trials", "camera_velocities"]


@dataclasses.dataclass(frozen=True)
class PoseRefinementOptions:
    """Settings of :func:`refine_registered_poses`.

    Attributes:
        readout: rolling-shutter readout, first row to last, in frame periods of the trial's frames (readout
            seconds × the trial's frames per second); 0: global shutter.
        calibrate: also estimate each camera's intrinsics correction.
        intrinsics_sigma: the correction's prior σ: (log focal scale, principal point px).
        loss_scale: Cauchy loss scale (px).
        max_iterations: Gauss–Newton steps at most.
        tolerance: stop when no pose (nor, with ``calibrate``, correction) moves more than this in a step (the
            poses' units and rad; log focal scale and px).
        min_measurements: a registered frame with fewer measurements keeps its pose (it still gives its
            neighbours their velocity): too few to fit a pose (the frontend registered it through points the
            measurements do not hold).
        block_frames: frames linearised at once (memory: ``block_frames × cameras × slots`` Jacobians of 2 × 9).
    """

    readout: float = 0.0
    calibrate: bool = False
    intrinsics_sigma: tuple[float, float] = (0.01, 5.0)
    loss_scale: float = 2.0
    max_iterations: int = 12
    tolerance: float = 1e-4
    min_measurements: int = 20
    block_frames: int = 32

    def __post_init__(self):
        if not (np.isfinite(self.readout) and 0.0 <= self.readout <= 2.0):
            raise ValueError(f"PoseRefinementOptions.readout must lie in [0, 2] frame periods, got {self.readout}")
        if not (len(self.intrinsics_sigma) == 2 and all(np.isfinite(s) and s > 0 for s in self.intrinsics_sigma)):
            raise ValueError(f"PoseRefinementOptions.intrinsics_sigma must be two positive numbers, got {self.intrinsics_sigma}")
        if not (self.loss_scale > 0 and self.max_iterations >= 1 and self.tolerance > 0 and self.block_frames >= 1
                and self.min_measurements >= 6):
            raise ValueError("PoseRefinementOptions: loss_scale and tolerance must be > 0, max_iterations and "
                             "block_frames >= 1, min_measurements >= 6")


@dataclasses.dataclass(frozen=True)
class PoseRefinement:
    """What :func:`refine_registered_poses` found.

    Attributes:
        world_from_camera: ``(T, C, 7)`` refined poses (wxyz_xyz); unregistered rows as given.
        intrinsics_correction: ``(C, 3)`` per camera (log focal scale, Δcx px, Δcy px); zeros without ``calibrate``.
        rms_px: ``(C, 2)`` per camera, root mean square reprojection error of its measurements before and after
            (inverse-variance weighted, px; measurements within 5 loss scales, NaN for a camera without any).
        iterations: Gauss–Newton steps taken.
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


def _measurement_residual(delta_k: jax.Array, pose: SE3, velocity: jax.Array, camera: CameraModel, point: jax.Array,
                          pixel: jax.Array, readout: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One measurement's ``(2,)`` residual (px) and validity at the increment ``delta_k`` ``(9,)``: pose (6, left)
    and intrinsics correction (3)."""
    s = pixel[1] / max(camera.height - 1, 1) - 0.5
    at_row = SE3.exp(s * readout * velocity) @ SE3.exp(delta_k[:6]) @ pose
    predicted, valid = corrected_camera(camera, delta_k[6:]).project(at_row.apply(point))
    return predicted - pixel, valid


def _frame_system(pose, velocity, correction, camera, points, pixels, weights, readout, loss_scale):
    """One camera-frame's normal equations at zero increment: ``(9, 9)`` ``JᵀWJ``, ``(9,)`` ``−JᵀWr`` and its
    robust cost (Cauchy, IRLS weights). The pose columns chain the projection's Jacobian (forward mode, 6
    directions: the point in the camera, the correction) with that of a left increment, ``[I | −[q]×]``."""

    def one(point, pixel):
        s = pixel[1] / max(camera.height - 1, 1) - 0.5
        motion = SE3.exp(s * readout * velocity)
        q = pose.apply(point)
        project = lambda pk: corrected_camera(camera, pk[3:]).project(pk[:3])  # noqa: E731
        pk = jnp.concatenate([motion.apply(q), correction])
        (predicted, valid), jac = project(pk), jax.jacfwd(lambda x: project(x)[0])(pk)
        increment = jnp.concatenate([jnp.eye(3), -_skew(q)], axis=1)  # d(exp(δ) q)/dδ at δ = 0, (3, 6)
        pose_jac = jac[:, :3] @ motion.rotation().as_matrix() @ increment
        return predicted - pixel, jnp.concatenate([pose_jac, jac[:, 3:]], axis=1), valid

    r, jac, valid = jax.vmap(one)(points, pixels)
    w = jnp.where(valid, weights, 0.0)
    e = w * jnp.sum(r * r, axis=-1)
    c2 = loss_scale * loss_scale
    robust = w / (1.0 + e / c2)
    h = jnp.einsum("n,nri,nrj->ij", robust, jac, jac)
    g = -jnp.einsum("n,nri,nr->i", robust, jac, r)
    return h, g, jnp.sum(c2 * jnp.log1p(e / c2))


def _skew(v: jax.Array) -> jax.Array:
    return jnp.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _frame_cost(pose, velocity, correction, camera, points, pixels, weights, readout, loss_scale, delta):
    """One camera-frame's robust cost (and inverse-variance weighted squared error and count of the measurements
    within 5 loss scales) after the pose increment ``delta`` ``(6,)`` at intrinsics correction ``correction``."""
    inc = jnp.concatenate([delta, correction])
    r, valid = jax.vmap(lambda p, x: _measurement_residual(inc, pose, velocity, camera, p, x, readout))(points, pixels)
    w = jnp.where(valid, weights, 0.0)
    e = w * jnp.sum(r * r, axis=-1)
    c2 = loss_scale * loss_scale
    inlier = (w > 0) & (e < 25 * c2)
    return jnp.sum(c2 * jnp.log1p(e / c2)), jnp.sum(jnp.where(inlier, e, 0.0)), jnp.sum(inlier)


def _over_frames_and_cameras(fn, per_frame_tail: int = 0):
    """``fn`` mapped over ``(B, C)`` camera-frames, the camera (and its correction) shared along frames; its
    ``per_frame_tail`` last arguments are per camera-frame too."""
    tail = (0,) * per_frame_tail
    per_camera = jax.vmap(fn, in_axes=(0, 0, 0, 0, 0, 0, 0, None, None) + tail)
    return jax.vmap(per_camera, in_axes=(0, 0, None, None, 0, 0, 0, None, None) + tail)


@eqx.filter_jit
def _block_systems(poses, velocities, corrections, cameras, points, pixels, weights, readout, loss_scale):
    return _over_frames_and_cameras(_frame_system)(SE3(poses), velocities, corrections, cameras, points, pixels,
                                                   weights, readout, loss_scale)


@eqx.filter_jit
def _block_costs(poses, velocities, corrections, cameras, points, pixels, weights, readout, loss_scale, deltas):
    return _over_frames_and_cameras(_frame_cost, per_frame_tail=1)(SE3(poses), velocities, corrections, cameras, points,
                                                                   pixels, weights, readout, loss_scale, deltas)


class _BlockReader:
    """Iterates over :func:`_blocks` of ``source``; keeps them in memory when they take less than ``budget`` bytes
    (a short trial: the refinement reads it twice a step), else reads them again each time (memory of a block)."""

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


def _padded(a: np.ndarray, start: int, stop: int, size: int) -> np.ndarray:
    part = a[start:stop]
    return np.concatenate([part, np.repeat(part[-1:], size - len(part), axis=0)]) if len(part) < size else part


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
        progress: receives one line per step.

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
    num_cameras = cameras.batch_shape[0]
    correction = np.zeros((num_cameras, 3))
    prior = 1.0 / np.array([o.intrinsics_sigma[0], o.intrinsics_sigma[1], o.intrinsics_sigma[1]]) ** 2
    damping = np.full(num_cameras, 1e-4)
    free = np.concatenate([t.free for t in trials])

    def camera_cost(frame_costs, corr):
        return frame_costs.sum(0) + (np.sum(prior * corr ** 2, axis=-1) if o.calibrate else 0.0)

    def split(a: np.ndarray) -> list[np.ndarray]:
        return np.split(a, np.cumsum([t.num_frames for t in trials])[:-1])

    rms_before = [t.rms(correction) for t in trials]
    iterations = 0
    for iterations in range(1, o.max_iterations + 1):
        h, g, frame_costs = (np.concatenate(part) for part in zip(*(t.linearise(correction) for t in trials)))
        before = camera_cost(frame_costs, correction)
        step, dk_kept = np.zeros(h.shape[:2] + (6,)), np.zeros((num_cameras, 3))
        after = before.copy()
        pending = free.any(0)
        for _ in range(4):  # a camera whose cost rose tries again with more damping (at most 4 times a step)
            if not pending.any():
                break
            deltas, dk = _solve(h, g, free & pending[None], correction, prior if o.calibrate else None, damping)
            trial_costs = camera_cost(np.concatenate([t.costs(correction + dk, d)[0] for t, d in zip(trials, split(deltas))]),
                                      correction + dk)
            kept = pending & (trial_costs <= before)
            step[:, kept], dk_kept[kept], after[kept] = deltas[:, kept], dk[kept], trial_costs[kept]
            damping = np.where(kept, np.maximum(damping / 3.0, 1e-9), np.where(pending, damping * 10.0, damping))
            pending &= ~kept
        for t, d in zip(trials, split(step)):
            t.apply(d)
        correction = correction + dk_kept
        moved = max(np.abs(step).max(initial=0.0), np.abs(dk_kept).max(initial=0.0) if o.calibrate else 0.0)
        if progress:
            progress(f"pose refinement step {iterations}: cost {before.sum():.6g} → {after.sum():.6g}, "
                     f"largest step {moved:.2e}")
        if moved < o.tolerance and not pending.any():  # converged, not merely every step refused
            break
    return [t.result(correction, before_rms, t.rms(correction), iterations) for t, before_rms in zip(trials, rms_before)]


class _Trial:
    """One trial's state in :func:`refine_trials`: its measurements (read a block at a time), registered and
    re-fitted frames, current ``cam_from_world`` poses and velocities."""

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
        self.options, self.cameras = options, cameras
        self.block = min(options.block_frames, self.num_frames)
        self.blocks = _BlockReader(source, self.block)
        counts = np.zeros((self.num_frames, num_cameras), int)
        for start, stop, _, _, weights in self.blocks:
            counts[start:stop] = (weights[: stop - start] > 0).sum(-1)
        self.free = self.registered & (counts >= options.min_measurements)
        self.safe = np.where(self.registered[..., None], self.poses0, np.array([1.0, 0, 0, 0, 0, 0, 0]))
        self.cam_from_world = np.asarray(SE3(jnp.asarray(self.safe)).inverse().wxyz_xyz)
        self.readout, self.scale = jnp.asarray(float(options.readout)), jnp.asarray(float(options.loss_scale))
        self._velocities()

    def _velocities(self) -> None:
        self.velocities = (camera_velocities(self.cam_from_world, self.registered) if self.options.readout > 0
                           else np.zeros(self.cam_from_world.shape[:2] + (6,)))

    def _padded(self, a: np.ndarray, start: int, stop: int) -> np.ndarray:
        return _padded(a, start, stop, self.block)

    def linearise(self, correction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(T, C, 9, 9)`` ``JᵀWJ``, ``(T, C, 9)`` ``−JᵀWr`` and ``(T, C)`` robust costs (zero where not re-fitted)."""
        shape = self.cam_from_world.shape[:2]
        h, g, cost = np.zeros(shape + (9, 9)), np.zeros(shape + (9,)), np.zeros(shape)
        for start, stop, xyz, pixels, weights in self.blocks:
            n = stop - start
            hb, gb, cb = _block_systems(self._padded(self.cam_from_world, start, stop),
                                        self._padded(self.velocities, start, stop), jnp.asarray(correction),
                                        self.cameras, xyz, pixels, weights, self.readout, self.scale)
            h[start:stop], g[start:stop], cost[start:stop] = np.asarray(hb)[:n], np.asarray(gb)[:n], np.asarray(cb)[:n]
        h[~self.free], g[~self.free], cost[~self.free] = 0.0, 0.0, 0.0
        return h, g, cost

    def costs(self, correction: np.ndarray, deltas: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per camera-frame robust cost after the pose increments ``deltas`` ``(T, C, 6)`` at ``correction``, and per
        camera the weighted squared error and count of its inliers (within 5 loss scales)."""
        shape = self.cam_from_world.shape[:2]
        deltas = np.zeros(shape + (6,)) if deltas is None else deltas
        cost, squared, count = np.zeros(shape), np.zeros(shape[1]), np.zeros(shape[1])
        for start, stop, xyz, pixels, weights in self.blocks:
            n = stop - start
            c, s, k = _block_costs(self._padded(self.cam_from_world, start, stop), self._padded(self.velocities, start, stop),
                                   jnp.asarray(correction), self.cameras, xyz, pixels, weights, self.readout, self.scale,
                                   self._padded(deltas, start, stop))
            mask = self.free[start:stop]
            cost[start:stop] = np.where(mask, np.asarray(c)[:n], 0.0)
            squared += np.where(mask, np.asarray(s)[:n], 0.0).sum(0)
            count += np.where(mask, np.asarray(k)[:n], 0).sum(0)
        return cost, squared, count

    def rms(self, correction: np.ndarray) -> np.ndarray:
        _, squared, count = self.costs(correction)
        return np.sqrt(squared / np.where(count > 0, count, np.nan))

    def apply(self, step: np.ndarray) -> None:
        """Move the re-fitted frames by the left increments ``step`` ``(T, C, 6)``; recompute the velocities."""
        moved = np.asarray((SE3.exp(jnp.asarray(step)) @ SE3(jnp.asarray(self.cam_from_world))).wxyz_xyz)
        self.cam_from_world = np.where(self.free[..., None], moved, self.cam_from_world)
        self._velocities()

    def result(self, correction: np.ndarray, rms_before: np.ndarray, rms_after: np.ndarray, iterations: int) -> PoseRefinement:
        refined = np.asarray(SE3(jnp.asarray(self.cam_from_world)).inverse().wxyz_xyz)
        refined = np.where(self.free[..., None], refined, self.poses0)
        moved_m = np.where(self.registered, np.linalg.norm(refined[..., 4:] - self.safe[..., 4:], axis=-1), 0.0)
        turn = np.abs(np.sum(refined[..., :4] * self.safe[..., :4], axis=-1)).clip(0.0, 1.0)
        moved_deg = np.where(self.registered, np.degrees(2 * np.arccos(turn)), 0.0)
        return PoseRefinement(refined, correction, np.stack([rms_before, rms_after], axis=-1), iterations, moved_m,
                              moved_deg, self.free)


def _solve(h: np.ndarray, g: np.ndarray, registered: np.ndarray, correction: np.ndarray, prior: np.ndarray | None,
           damping: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The damped Gauss–Newton step: ``(T, C, 6)`` pose increments and ``(C, 3)`` intrinsics increments (zero
    without ``prior``), the intrinsics eliminated per camera by a Schur complement."""
    h = np.where(registered[..., None, None], h, 0.0)  # camera-frames left out (not re-fitted, or not pending)
    g = np.where(registered[..., None], g, 0.0)
    lam = damping[None, :, None]
    a = h[..., :6, :6]
    a = a + np.einsum("...i,ij->...ij", lam * np.diagonal(a, axis1=-2, axis2=-1) + 1e-9, np.eye(6))
    a[~registered] = np.eye(6)
    gp = g[..., :6]
    if prior is None:
        return np.linalg.solve(a, gp[..., None])[..., 0], np.zeros_like(correction)
    b = h[..., :6, 6:]  # (T, C, 6, 3)
    a_inv_b = np.linalg.solve(a, b)
    a_inv_g = np.linalg.solve(a, gp[..., None])[..., 0]
    s = h[..., 6:, 6:].sum(0) - np.einsum("tcij,tcik->cjk", b, a_inv_b) + np.eye(3) * prior
    s = s + np.einsum("ci,ij->cij", damping[:, None] * np.diagonal(s, axis1=-2, axis2=-1), np.eye(3))
    rhs = g[..., 6:].sum(0) - np.einsum("tcij,tci->cj", b, a_inv_g) - prior * correction
    dk = np.linalg.solve(s, rhs[..., None])[..., 0]
    deltas = a_inv_g - np.einsum("tcij,cj->tci", a_inv_b, dk)
    return np.where(registered[..., None], deltas, 0.0), dk
