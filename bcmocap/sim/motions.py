"""Real CMU motions for synthetic captures, reduced to the body-mounted-camera skeleton.

The paper uses a predefined kinematic structure with one or more cameras per link (Fig. 2c). CMU's
31-bone skeleton has links no camera sees (fingers, toes, clavicles, three spine bones); the ground
truth is therefore the CMU motion *reduced* to the camera skeleton: each kept segment takes the world
orientation of one CMU bone and its joint sits where a CMU joint sits at rest. The result is an exactly
representable, rigid "Vicon-style" ground truth with real human joint trajectories.

Besides the bundled trials, :func:`load_motion_file` reduces any BVH file or ASF/AMC pair of a human
skeleton whose bones carry one of the usual names (CMU's ASF bones, CMU's BVH conversions, Mixamo,
Unity-like rigs: :data:`BONE_ALIASES`); knees and elbows given as 3-DOF joints become hinges about the
axis they mostly turn about (:func:`reduce_motion` with ``fit_hinges``).

The bundled trials (:data:`CMU_TRIALS`). Walking (35_01), running (02_03) and a two-footed jump (02_04) each
keep one heading (pelvis yaw within 15 deg over the trial). The trunk leans at most 66 deg, in the jump's
crouch, and a wrist rises above the neck in 5 % of the jump's frames only. Two more trials exercise what those
three do not (figures at 60 fps over the bundled excerpts):

- ``scoop`` (02_06, "bend over, scoop up, rise, lift arm", its first 5 s): the subject bends to the floor twice
  and lifts the right arm overhead in between. The trunk leans up to 106 deg from vertical (median 41 deg)
  and the pelvis drops from 1.0 to 0.6 m. The right wrist comes within 6 cm of the floor, then rises to 1.83 m,
  0.5 m above the neck (a wrist is above the neck in 31 % of the frames). Torso and head cameras face the
  floor; the camera skeleton's one rigid torso departs most from CMU's three spine bones here (wrists up to
  11 cm from CMU's, against 6 cm in ``hop``).
- ``hop`` (131_03, "start, hop, stop", a dance, from 0.8 s): the subject stands on the left foot for 40 % of the
  frames while the right leg kicks, leaps with both feet off the floor (0.3 m up) and spins on one foot. The
  heading sweeps 475 deg (net -355 deg), turning at up to 490 deg/s. This tests single-leg support, views
  that sweep the whole room, and the blur and rolling shutter of fast camera rotation. The trial is a BVH
  conversion, so its knees and elbows are fitted hinges; the fit is exact (CMU's knees and elbows have one
  DOF) and moves no wrist or ankle relative to its joint.

Subject 01's "forward jumps, turn around" (01_01) was left out: it repeats the two-footed jump and turns at
walking speed, and CMU's index warns that its lower-numbered subjects "may not be as high quality".
"""

from __future__ import annotations

import dataclasses
import os
from importlib import resources
from pathlib import Path


import numpy as np

from ..geometry import SE3, SO3, slerp
from ..kinematics.fk import forward_kinematics
from ..kinematics.skeleton import JointType, Motion, Skeleton

#: Bundled CMU trials (frames at 120 Hz, files in ``bcmocap/data/cmu``): name → (ASF, AMC, description), or
#: (None, BVH, description) for a BVH conversion, whose one file holds the skeleton and the motion.
CMU_TRIALS = {
    "walk": ("35.asf", "35_01.amc", "subject 35 trial 01, walking"),
    "run": ("02.asf", "02_03.amc", "subject 02 trial 03, running/jogging"),
    "jump": ("02.asf", "02_04.amc", "subject 02 trial 04, jumping and balancing"),
    "scoop": ("02.asf", "02_06_first600.amc", "subject 02 trial 06, first 5 s: bend over, scoop up, rise, lift arm"),
    "hop": (None, "131_03_from97.bvh", "subject 131 trial 03 from 0.8 s: kicks on one leg, a leap, a spin"),
}
CMU_FPS = 120.0
CMU_UNIT_M = 0.0254 / 0.45  # CMU's length unit, 1/0.45 inch (m): the ASF files state it, the BVH conversions do not


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


def _fitted_hinge_axis(relative_wxyz: np.ndarray) -> np.ndarray:
    """Unit axis (child frame) about which rotations ``(T, 4)`` mostly turn: the principal direction of their
    rotation vectors, signed so that the mean angle about it is positive (flexion positive)."""
    rotvec = np.asarray(SO3(relative_wxyz).log())
    _, _, vt = np.linalg.svd(rotvec, full_matrices=False)
    axis = vt[0]
    return axis if np.mean(rotvec @ axis) >= 0 else -axis


def reduce_motion(
    skeleton: Skeleton, motion: Motion, segments: tuple[BodySegment, ...] = BODY_SEGMENTS, *, fit_hinges: bool = False
) -> tuple[Skeleton, Motion]:
    """Reduce a full (e.g. CMU) skeleton and motion to a coarser skeleton.

    Args:
        skeleton, motion: the full skeleton and a ``(T, J_full)`` motion of it.
        segments: the reduced segments (any order; parents are placed first).
        fit_hinges: a HINGE segment whose bone is not a hinge (a BVH knee with three rotation channels)
            turns about the principal axis of its rotations relative to its parent over the motion;
            without it such a segment is refused.

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
            if skeleton.joint_types[o_bone] == JointType.HINGE:
                axes.append(np.asarray(skeleton.hinge_axes[o_bone]))
            elif fit_hinges and parent >= 0:
                parent_bone = orient[parent]
                axes.append(_fitted_hinge_axis(np.asarray(
                    (SO3(world_rot[:, parent_bone]).inverse() @ SO3(world_rot[:, o_bone])).wxyz)))
            else:
                raise ValueError(f"reduce_motion: '{seg.name}' is a hinge but bone '{seg.orientation_bone}' is not")
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


ARM_T_POSE_TOLERANCE_DEG = 20.0  # an upper arm further than this from sideways at rest is turned into the T-pose


def arms_in_t_pose(skeleton: Skeleton, motion: Motion) -> tuple[Skeleton, Motion]:
    """The same body and motion with a T-pose rest: arms straight out sideways with all joint angles zero.

    The studio's rig mounts arm cameras on the arm's upper side at rest and its range-of-motion trial starts in the
    rest pose (the T-pose, :mod:`bcmocap.sim.rom`). Some files rest with the arms hanging (CMU's BVH conversions), so
    each arm whose upper arm is more than :data:`ARM_T_POSE_TOLERANCE_DEG` from sideways at rest is turned about its
    shoulder by the rotation ``A`` that takes it sideways: the arm's offsets and hinge axes become ``A`` times
    theirs, the upper arm's local rotations ``L A⁻¹`` and the forearm's and hand's ``A L A⁻¹``. Every segment's
    world motion is unchanged; only the arm segments' frames turn with their rest. Arms already sideways (the ASF
    trials) are left exactly as they are.

    Args:
        skeleton: a camera skeleton with the segment names of :data:`BODY_SEGMENTS`; motion: its ``(T, J)`` motion.
    """
    from .rig import body_axes

    rest = np.asarray(forward_kinematics(skeleton, skeleton.rest_motion()).translation())
    _, left, _ = body_axes(skeleton)
    offsets, axes = np.array(skeleton.offsets), np.array(skeleton.hinge_axes)
    rotations = np.array(motion.rotations)
    for side, sign in (("left", 1.0), ("right", -1.0)):
        upper, forearm, hand = (skeleton.index(f"{side}_{s}") for s in ("upper_arm", "forearm", "hand"))
        along = rest[forearm] - rest[upper]
        along /= np.linalg.norm(along)
        target = sign * left
        angle = float(np.arccos(np.clip(along @ target, -1.0, 1.0)))
        if np.degrees(angle) <= ARM_T_POSE_TOLERANCE_DEG:
            continue
        axis = np.cross(along, target)
        if np.linalg.norm(axis) < 1e-9:  # the arm points straight across the body: turn it about the vertical
            axis = np.array([0.0, 0.0, 1.0])
        turn = SO3.exp(angle * axis / np.linalg.norm(axis))
        matrix = np.asarray(turn.as_matrix())
        for j in (forearm, hand):
            offsets[j] = matrix @ offsets[j]
        for j in (upper, forearm, hand):
            axes[j] = matrix @ axes[j]
            local = SO3(rotations[:, j]) @ turn.inverse()
            rotations[:, j] = np.asarray((local if j == upper else turn @ local).wxyz)
    if np.array_equal(offsets, np.asarray(skeleton.offsets)):
        return skeleton, motion
    turned = Skeleton(skeleton.names, skeleton.parents, offsets, skeleton.joint_types, axes)
    return turned, Motion(np.asarray(motion.root_position), rotations)


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


def cmu_trial_path(name: str) -> tuple[Path, ...]:
    """Paths of a bundled CMU trial's files: ``(ASF, AMC)``, or ``(BVH,)`` for a BVH conversion."""
    if name not in CMU_TRIALS:
        raise ValueError(f"unknown CMU trial '{name}'; bundled trials: {sorted(CMU_TRIALS)}")
    asf, motion, _ = CMU_TRIALS[name]
    base = resources.files("bcmocap") / "data" / "cmu"
    return tuple(Path(str(base / f)) for f in (asf, motion) if f is not None)


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
        name: "walk", "run", "jump", "scoop" or "hop" (see :data:`CMU_TRIALS`).
        fps: output frame rate.
        seconds: length to keep (None: all), starting at ``start_seconds``.
        repeat: if ``seconds`` is longer than the trial, extend it with :func:`back_and_forth`
            (otherwise the trial's own length is the limit).

    A BVH trial keeps CMU's floor, as the ASF/AMC trials do. Its hinges are fitted over the whole trial, so
    the skeleton does not depend on ``seconds`` or ``start_seconds``.
    """
    from ..io.asf import load_cmu

    paths = cmu_trial_path(name)
    if len(paths) == 1:
        full_skeleton, full_motion, _ = _read_motion_source((str(paths[0]),), CMU_FPS, CMU_UNIT_M)
    else:
        full_skeleton, full_motion = load_cmu(*paths, fps=CMU_FPS)
    first = int(round(start_seconds * CMU_FPS))
    last = full_motion.num_frames if seconds is None else min(full_motion.num_frames, first + int(round(seconds * CMU_FPS)) + 1)
    if last - first < 2:
        raise ValueError(f"CMU trial '{name}' has {full_motion.num_frames} frames; nothing left from {start_seconds} s")
    if len(paths) == 1:
        segments = _body_segments_for(full_skeleton, str(paths[0]))
        skeleton, motion = arms_in_t_pose(*reduce_motion(full_skeleton, full_motion, segments, fit_hinges=True))
        motion = motion[first:last]
    else:
        skeleton, motion = reduce_motion(full_skeleton, full_motion[first:last])
    motion = resample(motion, CMU_FPS, fps)
    if seconds is not None:
        wanted = int(round(seconds * fps))
        motion = back_and_forth(motion, wanted) if repeat and wanted > motion.num_frames else motion[:wanted]
    return skeleton, motion




#: Names a motion file may give each CMU ASF bone that :data:`BODY_SEGMENTS` uses, first match wins; matched
#: without case, namespace (``mixamorig:``) or punctuation; ``{side}`` is ``left``/``l`` or ``right``/``r``, as a
#: prefix or a suffix (``LeftArm``, ``larm``, ``upperarm_l``). The root bone is always the file's first segment.
#: CMU's BVH conversions name bones by the joint they start at (``LeftHip`` is the thigh, ``LeftShoulder`` the
#: upper arm); Mixamo's ``LeftShoulder`` is the clavicle, so ``arm`` names are tried before ``shoulder``.
BONE_ALIASES: dict[str, tuple[str, ...]] = {
    "thorax": ("thorax", "chest2", "spine2", "upperchest", "spine1", "chest", "spine"),
    "lowerback": ("lowerback", "spine", "abdomen", "chest"),
    "head": ("head",),
    "lowerneck": ("lowerneck", "neck", "neck1"),
    "{s}humerus": ("{s}humerus", "{side}arm", "{side}upperarm", "{side}shoulder"),
    "{s}radius": ("{s}radius", "{side}forearm", "{side}lowerarm", "{side}elbow"),
    "{s}hand": ("{s}hand", "{side}hand"),
    "{s}wrist": ("{s}wrist", "{side}wrist", "{side}hand"),
    "{s}femur": ("{s}femur", "{side}upleg", "{side}upperleg", "{side}thigh", "{side}hip"),
    "{s}tibia": ("{s}tibia", "{side}leg", "{side}lowerleg", "{side}shin", "{side}knee"),
    "{s}foot": ("{s}foot", "{side}foot", "{side}ankle"),
}
#: Length units a BVH file may be written in (m per unit): metres, centimetres, millimetres, inches, CMU's 1/0.45 inch.
BVH_UNITS_M = (1.0, 0.01, 0.001, 0.0254, 0.0254 / 0.45)
_SUBJECT_HEIGHT_M = 1.7  # the unit guessed for a BVH file makes its rest pose closest to this height
_SIDES = {"l": ("left", "l"), "r": ("right", "r")}


def _normalised(name: str) -> str:
    return "".join(ch for ch in name.rsplit(":", 1)[-1].rsplit("|", 1)[-1].lower() if ch.isalnum())


def _find_bone(skeleton: Skeleton, cmu_bone: str, where: str) -> str:
    """The name in ``skeleton`` of the bone CMU's ASF calls ``cmu_bone`` (see :data:`BONE_ALIASES`)."""
    if cmu_bone == "root":
        return skeleton.names[0]
    lookup = {_normalised(n): n for n in reversed(skeleton.names)}  # the first segment of a name wins
    s = cmu_bone[0] if cmu_bone[0] in _SIDES and cmu_bone[1:] and f"{{s}}{cmu_bone[1:]}" in BONE_ALIASES else ""
    template = f"{{s}}{cmu_bone[1:]}" if s else cmu_bone
    for pattern in BONE_ALIASES[template]:
        if "{side}" in pattern:
            base = pattern.replace("{side}", "")
            names = [f"{side}{base}" for side in _SIDES[s]] + [f"{base}{side}" for side in _SIDES[s]]
        else:
            names = [pattern.replace("{s}", s)]
        for candidate in names:
            if candidate in lookup:
                return lookup[candidate]
    tried = ", ".join(p.replace("{s}", s).replace("{side}", _SIDES[s][0] if s else "") for p in BONE_ALIASES[template])
    raise ValueError(f"{where}: no bone for the body's '{cmu_bone}' (tried {tried}); bones: {list(skeleton.names)}")


def _body_segments_for(skeleton: Skeleton, where: str) -> tuple[BodySegment, ...]:
    """:data:`BODY_SEGMENTS` with the bone names of ``skeleton``."""
    return tuple(dataclasses.replace(seg, orientation_bone=_find_bone(skeleton, seg.orientation_bone, where),
                                     joint_bone=_find_bone(skeleton, seg.joint_bone, where))
                 for seg in BODY_SEGMENTS)


def _on_the_floor(skeleton: Skeleton, motion: Motion) -> Motion:
    """``motion`` moved up or down so that the lowest point of the body's capsules over it touches z = 0."""
    from .observe import body_capsules

    caps = body_capsules(skeleton)
    world = np.asarray(forward_kinematics(skeleton, motion).wxyz_xyz)  # (T, J, 7)
    low = np.inf
    for cap in caps:
        ends = np.asarray(SE3(world[:, cap.segment]) @ np.array([cap.a, cap.b], np.float64)[:, None])  # (2, T, 3)
        low = min(low, float(ends[..., 2].min()) - cap.radius)
    root = np.asarray(motion.root_position) - np.array([0.0, 0.0, low])
    return Motion(root, np.asarray(motion.rotations))


def _read_motion_source(paths: tuple[str, ...], source_fps: float, unit_m: float) -> tuple[Skeleton, Motion, float]:
    """``(full skeleton, full motion, its frame rate)`` of a BVH file or an ASF/AMC pair."""
    if len(paths) == 1:
        from ..io.bvh import read_bvh

        path = Path(paths[0])
        if not path.is_file():
            raise ValueError(f"{path}: missing (expected a BVH motion file)")
        if unit_m <= 0:
            probe = read_bvh(path, length_unit_m=1.0)
            rest = np.asarray(forward_kinematics(probe.skeleton, probe.skeleton.rest_motion()).translation())
            height = float(np.ptp(rest[:, 2]))
            if not height > 0:
                raise ValueError(f"{path}: the rest pose has no height (is the file Y up?)")
            unit_m = min(BVH_UNITS_M, key=lambda u: abs(np.log(height * u / _SUBJECT_HEIGHT_M)))
        data = read_bvh(path, length_unit_m=unit_m)
        return data.skeleton, data.motion, source_fps if source_fps > 0 else 1.0 / data.frame_time_s
    from ..io.asf import read_amc, read_asf

    for path in paths:
        if not Path(path).is_file():
            raise ValueError(f"{path}: missing (expected the {Path(path).suffix[1:].upper()} file of an ASF/AMC pair)")
    fps = source_fps if source_fps > 0 else CMU_FPS
    asf = read_asf(paths[0], length_unit_m=unit_m if unit_m > 0 else None)
    return asf.skeleton, read_amc(paths[1], asf, fps=fps), fps


def load_motion_file(
    paths: str | os.PathLike | tuple, *, fps: float = 60.0, seconds: float | None = None, repeat: bool = False,
    source_fps: float = 0.0, unit_m: float = 0.0,
) -> tuple[Skeleton, Motion]:
    """A human motion from a BVH file or an ASF/AMC pair, reduced to the camera skeleton and resampled.

    Bones are found by name (:data:`BONE_ALIASES`); 3-DOF knees and elbows become hinges about their
    principal axis (:func:`reduce_motion` with ``fit_hinges``). The motion is moved vertically so that the
    lowest point of the body over the motion touches the floor (z = 0), where the studio's room has it.

    Args:
        paths: a ``.bvh`` path, or the ``(.asf, .amc)`` paths of an Acclaim pair.
        fps: output frame rate (Hz).
        seconds: length to keep from the start (None: all); repeat: extend a shorter motion with
            :func:`back_and_forth`.
        source_fps: the file's frame rate (Hz); 0: a BVH file's ``Frame Time``, or CMU's 120 Hz for an AMC file.
        unit_m: metres per length unit of a BVH file; 0 guesses among :data:`BVH_UNITS_M` the one that makes
            the rest pose about 1.7 m tall. An ASF file states its unit (``:units length``); a positive
            ``unit_m`` replaces it.

    Raises:
        ValueError: naming the file when it is missing or malformed, or the body bone it has no name for.
    """
    paths = (str(paths),) if isinstance(paths, (str, os.PathLike)) else tuple(str(p) for p in paths)
    if len(paths) not in (1, 2):
        raise ValueError(f"load_motion_file: expected a BVH path or an (ASF, AMC) pair, got {paths!r}")
    full_skeleton, full_motion, source = _read_motion_source(paths, source_fps, unit_m)
    if full_motion.num_frames < 2:
        raise ValueError(f"{paths[-1]}: the motion has {full_motion.num_frames} frame(s); at least 2 are needed")
    last = full_motion.num_frames if seconds is None else min(full_motion.num_frames, int(round(seconds * source)) + 1)
    segments = _body_segments_for(full_skeleton, paths[0])
    skeleton, motion = reduce_motion(full_skeleton, full_motion[:last], segments, fit_hinges=True)
    rest = np.asarray(forward_kinematics(skeleton, skeleton.rest_motion()).translation())
    if rest[skeleton.index("head"), 2] <= rest[0, 2]:
        raise ValueError(f"{paths[0]}: the head is not above the pelvis at rest; the file must be Y up")
    skeleton, motion = arms_in_t_pose(skeleton, motion)
    motion = _on_the_floor(skeleton, resample(motion, source, fps))
    if seconds is not None:
        wanted = int(round(seconds * fps))
        motion = back_and_forth(motion, wanted) if repeat and wanted > motion.num_frames else motion[:wanted]
    return skeleton, motion
