"""Synthetic range-of-motion trials: every joint exercised in turn, observed as SfM-like camera poses.

A trial starts with the subject holding the rest pose (the T-pose with straight limbs, which defines
the segment frames, see :mod:`bcmocap.kinematics.rom`), then exercises one joint at a time in the
skeleton's order: a ball joint sweeps a cone with a twist (every rotation axis is used), a hinge flexes
from straight twice, the root turns, bends and shifts. The cameras of the rig follow by forward
kinematics; their poses are then degraded like structure-from-motion output: rotation noise (right-
multiplied, as :mod:`bcmocap.sim.observe` does), position noise, a share of camera-frames missing
(unregistered) and optionally a share of grossly wrong registrations. All randomness comes from ``seed``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from ..geometry import SE3, SO3, apply_pose, invert_pose, quat_conjugate, quat_multiply
from ..kinematics.rig import Rig, camera_poses
from ..kinematics.rom import RomEstimate, RomOptions, Topology, skeleton_from_range_of_motion
from ..kinematics.skeleton import JointType, Motion, Skeleton
from .rig import standard_rig

#: Range exercised per kind of segment (name without ``left_``/``right_``), degrees: the radius of a
#: ball joint's cone (its twist is half of it) or a hinge's flexion (positive, as in the CMU data).
ROM_AMPLITUDE_DEG = {
    "pelvis": 30.0, "torso": 40.0, "head": 40.0, "upper_arm": 70.0, "forearm": 120.0, "hand": 50.0,
    "thigh": 60.0, "shin": 110.0, "foot": 35.0,
}
DEFAULT_AMPLITUDE_DEG = 35.0
ROOT_HEIGHT_M = 0.95


def _kind(name: str) -> str:
    for side in ("left_", "right_"):
        if name.startswith(side):
            return name[len(side):]
    return name


def range_of_motion(
    skeleton: Skeleton,
    *,
    fps: float = 60.0,
    hold_seconds: float = 1.0,
    seconds_per_joint: float = 3.0,
    exercised: Sequence[str] | None = None,
    amplitude_scale: float = 1.0,
) -> tuple[Motion, np.ndarray]:
    """A range-of-motion motion for ``skeleton``: rest hold, then each joint in turn, then a short hold.

    Args:
        skeleton: the subject's true skeleton.
        fps: frame rate (Hz).
        hold_seconds: length of the initial rest-pose hold (the rest frames).
        seconds_per_joint: time each segment's joint is exercised.
        exercised: segments whose joints move (default: all but FIXED ones; the root's slot turns,
            bends and shifts the whole body). Leaving one out simulates a joint the subject forgot.
        amplitude_scale: multiplies every range of :data:`ROM_AMPLITUDE_DEG`.

    Returns:
        The ``(T, J)`` motion and the indices of its rest frames.
    """
    if exercised is None:
        exercised = [n for n, t in zip(skeleton.names, skeleton.joint_types) if t != JointType.FIXED]
    order = [skeleton.index(n) for n in exercised]
    hold = max(int(round(hold_seconds * fps)), 1)
    per = max(int(round(seconds_per_joint * fps)), 4)
    total = hold + per * len(order) + hold // 2
    rot = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (total, skeleton.num_segments, 1))
    pos = np.tile(np.array([0.0, 0.0, ROOT_HEIGHT_M]), (total, 1))
    u = (np.arange(per) + 0.5) / per
    envelope = np.sin(np.pi * u) ** 2
    for slot, j in enumerate(order):
        frames = slice(hold + slot * per, hold + (slot + 1) * per)
        amp = np.deg2rad(ROM_AMPLITUDE_DEG.get(_kind(skeleton.names[j]), DEFAULT_AMPLITUDE_DEG)) * amplitude_scale
        if skeleton.joint_types[j] == JointType.HINGE:
            angle = amp * (1.0 - np.cos(4.0 * np.pi * u)) / 2.0
            rotvec = angle[:, None] * np.asarray(skeleton.hinge_axes[j])
        else:
            rotvec = amp * envelope[:, None] * np.stack(
                [np.cos(4.0 * np.pi * u), np.sin(4.0 * np.pi * u), 0.5 * np.sin(6.0 * np.pi * u)], axis=1
            )
        rot[frames, j] = np.asarray(SO3.exp(jnp.asarray(rotvec)).wxyz)
        if j == 0:
            pos[frames] += 0.2 * envelope[:, None] * np.stack([np.sin(2 * np.pi * u), np.cos(2 * np.pi * u), 0 * u], 1)
    return Motion(pos, rot), np.arange(hold)


@dataclasses.dataclass
class RangeOfMotionTrial:
    """A simulated range-of-motion trial with its ground truth.

    Attributes:
        skeleton, rig: the true model. motion: the true ``(T, J)`` motion.
        world_from_camera: ``(T, C, 7)`` noisy registered camera poses (NaN where unregistered).
        registered: ``(T, C)`` bool. outliers: ``(T, C)`` bool, grossly wrong registrations.
        rest_frames: frames in the rest pose. fps: frame rate (Hz).
        root_origin: the root's children whose joint is the true skeleton's root origin (None: their mean).
    """

    skeleton: Skeleton
    rig: Rig
    motion: Motion
    world_from_camera: np.ndarray
    registered: np.ndarray
    outliers: np.ndarray
    rest_frames: np.ndarray
    fps: float
    root_origin: tuple[str, ...] | None

    @property
    def num_frames(self) -> int:
        return self.motion.num_frames

    @property
    def assignment(self) -> dict[str, str]:
        """Camera name → segment name (the hardware setup: which limb each camera is strapped to)."""
        return {c: self.skeleton.names[s] for c, s in zip(self.rig.names, self.rig.segments)}

    def estimate(self, options: RomOptions = RomOptions(), **kwargs) -> RomEstimate:
        """:func:`~bcmocap.kinematics.rom.skeleton_from_range_of_motion` on this trial (same topology, intrinsics)."""
        kwargs.setdefault("root_origin", self.root_origin)
        return skeleton_from_range_of_motion(
            Topology.from_skeleton(self.skeleton), self.assignment, self.world_from_camera, self.registered,
            rest_frames=self.rest_frames, intrinsics=self.rig.intrinsics, options=options, **kwargs,
        )


def sfm_like_poses(
    true_poses: SE3,
    rng: np.random.Generator,
    *,
    rotation_sigma_deg: float = 1.0,
    position_sigma_m: float = 0.01,
    missing_fraction: float = 0.1,
    outlier_fraction: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True camera poses ``(T, C)`` degraded like structure-from-motion output.

    Args:
        true_poses: ``(T, C)`` world_from_camera.
        rng: the source of every random draw.
        rotation_sigma_deg, position_sigma_m: noise of registered poses (per axis; rotation right-multiplied).
        missing_fraction: share of camera-frames left unregistered (independently per camera and frame).
        outlier_fraction: share of registered camera-frames replaced by gross errors (5–30°, 10–50 cm).

    Returns:
        ``(T, C, 7)`` poses (NaN where unregistered), ``(T, C)`` registered, ``(T, C)`` outliers.
    """
    t, c = true_poses.wxyz_xyz.shape[:2]
    rot_noise = np.deg2rad(rotation_sigma_deg) * rng.normal(size=(t, c, 3))
    pos_noise = position_sigma_m * rng.normal(size=(t, c, 3))
    registered = rng.random((t, c)) >= missing_fraction
    outliers = registered & (rng.random((t, c)) < outlier_fraction)
    axis = rng.normal(size=(t, c, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    direction = rng.normal(size=(t, c, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    rot_noise = np.where(outliers[..., None], axis * np.deg2rad(rng.uniform(5.0, 30.0, (t, c, 1))), rot_noise)
    pos_noise = np.where(outliers[..., None], direction * rng.uniform(0.1, 0.5, (t, c, 1)), pos_noise)
    noisy = SE3.from_rotation_and_translation(
        true_poses.rotation() @ SO3.exp(jnp.asarray(rot_noise)), true_poses.translation() + pos_noise
    )
    return np.where(registered[..., None], np.asarray(noisy.wxyz_xyz), np.nan), registered, outliers


def range_of_motion_trial(
    skeleton: Skeleton | None = None,
    rig: Rig | None = None,
    *,
    motion: str = "walk",
    fps: float = 60.0,
    hold_seconds: float = 1.0,
    seconds_per_joint: float = 3.0,
    exercised: Sequence[str] | None = None,
    rotation_sigma_deg: float = 1.0,
    position_sigma_m: float = 0.01,
    missing_fraction: float = 0.1,
    outlier_fraction: float = 0.0,
    seed: int = 0,
) -> RangeOfMotionTrial:
    """Simulate a range-of-motion trial seen through SfM-like camera poses.

    Args:
        skeleton: the subject (default: the camera skeleton of the bundled CMU trial ``motion``, so
            the trial matches :func:`~bcmocap.sim.standard_capture` of that motion).
        rig: the cameras (default: :func:`~bcmocap.sim.standard_rig` of the skeleton).
        motion: bundled CMU trial whose subject is used when ``skeleton`` is None.
        fps, hold_seconds, seconds_per_joint, exercised: see :func:`range_of_motion`.
        rotation_sigma_deg, position_sigma_m: noise of registered poses (per axis).
        missing_fraction: share of camera-frames left unregistered (independently per camera and frame).
        outlier_fraction: share of registered camera-frames replaced by gross errors (5–30°, 10–50 cm).
        seed: random seed.
    """
    if skeleton is None:
        from .motions import load_body_motion

        skeleton, _ = load_body_motion(motion, fps=fps, seconds=0.05)
    rig = standard_rig(skeleton) if rig is None else rig
    rig.check(skeleton)
    truth, rest_frames = range_of_motion(
        skeleton, fps=fps, hold_seconds=hold_seconds, seconds_per_joint=seconds_per_joint, exercised=exercised
    )
    poses, registered, outliers = sfm_like_poses(
        camera_poses(skeleton, rig, truth), np.random.default_rng(seed), rotation_sigma_deg=rotation_sigma_deg,
        position_sigma_m=position_sigma_m, missing_fraction=missing_fraction, outlier_fraction=outlier_fraction)
    root_kids = [k for k in skeleton.children(0) if np.linalg.norm(np.asarray(skeleton.offsets[k])) < 1e-9]
    root_origin = (skeleton.names[root_kids[0]],) if root_kids else None
    return RangeOfMotionTrial(skeleton, rig, truth, poses, registered, outliers, rest_frames, fps, root_origin)


def _bones(skeleton: Skeleton) -> list[tuple[str, int, int]]:
    """(name, segment a, segment b): distances between joint centres on one segment (root: between its children)."""
    out = []
    for j in range(skeleton.num_segments):
        kids = skeleton.children(j)
        if j == 0:
            out += [(f"{skeleton.names[a]}~{skeleton.names[b]}", a, b) for i, a in enumerate(kids) for b in kids[i + 1:]]
        else:
            out += [(f"{skeleton.names[j]}→{skeleton.names[k]}", j, k) for k in kids]
    return out


def _joint_world_rest(skeleton: Skeleton) -> np.ndarray:
    """Joint positions at rest as offsets composed along the chain (all frames parallel at rest)."""
    pos = np.zeros((skeleton.num_segments, 3))
    for j in range(1, skeleton.num_segments):
        pos[j] = pos[skeleton.parents[j]] + np.asarray(skeleton.offsets[j])
    return pos


def skeleton_errors(truth: Skeleton, truth_rig: Rig, estimate: Skeleton, estimate_mounts: np.ndarray) -> dict:
    """How far an estimated skeleton and its mounts are from the truth (same topology and camera order).

    Joint centres are compared where the algorithm measures them, in the frames of the cameras on the
    joint's parent and child segments (independent of how segment frames are oriented); bone lengths
    are distances between joint centres on one segment (for the root: between its children's joints,
    since its own origin is a convention); mount rotations compare ``segment_from_camera`` directly,
    which assumes the estimate's segment frames follow the truth's convention (parallel in the rest
    pose), as :func:`~bcmocap.kinematics.rom.skeleton_from_range_of_motion` builds them.

    Returns:
        dict with ``joint_centre_m`` (joint name → mean error over those cameras, m),
        ``bone_length_pct`` (bone name → |error| in % of the true length), ``mount_rotation_deg``
        (camera → angle), ``mount_translation_m`` (camera → distance), ``hinge_axis_deg`` (joint → angle).
    """
    if estimate.names != truth.names or estimate.parents != truth.parents:
        raise ValueError("skeleton_errors: the estimate and the truth have different topologies")
    est_mounts = np.asarray(estimate_mounts, dtype=np.float64)
    true_mounts = np.asarray(truth_rig.segment_from_camera)
    if est_mounts.shape != true_mounts.shape:
        raise ValueError(f"skeleton_errors: {est_mounts.shape[0]} estimated mounts for {truth_rig.num_cameras} cameras")
    est_cam, true_cam = invert_pose(est_mounts), invert_pose(true_mounts)
    centre = {}
    for j in range(1, truth.num_segments):
        p = truth.parents[j]
        errs = []
        for c, s in enumerate(truth_rig.segments):
            if s not in (j, p):
                continue
            est_pt = np.zeros(3) if s == j else np.asarray(estimate.offsets[j])
            true_pt = np.zeros(3) if s == j else np.asarray(truth.offsets[j])
            errs.append(np.linalg.norm(apply_pose(est_cam[c], est_pt) - apply_pose(true_cam[c], true_pt)))
        centre[truth.names[j]] = float(np.mean(errs)) if errs else float("nan")
    est_rest, true_rest = _joint_world_rest(estimate), _joint_world_rest(truth)
    bones = {}
    for name, a, b in _bones(truth):
        true_len = np.linalg.norm(true_rest[b] - true_rest[a])
        if true_len > 0.01:
            bones[name] = float(100.0 * abs(np.linalg.norm(est_rest[b] - est_rest[a]) - true_len) / true_len)
    rel = quat_multiply(quat_conjugate(est_mounts[:, :4]), true_mounts[:, :4])
    rot = np.rad2deg(2.0 * np.arctan2(np.linalg.norm(rel[:, 1:], axis=-1), np.abs(rel[:, 0])))
    trans = np.linalg.norm(est_mounts[:, 4:] - true_mounts[:, 4:], axis=-1)
    axes = {}
    for j in range(truth.num_segments):
        if truth.joint_types[j] == JointType.HINGE:
            cos = abs(float(np.dot(np.asarray(truth.hinge_axes[j]), np.asarray(estimate.hinge_axes[j]))))
            axes[truth.names[j]] = float(np.rad2deg(np.arccos(min(cos, 1.0))))
    return {
        "joint_centre_m": centre,
        "bone_length_pct": bones,
        "mount_rotation_deg": dict(zip(truth_rig.names, rot.tolist())),
        "mount_translation_m": dict(zip(truth_rig.names, trans.tolist())),
        "hinge_axis_deg": axes,
    }
