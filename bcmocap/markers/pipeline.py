"""The whole optical-marker pipeline of Kirk et al.: trajectories in, skeleton and motion out.

    trajectories ──preprocess──▶ (merge identities) ──segment──▶ groups ──joint costs, MST──▶ topology
        ──re-solve joints on all frames──▶ joints ──rigid fit──▶ Skeleton + marker offsets ──IK──▶ Motion
        ──human template──▶ each segment's label and the verdict (human, or which limbs are wrong)

:func:`fit_marker_skeleton` runs it on a :class:`~bcmocap.markers.MarkerTrajectories` (from a C3D file via
:func:`bcmocap.io.read_c3d`, or from a ``(frames, markers, 3)`` array) and returns a
:class:`MarkerSkeleton`, which can write a BVH file, a JSON description and a text report.
"""

from __future__ import annotations

import dataclasses
import json
import re
import time
import warnings
from pathlib import Path

import numpy as np

from ..kinematics.fk import joint_positions
from ..kinematics.skeleton import Motion, Skeleton
from ..precision import require_float64
from . import files
from .anatomy import Anatomy, body_regions, label_anatomy, region_penalties, template_penalties
from .identities import IdentityMerge, concurrent_labels, merge_identities
from .ik import IkResult, initial_motion, solve_ik
from .label_hints import group_label_penalties, informative, marker_hints, marker_label_weights
from .joints import MIN_COVERAGE, MIN_FRAMES, JointSolution, joint_cost_matrix, minimum_spanning_tree, solve_joints
from .preprocess import MarkerTrajectories, PreprocessReport, preprocess
from .rigid import RigidSkeleton, build_skeleton
from .segmentation import Segmentation, least_rigid_pair, segment_markers

__all__ = ["MarkerOptions", "MarkerSkeleton", "fit_marker_skeleton"]


@dataclasses.dataclass(frozen=True)
class MarkerOptions:
    """Settings of :func:`fit_marker_skeleton` (defaults as in the paper where it gives them).

    Attributes:
        num_groups: number of segments, or None for the eigengap.
        max_groups: largest number of segments the eigengap may choose.
        trim_frames: frames trimmed at both ends of every visible stretch.
        min_run_seconds: markers never seen this long at a stretch are ignored.
        spike_threshold_m: jumps farther than this from the local median are removed (None: keep).
        merge: marker identity merging: "auto" (when more labels than the most whose spans, first to last
            frame seen, overlap: a labelled capture with gaps is not merged), "yes", "no".
        num_markers: physical markers for merging (None: the most labels whose spans overlap).
        merge_method: "linkage" or "spectral" (see :mod:`bcmocap.markers.identities`).
        num_samplings: jittered samplings for segmentation.
        segmentation_scale_m: σ of the segmentation affinity (None: from the data).
        min_coverage: a pair of markers (segmentation) or of groups (topology) whose frames seen together
            show less than this share of the motion around them is unknown (see
            :func:`~.segmentation.pair_statistics` and :func:`~.joints.joint_cost_matrix`).
        alpha_topology: distance penalty of the all-pairs joint costs.
        dof_corrected_topology: the all-pairs costs corrected for the markers each pair has (see
            :func:`~.joints.joint_cost_matrix`); False is the paper's ``Q``.
        alpha_final: penalty stages of the final joint solve on all frames.
        topology_frames: frames (evenly spaced) used for the all-pairs joint costs.
        joint_frames: frames (evenly spaced) on which the tree's joints are solved; each frame's joint is
            then placed for the distances found.
        root: index of the marker group to make the root (None: the centre of the tree).
        rigid_tolerance_m: a segment whose two markers' distance varies more than this (standard
            deviation) spans a joint: the eigengap's count is raised until none does, and a given count
            that leaves one is reported (skin markers on one bone vary by 5–13 mm in the real CMU and
            Plug-in Gait files; across a joint by 1–11 cm).
        template_prior: where the tree is not a human body (:mod:`~bcmocap.markers.anatomy`), the joint cost of
            two segments whose labels the human template does not join (an arm on the pelvis, a right shin on
            the left thigh; labels of confidence 0.5 or more) is multiplied by this, the spanning tree built
            again and kept if it is more of a body (0: off). A soft cost: a joint the data support well still
            wins.
        template_rounds: how many times the tree may be rebuilt that way.
        label_prior: where the markers' names follow a known marker set (:mod:`~bcmocap.markers.label_hints`: at
            least 10 named, on both sides), the segmentation's affinity of two markers whose names put them on bones
            no rigid segment holds together (a thigh's and a shin's, a left and a right shin's) is divided by this;
            with the eigengap (``num_groups`` None) a group still holding such a pair is then split and a lone
            named marker joins a group it is rigid with and whose names allow it
            (:func:`~.segmentation.split_named_conflicts`, :func:`~.segmentation.merge_named_singles`); the joint
            cost of two segments whose names no joint of the body joins is multiplied by it; and the human
            template weighs the names (:func:`~.anatomy.label_anatomy`'s ``hints``). 0 turns it all off, else at
            least 1. A soft cost, as ``template_prior``: the motion still decides the joints.
        ik_chunk: frames solved together in inverse kinematics.
        seed: random seed (samplings, k-means).
    """

    num_groups: int | None = None
    max_groups: int = 20
    trim_frames: int = 2
    min_run_seconds: float = 0.5
    spike_threshold_m: float | None = 0.03
    merge: str = "auto"
    num_markers: int | None = None
    merge_method: str = "linkage"
    num_samplings: int = 8
    segmentation_scale_m: float | None = None
    min_coverage: float = MIN_COVERAGE
    alpha_topology: float = 1e-3
    dof_corrected_topology: bool = True
    alpha_final: tuple[float, ...] = (1e-2, 1e-4)
    topology_frames: int = 200
    joint_frames: int = 400
    root: int | None = None
    rigid_tolerance_m: float = 0.015
    template_prior: float = 10.0
    template_rounds: int = 2
    label_prior: float = 100.0
    ik_chunk: int = 256
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class MarkerSkeleton:
    """What the pipeline found.

    Attributes:
        skeleton: the rigid skeleton (BALL joints, FREE root, world-aligned rest frames at the pose of
            ``rigid.reference_frame``).
        motion: ``(F,)`` per-frame poses.
        fps: frame rate (Hz).
        trajectories: the markers the skeleton was fitted to (after preprocessing and merging).
        marker_segment: ``(M,)`` segment index of each of those markers.
        marker_offsets: ``(M, 3)`` their positions in their segment frames (m).
        segmentation: the marker groups.
        joint_costs: ``(G, G)`` all-pairs joint costs ``Q`` (m², by group).
        joints: the re-solved joints of the tree, by segment: ``joints[j - 1]`` connects segment ``j`` to its parent.
        rigid: the rigid fit.
        ik: inverse kinematics (filled marker positions, residuals).
        preprocess_report: what preprocessing removed.
        identities: the identity merge (None if not run).
        input_labels: the labels given to the pipeline.
        notes: warnings raised along the way (also emitted as :class:`UserWarning`).
        seconds: time per stage.
        anatomy: the tree labelled against a human template (:mod:`bcmocap.markers.anatomy`): each segment's label
            and confidence, and the verdict.
    """

    skeleton: Skeleton
    motion: Motion
    fps: float
    trajectories: MarkerTrajectories
    marker_segment: np.ndarray
    marker_offsets: np.ndarray
    segmentation: Segmentation
    joint_costs: np.ndarray
    joints: tuple[JointSolution, ...]
    rigid: RigidSkeleton
    ik: IkResult
    preprocess_report: PreprocessReport
    identities: IdentityMerge | None
    input_labels: tuple[str, ...]
    notes: tuple[str, ...]
    seconds: dict
    anatomy: Anatomy

    @property
    def edges(self) -> list[tuple[str, str]]:
        """``(parent, child)`` segment names of every joint."""
        s = self.skeleton
        return [(s.names[s.parents[j]], s.names[j]) for j in range(1, s.num_segments)]

    def segment_markers(self, j: int) -> list[str]:
        """Labels of the markers on segment ``j``."""
        return [self.trajectories.labels[m] for m in np.flatnonzero(self.marker_segment == j)]

    def segment_lengths(self) -> dict[str, float]:
        """Distance (m) between every two joints of a segment, keyed ``"segment: joint–joint"``."""
        s = self.skeleton
        out = {}
        for j in range(s.num_segments):
            points = ([(s.names[j], np.zeros(3))] if j > 0 else []) + [(s.names[c], np.asarray(s.offsets[c])) for c in s.children(j)]
            for a in range(len(points)):
                for b in range(a + 1, len(points)):
                    out[f"{s.names[j]}: {points[a][0]}–{points[b][0]}"] = float(np.linalg.norm(points[a][1] - points[b][1]))
        return out

    def tree_lines(self) -> list[str]:
        """The topology as an indented tree, each segment with its markers."""
        s = self.skeleton
        lines = []

        def walk(j, depth):
            marks = ", ".join(self.segment_markers(j))
            label = f"{self.anatomy.labels[j]} ({self.anatomy.confidence[j]:.2f})"
            lines.append(f"{'  ' * depth}{s.names[j]}  {label}  [{marks}]")
            for c in s.children(j):
                walk(c, depth + 1)

        walk(0, 0)
        return lines

    def verdict_lines(self) -> list[str]:
        """Whether the tree is a human body, and what is wrong with it where it is not."""
        a = self.anatomy
        lines = ["verdict: a human body" if a.human else
                 f"verdict: NOT a human body: {', '.join(l.replace('_', ' ') for l in a.wrong_limbs)} wrong"]
        fixes = self.fixes()
        for limb, reason in a.wrong_limbs.items():
            lines.append(f"  {limb.replace('_', ' ')}: {reason}")
            lines.append(f"    try: {fixes[limb]}")
        lines += [f"  note: {note}" for note in a.notes]
        return lines

    def fixes(self) -> dict[str, str]:
        """``{limb: what to try}`` for each wrong limb: the option of ``bcmocap markers`` most likely to fix it."""
        a, seg = self.anatomy, self.segmentation
        more = f"--groups {seg.num_groups + 1} (one segment more than the {seg.num_groups} found)"
        out = {}
        for limb, (kind, segments) in a.causes.items():
            lone = [m for j in segments for m in self.segment_markers(j) if len(self.segment_markers(j)) == 1]
            drop = f"--drop {' '.join(lone)} (a marker alone on its segment, placed by little)" if lone else None
            if kind == "on_pelvis":
                out[limb] = ("a trial, or --frames FIRST:LAST of one, in which the trunk bends and twists on the pelvis "
                             "(a range-of-motion trial): here nothing tells the thorax's joints from the pelvis's")
            elif kind == "head_in_trunk":
                out[limb] = drop or more
            elif kind == "rigid_leg":
                out[limb] = more + ": the knee's markers went with the thigh's or the foot's"
            elif kind in ("missing", "length", "too_many"):
                out[limb] = " or ".join(x for x in (drop, more) if x)
            else:
                out[limb] = drop or f"{more}, or --frames of a stretch where every joint moves"
        return out

    def labelled_skeleton(self) -> Skeleton:
        """The skeleton with its segments named by their labels (a repeated label numbered: spine, spine_2)."""
        s = self.skeleton
        names, seen = [], {}
        for label in self.anatomy.labels:
            seen[label] = seen.get(label, 0) + 1
            names.append(label if seen[label] == 1 else f"{label}_{seen[label]}")
        return Skeleton(names, s.parents, s.offsets, s.joint_types, s.hinge_axes)

    def report(self) -> str:
        """A short human-readable report."""
        s = self.skeleton
        f = self.motion.num_frames
        lines = [
            f"{f} frames at {self.fps:g} Hz ({f / self.fps:.1f} s), {len(self.input_labels)} labels in, "
            f"{self.trajectories.num_markers} markers used",
        ]
        rep = self.preprocess_report
        if rep.dropped:
            lines.append(f"ignored {len(rep.dropped)} labels: " + "; ".join(f"{a} ({b})" for a, b in rep.dropped[:8])
                         + (" …" if len(rep.dropped) > 8 else ""))
        lines.append(f"trimmed {rep.trimmed_samples} marker-frames at stretch ends, removed {rep.spikes_removed} jumps")
        if self.identities is not None and self.identities.num_markers < len(self.identities.marker_of_label):
            lines.append(f"merged {len(self.identities.marker_of_label)} labels into {self.identities.num_markers} markers")
        seg = self.segmentation
        lines.append(f"{seg.num_groups} segments ({seg.chosen_by}; affinity σ {seg.scale_m * 1000:.1f} mm, "
                     f"within-group cost {seg.cost * 1000:.2f} mm)")
        if seg.known is not None and not seg.known.all():
            m = len(seg.known)
            unknown = int((~seg.known[np.triu_indices(m, 1)]).sum())
            lines.append(f"{unknown} of {m * (m - 1) // 2} marker pairs unknown (seen together too little, or only while "
                         "the body around them was still): left out of the segmentation")
        lines += self.verdict_lines()
        lines.append("topology (root first; each segment's label against the human template, with its confidence):")
        lines += ["  " + x for x in self.tree_lines()]
        lines.append("joints (segment ← parent): cost Q, distance residual RMS, free directions")
        for j in range(1, s.num_segments):
            sol = self.joints[j - 1]
            free = {0: "", 1: "  (hinge-like: one axis exercised)"}.get(sol.null_dims, "  (NOT EXERCISED)")
            lines.append(f"  {s.names[j]:<18} ← {s.names[s.parents[j]]:<18} Q {sol.cost:.3g} m²  rms {sol.rms_m * 1000:.2f} mm{free}")
        lines.append("segment lengths (joint to joint, cm):")
        for k, v in self.segment_lengths().items():
            lines.append(f"  {k}: {v * 100:.1f}")
        rms = self.ik.residual_rms_m
        lines.append(f"inverse kinematics: marker RMS {np.nanmean(rms) * 1000:.2f} mm (median frame "
                     f"{np.nanmedian(rms) * 1000:.2f}, worst {np.nanmax(rms) * 1000:.2f}); "
                     f"{int((~np.isfinite(self.trajectories.positions[..., 0])).sum())} marker-frames filled")
        for note in self.notes:
            lines.append(f"warning: {note}")
        lines.append("time: " + ", ".join(f"{k} {v:.1f} s" for k, v in self.seconds.items()))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """A JSON-friendly description: segments, markers, joints and the report's figures."""
        s = self.skeleton
        return {
            "frames": int(self.motion.num_frames),
            "fps": self.fps,
            "verdict": {**self.anatomy.to_dict(s.names), "fixes": self.fixes()},
            "segments": [
                {
                    "name": s.names[j],
                    "label": self.anatomy.labels[j],
                    "label_confidence": float(self.anatomy.confidence[j]),
                    "parent": None if j == 0 else s.names[s.parents[j]],
                    "offset_m": np.asarray(s.offsets[j]).tolist(),
                    "markers": self.segment_markers(j),
                }
                for j in range(s.num_segments)
            ],
            "markers": {
                label: {"segment": s.names[int(self.marker_segment[m])], "offset_m": self.marker_offsets[m].tolist()}
                for m, label in enumerate(self.trajectories.labels)
            },
            "joints": [
                {
                    "child": s.names[j],
                    "parent": s.names[s.parents[j]],
                    "cost_m2": self.joints[j - 1].cost,
                    "rms_m": self.joints[j - 1].rms_m,
                    "free_directions": self.joints[j - 1].null_dims,
                }
                for j in range(1, s.num_segments)
            ],
            "segment_lengths_m": self.segment_lengths(),
            "ik_rms_m": float(np.nanmean(self.ik.residual_rms_m)),
            "ignored_labels": [list(x) for x in self.preprocess_report.dropped],
            "merged_labels": None if self.identities is None else {
                self.input_labels[k]: self.trajectories.labels[int(m)]
                for k, m in zip(self.preprocess_report.kept, self.identities.marker_of_label)
            },
            "notes": list(self.notes),
            "seconds": self.seconds,
        }

    def save(self, folder: str | Path) -> dict[str, Path]:
        """Write ``skeleton.bvh``, ``skeleton.json``, ``poses.npz`` and ``report.txt`` into ``folder``."""
        from ..io.bvh import write_bvh

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        paths = {"bvh": folder / files.SKELETON_BVH, "json": folder / files.SKELETON_JSON,
                 "poses": folder / files.POSES, "report": folder / files.REPORT}
        # A human body's joints are named by their labels; any other tree keeps the segments' own names.
        write_bvh(paths["bvh"], self.labelled_skeleton() if self.anatomy.human else self.skeleton, self.motion,
                  1.0 / self.fps)
        paths["json"].write_text(json.dumps(self.to_dict(), indent=2) + "\n")
        np.savez_compressed(
            paths["poses"],
            root_position=np.asarray(self.motion.root_position),
            rotations=np.asarray(self.motion.rotations),
            joint_positions=np.asarray(joint_positions(self.skeleton, self.motion)),
            marker_positions=self.ik.marker_positions,
            marker_labels=np.array(self.trajectories.labels),
            segment_names=np.array(self.skeleton.names),
        )
        paths["report"].write_text(self.report() + "\n")
        return paths


def _segment_names(trajectories: MarkerTrajectories, groups: np.ndarray) -> list[str]:
    names = []
    for g in range(int(groups.max()) + 1):
        first = trajectories.labels[int(np.flatnonzero(groups == g)[0])]
        first = re.sub(r"[^A-Za-z0-9_]", "", first.split(":")[-1]) or "m"
        names.append(f"seg{g}_{first}")
    return names


def _non_rigid_segments(seg, labels, names, tolerance_m: float) -> list[str]:
    """One message per segment whose least rigid marker pair varies in distance by more than
    ``tolerance_m`` (std), naming the pair and suggesting more segments."""
    out = []
    for g in range(seg.num_groups):
        std, i, j = least_rigid_pair(seg.distance_std, seg.members(g))
        if std > tolerance_m:
            out.append(f"segment '{names[g]}' is not rigid: {labels[i]} and {labels[j]} vary in distance by "
                       f"{std * 1000:.0f} mm (std; tolerance {tolerance_m * 1000:.0f} mm), so it likely spans a "
                       f"joint: {seg.num_groups} segments ({seg.chosen_by}) may be too few; try more (--groups)")
    return out


def _without(trajectories: MarkerTrajectories, seg: Segmentation, keep: np.ndarray) -> tuple[MarkerTrajectories, Segmentation]:
    """The markers ``keep`` only, in the trajectories and the segmentation."""
    sub = np.ix_(keep, keep)
    return trajectories.select(keep), dataclasses.replace(
        seg, groups=seg.groups[keep], distance_std=seg.distance_std[sub],
        coverage=None if seg.coverage is None else seg.coverage[sub], known=None if seg.known is None else seg.known[sub])


@dataclasses.dataclass(frozen=True)
class _TreeFit:
    joints: tuple
    rigid: RigidSkeleton
    by_child: dict
    ik: IkResult
    anatomy: Anatomy


def _fit_tree(clean: MarkerTrajectories, groups: np.ndarray, edges, names, options: MarkerOptions, seconds: dict,
              known: tuple[JointSolution, ...] = (), hints=None) -> _TreeFit:
    """The stages after the topology for the tree ``edges``: its joints on all frames (those in ``known`` reused),
    the rigid skeleton, inverse kinematics and the labels against the human template (each stage's time added to
    ``seconds``)."""
    t0 = time.perf_counter()
    reuse = {frozenset(sol.groups): sol for sol in known}
    todo = [e for e in edges if frozenset(e) not in reuse]
    solved = solve_joints(clean, groups, todo, alpha=options.alpha_final, max_iterations=400,
                          max_solve_frames=options.joint_frames) if todo else []
    reuse.update({frozenset(sol.groups): sol for sol in solved})
    joints = [reuse[frozenset(e)] for e in edges]
    seconds["joints"] = seconds.get("joints", 0.0) + time.perf_counter() - t0

    t0 = time.perf_counter()
    rigid = build_skeleton(clean.positions, groups, joints, root=options.root, names=names)
    seg_of_group = {int(g): k for k, g in enumerate(rigid.segment_groups)}
    by_child: dict[int, JointSolution] = {}
    joint_positions_by_edge = {}
    for sol in joints:
        a, b = seg_of_group[sol.groups[0]], seg_of_group[sol.groups[1]]
        parent, child = (a, b) if rigid.skeleton.parents[b] == a else (b, a)
        by_child[child] = sol
        joint_positions_by_edge[(parent, child)] = sol.positions
    seconds["rigid"] = seconds.get("rigid", 0.0) + time.perf_counter() - t0

    t0 = time.perf_counter()
    start = initial_motion(rigid, clean.positions, joint_positions_by_edge)
    ik = solve_ik(rigid, clean.positions, start, chunk=options.ik_chunk)
    seconds["ik"] = seconds.get("ik", 0.0) + time.perf_counter() - t0

    t0 = time.perf_counter()
    anatomy = label_anatomy(rigid.skeleton.parents, np.asarray(joint_positions(rigid.skeleton, ik.motion)),
                            ik.marker_positions, rigid.marker_segment, names=rigid.skeleton.names, hints=hints)
    seconds["anatomy"] = seconds.get("anatomy", 0.0) + time.perf_counter() - t0
    return _TreeFit(tuple(joints), rigid, by_child, ik, anatomy)


def _better(new: Anatomy, old: Anatomy) -> bool:
    """A body where there was none, or fewer wrong limbs, or as many at a lower template cost."""
    return (new.human, -len(new.wrong_limbs), -new.cost) > (old.human, -len(old.wrong_limbs), -old.cost)


def fit_marker_skeleton(trajectories: MarkerTrajectories, options: MarkerOptions = MarkerOptions()) -> MarkerSkeleton:
    """Estimate a skeleton and its motion from marker trajectories (Kirk, O'Brien & Forsyth 2005).

    Args:
        trajectories: ``(F, M, 3)`` marker positions in metres with NaN gaps, and the frame rate.
        options: see :class:`MarkerOptions`.

    Raises:
        ValueError: input the pipeline cannot use; the message names the marker, group or segment.
    """
    require_float64("bcmocap.markers.fit_marker_skeleton")
    notes: list[str] = []
    seconds: dict[str, float] = {}

    def note(message: str) -> None:
        notes.append(message)
        warnings.warn(message, UserWarning, stacklevel=3)

    if options.label_prior and options.label_prior < 1.0:
        raise ValueError(f"options.label_prior must be 0 (off) or at least 1, got {options.label_prior!r}")
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clean, report = preprocess(
            trajectories,
            trim_frames=options.trim_frames,
            min_run_seconds=options.min_run_seconds,
            spike_threshold_m=options.spike_threshold_m,
        )
    for w in caught:
        note(str(w.message))
    identities = None
    if options.merge not in ("auto", "yes", "no"):
        raise ValueError(f"options.merge must be 'auto', 'yes' or 'no', got {options.merge!r}")
    if options.merge == "yes" or (options.merge == "auto" and clean.num_markers > (options.num_markers or concurrent_labels(clean.visible))):
        clean, identities = merge_identities(clean, options.num_markers, method=options.merge_method, seed=options.seed)
    seconds["preprocess"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    hints = marker_hints(clean.labels) if options.label_prior else None  # None: the names are not used
    if hints is not None and not informative(hints):
        hints = None
    seg = segment_markers(
        clean,
        options.num_groups,
        num_samplings=options.num_samplings,
        scale_m=options.segmentation_scale_m,
        max_groups=options.max_groups,
        rigid_tolerance_m=options.rigid_tolerance_m,
        min_coverage=options.min_coverage,
        label_weights=None if hints is None else marker_label_weights(hints, options.label_prior),
        seed=options.seed,
    )
    if hints is not None:
        note(f"the markers' names follow a known marker set ({sum(h is not None for h in hints)} of "
             f"{len(hints)} named): they weigh on the segments and the tree as a soft prior (label_prior "
             f"{options.label_prior:g}; 0 turns it off)")
    if len(seg.left_out):
        note(f"markers {[clean.labels[k] for k in seg.left_out]} are seen together with too few others (or only "
             "while still) to place them on a segment; they are left out")
        keep = np.flatnonzero(seg.groups >= 0)
        clean, seg = _without(clean, seg, keep)
        hints = None if hints is None else [hints[k] for k in keep]
    seconds["segmentation"] = time.perf_counter() - t0
    names = _segment_names(clean, seg.groups)
    for g in range(seg.num_groups):
        if (seg.groups == g).sum() == 1:
            note(f"segment '{names[g]}' has a single marker ({clean.labels[int(np.flatnonzero(seg.groups == g)[0])]}): "
                 "its rotation about the joint-marker line is not determined")

    for message in _non_rigid_segments(seg, clean.labels, names, options.rigid_tolerance_m):
        note(message)

    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        q, pair_solutions = joint_cost_matrix(clean, seg.groups, alpha=options.alpha_topology, max_frames=options.topology_frames,
                                              dof_corrected=options.dof_corrected_topology, min_coverage=options.min_coverage)
    for w in caught:
        note(str(w.message))
    names_penalty = (np.ones_like(q) if hints is None
                     else group_label_penalties(hints, seg.groups, seg.num_groups, options.label_prior))
    edges = minimum_spanning_tree(q * names_penalty, names)
    by_pair = {frozenset(s.groups): s for s in pair_solutions}
    for a, b in edges:
        s = by_pair[frozenset((a, b))]
        if s.coverage < options.min_coverage or s.frames_used < MIN_FRAMES:
            note(f"segments '{names[a]}' and '{names[b]}' are connected although they are seen together too little "
                 f"({s.frames_used} frames, {s.coverage * 100:.0f} % of their relative motion): no better-seen pair "
                 "connects them")
    seconds["topology"] = time.perf_counter() - t0

    fit = _fit_tree(clean, seg.groups, edges, names, options, seconds, hints=hints)
    if options.template_prior and not fit.anatomy.human:
        t0 = time.perf_counter()
        tried = {frozenset(map(frozenset, edges))}
        template_seconds: dict = {}
        regions = body_regions(fit.ik.marker_positions, seg.groups, len(names))  # from where the markers are
        for _ in range(options.template_rounds):
            if fit.anatomy.human:
                break
            penalty = np.maximum(template_penalties(fit.rigid.segment_groups, fit.anatomy, len(names),
                                                    options.template_prior),
                                 region_penalties(regions, options.template_prior)) * names_penalty
            new_edges = minimum_spanning_tree(q * penalty, names)
            if frozenset(map(frozenset, new_edges)) in tried:
                break
            tried.add(frozenset(map(frozenset, new_edges)))
            candidate = _fit_tree(clean, seg.groups, new_edges, names, options, template_seconds, known=fit.joints,
                                  hints=hints)
            if _better(candidate.anatomy, fit.anatomy):
                moved = sorted(set(map(frozenset, new_edges)) - set(map(frozenset, edges)), key=sorted)
                note("the tree was rebuilt with the human template's prior on its joints (it was not a body): "
                     + ", ".join(" - ".join(names[g] for g in sorted(pair)) for pair in moved) + " joined instead")
                fit, edges = candidate, new_edges
        seconds["template"] = time.perf_counter() - t0
    joints, rigid, by_child, ik, anatomy = fit.joints, fit.rigid, fit.by_child, fit.ik, fit.anatomy
    for sol in joints:
        a, b = sol.groups
        if sol.null_dims >= 2:
            note(f"the joint between segments '{names[a]}' and '{names[b]}' is not exercised (the two barely move "
                 "relative to each other): its position is set by the distance prior only")
        if not sol.converged:
            note(f"the joint between segments '{names[a]}' and '{names[b]}' did not converge")
    return MarkerSkeleton(
        skeleton=rigid.skeleton,
        motion=ik.motion,
        fps=clean.fps,
        trajectories=clean,
        marker_segment=rigid.marker_segment,
        marker_offsets=rigid.marker_offsets,
        segmentation=seg,
        joint_costs=q,
        joints=tuple(by_child[j] for j in range(1, rigid.skeleton.num_segments)),
        rigid=rigid,
        ik=ik,
        preprocess_report=report,
        identities=identities,
        input_labels=trajectories.labels,
        notes=tuple(notes),
        seconds=seconds,
        anatomy=anatomy,
    )
