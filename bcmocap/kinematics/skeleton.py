"""Skeletons (kinematic trees) and motions (root pose and joint rotations over time).

Conventions. Segment ``j`` has a frame whose origin is joint ``j``; at rest (all rotations identity)
every segment frame is parallel to the world frame, as in BVH. ``offsets[j]`` is joint ``j``'s position
in its parent's frame at rest (metres). A motion holds, per frame, the root position in the world and
one rotation per segment: ``rotations[..., 0]`` is ``world_from_root``; ``rotations[..., j]`` for
``j > 0`` is the joint's local rotation ``parent_from_child`` relative to rest.

Per-frame solver variables are a flat tangent vector of size ``skeleton.num_dofs``:
``[root translation (3, m), root rotation (3, rad), then each joint's DOFs in order]`` where a ball joint
has 3 (rotation vector, right perturbation), a hinge 1 (angle about its axis) and a fixed joint 0.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from functools import cached_property

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import SO3


class JointType(enum.IntEnum):
    """Degrees of freedom of a joint."""

    FREE = 0  # 6-DOF root
    BALL = 1  # 3-DOF rotation
    HINGE = 2  # 1-DOF rotation about a fixed axis
    FIXED = 3  # rigidly attached


DOFS = {JointType.FREE: 6, JointType.BALL: 3, JointType.HINGE: 1, JointType.FIXED: 0}


class Skeleton(eqx.Module):
    """A kinematic tree with named segments.

    Attributes:
        offsets: ``(J, 3)`` joint positions in the parent segment frame at rest (m). Row 0 is unused.
        hinge_axes: ``(J, 3)`` unit rotation axes of hinge joints (segment frame); zeros elsewhere.
        names: segment names, unique; segment ``j``'s joint connects it to ``parents[j]``.
        parents: parent index per segment, ``-1`` for the root (index 0); ``parents[j] < j``.
        joint_types: one :class:`JointType` per segment; the root is ``FREE``, no other is.
    """

    offsets: jax.Array
    hinge_axes: jax.Array
    names: tuple[str, ...] = eqx.field(static=True)
    parents: tuple[int, ...] = eqx.field(static=True)
    joint_types: tuple[JointType, ...] = eqx.field(static=True)

    def __init__(
        self,
        names: Sequence[str],
        parents: Sequence[int],
        offsets,
        joint_types: Sequence[JointType | str] | None = None,
        hinge_axes=None,
    ):
        names = tuple(str(n) for n in names)
        parents = tuple(int(p) for p in parents)
        n = len(names)
        if n == 0:
            raise ValueError("Skeleton: at least one segment (the root) is needed")
        if len(set(names)) != n:
            dup = sorted({x for x in names if names.count(x) > 1})
            raise ValueError(f"Skeleton: duplicate segment names {dup}")
        if len(parents) != n:
            raise ValueError(f"Skeleton: {n} names but {len(parents)} parents")
        if parents[0] != -1:
            raise ValueError(f"Skeleton: segment 0 ('{names[0]}') must be the root (parent -1), got parent {parents[0]}")
        for j in range(1, n):
            if not 0 <= parents[j] < j:
                raise ValueError(
                    f"Skeleton: segment {j} ('{names[j]}') has parent {parents[j]}; parents must come before "
                    "their children (topological order) and only the root has parent -1"
                )
        if joint_types is None:
            joint_types = [JointType.FREE] + [JointType.BALL] * (n - 1)
        types = []
        for j, t in enumerate(joint_types):
            try:
                types.append(JointType[t.upper()] if isinstance(t, str) else JointType(t))
            except (KeyError, ValueError):
                choices = ", ".join(x.name.lower() for x in JointType)
                name = names[j] if j < n else f"#{j}"
                raise ValueError(f"Skeleton: segment '{name}' has unknown joint type {t!r}; choose one of {choices}") from None
        types = tuple(types)
        if len(types) != n:
            raise ValueError(f"Skeleton: {n} segments but {len(types)} joint types")
        if types[0] != JointType.FREE:
            raise ValueError(f"Skeleton: the root '{names[0]}' must have a FREE joint, got {types[0].name}")
        for j in range(1, n):
            if types[j] == JointType.FREE:
                raise ValueError(f"Skeleton: only the root may be FREE, but '{names[j]}' is")
        offsets = np.asarray(offsets, dtype=np.float64)
        if offsets.shape != (n, 3):
            raise ValueError(f"Skeleton: offsets must have shape ({n}, 3), got {offsets.shape}")
        if not np.all(np.isfinite(offsets)):
            raise ValueError("Skeleton: offsets contain NaN or inf")
        axes = np.zeros((n, 3)) if hinge_axes is None else np.asarray(hinge_axes, dtype=np.float64)
        if axes.shape != (n, 3):
            raise ValueError(f"Skeleton: hinge_axes must have shape ({n}, 3), got {axes.shape}")
        axes = axes.copy()
        for j in range(n):
            if types[j] == JointType.HINGE:
                norm = np.linalg.norm(axes[j])
                if not norm > 1e-9:
                    raise ValueError(f"Skeleton: hinge joint '{names[j]}' needs a non-zero axis")
                axes[j] /= norm
            else:
                axes[j] = 0.0
        self.names = names
        self.parents = parents
        self.joint_types = types
        self.offsets = jnp.asarray(offsets)
        self.hinge_axes = jnp.asarray(axes)

    # ---- topology -------------------------------------------------------------------------------
    @property
    def num_segments(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Index of the segment called ``name`` (ValueError listing the names if unknown)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"unknown segment '{name}'; the skeleton has {list(self.names)}") from None

    @cached_property
    def depths(self) -> tuple[int, ...]:
        depth = [0] * self.num_segments
        for j in range(1, self.num_segments):
            depth[j] = depth[self.parents[j]] + 1
        return tuple(depth)

    @cached_property
    def levels(self) -> tuple[tuple[int, ...], ...]:
        """Segment indices grouped by depth: level ``k`` holds the segments ``k`` joints from the root."""
        out: list[list[int]] = [[] for _ in range(max(self.depths) + 1)]
        for j, d in enumerate(self.depths):
            out[d].append(j)
        return tuple(tuple(level) for level in out)

    def children(self, j: int) -> tuple[int, ...]:
        return tuple(k for k in range(self.num_segments) if self.parents[k] == j)

    def chain(self, j: int) -> tuple[int, ...]:
        """Segments from the root down to ``j`` (inclusive)."""
        out = [j]
        while self.parents[out[-1]] >= 0:
            out.append(self.parents[out[-1]])
        return tuple(reversed(out))

    # ---- per-frame variable layout -------------------------------------------------------------
    @cached_property
    def dof_starts(self) -> tuple[int, ...]:
        """Start of each segment's DOFs in the per-frame tangent vector (root: 0)."""
        starts, k = [], 0
        for t in self.joint_types:
            starts.append(k)
            k += DOFS[t]
        return tuple(starts)

    @property
    def num_dofs(self) -> int:
        """Size of the per-frame tangent vector (6 for the root plus each joint's DOFs)."""
        return sum(DOFS[t] for t in self.joint_types)

    def rotation_basis(self) -> jax.Array:
        """``(J, 3, D)`` linear map from the tangent vector to each segment's rotation vector.

        Row 0 maps to the root's rotation (entries 3:6); a ball joint copies its 3 entries; a hinge
        scales its axis by its entry; a fixed joint gets zeros. Differentiable in ``hinge_axes``.
        """
        n, d = self.num_segments, self.num_dofs
        fixed_part = np.zeros((n, 3, d))  # the root's and the ball joints' identity blocks
        hinge_entry = np.zeros((n, 1, d), dtype=bool)  # where a hinge's axis goes
        fixed_part[0, :, 3:6] = np.eye(3)
        for j in range(1, n):
            s = self.dof_starts[j]
            if self.joint_types[j] == JointType.BALL:
                fixed_part[j, :, s : s + 3] = np.eye(3)
            elif self.joint_types[j] == JointType.HINGE:
                hinge_entry[j, 0, s] = True
        return jnp.where(hinge_entry, jnp.asarray(self.hinge_axes)[:, :, None], fixed_part)

    def dof_names(self) -> tuple[str, ...]:
        """Human-readable name of each entry of the per-frame tangent vector."""
        out = [f"{self.names[0]}.t{a}" for a in "xyz"] + [f"{self.names[0]}.r{a}" for a in "xyz"]
        for j in range(1, self.num_segments):
            if self.joint_types[j] == JointType.BALL:
                out += [f"{self.names[j]}.r{a}" for a in "xyz"]
            elif self.joint_types[j] == JointType.HINGE:
                out.append(f"{self.names[j]}.angle")
        return tuple(out)

    def retract(self, motion: Motion, delta: jax.Array) -> Motion:
        """Move a motion by tangent vectors: ``p + δ_t``, ``R_j exp(B_j δ)`` per segment.

        Args:
            motion: reference motion with batch shape ``S``.
            delta: ``(*S, D)`` tangent vectors.
        """
        if delta.shape[-1] != self.num_dofs:
            raise ValueError(f"retract: delta has {delta.shape[-1]} entries per frame, the skeleton has {self.num_dofs} DOFs")
        rotvec = jnp.einsum("jkd,...d->...jk", self.rotation_basis(), delta)
        rotations = (SO3(motion.rotations) @ SO3.exp(rotvec)).wxyz
        return Motion(motion.root_position + delta[..., :3], rotations)

    def difference(self, motion_a: Motion, motion_b: Motion) -> jax.Array:
        """Tangent vector from ``motion_a`` to ``motion_b`` (``retract(a, difference(a, b)) ≈ b``).

        Root translation difference in the world frame (m), then each segment's rotation
        ``log(R_a⁻¹ R_b)`` (rad) projected on its DOFs (a hinge keeps the component along its axis).
        Returns ``(*S, D)``.
        """
        rel = (SO3(motion_a.rotations).inverse() @ SO3(motion_b.rotations)).log()
        joints = jnp.einsum("jkd,...jk->...d", self.rotation_basis(), rel)
        return joints.at[..., :3].set(motion_b.root_position - motion_a.root_position)

    def project_rotations(self, rotations: jax.Array) -> jax.Array:
        """Nearest rotations ``(..., J, 4)`` the joint types allow: fixed → identity, hinge → about its axis.

        For a hinge the angle is the twist about the axis (swing–twist decomposition).
        """
        q = rotations
        axes = self.hinge_axes
        twist_vec = jnp.sum(q[..., 1:] * axes, axis=-1, keepdims=True) * axes
        twist = jnp.concatenate([q[..., :1], twist_vec], axis=-1)
        norm = jnp.linalg.norm(twist, axis=-1, keepdims=True)
        twist = jnp.where(norm > 1e-12, twist / jnp.where(norm > 1e-12, norm, 1.0), jnp.array([1.0, 0, 0, 0]))
        types = np.array(self.joint_types)
        is_hinge = jnp.asarray(types == JointType.HINGE)[:, None]
        is_fixed = jnp.asarray(types == JointType.FIXED)[:, None]
        out = jnp.where(is_hinge, twist, q)
        return jnp.where(is_fixed, jnp.array([1.0, 0, 0, 0]), out)

    def rest_motion(self, num_frames: int | None = None) -> Motion:
        """The rest pose (identity rotations, root at the origin), optionally repeated over frames."""
        shape = () if num_frames is None else (num_frames,)
        rot = jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0, 0.0]), (*shape, self.num_segments, 4))
        return Motion(jnp.zeros((*shape, 3)), rot)

    def subtree(self, j: int) -> tuple[int, ...]:
        """Segment ``j`` and all its descendants."""
        out = [j]
        for k in range(j + 1, self.num_segments):
            if self.parents[k] in out:
                out.append(k)
        return tuple(out)


class Motion(eqx.Module):
    """Root position and segment rotations, for one frame or a batch of frames.

    Attributes:
        root_position: ``(..., 3)`` root joint position in the world (m).
        rotations: ``(..., J, 4)`` unit quaternions (w, x, y, z): index 0 is ``world_from_root``,
            index ``j > 0`` the local rotation ``parent_from_child`` relative to rest.
    """

    root_position: jax.Array
    rotations: jax.Array

    def __init__(self, root_position, rotations):
        root_position = jnp.asarray(root_position)
        rotations = jnp.asarray(rotations)
        if root_position.shape[-1:] != (3,) or rotations.ndim < 2 or rotations.shape[-1] != 4:
            raise ValueError(
                f"Motion: expected root_position (..., 3) and rotations (..., J, 4), got {root_position.shape} "
                f"and {rotations.shape}"
            )
        if root_position.shape[:-1] != rotations.shape[:-2]:
            raise ValueError(
                f"Motion: batch shapes differ: root_position {root_position.shape}, rotations {rotations.shape}"
            )
        self.root_position = root_position
        self.rotations = rotations

    @property
    def num_frames(self) -> int:
        return self.root_position.shape[0]

    def __getitem__(self, index) -> Motion:
        """Frames selected by ``index`` (int, slice or index array) along the first axis."""
        return jax.tree.map(lambda a: a[index], self)

    def check(self, skeleton: Skeleton, what: str = "motion") -> None:
        """Raise ValueError if the motion does not fit ``skeleton`` or holds NaN/inf."""
        if self.rotations.shape[-2] != skeleton.num_segments:
            raise ValueError(
                f"{what}: rotations have {self.rotations.shape[-2]} segments, the skeleton has {skeleton.num_segments}"
            )
        for name, a in (("root_position", self.root_position), ("rotations", self.rotations)):
            bad = ~np.isfinite(np.asarray(a))
            if bad.any():
                idx = np.argwhere(bad)[0]
                raise ValueError(f"{what}: {name} has NaN/inf (first at index {tuple(int(i) for i in idx)})")

    @staticmethod
    def concatenate(motions: Sequence[Motion]) -> Motion:
        return Motion(
            jnp.concatenate([m.root_position for m in motions]), jnp.concatenate([m.rotations for m in motions])
        )
