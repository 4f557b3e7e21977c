"""Real CMU motions for synthetic captures, reduced to the body-mounted-camera skeleton.

The paper uses a predefined kinematic structure with one or more cameras per link (Fig. 2c). CMU's
31-bone skeleton has links no camera sees (fingers, toes, clavicles, three spine bones); the ground
truth is therefore the CMU motion *reduced* to the camera skeleton: each kept segment takes the world
orientation of one CMU bone and its joint sits where a CMU joint sits at rest. The result is an exactly
representable, rigid "Vicon-style" ground truth with real human joint trajectories.
"""

from __future__ import annotations

import dataclasses
from importlib import resources
from pathlib import Path


import numpy as np

from ..geometry import SO3, slerp
from ..kinematics.fk import forward_kinematics
from ..kinematics.skeleton import JointType, Motion, Skeleton

#: Bundled CMU trials (frames at 120 Hz): name → (ASF, AMC, description).
CMU_TRIALS = {
    "walk": ("35.asf", "35_01.amc", "subject 35 trial 01, walking"),
    "run": ("02.asf", "02_03.amc", "subject 02 trial 03, running/jogging"),
    "jump": ("02.asf", "02_04.amc", "subject 02 trial 04, jumping and balancing"),
}
CMU_FPS = 120.0


@dataclasses.dataclass(frozen=True)
class BodySegment:
    """A segment of the camera skeleton defined from CMU bones.

    Attributes:
        name: segment name; parent: parent segment name (None for the root).
        orientation_bone: the CMU bone whose world orientation the segment takes.
        joint_bone: the CMU bone whose joint (start) is this segment's joint.
        joint_type: BALL, HINGE (axis from the CMU bone's single DOF) or FREE for the root.
    """

    name: str
    parent: str | None
    orientation_bone: str
    joint_bone: str
    joint_type: JointType


#: The camera skeleton of the standard capture: pelvis, torso, head, and per side upper arm,
#: forearm (hinge elbow), hand, thigh, shin (hinge knee), foot — 15 segments, 40 DOFs.
BODY_SEGMENTS: tuple[BodySegment, ...] = (
    BodySegment("pelvis", None, "root", "root", JointType.FREE),
    BodySegment("torso", "pelvis", "thorax", "lowerback", JointType.BALL),
    BodySegment("head", "torso", "head", "lowerneck", JointType.BALL),
    *(
        seg
        for side, s in (("left", "l"), ("right", "r"))
        for seg in (
            BodySegment(f"{side}_upper_arm", "torso", f"{s}humerus", f"{s}humerus", JointType.BALL),
            BodySegment(f"{side}_forearm", f"{side}_upper_arm", f"{s}radius", f"{s}radius", JointType.HINGE),
            BodySegment(f"{side}_hand", f"{side}_forearm", f"{s}hand", f"{s}wrist", JointType.BALL),
            BodySegment(f"{side}_thigh", "pelvis", f"{s}femur", f"{s}femur", JointType.BALL),
            BodySegment(f"{side}_shin", f"{side}_thigh", f"{s}tibia", f"{s}tibia", JointType.HINGE),
            BodySegment(f"{side}_foot", f"{side}_shin", f"{s}foot", f"{s}foot", JointType.BALL),
        )
    ),
)


def _sorted_segments(segments):
    order, placed = [], set()
    pending = list(segments)
    while pending:
        progressed = False
        for seg in list(pending):
            if seg.parent is None or seg.parent in placed:
                order.append(seg)
                placed.add(seg.name)
                pending.remove(seg)
                progressed = True
        if not progressed:
            raise ValueError(f"body segments with unknown parents: {[s.name for s in pending]}")
    return order


def reduce_motion(
    skeleton: Skeleton, motion: Motion, segments: tuple[BodySegment, ...] = BODY_SEGMENTS
) -> tuple[Skeleton, Motion]:
    """Reduce a full (e.g. CMU) skeleton and motion to a coarser skeleton.

    Args:
        skeleton, motion: the full skeleton and a ``(T, J_full)`` motion of it.
        segments: the reduced segments (any order; parents are placed first).

    Returns:
        The reduced skeleton and its ``(T, J)`` motion. Hinge rotations are projected on their axis.
    """
    segments = _sorted_segments(segments)
    names = [s.name for s in segments]
    rest = np.asarray(forward_kinematics(skeleton, skeleton.rest_motion()).translation())
    world = forward_kinematics(skeleton, motion)
    world_rot = np.asarray(world.rotation().wxyz)
    parents, offsets, types, axes, orient = [], [], [], [], []
    for seg in segments:
        j_bone = skeleton.index(seg.joint_bone)
        o_bone = skeleton.index(seg.orientation_bone)
        parent = -1 if seg.parent is None else names.index(seg.parent)
        parents.append(parent)
        if parent < 0:
            offsets.append(np.zeros(3))
        else:
            parent_joint = skeleton.index(segments[parent].joint_bone)
            offsets.append(rest[j_bone] - rest[parent_joint])
        types.append(seg.joint_type)
        if seg.joint_type == JointType.HINGE:
            if skeleton.joint_types[o_bone] != JointType.HINGE:
                raise ValueError(f"reduce_motion: '{seg.name}' is a hinge but bone '{seg.orientation_bone}' is not")
            axes.append(np.asarray(skeleton.hinge_axes[o_bone]))
        else:
            axes.append(np.zeros(3))
        orient.append(o_bone)
    reduced = Skeleton(names, parents, np.stack(offsets), types, np.stack(axes))
    seg_world = world_rot[:, orient]  # (T, J, 4)
    local = np.array(seg_world)
    parent_idx = np.array([max(p, 0) for p in parents])
    rel = (SO3(seg_world[:, parent_idx]).inverse() @ SO3(seg_world)).wxyz
    local[:, 1:] = np.asarray(rel)[:, 1:]
    local = np.asarray(reduced.project_rotations(local))
    root_pos = np.asarray(world.translation())[:, skeleton.index(segments[0].joint_bone)]
    return reduced, Motion(root_pos, local)


def resample(motion: Motion, source_fps: float, target_fps: float) -> Motion:
    """Resample a motion in time: linear for the root position, slerp for rotations."""
    n = motion.num_frames
    duration = (n - 1) / source_fps
    t = np.arange(0.0, duration + 1e-9, 1.0 / target_fps) * source_fps
    i0 = np.minimum(np.floor(t).astype(int), n - 1)
    i1 = np.minimum(i0 + 1, n - 1)
    frac = t - i0
    root = np.asarray(motion.root_position)
    rot = np.asarray(motion.rotations)
    position = root[i0] * (1 - frac[:, None]) + root[i1] * frac[:, None]
    rotations = slerp(rot[i0], rot[i1], np.broadcast_to(frac[:, None], (len(t), rot.shape[1])))
    return Motion(position, rotations)


def cmu_trial_path(name: str) -> tuple[Path, Path]:
    """Paths of a bundled CMU trial's ASF and AMC files."""
    if name not in CMU_TRIALS:
        raise ValueError(f"unknown CMU trial '{name}'; bundled trials: {sorted(CMU_TRIALS)}")
    asf, amc, _ = CMU_TRIALS[name]
    base = resources.files("bcmocap") / "data" / "cmu"
    return Path(str(base / asf)), Path(str(base / amc))


def back_and_forth(motion: Motion, num_frames: int) -> Motion:
    """Extend a motion to ``num_frames`` by playing it forward, then backward, and so on.

    Positions and rotations stay continuous (no seam), so long benchmark sequences can be built from a
    short real trial; the backward passes are the same real poses in reverse order.
    """
    n = motion.num_frames
    if n < 2:
        raise ValueError("back_and_forth: the motion needs at least 2 frames")
    period = 2 * n - 2
    idx = np.arange(num_frames) % period
    return motion[np.where(idx < n, idx, period - idx)]


def load_body_motion(
    name: str, *, fps: float = 60.0, seconds: float | None = None, start_seconds: float = 0.0, repeat: bool = False
) -> tuple[Skeleton, Motion]:
    """A bundled CMU trial reduced to the camera skeleton and resampled.

    Args:
        name: "walk", "run" or "jump" (see :data:`CMU_TRIALS`).
        fps: output frame rate.
        seconds: length to keep (None: all), starting at ``start_seconds``.
        repeat: if ``seconds`` is longer than the trial, extend it with :func:`back_and_forth`
            (otherwise the trial's own length is the limit).
    """
    from ..io.asf import load_cmu

    asf, amc = cmu_trial_path(name)
    full_skeleton, full_motion = load_cmu(asf, amc, fps=CMU_FPS)
    first = int(round(start_seconds * CMU_FPS))
    last = full_motion.num_frames if seconds is None else min(full_motion.num_frames, first + int(round(seconds * CMU_FPS)) + 1)
    if last - first < 2:
        raise ValueError(f"CMU trial '{name}' has {full_motion.num_frames} frames; nothing left from {start_seconds} s")
    skeleton, motion = reduce_motion(full_skeleton, full_motion[first:last])
    motion = resample(motion, CMU_FPS, fps)
    if seconds is not None:
        wanted = int(round(seconds * fps))
        motion = back_and_forth(motion, wanted) if repeat and wanted > motion.num_frames else motion[:wanted]
    return skeleton, motion


