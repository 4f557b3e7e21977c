"""Forward kinematics: root pose and joint rotations → segment, joint and camera poses (Eqs. 3–5).

The tree is walked level by level (all segments at one depth composed in one batched operation), so
the compiled graph grows with the tree's depth, not its number of segments. Every function broadcasts
over leading batch axes (frames, windows): no Python loop over frames.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import SE3, SO3
from .skeleton import Motion, Skeleton


def forward_kinematics(skeleton: Skeleton, motion: Motion) -> SE3:
    """World poses of all segments.

    Args:
        skeleton: the tree.
        motion: batch shape ``S``; ``rotations`` ``(*S, J, 4)``.

    Returns:
        ``world_from_segment`` as an SE3 with batch shape ``(*S, J)``; its translation is the joint position (m).
    """
    batch = motion.root_position.shape[:-1]
    offsets = jnp.broadcast_to(skeleton.offsets, (*batch, skeleton.num_segments, 3))
    translations = offsets.at[..., 0, :].set(motion.root_position)
    local = SE3.from_rotation_and_translation(SO3(motion.rotations), translations).wxyz_xyz
    world = local
    for level in skeleton.levels[1:]:
        idx = np.asarray(level)
        par = np.asarray([skeleton.parents[j] for j in level])
        composed = SE3(world[..., par, :]) @ SE3(local[..., idx, :])
        world = world.at[..., idx, :].set(composed.wxyz_xyz)
    return SE3(world)


def joint_positions(skeleton: Skeleton, motion: Motion) -> jax.Array:
    """``(*S, J, 3)`` world positions of every joint (segment origin), m."""
    return forward_kinematics(skeleton, motion).translation()


def world_rotations(skeleton: Skeleton, motion: Motion) -> jax.Array:
    """``(*S, J, 4)`` world orientation of every segment."""
    return forward_kinematics(skeleton, motion).rotation().wxyz
