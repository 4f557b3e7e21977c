"""Temporal smoothness of the root (Eq. 10) and of the joint angles (Eq. 11).

Differences between consecutive frames are taken on the manifold: root translation difference in
metres and ``log(R_{t-1}⁻¹ R_t)`` for rotations (radians), projected on each joint's DOFs, so a hinge
contributes its angle difference. ``data`` is a ``(T,)`` mask of the pairs to use (row t pairs t-1, t).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..kinematics.skeleton import Skeleton
from .base import PairTerm


class RootSmoothness(PairTerm):
    """λ_O ‖O(t) − O(t−1)‖²: root translation (m) and root orientation (rad) per frame.

    ``rotation_scale`` converts radians to the same footing as metres (default 1: 1 rad ≙ 1 m).
    """

    rotation_scale: float = 1.0

    def residual(self, x, data, variables):
        prev, curr = x[0], x[1]
        dp = curr.motion.root_position - prev.motion.root_position
        dr = _rotation_differences(prev.motion.rotations[:1], curr.motion.rotations[:1])[0]
        r = jnp.concatenate([dp, self.rotation_scale * dr])[:, None]
        return r, jnp.broadcast_to(data > 0, (6,))


class JointSmoothness(PairTerm):
    """λ_A ‖A(t) − A(t−1)‖²: every non-root joint's DOFs (rad)."""

    skeleton: Skeleton = None

    def residual(self, x, data, variables):
        rel = _rotation_differences(x.motion.rotations[0, 1:], x.motion.rotations[1, 1:])
        dofs = jnp.einsum("jkd,jk->d", self.skeleton.rotation_basis()[1:, :, 6:], rel)
        return dofs[:, None], jnp.broadcast_to(data > 0, dofs.shape)


def _rotation_differences(q_prev, q_curr):
    from ..geometry import SO3

    return (SO3(q_prev).inverse() @ SO3(q_curr)).log()


def pair_mask(num_frames: int) -> np.ndarray:
    """``(T,)`` data for smoothness terms: every pair used (row 0 has no previous frame)."""
    mask = np.ones(num_frames)
    mask[0] = 0.0
    return mask
