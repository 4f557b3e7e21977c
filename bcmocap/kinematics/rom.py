"""Skeleton and camera mounts from a range-of-motion trial (Appendix, Eqs. 12–17, and §4.2 Eqs. 3–5).

The subject wears the cameras and exercises every joint; SfM gives each camera's pose over the trial.
The cameras of one segment are first merged into a virtual camera ``V`` (:mod:`.virtual`). A joint
then sits at a point fixed in both its parent's and its child's virtual camera frames (Eq. 12), so
over all frames where both are known

    parent_from_child(t) · c_child = c_parent        (Eq. 13)

which is linear in ``y = (c_child, c_parent)``: ``[R(t), −I] y = −t(t)``. Eq. (14) stacks these rows
differenced against the first frame to eliminate ``c_parent``; here every frame is stacked with
``c_parent`` kept as an unknown (no frame is privileged, and both centres come out at once), and the
system is solved in its inhomogeneous form (homogeneous coordinate 1) by least squares through the
eigen-decomposition of its 6×6 normal matrix, i.e. the SVD of the stacked rows. The singular values
say how well the trial determines the centre: a ball joint exercised about several axes has none
near zero; a hinge (knee, elbow) has exactly one, whose singular vector is the hinge axis (the
two-dimensional null space of Eq. 16 in homogeneous form); a joint the trial did not exercise has
one or more and is reported, as is a centre whose standard error is large.

Frame weights. A range-of-motion trial exercises one joint at a time, so for any joint most frames
repeat one relative pose. Their rotation noise then acts as fake motion and biases least squares
(errors in variables) toward the cameras, by ~30 % of the distance with 1° noise. Each frame is
therefore weighted by ``1 / (number of frames within pose_radius_deg of its relative rotation)``:
a static stretch counts as one pose. On top, frames are reweighted by a Tukey biweight of their
residual (scale from its median) so that badly registered camera poses drop out. A hinge's centre
is fixed on its axis by the straight rest pose: parent joint, hinge and child joint collinear at the
rest frames (Eq. 17).

Segment frames (a convention, stated here because joint angles and mounts depend on it). As in
:mod:`bcmocap.kinematics.skeleton` and the simulator's BVH-style skeletons: each segment's origin is
its joint centre, and in the **rest pose** every segment frame is parallel to one common frame,
``world_from_rest`` (the world axes by default). The trial therefore starts (or contains) a few
frames in which the subject holds the rest pose — the T-pose with straight limbs, as Vicon-style
calibrations do — and ``rest_frames`` says which. Joint angles are then rotations relative to that
pose and come out directly comparable with a skeleton built the same way (the simulator's). The
root has no joint: its origin is the mean of chosen child joints (``root_origin``; the simulator's
CMU skeletons put it at the lower-back joint, i.e. ``root_origin=("torso",)``).

Bone vectors (Eq. 15) are differences of joint centres in a segment's frame; camera mounts follow
from where each camera sits relative to its segment's virtual camera (Eq. 5). The result is the
core's :class:`~bcmocap.kinematics.Skeleton` and :class:`~bcmocap.kinematics.Rig`.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping, Sequence

import numpy as np

from ..cameras import CameraModel, camera_at, stack_cameras
from ..geometry import (
    apply_pose,
    compose_poses,
    invert_pose,
    matrix_from_quat,
    quat_conjugate,
    quat_from_matrix,
    quat_multiply,
    rotate_by_quat,
    rotation_from_covariance,
)
from ..precision import require_float64
from .rig import Rig
from .skeleton import JointType, Skeleton
from .virtual import (
    TUKEY_CUTOFF,
    VirtualCamera,
    estimate_virtual_camera,
    robust_average_poses,
)

#: Iterations of least absolute deviations (reweighted least squares) that start a robust joint solve: 10 bring the
#: fit within a fraction of the inlier noise of its minimum on the realism captures.
LAD_ITERATIONS = 10


@dataclasses.dataclass(frozen=True)
class Topology:
    """A predefined kinematic structure without dimensions: names, parents and joint types.

    Attributes:
        names: segment names; ``parents``: parent index per segment (``-1`` for the root, parents first);
        joint_types: one :class:`JointType` per segment (root FREE; FIXED joints cannot be estimated).
    """

    names: tuple[str, ...]
    parents: tuple[int, ...]
    joint_types: tuple[JointType, ...]

    def __post_init__(self):
        # The skeleton's own checks (unique names, topological order, a FREE root) with placeholder sizes.
        n = len(self.names)
        sk = Skeleton(self.names, self.parents, np.zeros((n, 3)), self.joint_types, np.ones((n, 3)))
        object.__setattr__(self, "names", sk.names)
        object.__setattr__(self, "parents", sk.parents)
        object.__setattr__(self, "joint_types", sk.joint_types)

    @classmethod
    def from_skeleton(cls, skeleton: Skeleton) -> Topology:
        """The topology of an existing skeleton (its dimensions are ignored)."""
        return cls(skeleton.names, skeleton.parents, skeleton.joint_types)

    @classmethod
    def from_segments(cls, segments: Sequence[tuple[str, str | None, JointType | str]]) -> Topology:
        """From ``(name, parent name or None, joint type)`` triples, parents listed before children."""
        names = [s[0] for s in segments]
        parents = []
        for name, parent, _ in segments:
            if parent is not None and parent not in names:
                raise ValueError(f"Topology: segment '{name}' has unknown parent '{parent}'; segments are {names}")
            parents.append(-1 if parent is None else names.index(parent))
        return cls(tuple(names), tuple(parents), tuple(s[2] for s in segments))

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"unknown segment '{name}'; the topology has {list(self.names)}") from None

    def children(self, j: int) -> tuple[int, ...]:
        return tuple(k for k, p in enumerate(self.parents) if p == j)


@dataclasses.dataclass(frozen=True)
class RomOptions:
    """Thresholds of the range-of-motion estimate.

    Attributes:
        min_frames: a camera (or a joint's parent/child pair) seen in fewer frames is reported.
        min_spread: smallest normalised singular value of Eq. (13)'s system below which a direction
            counts as not exercised (≈ the RMS rotation, in rad, that moves the centre along it, over
            √2, between the distinct poses of the trial; 1° camera noise alone gives ≈ 0.025, a ball
            joint swept through ±30° ≈ 0.2).
        max_centre_std_m: a centre whose standard error along its worst direction exceeds this is
            reported as not determined by the trial.
        robust: reweight frames (Tukey) in the joint solves and the virtual-camera averages.
        degenerate: what to do with a ball joint exercised about one axis only: "raise" (default);
            "hinge" — warn and fix its centre on that axis with the straight-rest-pose constraint
            (Eq. 17), as for a knee; or "mirror" — warn and give any ball joint the trials do not determine
            (moved about too few axes, its centre's standard error over ``max_centre_std_m``, or its segments
            known together in too few frames) its other side's centre (``left_``/``right_`` names) mirrored
            through the body's midplane, a hip or a shoulder as much as an ankle; and a hinge flexed enough to
            fix its axis but whose centre's standard error is over ``max_centre_std_m`` its own axis with its
            other side's centre, mirrored. Both sides undetermined raise.
            A direction moved less than ``min_spread`` but more than half of it (1° of camera noise alone reads
            half), where the centre's standard error is within ``max_centre_std_m``, is kept as fitted (warned).
        centred_virtual: virtual cameras at the mean of their cameras (True) or at a reference camera.
        pose_radius_deg: frames whose parent→child rotations are closer than this count as one pose
            when weighting frames (a few times the rotation noise).
        unregistered_ends: what to do with an end segment (a foot, a hand: no children) none of whose cameras
            is registered in ``min_frames`` frames, or whose joint centre the trials do not determine: "raise"
            (default), or "mirror" — warn, and give it the joint centre of its other side's segment (``left_``/
            ``right_`` names) mirrored through the body's midplane (the plane halfway between the root's
            ``left_`` and ``right_`` children), and a camera that never registered its other side's camera's
            mount, mirrored; a knee whose foot is left out so is placed on its axis nearest the other knee,
            mirrored. Both sides undetermined still raise.
        unregistered_rest: what to do with a segment none of whose cameras is registered in the rest frames and that
            has no carried rest orientation (``rest_orientations``): "raise" (default), or "mirror" — warn, and turn
            its virtual camera so that, at rest, its bone and the way its child joint bends are its other side's
            (``left_``/``right_`` names) mirrored through the body's midplane (a symmetric rest pose; its camera
            registrations elsewhere, in any trial, give both in its own frame).
    """

    min_frames: int = 20
    min_spread: float = 0.05
    max_centre_std_m: float = 0.02
    robust: bool = True
    degenerate: str = "raise"
    centred_virtual: bool = True
    pose_radius_deg: float = 5.0
    unregistered_ends: str = "raise"
    unregistered_rest: str = "raise"

    def __post_init__(self):
        if self.degenerate not in ("raise", "hinge", "mirror"):
            raise ValueError(f"RomOptions: degenerate must be 'raise', 'hinge' or 'mirror', got {self.degenerate!r}")
        if self.unregistered_ends not in ("raise", "mirror"):
            raise ValueError(f"RomOptions: unregistered_ends must be 'raise' or 'mirror', got {self.unregistered_ends!r}")
        if self.unregistered_rest not in ("raise", "mirror"):
            raise ValueError(f"RomOptions: unregistered_rest must be 'raise' or 'mirror', got {self.unregistered_rest!r}")


@dataclasses.dataclass(frozen=True)
class JointEstimate:
    """One joint's centre and how well the trial determined it.

    Attributes:
        segment, parent: the child and parent segment names.
        joint_type: as declared in the topology.
        centre_in_child, centre_in_parent: ``(3,)`` the centre in the child's and parent's virtual camera frames (m).
        axis_in_child: ``(3,)`` unit hinge axis in the child's virtual camera frame (hinges only, else None).
        frames: frames where both segments were known; inlier_fraction: share kept by the reweighting.
        rms_residual_m: RMS over inlier frames of ``|parent_from_child · c_child − c_parent|`` (m).
        spread: ``(6,)`` normalised singular values of Eq. (13)'s system, ascending.
        std_m: standard error of the centre along its worst determined direction (m).
        placed_by: where the trials did not determine the centre, how it was placed (``"right_thigh's, mirrored"``:
            its other side's centre mirrored through the midplane); the statistics above are then those of the fit
            that fell short. None where the trials determined it.
    """

    segment: str
    parent: str
    joint_type: JointType
    centre_in_child: np.ndarray
    centre_in_parent: np.ndarray
    axis_in_child: np.ndarray | None
    frames: int
    inlier_fraction: float
    rms_residual_m: float
    spread: np.ndarray
    std_m: float
    placed_by: str | None = None


@dataclasses.dataclass(frozen=True)
class RomEstimate:
    """What a range-of-motion trial gives: the skeleton, the camera mounts and the diagnostics.

    Attributes:
        skeleton: the estimated :class:`Skeleton` (segment frames as in the module docstring).
        rig: the estimated :class:`Rig` (None when no intrinsics were given).
        segment_from_camera: ``(C, 7)`` estimated mounts, in the order of the camera assignment.
        camera_names: camera names in that order; camera_segments: their segment indices.
        joints: segment name → :class:`JointEstimate` (every segment but the root).
        virtual_cameras: segment name → the :class:`VirtualCamera` of its cameras.
        segment_from_virtual: ``(J, 7)`` where each virtual camera sits on its segment.
    """

    skeleton: Skeleton
    rig: Rig | None
    segment_from_camera: np.ndarray
    camera_names: tuple[str, ...]
    camera_segments: tuple[int, ...]
    joints: dict[str, JointEstimate]
    virtual_cameras: dict[str, VirtualCamera]
    segment_from_virtual: np.ndarray

    def summary(self) -> str:
        """A table of the joints: type, frames, inliers, residual (mm), weakest spread, standard error (mm)."""
        lines = [f"{'joint':<18}{'type':<7}{'frames':>7}{'inliers':>9}{'rms mm':>8}{'spread':>8}{'std mm':>8}"]
        for name, j in self.joints.items():
            weakest = j.spread[1] if j.joint_type == JointType.HINGE else j.spread[0]
            lines.append(
                f"{name:<18}{j.joint_type.name.lower():<7}{j.frames:>7}{100 * j.inlier_fraction:>8.0f}%"
                f"{1e3 * j.rms_residual_m:>8.2f}{weakest:>8.3f}{1e3 * j.std_m:>8.2f}"
                + (f"  not determined: {j.placed_by}" if j.placed_by else "")
            )
        return "\n".join(lines)


def _pose_density_weights(q: np.ndarray, radius_rad: float) -> np.ndarray:
    """``1 / (number of frames whose rotation is within radius_rad of each frame's)`` for quaternions ``(N, 4)``."""
    cos_half = np.cos(radius_rad / 2.0)
    counts = np.concatenate([(np.abs(q[i : i + 512] @ q.T) >= cos_half).sum(axis=1) for i in range(0, len(q), 512)])
    return 1.0 / counts


def _solve_centre(parent_from_child: np.ndarray, drop: int, options: RomOptions, iterations: int = 15):
    """Weighted least squares for ``y = (c_child, c_parent)`` from ``[R, −I] y = −t`` over frames.

    Frame weights: ``1 / (number of frames in a similar relative pose)`` — a long stretch where the
    joint does not move counts like one pose, so the rotation noise of those frames cannot pose as
    motion and bias the centre toward the cameras (errors in variables) — times a Tukey weight of
    the frame's residual when robust, reweighted from a least-absolute-deviations fit (least squares
    would let a few frames of a camera that drifted tens of centimetres set the residual scale, and
    keep them). ``drop`` smallest eigen-directions are left out (a hinge's axis): the minimum-norm
    solution in the others.

    Returns:
        y ``(6,)``, eigenvectors ``(6, 6)`` (columns, ascending), normalised singular values ``(6,)``
        ascending, the covariance of y ``(6, 6)`` (m²), residual norms ``(N,)`` and Tukey weights ``(N,)``.
    """
    rot = matrix_from_quat(parent_from_child[:, :4])
    a = np.concatenate([rot, -np.broadcast_to(np.eye(3), rot.shape)], axis=2)  # (N, 3, 6)
    b = -parent_from_child[:, 4:]
    base = _pose_density_weights(parent_from_child[:, :4], np.deg2rad(options.pose_radius_deg))

    def fit(w):
        normal = np.einsum("n,nia,nib->ab", w, a, a)
        evals, evecs = np.linalg.eigh(normal)
        keep = (np.arange(6) >= drop) & (evals > 1e-20 * evals[-1])
        v = evecs[:, keep]
        y = v @ ((v.T @ np.einsum("n,nia,ni->a", w, a, b)) / evals[keep])
        return y, np.linalg.norm(np.einsum("nij,j->ni", a, y) - b, axis=1), evals, evecs, keep, v

    def tukey_of(r, among):
        scale = max(float(np.median(r[among])), 1e-9)
        return np.where(r < TUKEY_CUTOFF * scale, (1.0 - (r / (TUKEY_CUTOFF * scale)) ** 2) ** 2, 0.0)

    tukey = np.ones(len(a))
    if options.robust:  # Tukey's weights start from least absolute deviations over the frames, each counted once
        # (a few frames of a camera that drifted tens of centimetres are poses seen nowhere else, so the pose-density
        # weights would count each of them many times over, and least squares would let them set the scale)
        lad = np.ones(len(a))
        for _ in range(LAD_ITERATIONS):
            _, r, *_ = fit(lad)
            lad = 1.0 / np.maximum(r, 1e-3 * max(float(np.median(r)), 1e-9))
        tukey = tukey_of(r, r >= 0)
    for it in range(iterations if options.robust else 1):
        w = base * tukey
        y, r, evals, evecs, keep, v = fit(w)
        if not options.robust or it == iterations - 1:
            break
        new = tukey_of(r, tukey > 0)
        if np.allclose(new, tukey, atol=1e-9):
            break
        tukey = new
    # sandwich covariance: the weights are not inverse variances; residual variance per coordinate
    inlier = tukey > 0
    sigma2 = float(np.sum(r[inlier] ** 2) / max(3 * inlier.sum() - int(keep.sum()), 1))
    inv = (v / evals[keep]) @ v.T
    cov = sigma2 * inv @ np.einsum("n,nia,nib->ab", w**2, a, a) @ inv
    spread = np.sqrt(np.maximum(evals, 0.0) / w.sum())
    return y, evecs, spread, cov, r, tukey


def _joint_estimate(segment, parent, joint_type, parent_from_child, drop, options, families) -> JointEstimate:
    y, evecs, spread, cov, r, tukey = _solve_centre(parent_from_child, drop, options)
    inlier = tukey > 0
    std = float(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0)))
    axis = None
    if drop:
        null = evecs[:, 0]
        axis = null[:3] / np.linalg.norm(null[:3])
        families[segment] = (y, null)
    return JointEstimate(
        segment, parent, joint_type, y[:3], y[3:], axis, len(parent_from_child), float(inlier.mean()),
        float(np.sqrt(np.mean(r[inlier] ** 2))), spread, std,
    )


def _as_pairs(cameras) -> list[tuple[str, str]]:
    pairs = list(cameras.items()) if isinstance(cameras, Mapping) else [tuple(p) for p in cameras]
    for p in pairs:
        if len(p) != 2:
            raise ValueError(f"camera assignment: expected (camera, segment) pairs, got {p!r}")
    return [(str(c), str(s)) for c, s in pairs]


def _check_assignment(topology: Topology, pairs, world_from_camera, registered, options: RomOptions, more_registered=()):
    """The cameras of each segment (indices into ``pairs``); ValueError for an assignment the trials cannot
    estimate (counting each camera's registrations over the range-of-motion trial and ``more_registered``)."""
    names = [c for c, _ in pairs]
    if len(set(names)) != len(names):
        raise ValueError(f"camera assignment: duplicate camera names {sorted({n for n in names if names.count(n) > 1})}")
    unknown = sorted({s for _, s in pairs if s not in topology.names})
    if unknown:
        bad = [c for c, s in pairs if s in unknown]
        raise ValueError(
            f"camera assignment names unknown segments {unknown} (cameras {bad}); the topology has {list(topology.names)}"
        )
    c = len(pairs)
    if world_from_camera.ndim != 3 or world_from_camera.shape[1:] != (c, 7) or registered.shape != world_from_camera.shape[:2]:
        raise ValueError(
            f"skeleton_from_range_of_motion: expected world_from_camera (T, {c}, 7) and registered (T, {c}) for the "
            f"{c} assigned cameras, got {world_from_camera.shape} and {registered.shape}"
        )
    seg_cams = [[i for i, (_, s) in enumerate(pairs) if s == name] for name in topology.names]
    missing = [topology.names[j] for j, cams in enumerate(seg_cams) if not cams]
    if missing:
        raise ValueError(f"segments {missing} have no camera: every segment needs one to place its joint and frame")
    for j, t in enumerate(topology.joint_types):
        if t == JointType.FIXED:
            raise ValueError(
                f"segment '{topology.names[j]}' has a FIXED joint: its centre cannot be found from motion; merge it "
                "into its parent or declare it a ball joint"
            )
    counts = registered.sum(axis=0) + sum((np.asarray(r, bool).sum(axis=0) for r in more_registered), np.zeros(c, int))
    trials = "the range-of-motion trial" if not more_registered else f"the {1 + len(more_registered)} trials"
    for j, cams in enumerate(seg_cams):
        usable = [i for i in cams if counts[i] >= options.min_frames]
        for i in cams:
            if counts[i] >= options.min_frames:
                continue
            if not usable:
                raise ValueError(
                    f"camera '{names[i]}' is registered in only {counts[i]} frames of {trials} "
                    f"(< {options.min_frames}) and segment '{topology.names[j]}' has no better camera: its joint and "
                    "frame cannot be estimated"
                )
            if counts[i] == 0:
                raise ValueError(
                    f"camera '{names[i]}' is never registered in {trials}: its mount on "
                    f"'{topology.names[j]}' is unknown; re-register it or remove it from the assignment"
                )
    return seg_cams


def _average_rotation(quats: np.ndarray) -> np.ndarray:
    poses = np.concatenate([quats, np.zeros((len(quats), 3))], axis=1)
    return robust_average_poses(poses)[0][:4]


def skeleton_from_range_of_motion(
    topology: Topology | Skeleton,
    cameras: Mapping[str, str] | Sequence[tuple[str, str]],
    world_from_camera: np.ndarray,
    registered: np.ndarray,
    *,
    rest_frames,
    intrinsics: CameraModel | None = None,
    root_origin: Sequence[str] | None = None,
    world_from_rest: np.ndarray | None = None,
    more_trials: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    rest_orientations: np.ndarray | None = None,
    sibling_rotations: Mapping[str, tuple[str, np.ndarray]] | None = None,
    up: np.ndarray | None = None,
    options: RomOptions = RomOptions(),
) -> RomEstimate:
    """Estimate a skeleton and its camera mounts from the camera poses of a range-of-motion trial.

    Args:
        topology: the predefined kinematic structure (a :class:`Topology`, or a skeleton whose
            dimensions are ignored).
        cameras: camera name → segment name, in the order of the camera axis of the poses.
        world_from_camera: ``(T, C, 7)`` registered camera poses (wxyz_xyz, m); unregistered rows
            are never read (they may hold NaN).
        registered: ``(T, C)`` bool.
        rest_frames: frames (indices, a slice or a bool mask) where the subject holds the rest pose:
            they define the segment frames and the straight limbs of the hinge constraint.
        intrinsics: the cameras' models stacked over C (calibrated beforehand) to build a :class:`Rig`.
        root_origin: child segments whose joint centres' mean is the root's origin (default: all
            of the root's children).
        world_from_rest: ``(4,)`` quaternion, the common orientation of all segment frames in the
            rest pose (default: the world axes).
        more_trials: ``(world_from_camera (T', C, 7), registered (T', C))`` of other trials with the same
            mounts, in the same world frame (e.g. the capture itself): their parent→child poses join each
            joint's centre fit, so a joint the range-of-motion trial moved too little (or registered too
            rarely) is determined by all the motion there is; their frames also count towards each camera's
            registrations, the virtual cameras and the hinges' flexion sides. The rest pose comes from the
            range-of-motion trial's rest frames alone.
        rest_orientations: ``(C, 4)`` each camera's world orientation (wxyz) in the rest pose where it is known
            other than by a registration in the rest frames (e.g. carried there by the camera's gyro from the
            frames it registered in), NaN where not. Read only for a segment none of whose cameras is
            registered in the rest frames; its position there follows from its parent's and the joint centre.
        sibling_rotations: camera name → ``(sibling, (4,) wxyz sibling_from_camera rotation)`` for cameras registered
            in no frame of any trial whose orientation relative to another camera of their segment is known otherwise
            (e.g. from their gyros: :func:`~bcmocap.pipeline.gyro_turns.rotations_from_siblings_by_gyro`). They are
            left out of the estimate, and each one's mount is its sibling's turned by that rotation, at the sibling's
            position: where it sits on the segment is not determined (no term that reads only its turns needs it).
        up: ``(3,)`` the world's up, where the body's midplane is vertical at rest (the rest pose stands upright): the
            midplane that mirrors a joint or a rest orientation (``"mirror"`` settings) then holds ``up``, its normal
            the line between its two centres less that line's part along ``up`` (over a lever of 80 cm, 1° of tilt
            between the hip centres moves a mirrored ankle by 3 cm). None: the plane normal to that line, as the
            centres give it.
        options: thresholds and choices (:class:`RomOptions`).

    Raises:
        ValueError: an assignment naming unknown segments; a segment without cameras; a camera with
            too few registered frames in all trials and no other camera on its segment; a joint the trials
            did not exercise (naming it and what is missing); a segment neither registered in the rest frames
            nor given a rest orientation; a ``sibling_rotations`` entry naming an unknown camera, a sibling on
            another segment or itself placed by a sibling, a camera that is registered, or no quaternion; an ``up``
            that is not a finite non-zero ``(3,)`` vector, or along the line between the midplane's centres.

    Warns:
        UserWarning: a camera registered with its segment's other cameras in few frames; a hinge whose
            rotations are not about one axis; a degenerate ball joint regularised as a hinge.
    """
    require_float64("bcmocap.kinematics.skeleton_from_range_of_motion")
    if isinstance(topology, Skeleton):
        topology = Topology.from_skeleton(topology)
    pairs = _as_pairs(cameras)
    world_from_camera = np.asarray(world_from_camera, dtype=np.float64)
    registered = np.asarray(registered, dtype=bool)
    _check_more_trials(pairs, more_trials)
    if sibling_rotations:
        return _with_sibling_mounts(sibling_rotations, topology, pairs, world_from_camera, registered,
                                    rest_frames=rest_frames, intrinsics=intrinsics, root_origin=root_origin,
                                    world_from_rest=world_from_rest, more_trials=more_trials,
                                    rest_orientations=rest_orientations, up=up, options=options)
    ends = _unregistered_ends(topology, pairs, registered, options, [reg for _, reg in more_trials])
    if ends:
        return _with_mirrored_ends(ends, topology, pairs, world_from_camera, registered, rest_frames=rest_frames,
                                   intrinsics=intrinsics, root_origin=root_origin, world_from_rest=world_from_rest,
                                   more_trials=more_trials, rest_orientations=rest_orientations, up=up, options=options)
    seg_cams = _check_assignment(topology, pairs, world_from_camera, registered, options,
                                 [reg for _, reg in more_trials])
    carried = _check_rest_orientations(rest_orientations, len(pairs))
    rest = np.zeros(registered.shape[0], bool)
    rest[rest_frames] = True
    if not rest.any():
        raise ValueError("skeleton_from_range_of_motion: rest_frames selects no frame")

    vcs, pooled = _segment_virtual_cameras(topology, pairs, seg_cams, world_from_camera, registered, more_trials, options)
    world_v, known = pooled[0]
    joints, families = _estimate_joint_centres(topology, pooled, more_trials, options)
    all_v, all_known = (np.concatenate(x) for x in zip(*pooled))
    up = None if up is None else _unit_up(up)
    world_from_v_rest = _rest_pose(topology, joints, families, world_v, known, rest,
                                   _carried_segment_rest(topology, seg_cams, vcs, carried),
                                   mirror=options.unregistered_ends == "mirror",
                                   mirror_rest=(all_v, all_known) if options.unregistered_rest == "mirror" else None,
                                   up=up)
    skeleton, seg_from_v = _segment_frames(topology, joints, world_from_v_rest, world_from_rest, root_origin, all_v, all_known)
    camera_segments = tuple(topology.index(s) for _, s in pairs)
    mounts = np.zeros((len(pairs), 7))
    for j, cams in enumerate(seg_cams):
        vc = vcs[topology.names[j]]
        mounts[cams] = compose_poses(seg_from_v[j], vc.virtual_from_camera)
    names = tuple(c for c, _ in pairs)
    rig = None if intrinsics is None else Rig(names, camera_segments, mounts, intrinsics)
    return RomEstimate(skeleton, rig, mounts, names, camera_segments, joints, vcs, seg_from_v)


def _other_side(name: str) -> str | None:
    for a, b in (("left_", "right_"), ("right_", "left_")):
        if name.startswith(a):
            return b + name[len(a):]
    return None


def _why_not_mirrored(name: str, topology: Topology, options: RomOptions, *, end: bool,
                      other_undetermined: bool = False, axis_unfixed: bool = False) -> str:
    """Why neither ``unregistered_ends = "mirror"`` (for an ``end`` segment's joint) nor ``degenerate = "mirror"``
    placed the undetermined joint ``name`` from its other side: a clause to append to the error ("" where neither
    setting is on for it). ``axis_unfixed``: a hinge whose rotations do not fix its axis (mirroring keeps the axis)."""
    by_ends = end and options.unregistered_ends == "mirror"
    if not by_ends and options.degenerate != "mirror":
        if options.unregistered_ends == "mirror":
            return (" (unregistered_ends = 'mirror' places end segments only, and this one has children; degenerate = "
                    "'mirror' would mirror a ball joint)")
        return ""
    setting = "unregistered_ends" if by_ends else "degenerate"
    other = _other_side(name)
    if axis_unfixed and not by_ends:
        why = "the rotations do not fix its axis either"
    elif other is None:
        why = "it has no left_/right_ counterpart to mirror"
    elif other_undetermined:
        why = f"its other side '{other}' is undetermined too"
    elif other not in topology.names:
        why = f"its other side '{other}' is not in the model being fitted"
        if options.unregistered_ends == "mirror":
            why += " (an end segment whose cameras registered too little is left out, to be mirrored from this side)"
    elif not by_ends and not _has_hip_pair(topology):
        why = "the root has no left_/right_ pair of children to find the body's midplane"
    else:
        why = "only ball joints, and hinges whose axis the trials fix, are mirrored"
    return f" ({setting} = 'mirror' could not place it: {why})"


def _unregistered_ends(topology: Topology, pairs, registered, options: RomOptions, more_registered) -> list[int]:
    """With ``unregistered_ends = "mirror"``, the end segments (no children) none of whose cameras is registered in
    ``min_frames`` frames of all trials and whose other side's segment has a camera that is: their indices."""
    if options.unregistered_ends != "mirror" or np.ndim(registered) != 2 or np.shape(registered)[1] != len(pairs):
        return []
    counts = np.asarray(registered, bool).sum(axis=0) + sum((np.asarray(r, bool).sum(axis=0) for r in more_registered),
                                                           np.zeros(len(pairs), int))
    placed = {s for (_, s), n in zip(pairs, counts) if n >= options.min_frames}
    ends = []
    for j, name in enumerate(topology.names):
        other = _other_side(name)
        has_cameras = any(s == name for _, s in pairs)
        if (has_cameras and name not in placed and not topology.children(j) and topology.parents[j] >= 0
                and other in topology.names and other in placed):
            ends.append(j)
    return ends


def _hip_pair(names, parents) -> tuple[int, int]:
    """The root's first ``left_`` child and its ``right_`` twin, whose centres' midplane is the body's (ValueError
    without such a pair)."""
    kids = {names[k]: k for k in range(len(names)) if parents[k] == 0}
    for name, k in kids.items():
        if name.startswith("left_") and _other_side(name) in kids:
            return k, kids[_other_side(name)]
    raise ValueError("unregistered_ends = 'mirror': the root has no pair of left_/right_ children to find the body's "
                     "midplane")


def _has_hip_pair(topology: Topology) -> bool:
    """Whether the root has a ``left_``/``right_`` pair of children (:func:`_hip_pair`), which mirroring needs."""
    try:
        _hip_pair(topology.names, topology.parents)
    except ValueError:
        return False
    return True


def _midplane_pair(names, parents, undetermined=frozenset(), placed=frozenset()) -> tuple[int, int]:
    """The joints whose centres at rest fix the body's midplane: the root's ``left_``/``right_`` children
    (:func:`_hip_pair`), or where either is ``undetermined`` (a hip the trials did not determine), the first
    ``left_`` joint of the tree whose ``right_`` twin is there and neither is, preferring a pair neither of whose
    centres is ``placed`` by the rest pose (a knee, placed on its axis by the hip above it, would lean on the centre
    being mirrored). ValueError without one."""
    left, right = _hip_pair(names, parents)
    if names[left] not in undetermined and names[right] not in undetermined:
        return left, right
    pairs = [(k, names.index(_other_side(name))) for k, name in enumerate(names)
             if name.startswith("left_") and _other_side(name) in names
             and not {name, _other_side(name)} & set(undetermined)]
    for k, m in sorted(pairs, key=lambda pair: bool({names[pair[0]], names[pair[1]]} & set(placed))):
        return k, m
    raise ValueError(f"'{names[left]}' or '{names[right]}' is undetermined and no other left_/right_ pair of joints "
                     "is determined to find the body's midplane")


def _midplane_reflection(skeleton: Skeleton, up: np.ndarray | None = None) -> np.ndarray:
    """``(3, 3)`` the reflection through the body's midplane in the rest frame (:func:`_hip_pair`; ``up`` ``(3,)`` in
    the rest frame: :func:`_midplane_normal`)."""
    left, right = _hip_pair(skeleton.names, skeleton.parents)
    normal = _midplane_normal(np.asarray(skeleton.offsets)[left], np.asarray(skeleton.offsets)[right], up)
    return np.eye(3) - 2.0 * np.outer(normal, normal)


def _unit_up(up) -> np.ndarray:
    """``up`` as a ``(3,)`` unit vector (ValueError naming it otherwise)."""
    up = np.asarray(up, np.float64)
    if up.shape != (3,) or not np.all(np.isfinite(up)) or np.linalg.norm(up) == 0:
        raise ValueError(f"skeleton_from_range_of_motion: up must be a non-zero finite (3,) vector, got {up!r}")
    return up / np.linalg.norm(up)


def _midplane_normal(left: np.ndarray, right: np.ndarray, up: np.ndarray | None) -> np.ndarray:
    """``(3,)`` or ``(N, 3)`` unit normal of the body's midplane from a ``left_``/``right_`` pair of centres (the same
    shape): the line between them, less its part along ``up`` (unit ``(3,)``) where given (the midplane is vertical at
    rest). ValueError where that leaves less than half the line (the pair is more above each other than side by
    side: up is not the body's)."""
    line = np.asarray(left, np.float64) - np.asarray(right, np.float64)
    if up is None:
        return line / (np.linalg.norm(line) if line.ndim == 1 else np.linalg.norm(line, axis=1, keepdims=True))
    normal = line - (line @ up)[..., None] * up
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    if np.any(length < 0.5 * np.linalg.norm(line, axis=-1, keepdims=True)):
        raise ValueError(f"the line between the midplane's left_ and right_ centres at rest lies within 30° of up "
                         f"{np.round(up, 3).tolist()}: up is not the body's (the rest pose stands upright)")
    return normal / length


def _with_mirrored_ends(ends, topology: Topology, pairs, world_from_camera, registered, *, more_trials,
                        rest_orientations, options, **kwargs) -> RomEstimate:
    """The estimate without the unregistered ``ends``, then each end put back as its other side mirrored through
    the midplane: its joint centre (bone offset) and hinge axis, and its cameras' mounts (each camera of the end
    takes the mount of its other side's camera in the same place, else the first one's); warns naming each."""
    keep = [j for j in range(len(topology.names)) if j not in ends]
    old_to_new = {j: k for k, j in enumerate(keep)}
    reduced = Topology(tuple(topology.names[j] for j in keep),
                       tuple(-1 if topology.parents[j] < 0 else old_to_new[topology.parents[j]] for j in keep),
                       tuple(topology.joint_types[j] for j in keep))
    dropped = {topology.names[j] for j in ends}
    cams = [i for i, (_, s) in enumerate(pairs) if s not in dropped]
    intrinsics = kwargs.pop("intrinsics")
    part = _estimate_with_cameras(cams, reduced, pairs, world_from_camera, registered, more_trials=more_trials,
                                  rest_orientations=rest_orientations, options=options, intrinsics=intrinsics, **kwargs)
    up, rest_q = kwargs.get("up"), kwargs.get("world_from_rest")
    if up is not None and rest_q is not None:  # the offsets are in the rest frame
        up = matrix_from_quat(np.asarray(rest_q, np.float64) / np.linalg.norm(rest_q)).T @ _unit_up(up)
    mirror = _midplane_reflection(part.skeleton, None if up is None else _unit_up(up))
    n = len(topology.names)
    offsets, axes = np.zeros((n, 3)), np.zeros((n, 3))
    offsets[keep] = np.asarray(part.skeleton.offsets)
    axes[keep] = np.asarray(part.skeleton.hinge_axes)
    for j in ends:
        k = part.skeleton.index(_other_side(topology.names[j]))
        offsets[j] = mirror @ np.asarray(part.skeleton.offsets)[k]
        axes[j] = -mirror @ np.asarray(part.skeleton.hinge_axes)[k]  # an axis is a pseudovector
    skeleton = Skeleton(topology.names, topology.parents, offsets, topology.joint_types, axes)
    mounts = np.zeros((len(pairs), 7))
    mounts[cams] = part.segment_from_camera
    flip_x = np.diag([-1.0, 1.0, 1.0])  # the mirrored camera still has its x axis to its own right
    for j in ends:
        name, other = topology.names[j], _other_side(topology.names[j])
        own = [i for i, (_, s) in enumerate(pairs) if s == name]
        theirs = [part.camera_names.index(c) for c, s in (pairs[i] for i in cams) if s == other]
        for rank, i in enumerate(own):
            source = part.segment_from_camera[theirs[min(rank, len(theirs) - 1)]]
            rot = mirror @ matrix_from_quat(source[:4]) @ flip_x
            mounts[i] = np.concatenate([quat_from_matrix(rot), mirror @ source[4:]])
        warnings.warn(
            f"segment '{name}': none of its cameras ({', '.join(pairs[i][0] for i in own)}) is registered in "
            f"{options.min_frames} frames of the trials; its joint centre and camera mounts are '{other}''s mirrored "
            "through the body's midplane (unregistered_ends = 'mirror')", stacklevel=2)
    camera_segments = tuple(topology.index(s) for _, s in pairs)
    names = tuple(c for c, _ in pairs)
    rig = None if intrinsics is None else Rig(names, camera_segments, mounts, intrinsics)
    return RomEstimate(skeleton, rig, mounts, names, camera_segments, part.joints, part.virtual_cameras,
                       part.segment_from_virtual)


def _estimate_with_cameras(cams, topology: Topology, pairs, world_from_camera, registered, *, more_trials,
                           rest_orientations, intrinsics, **kwargs) -> RomEstimate:
    """:func:`skeleton_from_range_of_motion` on the cameras ``cams`` (indices into ``pairs``) alone."""
    return skeleton_from_range_of_motion(
        topology, [pairs[i] for i in cams], np.asarray(world_from_camera)[:, cams], np.asarray(registered)[:, cams],
        more_trials=[(np.asarray(p)[:, cams], np.asarray(r)[:, cams]) for p, r in more_trials],
        rest_orientations=None if rest_orientations is None else np.asarray(rest_orientations, np.float64)[cams],
        intrinsics=None if intrinsics is None else stack_cameras([camera_at(intrinsics, i) for i in cams]), **kwargs)


def _with_sibling_mounts(sibling_rotations, topology: Topology, pairs, world_from_camera, registered, *, more_trials,
                         rest_orientations, options, **kwargs) -> RomEstimate:
    """The estimate without the cameras of ``sibling_rotations`` (see :func:`skeleton_from_range_of_motion`), then each
    one's mount its sibling's turned by its rotation, at the sibling's position; warns naming each."""
    names = [c for c, _ in pairs]
    segment_of = dict(pairs)
    for name, (sibling, _) in sibling_rotations.items():
        if name not in segment_of or sibling not in segment_of:
            raise ValueError(f"sibling_rotations: '{name}' → '{sibling}': both must be assigned cameras")
        if segment_of[name] != segment_of[sibling]:
            raise ValueError(f"sibling_rotations: '{name}' → '{sibling}': the sibling must be on the same segment "
                             f"('{segment_of[name]}', not '{segment_of[sibling]}')")
        if sibling in sibling_rotations:
            raise ValueError(f"sibling_rotations: '{name}' → '{sibling}': the sibling must be placed by its own "
                             "registrations, not by another camera")
        rotation = np.asarray(sibling_rotations[name][1], np.float64)
        if rotation.shape != (4,) or not np.isfinite(rotation).all() or not np.linalg.norm(rotation) > 0:
            raise ValueError(f"sibling_rotations: '{name}': expected a (4,) wxyz quaternion, got {rotation.tolist()}")
        counts = np.asarray(registered, bool)[:, names.index(name)].sum() + sum(
            np.asarray(r, bool)[:, names.index(name)].sum() for _, r in more_trials)
        if counts:
            raise ValueError(f"sibling_rotations: camera '{name}' is registered in {counts} frames; its own frames place it")
    keep = [i for i, c in enumerate(names) if c not in sibling_rotations]
    intrinsics = kwargs.pop("intrinsics")
    part = _estimate_with_cameras(keep, topology, pairs, world_from_camera, registered, more_trials=more_trials,
                                  rest_orientations=rest_orientations, options=options, intrinsics=intrinsics, **kwargs)
    mounts = np.zeros((len(pairs), 7))
    mounts[keep] = part.segment_from_camera
    for name, (sibling, rotation) in sibling_rotations.items():
        source = part.segment_from_camera[part.camera_names.index(sibling)]
        q = np.asarray(rotation, np.float64) / np.linalg.norm(rotation)
        mounts[names.index(name)] = np.concatenate([quat_multiply(source[:4], q), source[4:]])
        warnings.warn(f"camera '{name}' is registered in no frame of the trials: its mount is '{sibling}''s turned by "
                      f"the rotation between them given in sibling_rotations, at '{sibling}''s position (where it sits "
                      f"on '{segment_of[name]}' is not determined)", stacklevel=2)
    camera_segments = tuple(topology.index(s) for _, s in pairs)
    rig = None if intrinsics is None else Rig(tuple(names), camera_segments, mounts, intrinsics)
    return RomEstimate(part.skeleton, rig, mounts, tuple(names), camera_segments, part.joints, part.virtual_cameras,
                       part.segment_from_virtual)


def _check_more_trials(pairs, more_trials) -> None:
    for k, (poses, reg) in enumerate(more_trials):
        if np.ndim(poses) != 3 or np.shape(poses)[1:] != (len(pairs), 7) or np.shape(reg) != np.shape(poses)[:2]:
            raise ValueError(
                f"skeleton_from_range_of_motion: more_trials[{k}]: expected world_from_camera (T, {len(pairs)}, 7) and "
                f"registered (T, {len(pairs)}) for the {len(pairs)} assigned cameras, got {np.shape(poses)} and {np.shape(reg)}"
            )


def _check_rest_orientations(rest_orientations, num_cameras: int) -> np.ndarray:
    """``(C, 4)`` unit quaternions (NaN rows where none is given) from the ``rest_orientations`` argument."""
    if rest_orientations is None:
        return np.full((num_cameras, 4), np.nan)
    q = np.asarray(rest_orientations, dtype=np.float64)
    if q.shape != (num_cameras, 4):
        raise ValueError(f"skeleton_from_range_of_motion: rest_orientations: expected ({num_cameras}, 4) for the "
                         f"{num_cameras} assigned cameras, got {q.shape}")
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    given = np.isfinite(q).all(axis=1)
    bad = np.flatnonzero(~given & ~np.isnan(q).all(axis=1) | given & (np.abs(norm[:, 0] - 1.0) > 1e-6))
    if bad.size:
        raise ValueError(f"skeleton_from_range_of_motion: rest_orientations: row {bad[0]} is {q[bad[0]].tolist()}; rows "
                         "must be unit quaternions (wxyz) or all NaN")
    return np.where(given[:, None], q / np.where(given[:, None], norm, 1.0), np.nan)


def _carried_segment_rest(topology, seg_cams, vcs, carried) -> np.ndarray:
    """``(J, 4)`` each segment's world_from_virtual rest orientation from its cameras' ``carried`` ``(C, 4)`` rest
    orientations (their robust mean through the virtual camera), NaN where no camera of the segment has one."""
    out = np.full((len(topology.names), 4), np.nan)
    for j, cams in enumerate(seg_cams):
        vc = vcs[topology.names[j]]
        qs = [quat_multiply(carried[i], quat_conjugate(vc.virtual_from_camera[k, :4]))
              for k, i in enumerate(cams) if np.isfinite(carried[i]).all()]
        if qs:
            out[j] = _average_rotation(np.array(qs))
    return out


def _segment_virtual_cameras(topology, pairs, seg_cams, world_from_camera, registered, more_trials, options):
    """One virtual camera per segment from the frames of all trials (the range-of-motion trial and
    ``more_trials``), and the ``(world_v, known)`` virtual-camera poses of each trial (in that order; see
    :func:`_virtual_poses`)."""
    all_poses = np.concatenate([world_from_camera, *(np.asarray(p, np.float64) for p, _ in more_trials)])
    all_registered = np.concatenate([registered, *(np.asarray(r, bool) for _, r in more_trials)])
    vcs: dict[str, VirtualCamera] = {
        topology.names[j]: estimate_virtual_camera(
            [pairs[i][0] for i in cams], all_poses[:, cams], all_registered[:, cams], name=topology.names[j],
            centred=options.centred_virtual, min_frames=options.min_frames,
        )
        for j, cams in enumerate(seg_cams)
    }
    pooled = [_virtual_poses(vcs, topology, seg_cams, poses, reg, options)
              for poses, reg in [(world_from_camera, registered), *more_trials]]
    return vcs, pooled


def _estimate_joint_centres(topology, pooled, more_trials, options):
    """Joint centres (Eqs. 12-14, 16) from the parent→child virtual-camera poses of all ``pooled`` trials.

    Returns the :class:`JointEstimate` per child segment name and the hinge-like ``families`` (name →
    ``(y, null)``: a centre fixed only up to a line, placed on it by the rest pose, see :func:`_rest_pose`).
    Raises ValueError for a joint the trials did not exercise; warns for a hinge whose rotations are not
    about one axis and for a ball joint regularised as a hinge.
    """
    joints: dict[str, JointEstimate] = {}
    families: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    undetermined: dict[str, tuple[str, str, str]] = {}  # joint → (the error, why, the setting mirroring it)
    for j in range(1, len(topology.names)):
        name, p = topology.names[j], topology.parents[j]
        pname, jtype = topology.names[p], topology.joint_types[j]
        rel = np.concatenate([compose_poses(invert_pose(wv[kn[:, j] & kn[:, p], p]), wv[kn[:, j] & kn[:, p], j])
                              for wv, kn in pooled])
        trials = "trial" if not more_trials else f"{1 + len(more_trials)} trials"
        end_mirrorable = (options.unregistered_ends == "mirror" and not topology.children(j)
                          and _other_side(name) in topology.names)
        mirrorable = end_mirrorable or (options.degenerate == "mirror" and jtype == JointType.BALL
                                        and _other_side(name) in topology.names and _has_hip_pair(topology))
        if len(rel) < options.min_frames:
            failure = (f"joint '{name}' (between '{pname}' and '{name}'): both segments are known in only {len(rel)} "
                       f"frames (< {options.min_frames}) of the {trials}")
            if not mirrorable:
                raise ValueError(failure + _why_not_mirrored(name, topology, options, end=not topology.children(j)))
            undetermined[name] = (failure, f"both segments are known in only {len(rel)} frames",
                                  "unregistered_ends" if end_mirrorable else "degenerate")
            joints[name] = JointEstimate(name, pname, jtype, np.zeros(3), np.zeros(3), None, len(rel), 0.0, np.nan,
                                         np.zeros(6), np.inf)
            continue
        hinge = jtype == JointType.HINGE
        est = _joint_estimate(name, pname, jtype, rel, 1 if hinge else 0, options, families)
        weak = int(np.sum(est.spread < options.min_spread))
        what = f"joint '{name}' (between '{pname}' and '{name}', {jtype.name.lower()})"
        if hinge:
            if weak > 1 or est.std_m > options.max_centre_std_m:
                failure = (f"{what}: the {trials} did not exercise it: rotation spread about its axis "
                           f"{est.spread[1]:.4f} (need ≥ {options.min_spread}), centre standard error "
                           f"{100 * est.std_m:.2f} cm; flex the joint through its range in the trial")
                # its axis comes from the rotations alone: where they fix it (one weak direction, the axis itself),
                # "mirror" keeps the axis and takes the centre from the other side
                if not (options.degenerate == "mirror" and weak <= 1 and _other_side(name) in topology.names
                        and _has_hip_pair(topology)):
                    raise ValueError(failure + _why_not_mirrored(  # hinges are mirrored by degenerate only
                        name, topology, options, end=False, axis_unfixed=weak > 1))
                undetermined[name] = (failure, f"the {trials} do{'es' * (not more_trials)} not determine its centre "
                                      f"(centre standard error {100 * est.std_m:.2f} cm)", "degenerate")
            if est.spread[0] > max(options.min_spread, 0.3 * est.spread[1]):
                warnings.warn(
                    f"{what}: its rotations are not about a single axis (spreads {est.spread[0]:.3f} and "
                    f"{est.spread[1]:.3f}); it is estimated as a hinge about the least-moving axis",
                    stacklevel=3,
                )
        elif weak or est.std_m > options.max_centre_std_m:
            # a direction moved less than min_spread but more than half of it (1° of camera noise alone reads half)
            # that the fit still pins within the limit
            # (an end unregistered_ends mirrors is mirrored, as before this rule)
            marginal = (options.degenerate == "mirror" and not end_mirrorable and weak == 1
                        and est.std_m <= options.max_centre_std_m and est.spread.min() >= options.min_spread / 2)
            if marginal:
                warnings.warn(
                    f"{what}: the {trials} exercised it little about one axis (spread {est.spread[0]:.4f} < "
                    f"{options.min_spread}), but its centre's standard error, {100 * est.std_m:.2f} cm, is within the "
                    f"limit of {100 * options.max_centre_std_m:.3g} cm: kept (degenerate = 'mirror')", stacklevel=3)
            elif weak == 1 and options.degenerate == "hinge":
                warnings.warn(
                    f"{what}: the trial exercised it about one axis only (spread {est.spread[0]:.4f} < "
                    f"{options.min_spread}); its centre is fixed on that axis by the straight rest pose",
                    stacklevel=3,
                )
                est = _joint_estimate(name, pname, jtype, rel, 1, options, families)
            else:
                spreads = np.array2string(est.spread[:3], precision=4)
                why = (f"{weak} direction(s) with rotation spread below {options.min_spread} (spreads {spreads}), "
                       f"centre standard error {100 * est.std_m:.2f} cm" if weak else
                       f"centre standard error {100 * est.std_m:.2f} cm, above the limit of {100 * options.max_centre_std_m:.3g} cm "
                       f"(rotation spreads {spreads})")
                failure = (f"{what}: the {trials} do{'es' * (not more_trials)} not determine its centre: {why}; exercise "
                           "the joint about more axes, or declare it a hinge")
                if not mirrorable:
                    raise ValueError(failure + _why_not_mirrored(name, topology, options, end=not topology.children(j)))
                undetermined[name] = (failure, f"the {trials} do{'es' * (not more_trials)} not determine its centre ({why})",
                                      "unregistered_ends" if end_mirrorable else "degenerate")
        joints[name] = est
    for name, (failure, why, setting) in undetermined.items():  # one whose other side is determined takes it mirrored
        if _other_side(name) in undetermined:
            raise ValueError(failure + _why_not_mirrored(name, topology, options, end=setting == "unregistered_ends",
                                                         other_undetermined=True))
        warnings.warn(f"joint '{name}': {why}; its centre is '{_other_side(name)}''s mirrored through the body's "
                      f"midplane ({setting} = 'mirror')", stacklevel=3)
        families[name] = (None, None)
    return joints, families


def _rest_pose(topology, joints, families, world_v, known, rest, carried_rest, mirror: bool = False,
               mirror_rest: tuple[np.ndarray, np.ndarray] | None = None, up: np.ndarray | None = None) -> np.ndarray:
    """Rest pose (Eq. 17): ``(J, 4)`` world_from_virtual orientations of the segments in the ``rest`` frames
    ``(T,)``; places each hinge-like family's centre on its axis, updating ``joints`` in place.

    A segment none of whose cameras is registered in the rest frames takes its ``carried_rest`` ``(J, 4)``
    orientation, else (``mirror_rest``: the ``(world_v, known)`` of all trials) its other side's mirrored
    (:func:`_mirrored_rest_orientation`), else ValueError; its virtual camera's pose in each rest frame where its
    parent's is known is put where that orientation and the joint centre hang it from the parent (for the families'
    placement). ``up``: the world's unit up, which the midplane of any mirroring holds (:func:`_midplane_normal`).
    """
    world_v, known = world_v.copy(), known.copy()
    n = len(topology.names)
    at_rest = np.array([rest & known[:, j] for j in range(n)]).T  # (T, J)
    world_from_v_rest = np.full((n, 4), np.nan)
    for j in range(n):  # registered at rest, else carried there: what a mirrored segment reads of its other side
        world_from_v_rest[j] = _average_rotation(world_v[at_rest[:, j], j, :4]) if at_rest[:, j].any() else carried_rest[j]
    for j in range(n):  # parents first
        if at_rest[:, j].any():
            continue
        if not np.isfinite(world_from_v_rest[j]).all():
            why = (f"segment '{topology.names[j]}': none of its cameras is registered in the rest frames, and none has "
                   "a rest orientation carried from other frames (e.g. by its gyro)")
            if mirror_rest is None:
                raise ValueError(why)
            world_from_v_rest[j] = _mirrored_rest_orientation(topology, joints, families, j, world_from_v_rest,
                                                              world_v, known, rest, *mirror_rest, why, up)
        q_rest = world_from_v_rest[j]
        p = topology.parents[j]
        hang = rest & known[:, p] if p >= 0 else np.zeros_like(rest)
        if hang.any():
            est = joints[topology.names[j]]
            centre = apply_pose(world_v[hang, p], est.centre_in_parent)
            q = np.broadcast_to(q_rest, (int(hang.sum()), 4))
            world_v[hang, j] = np.concatenate([q, centre - rotate_by_quat(q, est.centre_in_child)], axis=1)
            known[hang, j] = True
    # A family's placement reads its neighbours' centres; where neighbours are families too (an elbow next to a
    # wrist moved about one axis), alternate until the placements settle.
    _check_neighbouring_axes(topology, {k: v for k, v in families.items() if v[1] is not None}, world_from_v_rest)
    undetermined = {name for name, (_, null) in families.items() if null is None}
    placed = set(families) - undetermined
    for _ in range(1 if len(families) < 2 else 10):
        for name, (y0, null) in families.items():
            if null is None:  # a centre the trials did not determine: its other side's, mirrored
                joints[name] = _resolve_by_mirror(topology, joints, name, np.zeros(6), np.eye(6), world_v,
                                                  known & rest[:, None], undetermined, placed, up)
            else:
                joints[name] = _resolve_on_axis(topology, joints, name, y0, null, world_v, known & rest[:, None], mirror,
                                                undetermined, placed, up)
    return world_from_v_rest


def _bone_directions(topology, joints, families, s: int, all_v, all_known, fail) -> tuple[np.ndarray, np.ndarray, bool]:
    """Segment ``s``'s bone and how its child joint bends, in its virtual camera frame (from the frames of all trials
    ``all_v`` ``(T, J, 7)``, ``all_known`` ``(T, J)``): ``(2, 3)`` unit vectors and whether the second is a hinge's
    axis. A hinge child: the bone's direction normal to the hinge's axis (where along the axis its centre lies is
    not known before the rest pose) and the axis; a ball child: the bone (joint centre to the child's centre) and,
    normal to it, the median direction from the child's centre to the child's virtual camera. A bone that starts at a
    hinge placed on its axis by the rest pose is taken normal to that axis too. Also ``(3,)`` that median direction
    (which side a hinge bends to). ``fail(why)`` raises."""
    name = topology.names[s]
    kids = topology.children(s)
    if len(kids) != 1:
        fail(f"'{name}' has {len(kids)} child joints, not one whose centre gives its bone")
    c = kids[0]
    undetermined = [n for n in (name, topology.names[c]) if families.get(n, (0, 0))[1] is None]
    if undetermined:
        fail(f"the centre of '{undetermined[0]}' is not determined")
    est_s, est_c = joints[name], joints[topology.names[c]]
    both = all_known[:, s] & all_known[:, c]
    if not both.any():
        fail(f"'{name}' and its child '{topology.names[c]}' are never known in one frame")
    rot_s = matrix_from_quat(all_v[both, s, :4])  # (N, 3, 3)
    child_origin = np.einsum("nba,nb->na", rot_s, all_v[both, c, 4:] - all_v[both, s, 4:])
    bend = np.median(child_origin - est_c.centre_in_parent, axis=0)  # child's centre → its camera, in s's frame
    bone = est_c.centre_in_parent - est_s.centre_in_child
    if est_s.axis_in_child is not None and name in families:  # its own centre's place on its own axis: not known yet
        bone = bone - (bone @ est_s.axis_in_child) * est_s.axis_in_child
    if est_c.axis_in_child is not None:
        rot_sc = np.einsum("nba,nbc->nac", rot_s, matrix_from_quat(all_v[both, c, :4]))
        axis = np.mean(rot_sc @ est_c.axis_in_child, axis=0)
        axis /= np.linalg.norm(axis)
        bone = bone - (bone @ axis) * axis
        second, hinge = axis, True
    else:
        unit = bone / np.linalg.norm(bone)
        second, hinge = bend - (bend @ unit) * unit, False
    for v, what in ((bone, "bone"), (second, "child's bend")):
        if np.linalg.norm(v) < 1e-9:
            fail(f"'{name}''s {what} has no direction")
    return np.stack([bone / np.linalg.norm(bone), second / np.linalg.norm(second)]), bend, hinge


def _mirrored_rest_orientation(topology, joints, families, j, world_from_v_rest, world_v, known, rest, all_v, all_known,
                               why, up=None) -> np.ndarray:
    """``(4,)`` the world_from_virtual rest orientation of segment ``j``, which no rest frame registered: the one that
    puts its bone and its child joint's bend (:func:`_bone_directions`, from the frames of all trials) where its
    other side's, at rest (``world_from_v_rest`` ``(J, 4)``), mirrored through the body's midplane puts them (the
    plane halfway between the centres of :func:`_midplane_pair` in the ``rest`` frames of ``world_v``, ``known``,
    holding ``up`` where given).
    A hinge's axis is a line: of its two directions, the one that puts the child's camera on the mirrored side.
    ValueError (``why`` and what is missing) where that cannot be done; warns naming the segment."""
    name = topology.names[j]

    def fail(reason):
        raise ValueError(f"{why}; unregistered_rest = 'mirror' could not take its other side's: {reason}")

    other = _other_side(name)
    if other not in topology.names:
        fail("it has no left_/right_ counterpart")
    o = topology.index(other)
    if not np.isfinite(world_from_v_rest[o]).all():
        fail(f"'{other}' has no rest orientation either")
    undetermined = {n for n, (_, null) in families.items() if null is None}
    try:
        left, right = _midplane_pair(topology.names, topology.parents, undetermined,
                                     set(families) - undetermined)
    except ValueError as err:
        fail(str(err))
    ends = [topology.parents[left], topology.parents[right]]
    ok = rest & known[:, ends].all(axis=1)
    if not ok.any():
        fail(f"the midplane's joints '{topology.names[left]}' and '{topology.names[right]}' are never known in "
             "the rest frames")
    a, b = (np.mean(apply_pose(world_v[ok, topology.parents[k]], joints[topology.names[k]].centre_in_parent), axis=0)
            for k in (left, right))
    normal = _midplane_normal(a, b, up)
    reflect = np.eye(3) - 2.0 * np.outer(normal, normal)
    own, own_bend, hinge = _bone_directions(topology, joints, families, j, all_v, all_known, fail)
    theirs, their_bend, _ = _bone_directions(topology, joints, families, o, all_v, all_known, fail)
    rot_o = matrix_from_quat(world_from_v_rest[o])
    target = (reflect @ rot_o @ theirs.T).T  # polar vectors, and a hinge's axis up to its sign
    target_bend = reflect @ rot_o @ their_bend
    candidates = [rotation_from_covariance((target * np.array([[1.0], [sign]])).T @ own)  # Kabsch: own → target
                  for sign in ((1.0, -1.0) if hinge else (1.0,))]
    rot = max(candidates, key=lambda r: float((r @ own_bend) @ target_bend))
    warnings.warn(f"segment '{name}': none of its cameras is registered in the rest frames and none has a carried rest "
                  f"orientation; its rest orientation puts its bone and its child joint's bend where '{other}''s are, "
                  f"mirrored through the body's midplane (unregistered_rest = 'mirror')", stacklevel=4)
    return quat_from_matrix(rot)


def _segment_frames(topology, joints, world_from_v_rest, world_from_rest, root_origin, world_v, known):
    """Segment frames, bone vectors (Eq. 15) and hinge axes: the :class:`Skeleton` and ``(J, 7)``
    segment_from_virtual (wxyz_xyz) of each segment's virtual camera."""
    n = len(topology.names)
    rest_q = np.array([1.0, 0, 0, 0]) if world_from_rest is None else np.asarray(world_from_rest, dtype=np.float64)
    seg_from_v_rot = quat_multiply(quat_conjugate(rest_q / np.linalg.norm(rest_q)), world_from_v_rest)
    origin = np.zeros((n, 3))
    kids = topology.children(0)
    chosen = [topology.index(s) for s in root_origin] if root_origin is not None else list(kids)
    for k in chosen:
        if topology.parents[k] != 0:
            raise ValueError(f"root_origin: '{topology.names[k]}' is not a child of the root '{topology.names[0]}'")
    if chosen:  # (a lone root keeps its virtual camera's origin)
        origin[0] = np.mean([joints[topology.names[k]].centre_in_parent for k in chosen], axis=0)
    for j in range(1, n):
        origin[j] = joints[topology.names[j]].centre_in_child
    rot_sv = matrix_from_quat(seg_from_v_rot)  # (J, 3, 3)
    seg_from_v = np.concatenate([seg_from_v_rot, -np.einsum("jab,jb->ja", rot_sv, origin)], axis=1)
    offsets = np.zeros((n, 3))
    axes = np.zeros((n, 3))
    for j in range(1, n):
        est, p = joints[topology.names[j]], topology.parents[j]
        offsets[j] = rot_sv[p] @ (est.centre_in_parent - origin[p])
        if topology.joint_types[j] == JointType.HINGE:
            axes[j] = rot_sv[j] @ est.axis_in_child
            axes[j] *= _flexion_sign(world_v, known, j, p, seg_from_v_rot, axes[j])
    skeleton = Skeleton(topology.names, topology.parents, offsets, topology.joint_types, axes)
    return skeleton, seg_from_v


def _virtual_poses(vcs, topology, seg_cams, world_from_camera, registered, options):
    """``(T, J, 7)`` virtual-camera poses and ``(T, J)`` known of one trial's ``(T, C, 7)`` camera poses."""
    world_from_camera = np.asarray(world_from_camera, dtype=np.float64)
    registered = np.asarray(registered, dtype=bool)
    world_v = np.full((len(registered), len(topology.names), 7), np.nan)
    known = np.zeros((len(registered), len(topology.names)), bool)
    for j, cams in enumerate(seg_cams):
        world_v[:, j], known[:, j] = vcs[topology.names[j]].world_from_virtual(
            world_from_camera[:, cams], registered[:, cams], robust=options.robust)
    return world_v, known


def _check_neighbouring_axes(topology, families, world_from_v_rest, max_angle_deg: float = 10.0) -> None:
    """Raise ValueError if two neighbouring joints whose centres lie on axes have nearly parallel axes at rest: the
    straight rest pose then leaves a whole family of placements (both slide along their axes together)."""
    axes = {}
    for name, (_, null) in families.items():
        j = topology.index(name)
        axes[name] = rotate_by_quat(world_from_v_rest[j][None], (null[:3] / np.linalg.norm(null[:3]))[None])[0]
    for name in families:
        j = topology.index(name)
        for other in (topology.names[topology.parents[j]], *(topology.names[k] for k in topology.children(j))):
            if other in families and abs(float(axes[name] @ axes[other])) > np.cos(np.deg2rad(max_angle_deg)):
                raise ValueError(
                    f"joints '{name}' and '{other}': both centres lie on axes (a hinge, or a ball joint moved about one "
                    f"axis only) that are parallel at rest, so the straight rest pose cannot place them; exercise the "
                    f"ball joint about more axes"
                )


def _resolve_on_axis(topology, joints, name, y0, null, world_v, rest_known, mirror: bool = False,
                     undetermined=frozenset(), placed=frozenset(), up=None) -> JointEstimate:
    """Pick the point on a hinge's axis that is collinear with the joints above and below at rest (Eq. 17); for a
    joint at the end of a chain (a wrist, an ankle moved about one axis), collinear with the two joints above it
    (the straight limb extended). A neighbour that is itself on an axis is taken where it currently is. With
    ``mirror`` (``unregistered_ends = "mirror"``), a joint at the end of a chain whose grandparent is the root (a knee
    whose foot was left out) takes the point nearest its other side's centre mirrored through the midplane."""
    j = topology.index(name)
    p = topology.parents[j]
    kids = topology.children(j)
    if mirror and topology.parents[p] == 0 and not kids and _other_side(name) in joints:
        return _resolve_by_mirror(topology, joints, name, y0, null, world_v, rest_known, undetermined, placed, up)
    if topology.parents[p] < 0 or len(kids) > 1 or (not kids and topology.parents[topology.parents[p]] < 0):
        raise ValueError(
            f"joint '{name}': a centre on an axis is fixed by the straight limb of the rest pose — collinear with the "
            f"joints above and below it, or with the two above it at the end of a chain — so its parent must have a "
            f"joint (not the root), and it needs one child (has {len(kids)}) or a grandparent with a joint"
        )
    if kids:  # the parent's joint and the child's
        segments = (p, j)
        centres = (joints[topology.names[p]].centre_in_child, joints[topology.names[kids[0]]].centre_in_parent)
    else:  # the grandparent's joint and the parent's
        segments = (topology.parents[p], p)
        centres = (joints[topology.names[segments[0]]].centre_in_child, joints[topology.names[p]].centre_in_child)
    ok = rest_known[:, j] & rest_known[:, p] & rest_known[:, segments[0]]
    if not ok.any():
        raise ValueError(f"joint '{name}': its segments are never all known in the rest frames")
    wv = world_v[ok]
    wp, wc = wv[:, p], wv[:, j]
    upper, lower = (apply_pose(wv[:, seg], centre) for seg, centre in zip(segments, centres))
    d = upper - lower
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rows, rhs = [], []
    for pose, base, step in ((wc, y0[:3], null[:3]), (wp, y0[3:], null[3:])):
        k0 = apply_pose(pose, base)
        dk = rotate_by_quat(pose[:, :4], step)
        rows.append(np.cross(d, dk).ravel())
        rhs.append(-np.cross(d, k0 - lower).ravel())
    rows, rhs = np.concatenate(rows), np.concatenate(rhs)
    if np.linalg.norm(rows) < 1e-3 * np.sqrt(len(rows)):
        raise ValueError(f"joint '{name}': its axis is parallel to the limb at rest, the straight pose cannot place it")
    s = float(rows @ rhs / (rows @ rows))
    y = y0 + s * null
    return dataclasses.replace(joints[name], centre_in_child=y[:3], centre_in_parent=y[3:])


def _resolve_by_mirror(topology, joints, name, y0, null, world_v, rest_known, undetermined=frozenset(),
                       placed=frozenset(), up=None) -> JointEstimate:
    """The centre ``y0 + null · a`` (``null`` ``(6,)`` a hinge's axis, or ``(6, 6)``: any centre) nearest, over the rest
    frames, its other side's centre mirrored through the midplane (halfway between the centres of a ``left_``/``right_``
    pair, normal to the line between them and, where ``up`` is given, holding it: :func:`_midplane_pair`, none of whose
    centres is ``undetermined``, and preferably none ``placed`` on an axis by the rest pose)."""
    j = topology.index(name)
    p = topology.parents[j]
    other = topology.index(_other_side(name))
    left, right = _midplane_pair(topology.names, topology.parents, undetermined, placed)
    ends = (p, other, topology.parents[left], topology.parents[right])
    ok = rest_known[:, j] & np.all(rest_known[:, list(ends)], axis=1)
    if not ok.any():
        raise ValueError(f"joint '{name}': it, its other side and the midplane's joints '{topology.names[left]}' and "
                         f"'{topology.names[right]}' are never all known in the rest frames")
    wv = world_v[ok]
    a, b = (apply_pose(wv[:, topology.parents[k]], joints[topology.names[k]].centre_in_parent) for k in (left, right))
    normal = _midplane_normal(a, b, up)
    target = apply_pose(wv[:, other], joints[topology.names[other]].centre_in_child)
    target = target - 2.0 * np.sum((target - 0.5 * (a + b)) * normal, axis=1, keepdims=True) * normal
    null = np.asarray(null, np.float64).reshape(6, -1)  # (6, k) free directions of y = (c_child, c_parent)
    rows, rhs = [], []
    for pose, base, step in ((wv[:, j], y0[:3], null[:3]), (wv[:, p], y0[3:], null[3:])):
        rot = matrix_from_quat(pose[:, :4])  # (N, 3, 3)
        rows.append((rot @ step).reshape(-1, null.shape[1]))
        rhs.append((target - apply_pose(pose, base)).ravel())
    y = y0 + null @ np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)[0]
    whole = null.shape[1] == 6  # the whole centre is the other side's (not a point on the joint's own axis)
    return dataclasses.replace(joints[name], centre_in_child=y[:3], centre_in_parent=y[3:],
                               placed_by=f"{topology.names[other]}'s, mirrored" if whole else joints[name].placed_by)


def _flexion_sign(world_v, known, j, p, seg_from_v_rot, axis) -> float:
    """+1 if the hinge angles over the trial, where it is bent (more than 1° from the rest pose), are mostly positive
    about ``axis`` (flexion positive), else −1. (Frames near rest are left out: where they are the most, their median
    sign is that of noise.)"""
    ok = known[:, j] & known[:, p]
    seg = quat_multiply(world_v[ok][:, [p, j], :4], quat_conjugate(seg_from_v_rot[[p, j]]))
    local = quat_multiply(quat_conjugate(seg[:, 0]), seg[:, 1])
    angle = 2.0 * np.arctan2(local[:, 1:] @ axis, local[:, 0])
    bent = angle[np.abs(angle) > np.radians(1.0)]
    return 1.0 if not bent.size or np.median(bent) >= 0 else -1.0

