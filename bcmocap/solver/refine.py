"""Refine the skeleton and camera mounts shared by all frames (issue 3, item 6; beyond the paper).

The paper keeps the skeleton and the mounts of the range-of-motion trial fixed in the final
optimisation (Eq. 1, skeleton as a hard constraint). Here they are refined from the capture itself,
by alternating two steps (:func:`solve_with_refinement`):

(a) the motion with the current skeleton and rig: the windowed solver, unchanged (:func:`solve`);
(b) the shared parameters θ — a 3-vector correction of every non-root ``Skeleton.offsets`` row, a
    6-DOF correction of every ``segment_from_camera`` (translation in the segment frame, rotation
    left-multiplied in the segment frame, so it turns the camera about its own centre) and a 2-DOF
    tilt of every hinge axis — by Levenberg–Marquardt on the same robust reprojection cost as
    :func:`paper_problem` plus a prior ``½ Σ (θ/σ)²`` towards the range-of-motion values
    (:func:`refine_skeleton_and_rig`).

Step (b) does not hold the motion fixed (a plain block-coordinate descent would: ``hold_motion``).
It is one least-squares problem over every used frame's motion tangent and θ, solved by the
project's one Levenberg–Marquardt (:func:`~bcmocap.solver.levenberg_marquardt`). The frames are
independent given θ, so the Gauss–Newton matrix is block diagonal in the motion, bordered by θ (θ
is the solver's static variables) and each step eliminates the motion (Schur complement, per frame):
``S = Σ_t C_t − B_tᵀ A_t⁻¹ B_t`` where ``A_t``, ``B_t``, ``C_t`` are the frame's motion–motion,
motion–θ and θ–θ blocks of ``Σ ρ' JᵀJ``. The step in θ therefore already accounts for how the
motion re-fits, and each frame's motion moves with it (``δm_t = −A_t⁻¹(g_t + B_t δθ)``). With the
motion held fixed instead, the motion has compensated the wrong skeleton and pins θ near its old
value, and the alternation crawls; eliminated, one round does nearly all of it.

Only the reprojection term enters (b): smoothness acts on the motion alone, and the homography
transfer (camera-frames that did not register) carries almost nothing on the mounts. The Jacobian
is never formed over all measurements: a camera's measurements enter through its ``3 × 4``
``cam_from_world`` matrix (a ``12 × 12`` normal block per camera), chained with the autodiff
Jacobian of those matrices with respect to the frame's motion tangent and θ. Frames are linearised
in fixed-size chunks (``lax.map``, one compilation); the system holds ``A_t`` and ``B_t`` per frame
(``T × D × (D + P)`` numbers).

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
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..correspondences import Correspondences
from ..geometry import SE3, SO3
from ..kinematics.rig import Rig, camera_poses
from ..kinematics.skeleton import JointType, Motion, Skeleton
from ..residuals import Reprojection
from ..precision import require_float64
from .levenberg_marquardt import NormalEquations, levenberg_marquardt
from .objective import ObjectiveWeights, paper_problem, paper_terms
from .solve import Solution, SolverOptions, solve


@dataclasses.dataclass(frozen=True)
class RefineOptions:
    """Settings of :func:`refine_skeleton_and_rig`.

    Attributes:
        offset_sigma_m: prior σ of each offset coordinate around the prior skeleton (m).
        mount_translation_sigma_m, mount_rotation_sigma_deg: prior σ of each mount's translation
            (m, segment frame) and rotation (°, per axis) around the prior rig.
        hinge_axis_sigma_deg: prior σ of each hinge axis's tilt (°, per perpendicular direction).
        refine_offsets, refine_mounts, refine_hinge_axes: which shared parameters move.
        hold_motion: keep the motion fixed in (b) (plain block-coordinate descent) instead of
            eliminating it frame by frame; only useful when the motion is known.
        hold_segment_frames: keep the mean rotation correction of the cameras of every FREE or
            BALL segment at zero, so segment frames (hence joint angles) stay those of the trial's
            rest pose; a hinge segment's cameras turn freely (its frame follows its parent's
            through the refined axis). Without it, only the prior holds these directions.
        root_origin: children of the root whose mean joint is the root's origin (held); default:
            the root's children with a zero offset if there are any, else all of them.
        max_steps: Levenberg–Marquardt iterations (accepted or rejected).
        xtol, ftol: stop after an accepted step that changes the variables (motion tangents and θ) by
            less than ``xtol`` in RMS (m and rad) and the cost by less than ``xtol + ftol · cost``
            (the ``atol`` and ``rtol`` of :func:`~bcmocap.solver.levenberg_marquardt`).
        damping_scale: initial damping relative to the Marquardt diagonal.
        chunk_frames: frames linearised together (``vmap``; the chunks run in sequence).
        frame_stride: use every k-th frame (the motion of the others does not move in (b)).
    """

    offset_sigma_m: float = 0.005
    mount_translation_sigma_m: float = 0.005
    mount_rotation_sigma_deg: float = 0.3
    hinge_axis_sigma_deg: float = 0.5
    refine_offsets: bool = True
    refine_mounts: bool = True
    refine_hinge_axes: bool = True
    hold_motion: bool = False
    hold_segment_frames: bool = True
    root_origin: tuple[str, ...] | None = None
    max_steps: int = 15
    xtol: float = 1e-5
    ftol: float = 1e-10
    damping_scale: float = 1e-4
    chunk_frames: int = 16
    frame_stride: int = 1

    def __post_init__(self):
        for name in ("offset_sigma_m", "mount_translation_sigma_m", "mount_rotation_sigma_deg", "hinge_axis_sigma_deg"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RefineOptions: {name} must be positive, got {getattr(self, name)}")
        if not (self.refine_offsets or self.refine_mounts or self.refine_hinge_axes):
            raise ValueError("RefineOptions: nothing to refine (refine_offsets, refine_mounts and refine_hinge_axes are all False)")
        for name in ("max_steps", "chunk_frames", "frame_stride"):
            if getattr(self, name) < 1:
                raise ValueError(f"RefineOptions: {name} must be ≥ 1, got {getattr(self, name)}")


@dataclasses.dataclass(frozen=True)
class RefineReport:
    """How one refinement went.

    Attributes:
        initial_cost, final_cost: robust reprojection cost ``½ Σ λρ`` plus the prior, before and after.
        initial_reprojection_cost, final_reprojection_cost: the reprojection part alone.
        num_steps, num_accepted_steps, converged: from the solver's
            :class:`~bcmocap.solver.Convergence` (converged: stopped by the tolerances, not by ``max_steps``).
        offset_change_m: largest change of an offset vector (norm, m) against the input.
        mount_translation_change_m, mount_rotation_change_deg: largest change of a mount.
        hinge_axis_change_deg: largest change of a hinge axis.
        prior_directions: directions of θ that the prior, not the data, determines (eigenvalues of the
            prior-whitened data matrix below 1; the held means are not counted).
        num_parameters: size of θ; frames: frames used; seconds: wall time.
    """

    initial_cost: float
    final_cost: float
    initial_reprojection_cost: float
    final_reprojection_cost: float
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
        motion: the used frames' motion solved with the parameters (the other frames', and with
            ``hold_motion`` all of them, only re-expressed about the refined hinge axes with the same
            angles), a starting point for the next solve.
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


@dataclasses.dataclass(frozen=True)
class _Layout:
    """Where each shared parameter sits in θ (static).

    θ = ``[offset corrections (J−1, 3) of segments 1…J−1, mount corrections (C, 6) (translation,
    rotation), hinge-axis tilts (H, 2)]`` relative to a base model; a hinge's tilt is along two unit
    vectors ``hinge_basis`` perpendicular to its base axis. ``active`` indexes the entries that move.
    """

    num_segments: int
    num_cameras: int
    origin_children: tuple[int, ...]
    held_frames: tuple[tuple[int, ...], ...]
    hinges: tuple[int, ...]
    hinge_basis: tuple[tuple[tuple[float, ...], ...], ...]
    active: tuple[int, ...]

    @property
    def num_offsets(self) -> int:
        return 3 * (self.num_segments - 1)

    @property
    def num_mounts(self) -> int:
        return 6 * self.num_cameras

    @property
    def size(self) -> int:
        return self.num_offsets + self.num_mounts + 2 * len(self.hinges)

    def split(self, theta):
        """θ → offsets ``(J−1, 3)``, mounts ``(C, 6)``, hinge tilts ``(H, 2)``."""
        a, b = self.num_offsets, self.num_offsets + self.num_mounts
        return theta[:a].reshape(-1, 3), theta[a:b].reshape(-1, 6), theta[b:].reshape(-1, 2)

    def held(self, d_off, d_mount):
        """Offset and mount corrections with the held means removed: the root-origin children's
        offsets, the rotations of the cameras of each held segment (both ``(n, k)``, numpy or JAX)."""
        xp = jnp if isinstance(d_off, jax.Array) else np
        project = np.eye(self.num_cameras)
        for group in self.held_frames:
            project[np.ix_(group, group)] -= 1.0 / len(group)
        if self.origin_children:
            pick = np.zeros(len(d_off))
            pick[np.asarray(self.origin_children) - 1] = 1.0 / len(self.origin_children)
            d_off = d_off - np.outer(pick > 0, pick) @ d_off
        return d_off, xp.concatenate([d_mount[:, :3], project @ d_mount[:, 3:]], axis=1)

    def sigmas(self, options: RefineOptions) -> np.ndarray:
        """Prior σ of every entry of θ (m or rad)."""
        mount = [options.mount_translation_sigma_m] * 3 + [np.deg2rad(options.mount_rotation_sigma_deg)] * 3
        return np.concatenate([
            np.full(self.num_offsets, options.offset_sigma_m), np.tile(mount, self.num_cameras),
            np.full(2 * len(self.hinges), np.deg2rad(options.hinge_axis_sigma_deg)),
        ])


def _perpendicular_basis(axis: np.ndarray) -> np.ndarray:
    """``(2, 3)`` orthonormal vectors perpendicular to a unit ``axis``."""
    u = np.cross(axis, np.eye(3)[np.argmin(np.abs(axis))])
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(axis, u)])


def _layout(skeleton: Skeleton, rig: Rig, options: RefineOptions) -> _Layout:
    kids = skeleton.children(0)
    if options.root_origin is None:
        origin = tuple(k for k in kids if np.linalg.norm(np.asarray(skeleton.offsets[k])) < 1e-12) or kids
    else:
        origin = tuple(skeleton.index(name) for name in options.root_origin)
        for k in origin:
            if skeleton.parents[k] != 0:
                raise ValueError(
                    f"RefineOptions.root_origin: '{skeleton.names[k]}' is not a child of the root '{skeleton.names[0]}'"
                )
    held = ()
    if options.hold_segment_frames:
        held = tuple(
            cams for j, t in enumerate(skeleton.joint_types)
            if t in (JointType.FREE, JointType.BALL) and (cams := tuple(c for c, s in enumerate(rig.segments) if s == j))
        )
    hinges = tuple(j for j, t in enumerate(skeleton.joint_types) if t == JointType.HINGE)
    basis = tuple(tuple(map(tuple, _perpendicular_basis(np.asarray(skeleton.hinge_axes[j])).tolist())) for j in hinges)
    n_off, n_mount = 3 * (skeleton.num_segments - 1), 6 * rig.num_cameras
    active = (
        ([*range(n_off)] if options.refine_offsets else [])
        + ([*range(n_off, n_off + n_mount)] if options.refine_mounts else [])
        + ([*range(n_off + n_mount, n_off + n_mount + 2 * len(hinges))] if options.refine_hinge_axes else [])
    )
    return _Layout(skeleton.num_segments, rig.num_cameras, tuple(origin), held, hinges, basis, tuple(active))


def _apply(layout: _Layout, skeleton: Skeleton, rig: Rig, theta: jax.Array) -> tuple[Skeleton, Rig]:
    """The model at θ relative to ``(skeleton, rig)``, the held means (``_Layout.held``) removed."""
    d_off, d_mount, tilt = layout.split(theta)
    d_off, d_mount = layout.held(d_off, d_mount)
    offsets = skeleton.offsets.at[1:].add(d_off)
    base = rig.segment_from_camera
    rotation = (SO3.exp(d_mount[:, 3:]) @ SO3(base[:, :4])).wxyz
    mounts = jnp.concatenate([rotation, base[:, 4:] + d_mount[:, :3]], axis=1)
    axes = skeleton.hinge_axes
    if layout.hinges:
        idx = np.asarray(layout.hinges)
        tilted = axes[idx] + jnp.einsum("hk,hkd->hd", tilt, jnp.asarray(layout.hinge_basis))
        axes = axes.at[idx].set(tilted / jnp.linalg.norm(tilted, axis=-1, keepdims=True))
    skeleton = eqx.tree_at(lambda s: (s.offsets, s.hinge_axes), skeleton, (offsets, axes))
    return skeleton, eqx.tree_at(lambda r: r.segment_from_camera, rig, mounts)


def _difference(layout: _Layout, skeleton: Skeleton, rig: Rig, other_skeleton: Skeleton, other_rig: Rig) -> np.ndarray:
    """θ such that ``_apply(layout, skeleton, rig, θ)`` is ``(other_skeleton, other_rig)``."""
    d_off = np.asarray(other_skeleton.offsets[1:] - skeleton.offsets[1:])
    if layout.origin_children:
        drift = d_off[np.asarray(layout.origin_children) - 1].mean(axis=0)
        if np.linalg.norm(drift) > 1e-9:
            names = [skeleton.names[k] for k in layout.origin_children]
            raise ValueError(
                f"refine: the skeleton's root origin (mean joint of {names}) moved by {1e3 * np.linalg.norm(drift):.3f} mm "
                "from the prior skeleton's; pass the same root_origin convention"
            )
    base, other = rig.segment_from_camera, other_rig.segment_from_camera
    rot = np.asarray((SO3(other[:, :4]) @ SO3(base[:, :4]).inverse()).log())
    for group in layout.held_frames:
        turn = rot[list(group)].mean(axis=0)
        if np.linalg.norm(turn) > 1e-9:
            raise ValueError(
                f"refine: the cameras of segment '{skeleton.names[rig.segments[group[0]]]}' turned by "
                f"{np.rad2deg(np.linalg.norm(turn)):.4f}° on average from the prior rig's, but its frame is held "
                "(hold_segment_frames)"
            )
    mounts = np.concatenate([np.asarray(other[:, 4:] - base[:, 4:]), rot], axis=1)
    tilts = []
    for j, basis in zip(layout.hinges, layout.hinge_basis):
        a, b = np.asarray(skeleton.hinge_axes[j]), np.asarray(other_skeleton.hinge_axes[j])
        if not b @ a > 0:
            raise ValueError(f"refine: the hinge axis of '{skeleton.names[j]}' points away from the prior skeleton's")
        tilts.append(np.asarray(basis) @ b / (b @ a))
    return np.concatenate([d_off.reshape(-1), mounts.reshape(-1), np.reshape(tilts, -1)])


def _changes(layout: _Layout, theta_a: np.ndarray, theta_b: np.ndarray) -> tuple[float, float, float, float]:
    """Largest offset (m), mount translation (m), mount rotation (°) and hinge-axis (°) change between two θ."""
    off, mounts, tilt = layout.split(theta_b - theta_a)
    off, mounts = layout.held(off, mounts)
    norm = lambda a: float(np.linalg.norm(a, axis=-1).max(initial=0.0))  # noqa: E731
    return norm(off), norm(mounts[:, :3]), float(np.rad2deg(norm(mounts[:, 3:]))), float(np.rad2deg(norm(tilt)))


# ---- linearisation -------------------------------------------------------------------------------


class _Model(eqx.Module):
    """The base model, the reprojection term (loss and weight; no data) and the static layout."""

    skeleton: Skeleton
    rig: Rig
    term: Reprojection
    layout: _Layout = eqx.field(static=True)
    hold_motion: bool = eqx.field(static=True)


def _camera_normal_block(term: Reprojection, matrix: jax.Array, camera, data):
    """One camera-frame's IRLS normal block ``(12, 12)``, gradient ``(12,)`` and cost w.r.t. its ``cam_from_world`` 3×4 matrix.

    Measurement i depends on the matrix only through its camera-frame point ``p_i = M [X_i; 1]``, so
    one 3-tangent forward pass gives every ``∂r_i/∂p_i``, and ``∂p_i/∂M = I₃ ⊗ [X_i; 1]ᵀ``.
    """
    points = data["points"]
    points_cam = points @ matrix[:, :3].T + matrix[:, 3]
    raw, valid = term.residual_in_camera(points_cam, camera, data)
    residual = lambda shift: term.masked(*term.residual_in_camera(points_cam + shift, camera, data))
    r, d_point = term.masked(raw, valid), jax.jacfwd(residual)(jnp.zeros(3))  # (n, k), (n, k, 3)
    homogeneous = jnp.concatenate([points, jnp.ones_like(points[:, :1])], axis=1)
    jac = jnp.einsum("nka,nb->nkab", d_point, homogeneous).reshape(*r.shape, 12)
    scale = term.irls_sqrt_weights(r)[:, None]
    jac, r = jac * scale[..., None], r * scale
    cost = 0.5 * jnp.sum(term.finish(raw, valid) ** 2)
    return jnp.einsum("nki,nkj->ij", jac, jac), jnp.einsum("nki,nk->i", jac, r), cost


def _frame_model(model: _Model, theta: jax.Array, reference_axes: jax.Array, reference: Motion, tangent: jax.Array):
    """The skeleton, rig and one frame's motion at θ ``(P,)`` and the frame's tangent ``(D,)`` (``(0,)``:
    motion held): the reference pose with its hinge angles kept about the axes at θ, then moved."""
    skeleton, rig = _apply(model.layout, model.skeleton, model.rig, theta)
    motion = _reaxis(model.layout, reference, reference_axes, skeleton.hinge_axes)
    return skeleton, rig, (skeleton.retract(motion, tangent) if tangent.shape[0] else motion)


def _frame_system(model: _Model, theta: jax.Array, reference_axes: jax.Array, reference: Motion, tangent: jax.Array, data):
    """One frame's Gauss–Newton blocks in (its motion tangent, the active entries of θ) at ``(tangent, θ)``.

    Returns ``A (D, D)``, ``B (D, Pa)``, ``C (Pa, Pa)``, ``g_m (D,)``, ``g_θ (Pa,)`` and the frame's robust
    cost (``D`` = 0 with the motion held). The reprojections enter through each camera's 3×4 matrix.
    """
    active, d = np.asarray(model.layout.active), tangent.shape[0]

    def matrices(z):
        skeleton, rig, motion = _frame_model(model, theta.at[active].set(z[d:]), reference_axes, reference, z[:d])
        return camera_poses(skeleton, rig, motion).inverse().as_matrix()[:, :3, :]

    z = jnp.concatenate([tangent, theta[active]])
    mats, d_mats = matrices(z), jax.jacfwd(matrices)(z)  # (C, 3, 4), (C, 3, 4, Z)
    hess, grad, cost = jax.vmap(lambda m, cam, dt: _camera_normal_block(model.term, m, cam, dt))(mats, model.rig.intrinsics, data)
    chain = d_mats.reshape(d_mats.shape[0], 12, -1)
    h = jnp.einsum("cai,cab,cbj->ij", chain, hess, chain)
    g = jnp.einsum("cai,ca->i", chain, grad)
    return h[:d, :d], h[:d, d:], h[d:, d:], g[:d], g[d:], jnp.sum(cost)


def _frame_residuals(model: _Model, theta: jax.Array, reference_axes: jax.Array, reference: Motion, tangent: jax.Array, data):
    """One frame's finished reprojection residuals ``(C, n, 2)`` (``½ Σ r²`` is its robust cost)."""
    skeleton, rig, motion = _frame_model(model, theta, reference_axes, reference, tangent)
    cam_from_world = camera_poses(skeleton, rig, motion).inverse()
    one = lambda p, cam, dt: model.term.finish(*model.term.residual(SE3(p), cam, dt))  # noqa: E731
    return jax.vmap(one)(cam_from_world.wxyz_xyz, rig.intrinsics, data)


def _reaxis(layout: _Layout, motion: Motion, old_axes: jax.Array, new_axes: jax.Array) -> Motion:
    """The motion with each hinge's angle about ``old_axes`` kept, now about ``new_axes`` (``(J, 3)``).

    A motion stores rotations; its joint angles are what stay when a hinge axis is refined.
    """
    if not layout.hinges:
        return motion
    idx = np.asarray(layout.hinges)
    q = motion.rotations[..., idx, :]
    half = jnp.arctan2(jnp.sum(q[..., 1:] * old_axes[idx], axis=-1), q[..., 0])[..., None]
    turned = jnp.concatenate([jnp.cos(half), jnp.sin(half) * new_axes[idx]], axis=-1)
    return Motion(motion.root_position, motion.rotations.at[..., idx, :].set(turned))


class _Frames:
    """The used frames of a capture cut into equal chunks (padded with zero-weight frames).

    ``motion`` and ``data`` are stacked per chunk: ``(K, F, ...)`` for ``K`` chunks of ``F`` frames.
    """

    def __init__(self, term: Reprojection, motion: Motion, stride: int, chunk: int):
        self.index = np.arange(0, motion.num_frames, stride)
        n = len(self.index)
        self.chunk = min(chunk, n)
        pad = -n % self.chunk
        take = np.concatenate([self.index, np.full(pad, self.index[-1])])
        data = {k: np.asarray(v)[take] for k, v in term.data.items()}
        data["weights"][n:] = 0.0
        padded = eqx.tree_at(lambda t: t.data, term, data)
        # The term's window resolves point ids into points (n, 3) per camera-frame.
        chunks = [padded.window(a, a + self.chunk).data for a in range(0, n + pad, self.chunk)]
        self.data = jax.tree.map(lambda *a: jnp.stack(a), *chunks)
        self.motion = jax.tree.map(lambda a: jnp.asarray(np.asarray(a)[take]).reshape(-1, self.chunk, *a.shape[1:]), motion)
        self.num_frames = n

    @property
    def num_padded(self) -> int:
        return len(self.index) + (-len(self.index) % self.chunk)


class _Problem(eqx.Module):
    """Refinement as one least-squares problem over ``v = (tangents (T, D), θ_active (Pa,))`` (the motion
    eliminated by :func:`levenberg_marquardt`'s Schur step), or ``θ_active[None]`` with the motion held:
    the robust reprojections of the used frames and the prior ``(θ/σ)``."""

    model: _Model
    theta: jax.Array  # (P,) θ; its active entries are variables
    sqrt_precision: jax.Array  # (Pa,) 1/σ of the active entries
    reference_axes: jax.Array  # (J, 3) hinge axes the reference motion's rotations are about
    reference: Motion  # (K, F) per chunk
    data: dict  # (K, F, C, ...) per chunk

    def split(self, v):
        """``(tangents (K, F, D), θ (P,), θ_active (Pa,))``."""
        k, f = self.reference.root_position.shape[:2]
        tangents, active_values = (jnp.zeros((k * f, 0)), v[0]) if self.model.hold_motion else v
        theta = self.theta.at[np.asarray(self.model.layout.active)].set(active_values)
        return tangents.reshape(k, f, tangents.shape[-1]), theta, active_values

    def _per_frame(self, fn, v):
        tangents, theta, _ = self.split(v)
        frames = jax.vmap(lambda ref, t, dt: fn(self.model, theta, self.reference_axes, ref, t, dt))
        chunked = jax.lax.map(lambda xs: frames(*xs), (self.reference, tangents, self.data))
        return jax.tree.map(lambda a: a.reshape(a.shape[0] * a.shape[1], *a.shape[2:]), chunked)

    def residuals(self, v, args=None):
        return self._per_frame(_frame_residuals, v), self.sqrt_precision * self.split(v)[2]

    def system(self, v) -> NormalEquations:
        a, b, c, g_m, g_theta, _ = self._per_frame(_frame_system, v)
        values = self.split(v)[2]
        precision = self.sqrt_precision**2
        static_matrix = jnp.sum(c, axis=0) + jnp.diag(precision)
        static_grad = jnp.sum(g_theta, axis=0) + precision * values
        if self.model.hold_motion:  # θ alone: one dense block
            return NormalEquations(static_matrix[None], (), static_grad[None], jnp.zeros((1, len(values), 0)),
                                   jnp.zeros((0, 0)), jnp.zeros(0))
        return NormalEquations(a, (), g_m, b, static_matrix, static_grad)

    def data_schur(self, v) -> jax.Array:
        """``Σ_t C_t − B_tᵀ A_t⁻¹ B_t`` without the prior: what the data say about θ once each frame's motion re-fits."""
        a, b, c, *_ = self._per_frame(_frame_system, v)
        if self.model.hold_motion:
            return jnp.sum(c, axis=0)
        d = a.shape[-1]
        # Motion DOFs without data in a frame (a leaf whose camera did not register) have zero rows in
        # B: the tiny shift keeps A invertible and leaves them out.
        shift = 1e-9 * jnp.trace(a, axis1=1, axis2=2)[:, None, None] / d + 1e-12
        gain = jnp.linalg.solve(a + shift * jnp.eye(d), b)
        return jnp.sum(c, axis=0) - jnp.einsum("tdp,tdq->pq", b, gain)


@eqx.filter_jit
def _refine(problem: _Problem, v0, options: RefineOptions):
    """The Levenberg–Marquardt solve; returns the solution, its report, the robust reprojection cost at
    the start and the end, and the data's Schur matrix at the end."""
    value, report = levenberg_marquardt(problem.residuals, eqx.Partial(_Problem.system, problem), v0, rtol=options.ftol,
                                        atol=options.xtol, damping_scale=options.damping_scale, max_steps=options.max_steps)
    data_cost = lambda v: 0.5 * jnp.sum(problem.residuals(v)[0] ** 2)  # noqa: E731
    return value, report, data_cost(v0), data_cost(value), problem.data_schur(value)


def _reprojection_term(correspondences: Correspondences, skeleton: Skeleton, weights: ObjectiveWeights) -> Reprojection:
    terms = paper_terms(correspondences, skeleton, weights, include_homography=False)
    return next(t for t in terms if isinstance(t, Reprojection))


def _without_data(term: Reprojection) -> Reprojection:
    """The term's loss and weight only: the data come chunk by chunk."""
    return Reprojection({}, points=jnp.zeros((0, 3)), weight=term.weight, loss=term.loss, name=term.name)


def _check_inputs(correspondences: Correspondences, skeleton: Skeleton, rig: Rig, motion: Motion, prior) -> None:
    paper_problem(correspondences, skeleton, rig)  # shapes of the measurements against the rig
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


def refine_skeleton_and_rig(
    correspondences: Correspondences,
    skeleton: Skeleton,
    rig: Rig,
    motion: Motion,
    options: RefineOptions = RefineOptions(),
    *,
    weights: ObjectiveWeights = ObjectiveWeights(),
    prior: tuple[Skeleton, Rig] | None = None,
) -> Refinement:
    """Refine bone offsets and camera mounts from a capture's reprojections, given a solved motion.

    Args:
        correspondences: the capture's measurements (``T`` frames, ``C`` cameras).
        skeleton, rig: the current model, e.g. from a range-of-motion trial.
        motion: ``(T, J)`` the motion solved with that model (the linearisation point).
        options: priors, what moves, iterations.
        weights: the robust loss of the reprojection term (as in :func:`paper_problem`).
        prior: the model the prior pulls towards (the range-of-motion estimate); default: the input.
            Pass the first model in every round of an alternation so the gauge stays where it was.

    Returns:
        The refined skeleton and rig, the motion moved with them, and a :class:`RefineReport`.

    Raises:
        ValueError: measurements, motion or prior that do not fit the model; unknown ``root_origin``.
    """
    require_float64("bcmocap.solver.refine_skeleton_and_rig")
    start_time = time.perf_counter()
    _check_inputs(correspondences, skeleton, rig, motion, prior)
    base_skeleton, base_rig = prior if prior is not None else (skeleton, rig)
    layout = _layout(base_skeleton, base_rig, options)
    active = np.asarray(layout.active)
    theta_in = _difference(layout, base_skeleton, base_rig, skeleton, rig)
    sigmas = layout.sigmas(options)[active]
    term = _reprojection_term(correspondences, skeleton, weights)
    model = _Model(base_skeleton, base_rig, _without_data(term), layout, options.hold_motion)
    frames = _Frames(term, motion, options.frame_stride, options.chunk_frames)
    problem = _Problem(model, jnp.asarray(theta_in), jnp.asarray(1.0 / sigmas), skeleton.hinge_axes, frames.motion, frames.data)
    theta0 = jnp.asarray(theta_in[active])
    v0 = theta0[None] if options.hold_motion else (jnp.zeros((frames.num_padded, skeleton.num_dofs)), theta0)
    value, lm, reprojection_before, reprojection_after, schur = _refine(problem, v0, options)
    tangents, theta, _ = problem.split(value)
    theta = np.asarray(theta)
    whitened = np.asarray(schur) * np.outer(sigmas, sigmas)
    prior_directions = int(np.sum(np.linalg.eigvalsh(0.5 * (whitened + whitened.T)) < 1.0))
    # Held means are no direction of the model: they are zero by construction, not by the prior.
    prior_directions -= 3 * (bool(layout.origin_children) * options.refine_offsets + len(layout.held_frames) * options.refine_mounts)
    new_skeleton, new_rig = _apply(layout, base_skeleton, base_rig, jnp.asarray(theta))
    moved = _reaxis(layout, motion, skeleton.hinge_axes, new_skeleton.hinge_axes)  # frames left out by the stride
    root, rotations = np.array(moved.root_position, dtype=np.float64), np.array(moved.rotations, dtype=np.float64)
    if not options.hold_motion:
        used = jax.tree.map(lambda a: a.reshape(-1, *a.shape[2:])[: frames.num_frames], frames.motion)
        solved = new_skeleton.retract(_reaxis(layout, used, skeleton.hinge_axes, new_skeleton.hinge_axes),
                                      tangents.reshape(-1, skeleton.num_dofs)[: frames.num_frames])
        root[frames.index], rotations[frames.index] = np.asarray(solved.root_position), np.asarray(solved.rotations)
    report = RefineReport(
        float(lm.initial_cost), float(lm.final_cost), float(reprojection_before), float(reprojection_after),
        int(lm.num_steps), int(lm.num_accepted_steps), bool(lm.converged),
        *_changes(layout, theta_in, theta), prior_directions, len(active), frames.num_frames,
        time.perf_counter() - start_time,
    )
    return Refinement(new_skeleton, new_rig, Motion(root, rotations), report)


def reprojection_cost(
    correspondences: Correspondences, skeleton: Skeleton, rig: Rig, motion: Motion, *, weights: ObjectiveWeights = ObjectiveWeights()
) -> float:
    """Robust reprojection cost ``½ Σ λρ(‖r‖²)`` of a motion over all frames (as in :func:`paper_problem`)."""
    _check_inputs(correspondences, skeleton, rig, motion, None)
    term = _reprojection_term(correspondences, skeleton, weights)
    frames = _Frames(term, motion, 1, RefineOptions.chunk_frames)
    total = 0.0
    for k in range(frames.num_padded // frames.chunk):
        ref = jax.tree.map(lambda a: a[k], frames.motion)
        total += float(_chunk_cost(skeleton, rig, _without_data(term), ref, {name: a[k] for name, a in frames.data.items()}))
    return total


@eqx.filter_jit
def _chunk_cost(skeleton: Skeleton, rig: Rig, term: Reprojection, motion: Motion, data):
    cam_from_world = camera_poses(skeleton, rig, motion).inverse()  # (F, C)
    one = lambda p, cam, dt: term.finish(*term.residual(SE3(p), cam, dt))  # noqa: E731
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
) -> RefinedSolution:
    """Eq. (1) with the skeleton and mounts refined: solve, then ``rounds`` × (refine, solve).

    Args:
        correspondences: the capture's measurements.
        skeleton, rig: the starting model (its values are the prior of every refinement).
        initial_motion: ``(T, J)`` starting motion for the first solve.
        rounds: refinements (each followed by a solve); 0 is the plain solve. With the motion
            eliminated one round does nearly all of it (on the walk benchmark a second round moved
            nothing by more than a micrometre).
        solver_options, refine_options, weights: as in :func:`solve`, :func:`refine_skeleton_and_rig`,
            :func:`paper_problem`.
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
                correspondences, skeleton, rig, solution.motion, refine_options, weights=weights, prior=prior
            )
            skeleton, rig, motion = refinement.skeleton, refinement.rig, refinement.motion
        start = time.perf_counter()
        solution = solve(paper_problem(correspondences, skeleton, rig, weights), motion, solver_options)
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
