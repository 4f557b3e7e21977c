"""The kinematic chain space (KCS, §3.1 of Wandt, Ackermann & Rosenhahn): matrices C and D.

A pose is ``X = (x_1 … x_J)`` (3 × J, one column per joint). A bone is the difference of two joints,
``b_k = X c_k`` with ``c_k`` holding +1 at the bone's end joint and −1 at its start joint, so all bones
are ``B = X C`` (Eq. 9) with ``C`` of shape ``(J, b)``. ``D`` (``(b, J)``) maps bones back to joints
(Eq. 10): column ``j`` sums the tree bones on the path from the root to joint ``j``, so ``B D`` is the
pose with the root at the origin. Bones never carry a translation: ``1ᵀ C = 0``.

Besides the tree's bones, a chain may hold *extra rigid links* between non-adjacent joints (the paper's
sword-fight example: both hands holding one object). They are extra columns of ``C`` (and zero rows of
``D``); the solver keeps their lengths constant like any bone.

Joint order is the caller's (it need not be topological); the topology must be a tree (one root, no
cycles) over all joints.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from functools import cached_property

import numpy as np

from ..geometry import rotation_from_covariance
from ..kinematics.skeleton import Skeleton

__all__ = ["CMU_JOINTS", "KinematicChainSpace", "mean_pose"]

# 19 joints of a CMU (Acclaim) skeleton read by bcmocap.io.read_asf (segment names; each is the joint at the
# start of that bone): pelvis, hips, knees, ankles, toes, chest, neck, head, head top, shoulders, elbows,
# wrists. Coincident joints (hip-joint bones of zero length, the clavicles' start) are left out.
CMU_JOINTS = (
    "root", "lfemur", "ltibia", "lfoot", "ltoes", "rfemur", "rtibia", "rfoot", "rtoes", "thorax", "lowerneck",
    "head", "head_end", "lhumerus", "lradius", "lwrist", "rhumerus", "rradius", "rwrist",
)


@dataclasses.dataclass(frozen=True)
class KinematicChainSpace:
    """Topology of a kinematic chain and its KCS matrices.

    Attributes:
        names: joint names, unique.
        parents: parent index per joint, ``-1`` for the single root; any order, no cycles.
        extra_links: ``(start, end)`` joint index pairs of rigid links that are not tree bones.

    Bone ``k < J - 1`` is the tree bone ending at the ``k``-th non-root joint (in joint order); bones
    ``J - 1 …`` are the extra links in the order given. Every bone points from its start (parent) to its
    end (child) joint.
    """

    names: tuple[str, ...]
    parents: tuple[int, ...]
    extra_links: tuple[tuple[int, int], ...] = ()

    def __post_init__(self):
        names = tuple(str(n) for n in self.names)
        parents = tuple(int(p) for p in self.parents)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "parents", parents)
        object.__setattr__(self, "extra_links", tuple((int(a), int(b)) for a, b in self.extra_links))
        n = len(names)
        if n < 2:
            raise ValueError(f"KinematicChainSpace: need at least 2 joints (one bone), got {n}")
        if len(set(names)) != n:
            dup = sorted({x for x in names if names.count(x) > 1})
            raise ValueError(f"KinematicChainSpace: duplicate joint names {dup}")
        if len(parents) != n:
            raise ValueError(f"KinematicChainSpace: {n} names but {len(parents)} parents")
        roots = [names[j] for j in range(n) if parents[j] == -1]
        if len(roots) != 1:
            raise ValueError(f"KinematicChainSpace: the topology needs exactly one root (parent -1), found {roots}")
        for j, p in enumerate(parents):
            if p != -1 and not 0 <= p < n:
                raise ValueError(f"KinematicChainSpace: joint '{names[j]}' has parent {p}, outside 0..{n - 1}")
            if p == j:
                raise ValueError(f"KinematicChainSpace: joint '{names[j]}' is its own parent (a cycle)")
        for j in range(n):
            seen = [j]
            k = parents[j]
            while k != -1:
                if k in seen:
                    loop = " -> ".join(names[i] for i in seen[seen.index(k):] + [k])
                    raise ValueError(f"KinematicChainSpace: the topology has a cycle: {loop}")
                seen.append(k)
                k = parents[k]
        tree = {(parents[j], j) for j in range(n) if parents[j] != -1}
        for a, b in self.extra_links:
            if not (0 <= a < n and 0 <= b < n) or a == b:
                raise ValueError(f"KinematicChainSpace: extra link ({a}, {b}) must join two different joints in 0..{n - 1}")
            if (a, b) in tree or (b, a) in tree:
                raise ValueError(f"KinematicChainSpace: extra link {names[a]}-{names[b]} duplicates a tree bone")
        if len({frozenset(x) for x in self.extra_links}) != len(self.extra_links):
            raise ValueError("KinematicChainSpace: an extra link is given twice")

    # ---- constructors --------------------------------------------------------------------------------
    @classmethod
    def from_parents(
        cls,
        names: Sequence[str],
        parents: Sequence[int | str | None],
        extra_links: Sequence[tuple[int | str, int | str]] = (),
    ) -> KinematicChainSpace:
        """A chain from joint names and parents given as indices or names (``-1``, ``None`` or "" for the root)."""
        names = tuple(str(n) for n in names)
        index = {n: i for i, n in enumerate(names)}

        def resolve(p, what):
            if p is None or (isinstance(p, str) and p in ("", "-1")):
                return -1
            if isinstance(p, (int, np.integer)):
                return int(p)
            if p not in index:
                raise ValueError(f"KinematicChainSpace: {what} names unknown joint '{p}'; joints are {list(names)}")
            return index[p]

        if len(parents) != len(names):
            raise ValueError(f"KinematicChainSpace: {len(names)} names but {len(parents)} parents")
        par = [resolve(p, f"the parent of '{names[j]}'") for j, p in enumerate(parents)]
        links = [(resolve(a, "an extra link"), resolve(b, "an extra link")) for a, b in extra_links]
        return cls(names, tuple(par), tuple(links))

    @classmethod
    def from_skeleton(
        cls,
        skeleton: Skeleton,
        joints: Sequence[str] | None = None,
        extra_links: Sequence[tuple[str, str]] = (),
    ) -> KinematicChainSpace:
        """The chain of a bcmocap skeleton: one joint per segment origin.

        Args:
            skeleton: the tree.
            joints: names of the segments to keep (default: all); a kept joint's parent is its nearest kept
                ancestor, so the kept set must contain the root or exactly one joint with no kept ancestor.
            extra_links: pairs of kept joint names joined by a rigid link.
        """
        keep = list(skeleton.names) if joints is None else [str(j) for j in joints]
        idx = [skeleton.index(n) for n in keep]
        if len(set(idx)) != len(idx):
            raise ValueError(f"from_skeleton: joints repeat a name: {keep}")
        pos = {s: k for k, s in enumerate(idx)}
        parents = []
        for s in idx:
            p = skeleton.parents[s]
            while p >= 0 and p not in pos:
                p = skeleton.parents[p]
            parents.append(pos[p] if p >= 0 else -1)
        return cls.from_parents(keep, parents, extra_links)

    # ---- sizes and matrices ----------------------------------------------------------------------------
    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def num_bones(self) -> int:
        """Tree bones plus extra links (the number of columns of C)."""
        return self.num_joints - 1 + len(self.extra_links)

    @cached_property
    def root(self) -> int:
        return self.parents.index(-1)

    @cached_property
    def links(self) -> tuple[tuple[int, int], ...]:
        """``(start, end)`` joint indices of every bone, tree bones first then the extra links."""
        tree = tuple((p, j) for j, p in enumerate(self.parents) if p != -1)
        return tree + self.extra_links

    @cached_property
    def bone_names(self) -> tuple[str, ...]:
        return tuple(f"{self.names[a]}->{self.names[b]}" for a, b in self.links)

    @cached_property
    def C(self) -> np.ndarray:
        """``(J, b)`` joints → bones (Eq. 9): ``B = X C``; +1 at a bone's end joint, −1 at its start."""
        c = np.zeros((self.num_joints, self.num_bones))
        for k, (a, b) in enumerate(self.links):
            c[b, k] = 1.0
            c[a, k] = -1.0
        c.flags.writeable = False
        return c

    @cached_property
    def D(self) -> np.ndarray:
        """``(b, J)`` bones → joints (Eq. 10): ``X = B D`` with the root at the origin (extra-link rows are zero)."""
        d = np.zeros((self.num_bones, self.num_joints))
        bone_of = {b: k for k, (a, b) in enumerate(self.links[: self.num_joints - 1])}
        for j in range(self.num_joints):
            k = j
            while self.parents[k] != -1:
                d[bone_of[k], j] = 1.0
                k = self.parents[k]
        d.flags.writeable = False
        return d

    @cached_property
    def D_least_squares(self) -> np.ndarray:
        """``(b, J)``: ``X = B D_ls`` is the pose whose bones best fit ``B`` (root at the origin).

        Equals :attr:`D` when ``B`` is consistent (``B = X C`` for some ``X``); with extra links and bones
        that do not close the loops exactly it spreads the mismatch over the loop instead of ignoring the link.
        """
        pinv = np.linalg.pinv(self.C)  # X C pinv(C) = X − mean over joints
        d = pinv - pinv[:, [self.root]]
        d.flags.writeable = False
        return d

    @cached_property
    def topological_order(self) -> tuple[int, ...]:
        """Joint indices with every parent before its children (breadth first from the root)."""
        children = [[] for _ in range(self.num_joints)]
        for j, p in enumerate(self.parents):
            if p != -1:
                children[p].append(j)
        order = [self.root]
        for j in order:
            order.extend(children[j])
        return tuple(order)

    # ---- maps ----------------------------------------------------------------------------------------
    def bones(self, joints) -> np.ndarray:
        """``(..., b, d)`` bone vectors of joint positions ``(..., J, d)`` (d = 2 or 3)."""
        joints = np.asarray(joints)
        self._check(joints, "bones: joints")
        return np.einsum("jb,...jd->...bd", self.C, joints)

    def joints(self, bones, least_squares: bool | None = None) -> np.ndarray:
        """``(..., J, d)`` joint positions (root at the origin) of bone vectors ``(..., b, d)``.

        ``least_squares`` (default: when the chain has extra links) uses :attr:`D_least_squares`.
        """
        bones = np.asarray(bones)
        if bones.ndim < 2 or bones.shape[-2] != self.num_bones:
            raise ValueError(f"joints: expected bones (..., {self.num_bones}, d), got shape {bones.shape}")
        if least_squares is None:
            least_squares = bool(self.extra_links)
        d = self.D_least_squares if least_squares else self.D
        return np.einsum("bj,...bd->...jd", d, bones)

    def _check(self, joints: np.ndarray, what: str) -> None:
        if joints.ndim < 2 or joints.shape[-2] != self.num_joints or joints.shape[-1] not in (2, 3):
            raise ValueError(
                f"{what}: expected shape (..., {self.num_joints}, 2 or 3) for the {self.num_joints} joints "
                f"{list(self.names)}, got {joints.shape}"
            )


def mean_pose(
    sequences: Sequence[np.ndarray] | np.ndarray,
    chain: KinematicChainSpace | None = None,
    iterations: int = 4,
) -> np.ndarray:
    """The mean pose ``X0`` of many frames, by generalised Procrustes analysis (rotations and translations).

    Averaging joint positions shortens every bone that rotates between frames (a swinging shin's mean
    vector is shorter than the shin), which biases the scale of a reconstruction that starts from
    ``B0 = X0 C`` (on CMU walking by about 4 %). Given ``chain``, each tree bone of the mean keeps its
    direction and gets its mean length over the frames instead.

    Args:
        sequences: joint positions ``(F, J, 3)`` or a list of them (possibly of different lengths).
        chain: the topology, to restore mean bone lengths (recommended).
        iterations: alignment rounds.

    Returns:
        ``(J, 3)`` mean pose with its centroid at the origin, in the orientation of the first frame.
    """
    arrays = [np.asarray(s, dtype=np.float64) for s in ([sequences] if isinstance(sequences, np.ndarray) else sequences)]
    for a in arrays:
        if a.ndim != 3 or a.shape[-1] != 3 or a.shape[1:] != arrays[0].shape[1:]:
            raise ValueError(f"mean_pose: expected joint arrays (F, J, 3) with the same J, got {[x.shape for x in arrays]}")
    frames = np.concatenate(arrays)
    if len(frames) == 0 or not np.all(np.isfinite(frames)):
        raise ValueError("mean_pose: needs at least one frame and finite joint positions")
    frames = frames - frames.mean(axis=1, keepdims=True)
    ref = frames[0].T
    for _ in range(iterations):
        m = np.einsum("fjd,kj->fdk", frames, ref)  # Σ_j x_j ref_jᵀ per frame, (F, 3, 3)
        rot = rotation_from_covariance(np.swapaxes(m, 1, 2))  # (F, 3, 3), maps frame → ref
        ref = np.einsum("fde,fje->dj", rot, frames) / len(frames)
    mean = ref.T
    if chain is not None:
        if chain.num_joints != mean.shape[0]:
            raise ValueError(f"mean_pose: the chain has {chain.num_joints} joints, the frames {mean.shape[0]}")
        tree = slice(0, chain.num_joints - 1)
        lengths = np.linalg.norm(chain.bones(frames)[:, tree], axis=-1).mean(axis=0)
        bones = chain.bones(mean)[tree]
        norm = np.linalg.norm(bones, axis=-1, keepdims=True)
        bones = np.where(norm > 1e-12, bones / np.where(norm > 1e-12, norm, 1.0) * lengths[:, None], bones)
        mean = np.einsum("bj,bd->jd", chain.D[tree], bones)
    return mean - mean.mean(axis=0)
