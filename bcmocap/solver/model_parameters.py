"""The skeleton and the camera mounts as variables: θ, its layout, and the model at θ.

θ = ``[offset corrections (J−1, 3) of segments 1…J−1, mount corrections (C, 6), hinge-axis tilts (H, 2)]``
relative to a base model (the range-of-motion estimate): a 3-vector added to every non-root
``Skeleton.offsets`` row, a 6-DOF correction of every ``segment_from_camera`` (translation in the segment
frame, rotation left-multiplied in the segment frame, so it turns the camera about its own centre) and a
2-DOF tilt of every hinge axis. Mount rotations live on SO(3): θ holds the tangent of the correction,
retracted by the exponential map, so the variables stay Euclidean. Motions store rotations; when a hinge
axis moves, a frame keeps its angle about the new axis (:func:`reaxis`).

:class:`ModelParameters` makes θ the static variables (``"model"``) of any solve
(:func:`bcmocap.solver.solve`): every term then sees the skeleton and rig at θ, and a prior
``½ Σ (θ/σ)²`` holds it near the base model. See :mod:`bcmocap.solver.refine` for the gauge.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import SO3
from ..kinematics.rig import Rig
from ..kinematics.skeleton import JointType, Motion, Skeleton

#: The name of the model's block among the static variables of a solve.
MODEL = "model"


@dataclasses.dataclass(frozen=True)
class ParameterLayout:
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

    def sigmas(self, offset_m: float, mount_translation_m: float, mount_rotation_deg: float, hinge_axis_deg: float) -> np.ndarray:
        """Prior σ ``(P,)`` of every entry of θ (m or rad) from the σ of each kind (m, m, °, °)."""
        mount = [mount_translation_m] * 3 + [np.deg2rad(mount_rotation_deg)] * 3
        return np.concatenate([
            np.full(self.num_offsets, offset_m), np.tile(mount, self.num_cameras),
            np.full(2 * len(self.hinges), np.deg2rad(hinge_axis_deg)),
        ])


def _perpendicular_basis(axis: np.ndarray) -> np.ndarray:
    """``(2, 3)`` orthonormal vectors perpendicular to a unit ``axis``."""
    u = np.cross(axis, np.eye(3)[np.argmin(np.abs(axis))])
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(axis, u)])


def parameter_layout(
    skeleton: Skeleton,
    rig: Rig,
    *,
    offsets: bool = True,
    mounts: bool = True,
    hinge_axes: bool = True,
    hold_segment_frames: bool = True,
    root_origin: Sequence[str] | None = None,
) -> ParameterLayout:
    """The θ of a skeleton and rig: which entries move (``offsets``, ``mounts``, ``hinge_axes``) and which
    means are held (module docstring: the root's origin among ``root_origin``, default the root's children
    with a zero offset, else all of them; with ``hold_segment_frames`` the mean rotation of each FREE or
    BALL segment's cameras).

    Raises:
        ValueError: a ``root_origin`` segment that is unknown or not a child of the root.
    """
    kids = skeleton.children(0)
    if root_origin is None:
        origin = tuple(k for k in kids if np.linalg.norm(np.asarray(skeleton.offsets[k])) < 1e-12) or kids
    else:
        origin = tuple(skeleton.index(name) for name in root_origin)
        for k in origin:
            if skeleton.parents[k] != 0:
                raise ValueError(
                    f"root_origin: '{skeleton.names[k]}' is not a child of the root '{skeleton.names[0]}'"
                )
    held = ()
    if hold_segment_frames:
        held = tuple(
            cams for j, t in enumerate(skeleton.joint_types)
            if t in (JointType.FREE, JointType.BALL) and (cams := tuple(c for c, s in enumerate(rig.segments) if s == j))
        )
    hinges = tuple(j for j, t in enumerate(skeleton.joint_types) if t == JointType.HINGE)
    basis = tuple(tuple(map(tuple, _perpendicular_basis(np.asarray(skeleton.hinge_axes[j])).tolist())) for j in hinges)
    n_off, n_mount = 3 * (skeleton.num_segments - 1), 6 * rig.num_cameras
    active = (
        ([*range(n_off)] if offsets else [])
        + ([*range(n_off, n_off + n_mount)] if mounts else [])
        + ([*range(n_off + n_mount, n_off + n_mount + 2 * len(hinges))] if hinge_axes else [])
    )
    return ParameterLayout(skeleton.num_segments, rig.num_cameras, tuple(origin), held, hinges, basis, tuple(active))


def apply_parameters(layout: ParameterLayout, skeleton: Skeleton, rig: Rig, theta: jax.Array) -> tuple[Skeleton, Rig]:
    """The model at θ ``(P,)`` relative to ``(skeleton, rig)``, the held means (:meth:`ParameterLayout.held`) removed."""
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


def parameter_difference(layout: ParameterLayout, skeleton: Skeleton, rig: Rig, other_skeleton: Skeleton, other_rig: Rig) -> np.ndarray:
    """θ ``(P,)`` such that ``apply_parameters(layout, skeleton, rig, θ)`` is ``(other_skeleton, other_rig)``."""
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


def parameter_changes(layout: ParameterLayout, theta_a: np.ndarray, theta_b: np.ndarray) -> tuple[float, float, float, float]:
    """Largest offset (m), mount translation (m), mount rotation (°) and hinge-axis (°) change between two θ."""
    off, mounts, tilt = layout.split(theta_b - theta_a)
    off, mounts = layout.held(off, mounts)
    norm = lambda a: float(np.linalg.norm(a, axis=-1).max(initial=0.0))  # noqa: E731
    return norm(off), norm(mounts[:, :3]), float(np.rad2deg(norm(mounts[:, 3:]))), float(np.rad2deg(norm(tilt)))


def reaxis(layout: ParameterLayout, motion: Motion, old_axes: jax.Array, new_axes: jax.Array) -> Motion:
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


class ModelParameters(eqx.Module):
    """The skeleton and rig as the static variables ``"model"`` of a solve: the active entries of θ.

    Attributes:
        skeleton, rig: the base model θ is relative to (the prior's centre).
        theta: ``(P,)`` θ the solve starts from; its inactive entries stay there.
        sqrt_precision: ``(Pa,)`` 1/σ of the active entries (prior ``½ Σ (θ/σ)²``).
        layout: which entries are active and which means are held.
    """

    skeleton: Skeleton
    rig: Rig
    theta: jax.Array
    sqrt_precision: jax.Array
    layout: ParameterLayout = eqx.field(static=True)

    @property
    def size(self) -> int:
        """``Pa``: the number of variables."""
        return len(self.layout.active)

    def start(self) -> jax.Array:
        """``(Pa,)`` the variables at ``theta``."""
        return self.theta[np.asarray(self.layout.active)]

    def full(self, values: jax.Array) -> jax.Array:
        """``(P,)`` θ with the active entries set to ``values`` ``(Pa,)``."""
        return self.theta.at[np.asarray(self.layout.active)].set(values)

    def model(self, values: jax.Array) -> tuple[Skeleton, Rig]:
        """The skeleton and rig at variables ``values`` ``(Pa,)``."""
        return apply_parameters(self.layout, self.skeleton, self.rig, self.full(values))

    def prior_residual(self, values: jax.Array) -> jax.Array:
        """``(Pa,)`` ``θ/σ`` of the active entries (relative to the base model)."""
        return self.sqrt_precision * values
