"""Joint rotations from reconstructed joint positions, so a KCS reconstruction can be written as BVH."""

from __future__ import annotations

import numpy as np

from ..geometry import quat_from_matrix, rotation_from_covariance, rotation_onto
from ..kinematics.skeleton import JointType, Motion, Skeleton
from .chain_space import KinematicChainSpace

__all__ = ["motion_from_joints"]


def motion_from_joints(
    chain: KinematicChainSpace,
    joints,
    rest_joints=None,
    lengths=None,
) -> tuple[Skeleton, Motion]:
    """A skeleton and motion whose forward kinematics follows ``joints`` (the tree bones; links are ignored).

    Each joint's world rotation takes its rest bones to the current ones: the smallest such rotation when
    it has one child, a least-squares (Kabsch) fit when it has several (with a weak pull towards the
    parent's rotation, which fixes the twist of a joint whose children are collinear), the parent's
    rotation for a leaf (written as a BVH end site). Bones keep fixed lengths, so joint positions are
    reproduced exactly when the input's bone lengths are constant.

    Args:
        chain: topology; the skeleton's segments are its joints in topological order.
        joints: ``(F, J, 3)`` joint positions (metres, Z up for a BVH that stands upright).
        rest_joints: ``(J, 3)`` pose giving the rest directions of the bones (default: the first frame).
        lengths: ``(J - 1,)`` tree bone lengths (default: mean over frames).

    Returns:
        ``(skeleton, motion)``; joint names as in ``chain``, all joints ball joints, leaves fixed.
    """
    x = np.asarray(joints, dtype=np.float64)
    if x.ndim != 3 or x.shape[1:] != (chain.num_joints, 3):
        raise ValueError(f"motion_from_joints: expected joints (F, {chain.num_joints}, 3), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("motion_from_joints: joints hold NaN or inf")
    rest = x[0] if rest_joints is None else np.asarray(rest_joints, dtype=np.float64)
    if rest.shape != (chain.num_joints, 3):
        raise ValueError(f"motion_from_joints: rest_joints must be ({chain.num_joints}, 3), got {rest.shape}")
    order = chain.topological_order
    new = {j: k for k, j in enumerate(order)}
    parents = chain.parents
    tree = [j for j in range(chain.num_joints) if parents[j] != -1]
    bones = x[:, tree] - x[:, [parents[j] for j in tree]]
    if lengths is None:
        lengths = np.linalg.norm(bones, axis=-1).mean(axis=0)
    lengths = np.asarray(lengths, dtype=np.float64)
    if lengths.shape != (len(tree),):
        raise ValueError(f"motion_from_joints: lengths must be ({len(tree)},), got {lengths.shape}")
    offsets = np.zeros((chain.num_joints, 3))
    for k, j in enumerate(tree):
        d = rest[j] - rest[parents[j]]
        n = np.linalg.norm(d)
        offsets[j] = d / n * lengths[k] if n > 1e-12 else np.array([0.0, 0.0, lengths[k]])
    children = [[] for _ in range(chain.num_joints)]
    for j in tree:
        children[parents[j]].append(j)

    f = x.shape[0]
    world = np.zeros((f, chain.num_joints, 3, 3))
    for j in order:
        parent_rot = world[:, parents[j]] if parents[j] != -1 else np.broadcast_to(np.eye(3), (f, 3, 3))
        kids = children[j]
        if not kids:
            world[:, j] = parent_rot
        elif len(kids) == 1:
            c = kids[0]
            swing = rotation_onto(np.einsum("fij,j->fi", parent_rot, offsets[c]), x[:, c] - x[:, j])
            world[:, j] = swing @ parent_rot
        else:
            src = np.stack([offsets[c] for c in kids], axis=-1)  # (3, n)
            dst = np.stack([x[:, c] - x[:, j] for c in kids], axis=-1)  # (F, 3, n)
            hint = 1e-3 * float(np.mean(lengths))
            src = np.concatenate([np.broadcast_to(src, (f, 3, len(kids))), hint * np.broadcast_to(np.eye(3), (f, 3, 3))], -1)
            dst = np.concatenate([dst, hint * parent_rot], -1)
            world[:, j] = rotation_from_covariance(dst @ np.swapaxes(src, -1, -2))  # R src ≈ dst
    local = world.copy()
    for j in order:
        if parents[j] != -1:
            local[:, j] = np.swapaxes(world[:, parents[j]], -1, -2) @ world[:, j]
    types = [JointType.FREE if parents[j] == -1 else (JointType.FIXED if not children[j] else JointType.BALL) for j in order]
    skeleton = Skeleton(
        [chain.names[j] for j in order],
        [new[parents[j]] if parents[j] != -1 else -1 for j in order],
        offsets[list(order)],
        joint_types=types,
    )
    rotations = np.array(quat_from_matrix(local[:, list(order)]))
    leaves = [k for k, j in enumerate(order) if not children[j] and parents[j] != -1]
    rotations[:, leaves] = np.array([1.0, 0.0, 0.0, 0.0])
    return skeleton, Motion(x[:, chain.root], rotations)
