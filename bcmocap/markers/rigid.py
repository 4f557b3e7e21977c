"""Rigid bodies (Kirk et al. §3.3): from noisy per-frame joints and markers to a true rigid skeleton.

For each marker group, the group's markers and the joints that connect it are mutually aligned over the
frames by Horn's absolute orientation (here its SVD form, Kabsch), iterated as a generalised Procrustes
analysis: every frame is aligned to the mean shape, the mean is recomputed, and so on. The mean position
of each point's cloud is its offset in the segment. Joints appear in both segments they connect, so the
segments chain into a rigid skeleton, which becomes a bcmocap :class:`~bcmocap.kinematics.Skeleton`
(BALL joints, a FREE root, segment frames world-aligned at rest as in BVH): the rest pose is the pose at a
reference frame, each segment's origin is its joint to its parent, and the root is the centre of the tree
(the group whose farthest group is the fewest joints away).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from ..geometry import kabsch
from ..kinematics.skeleton import Skeleton
from .joints import JointSolution

__all__ = ["RigidSkeleton", "build_skeleton", "procrustes"]


def procrustes(points: np.ndarray, iterations: int = 10, min_points: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Generalised Procrustes analysis of one rigid body's points over frames.

    Args:
        points: ``(F, N, 3)`` positions (NaN where unseen).
        iterations: align-and-average rounds.
        min_points: a frame takes part if it sees at least this many points.

    Returns:
        ``shape`` ``(N, 3)`` the mean shape (in the frame of the first usable frame, centred), ``R`` ``(F, 3, 3)``
        and ``t`` ``(F, 3)`` with ``points[f] ≈ R[f] @ shape + t[f]`` (NaN for unused frames), and ``used``
        ``(F,)``.

    Raises:
        ValueError: no frame sees ``min_points`` points, or some point is never seen in a used frame.
    """
    seen = np.isfinite(points).all(-1)
    used = seen.sum(1) >= min(min_points, points.shape[1])
    if not used.any():
        raise ValueError(f"procrustes: no frame sees {min_points} of the {points.shape[1]} points")
    p = points[used]
    s = seen[used]
    if not s.any(0).all():
        raise ValueError(f"procrustes: points {np.flatnonzero(~s.any(0)).tolist()} are never seen with enough others")
    # Start from the frame that sees the most points; fill its holes with the per-point mean.
    first = int(np.argmax(s.sum(1)))
    shape = np.where(s[first][:, None], p[first], np.nanmean(np.where(s[..., None], p, np.nan), axis=0))
    shape = shape - shape.mean(0)
    for _ in range(iterations):
        r, t = kabsch(np.broadcast_to(shape, p.shape), p, s.astype(float))
        local = np.einsum("fji,fnj->fni", r, p - t[:, None, :])  # Rᵀ (p − t)
        new = np.nansum(np.where(s[..., None], local, 0.0), axis=0) / s.sum(0)[:, None]
        new = new - new.mean(0)
        # Keep the orientation anchored: align the new mean to the previous one.
        ra, ta = kabsch(new, shape)
        new = new @ ra.T + ta
        if np.max(np.abs(new - shape)) < 1e-10:
            shape = new
            break
        shape = new
    r, t = kabsch(np.broadcast_to(shape, p.shape), p, s.astype(float))
    rot = np.full((points.shape[0], 3, 3), np.nan)
    trans = np.full((points.shape[0], 3), np.nan)
    rot[used], trans[used] = r, t
    return shape, rot, trans, used


@dataclasses.dataclass(frozen=True)
class RigidSkeleton:
    """The rigid skeleton fitted to marker groups.

    Attributes:
        skeleton: the :class:`Skeleton` (segment ``k`` is marker group ``segment_groups[k]``).
        segment_groups: ``(J,)`` the marker group of each segment.
        marker_segment: ``(M,)`` the segment of each marker.
        marker_offsets: ``(M, 3)`` each marker in its segment's frame (m).
        shape_rms_m: ``(J,)`` RMS residual of each segment's rigid (Procrustes) fit (m).
        reference_frame: the frame whose pose is the rest pose.
    """

    skeleton: Skeleton
    segment_groups: np.ndarray
    marker_segment: np.ndarray
    marker_offsets: np.ndarray
    shape_rms_m: np.ndarray
    reference_frame: int


def tree_from_edges(num_groups: int, edges: Sequence[tuple[int, int]], sizes: np.ndarray, root: int | None = None) -> tuple[list[int], list[int]]:
    """Breadth-first order of the groups from the root and each one's parent (``-1`` for the root).

    The default root is the tree's centre: least eccentricity, then most markers.
    """
    adj: list[list[int]] = [[] for _ in range(num_groups)]
    for a, b in edges:
        adj[a].append(b)
        adj[b].append(a)

    def bfs(start):
        order, parent, depth = [start], {start: -1}, {start: 0}
        k = 0
        while k < len(order):
            g = order[k]
            k += 1
            for h in sorted(adj[g]):
                if h not in parent:
                    parent[h] = g
                    depth[h] = depth[g] + 1
                    order.append(h)
        return order, parent, depth

    if root is None:
        ecc = [max(bfs(g)[2].values()) for g in range(num_groups)]
        root = min(range(num_groups), key=lambda g: (ecc[g], -int(sizes[g]), g))
    order, parent, _ = bfs(root)
    if len(order) != num_groups:
        missing = sorted(set(range(num_groups)) - set(order))
        raise ValueError(f"the joints do not connect groups {missing} to the rest of the skeleton")
    return order, [parent[g] for g in order]


def build_skeleton(
    positions: np.ndarray,
    groups: np.ndarray,
    joints: Sequence[JointSolution],
    *,
    root: int | None = None,
    names: Sequence[str] | None = None,
    reference_frame: int | None = None,
    max_frames: int | None = 500,
) -> RigidSkeleton:
    """Fit rigid bodies to the groups and chain them into a :class:`Skeleton` (§3.3).

    Args:
        positions: ``(F, M, 3)`` marker positions (m, NaN gaps).
        groups: ``(M,)`` group of each marker.
        joints: the solved joints of the tree's edges (``positions`` over all ``F`` frames).
        root: group to use as the root (None: the tree's centre).
        names: a name per group (None: ``seg<k>``).
        reference_frame: frame whose pose becomes the rest pose (None: the frame seeing most markers).
        max_frames: fit each group's shape on at most this many evenly spaced frames (and the reference
            frame): a shape is a constant, and every frame would only cost time. None: all frames.

    Raises:
        ValueError: a group cannot be fitted (its markers and joints are never seen together); the
            message names the group.
    """
    groups = np.asarray(groups)
    num = int(groups.max()) + 1
    sizes = np.bincount(groups, minlength=num)
    names = list(names) if names is not None else [f"seg{k}" for k in range(num)]
    order, parents = tree_from_edges(num, [j.groups for j in joints], sizes, root)
    seen = np.isfinite(positions[..., 0])
    if reference_frame is None:
        reference_frame = int(np.argmax(seen.sum(1)))
    joint_of = {frozenset(j.groups): j for j in joints}
    frames = np.arange(len(positions))
    if max_frames is not None and len(frames) > max_frames:
        frames = np.unique(np.append(np.linspace(0, len(frames) - 1, max_frames).round().astype(int), reference_frame))

    shapes: dict[int, np.ndarray] = {}
    rest: dict[int, np.ndarray] = {}  # shape rotated into the world at the reference frame
    point_index: dict[int, dict] = {}
    shape_rms = np.zeros(num)
    for g in range(num):
        markers = np.flatnonzero(groups == g)
        nbrs = [h for (a, b) in (j.groups for j in joints) for h in ((b,) if a == g else (a,) if b == g else ())]
        pts = [positions[frames, m] for m in markers] + [joint_of[frozenset((g, h))].positions[frames] for h in nbrs]
        pts = np.stack(pts, axis=1)  # (frames, N, 3)
        try:
            shape, rot, trans, used = procrustes(pts, min_points=3)
        except ValueError as exc:
            raise ValueError(f"segment '{names[g]}' (markers {markers.tolist()}): cannot fit a rigid body: {exc}") from None
        fitted = np.einsum("fij,nj->fni", rot, shape) + trans[:, None, :]
        err = np.linalg.norm(fitted - pts, axis=-1)
        shape_rms[g] = float(np.sqrt(np.nanmean(err[used] ** 2)))
        # Orientation at the reference frame (or the nearest frame the group is fitted in).
        usable = np.flatnonzero(used)
        f = int(usable[np.argmin(np.abs(frames[usable] - reference_frame))])
        rest[g] = shape @ rot[f].T
        shapes[g] = shape
        point_index[g] = {("m", int(m)): k for k, m in enumerate(markers)}
        point_index[g].update({("j", int(h)): len(markers) + k for k, h in enumerate(nbrs)})

    # Segment origins: the joint to the parent; the root's is the mean of its joints (or of its markers).
    origin: dict[int, np.ndarray] = {}
    for g, p in zip(order, parents):
        if p >= 0:
            origin[g] = rest[g][point_index[g][("j", p)]]
        else:
            jidx = [k for key, k in point_index[g].items() if key[0] == "j"]
            origin[g] = rest[g][jidx].mean(0) if jidx else rest[g].mean(0)
    offsets = np.zeros((num, 3))
    for k, (g, p) in enumerate(zip(order, parents)):
        if p >= 0:
            offsets[k] = rest[p][point_index[p][("j", g)]] - origin[p]
    segment_of_group = {g: k for k, g in enumerate(order)}
    skel = Skeleton(
        [names[g] for g in order],
        [-1 if p < 0 else segment_of_group[p] for p in parents],
        offsets,
    )
    marker_segment = np.array([segment_of_group[int(g)] for g in groups])
    marker_offsets = np.zeros((len(groups), 3))
    for m, g in enumerate(groups):
        marker_offsets[m] = rest[int(g)][point_index[int(g)][("m", m)]] - origin[int(g)]
    return RigidSkeleton(
        skeleton=skel,
        segment_groups=np.array(order),
        marker_segment=marker_segment,
        marker_offsets=marker_offsets,
        shape_rms_m=np.array([shape_rms[g] for g in order]),
        reference_frame=int(reference_frame),
    )
