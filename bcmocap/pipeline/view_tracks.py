"""The output folders of ``bcmocap markers`` and ``bcmocap kcs`` as what ``bcmocap view`` shows
(:class:`~bcmocap.viewer.inputs.TrackInput`), and which kind of folder ``bcmocap view`` was given.

``bcmocap markers FILE --out DIR`` writes (:meth:`bcmocap.markers.pipeline.MarkerSkeleton.save`):
``skeleton.json`` (``fps``; ``segments``: name, parent, markers; ``markers``: label → segment),
``poses.npz`` (``joint_positions`` ``(F, J, 3)``: each segment's origin, the joint to its parent, the
root's the mean of its joints; ``marker_positions`` ``(F, M, 3)``: the fitted markers, gaps filled;
``marker_labels`` ``(M,)``; ``segment_names`` ``(J,)``), ``skeleton.bvh`` and ``report.txt``. Shown: the
markers coloured by their segment, the ``J − 1`` joints, the skeleton (each segment's origin to its
parent's) and the segments (each marker to its segment's origin).

``bcmocap kcs INPUT --out DIR`` writes (:func:`bcmocap.kcs.command.run_kcs`): ``result.npz`` (``joints``
``(F, J, 3)`` in the model frame, m; ``names``; ``parents``; ``bone_names`` ``"a->b"``, the tree's bones
then the extra rigid links), ``report.json`` (``fps``, iterations, reprojection error, bone lengths),
``joints_3d.csv`` and ``motion.bvh``. Shown: the joints, the bones and the extra links.

Only those fixed names are read, with ``np.load(allow_pickle=False)``; anything missing or malformed is a
ValueError of one line naming the file and the field.
"""

from __future__ import annotations

import math
import pickle
import zipfile
from pathlib import Path

import numpy as np

from ..io.run_folder import RUN_LOG, read_json
from ..kcs import files as kcs_files
from ..markers import files as markers_files

#: Files by which a folder is recognised (a ``poses.npz`` beside an ``index.json`` is a correspondence store's).
MARKERS_FILES = (markers_files.POSES, markers_files.SKELETON_JSON, markers_files.SKELETON_BVH)
KCS_FILES = (kcs_files.RESULT, kcs_files.REPORT, kcs_files.JOINTS_CSV)
#: Segment colours (RGB), in segment order, repeated when there are more segments: no blue, which the
#: skeleton's lines use.
SEGMENT_COLOURS = ((230, 120, 20), (40, 170, 60), (210, 40, 40), (150, 80, 200), (140, 90, 60), (230, 110, 190),
                   (150, 150, 30), (20, 180, 190), (240, 190, 0), (90, 90, 90), (120, 200, 120), (200, 0, 120))
#: Joints, skeleton lines, and the extra rigid links of a kinematic chain (RGB).
JOINT, BONE, LINK = (25, 25, 25), (40, 110, 230), (255, 140, 0)


def folder_kind(folder: str | Path) -> str:
    """``"run"``, ``"markers"`` or ``"kcs"``: which command wrote ``folder``; ValueError (one line) when it
    is no folder or none of them."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such folder")
    if (folder / RUN_LOG).is_file():
        return "run"
    if any((folder / name).is_file() for name in MARKERS_FILES) and not (folder / "index.json").is_file():
        return "markers"
    if any((folder / name).is_file() for name in KCS_FILES):
        return "kcs"
    raise ValueError(f"{folder}: not an output folder of `bcmocap run` (run.json), `bcmocap markers` "
                     "(poses.npz, skeleton.json) or `bcmocap kcs` (result.npz)")


def load_track_folder(folder: str | Path, kind: str | None = None):
    """The :class:`~bcmocap.viewer.inputs.TrackInput` of a ``bcmocap markers`` or ``bcmocap kcs`` folder
    (``kind`` None: :func:`folder_kind`). Raises ValueError (one line naming the file) when it cannot."""
    kind = kind or folder_kind(folder)
    if kind == "markers":
        return load_markers_folder(folder)
    if kind == "kcs":
        return load_kcs_folder(folder)
    raise ValueError(f"{folder}: a `bcmocap {kind}` folder has no points to show this way")


def load_markers_folder(folder: str | Path):
    """The markers (coloured by segment), joints, skeleton and segments of a ``bcmocap markers`` folder."""
    from ..viewer.inputs import LineTracks, PointTracks, TrackInput

    folder = Path(folder)
    json_path, poses_path = folder / markers_files.SKELETON_JSON, folder / markers_files.POSES
    desc = read_json(_existing(json_path, "bcmocap markers"))
    fps = _fps(desc, json_path)
    segments = desc.get("segments") if isinstance(desc, dict) else None
    if not isinstance(segments, list) or not segments or not all(
            isinstance(s, dict) and isinstance(s.get("name"), str) and isinstance(s.get("markers"), list)
            for s in segments):
        raise ValueError(f"{json_path}: 'segments' must be a list of {{name, parent, markers}}")
    names = [s["name"] for s in segments]
    if len(set(names)) != len(names):
        raise ValueError(f"{json_path}: segment names repeat")
    parents = _parents([s.get("parent") for s in segments], names, json_path)
    arrays = _arrays(_existing(poses_path, "bcmocap markers"), {
        "joint_positions": "f", "marker_positions": "f", "marker_labels": "U", "segment_names": "U"})
    joints, markers = arrays["joint_positions"], arrays["marker_positions"]
    labels = [str(x) for x in arrays["marker_labels"]]
    frames = len(joints)
    _shape(joints, (None, len(names), 3), poses_path, "joint_positions", f"{len(names)} segments in skeleton.json")
    _shape(markers, (frames, len(labels), 3), poses_path, "marker_positions", "joint_positions' frames and "
           "marker_labels")
    if [str(x) for x in arrays["segment_names"]] != names:
        raise ValueError(f"{poses_path}: segment_names {arrays['segment_names'].tolist()} are not the segments of "
                         f"skeleton.json {names}")
    segment_of = {str(m): k for k, s in enumerate(segments) for m in s["markers"]}
    unassigned = [m for m in labels if m not in segment_of]
    if unassigned:
        raise ValueError(f"{json_path}: markers {unassigned[:5]} of poses.npz are on no segment")
    marker_segment = np.array([segment_of[m] for m in labels], int)
    colour = np.array([SEGMENT_COLOURS[k % len(SEGMENT_COLOURS)] for k in range(len(names))], np.uint8)
    children = [j for j in range(len(names)) if parents[j] >= 0]
    layers = {
        "markers": PointTracks("markers", markers, colour[marker_segment], tuple(labels), size_m=0.018),
        "joints": PointTracks("joints", joints[:, children], np.tile(np.uint8(JOINT), (len(children), 1)),
                              tuple(f"{names[parents[j]]}–{names[j]}" for j in children), size_m=0.03),
        "skeleton": LineTracks("skeleton (segment origins)", np.stack(
            [joints[:, [parents[j] for j in children]], joints[:, children]], axis=2),
            np.tile(np.uint8(BONE), (len(children), 1)), thickness_m=0.01),
        "segments": LineTracks("segments (marker to its segment)", np.stack(
            [joints[:, marker_segment], markers], axis=2), colour[marker_segment], thickness_m=0.004),
    }
    legend = [(f"{n}{' (' + str(s['label']) + ')' if s.get('label') else ''}: "
               f"{', '.join(map(str, s['markers'])) or 'no markers'}", tuple(int(c) for c in colour[k]))
              for k, (n, s) in enumerate(zip(names, segments))]
    notes = [f"`bcmocap markers` output: {frames} frames at {fps:g} Hz, {len(labels)} markers on {len(names)} "
             f"segments, {len(children)} joints. Markers are coloured by segment; black: joints; blue: the "
             "skeleton."]
    verdict = desc.get("verdict")
    if isinstance(verdict, dict) and isinstance(verdict.get("human"), bool):
        notes.append("Against the human template: a human body." if verdict["human"] else
                     f"Against the human template: NOT a human body ({', '.join(map(str, verdict.get('wrong_limbs', [])))} "
                     "wrong; the report says why).")
    report = ""
    if (folder / markers_files.REPORT).is_file():
        report = "```\n" + _text(folder / markers_files.REPORT) + "\n```"
    return TrackInput(title=folder.resolve().name, kind="markers", fps=fps, layers=layers, legend=legend,
                      report=report, notes=notes)


def load_kcs_folder(folder: str | Path):
    """The reconstructed joints, bones and extra rigid links of a ``bcmocap kcs`` folder."""
    from ..viewer.inputs import LineTracks, PointTracks, TrackInput

    folder = Path(folder)
    result_path, report_path = folder / kcs_files.RESULT, folder / kcs_files.REPORT
    arrays = _arrays(_existing(result_path, "bcmocap kcs"), {"joints": "f", "names": "U", "parents": "i"},
                     optional={"bone_names": "U"})
    joints = arrays["joints"]
    names = [str(x) for x in arrays["names"]]
    _shape(joints, (None, len(names), 3), result_path, "joints", "names")
    if len(set(names)) != len(names):
        raise ValueError(f"{result_path}: names repeat")
    parents = [int(p) for p in arrays["parents"]]
    if len(parents) != len(names):
        raise ValueError(f"{result_path}: {len(parents)} parents for {len(names)} names")
    _parents([names[p] if 0 <= p < len(names) else (None if p == -1 else p) for p in parents], names, result_path)
    links = _extra_links(result_path, [str(b) for b in arrays.get("bone_names", [])], names, parents)
    notes, report, fps = [], "", 30.0
    if report_path.is_file():
        summary = read_json(report_path)
        fps = _fps(summary, report_path)
        report = _kcs_report(summary)
    else:
        notes.append(f"{report_path.name} missing: playing at {fps:g} frames/s.")
    tree = [j for j in range(len(names)) if parents[j] >= 0]
    layers = {
        "joints": PointTracks("joints", joints, np.tile(np.uint8(JOINT), (len(names), 1)), tuple(names), size_m=0.03),
        "bones": LineTracks("bones", np.stack([joints[:, [parents[j] for j in tree]], joints[:, tree]], axis=2),
                            np.tile(np.uint8(BONE), (len(tree), 1)), thickness_m=0.012),
    }
    if links:
        layers["links"] = LineTracks("extra rigid links", np.stack(
            [joints[:, [a for a, _ in links]], joints[:, [b for _, b in links]]], axis=2),
            np.tile(np.uint8(LINK), (len(links), 1)), thickness_m=0.008)
    notes.insert(0, f"`bcmocap kcs` output: {len(joints)} frames, {len(names)} joints, {len(tree)} bones"
                    + (f", {len(links)} extra rigid links (orange)" if links else "")
                    + "; in the model frame (root at the origin).")
    return TrackInput(title=folder.resolve().name, kind="kcs", fps=fps, layers=layers, report=report, notes=notes)


# ---- reading and checking -------------------------------------------------------------------------
def _existing(path: Path, command: str) -> Path:
    if not path.is_file():
        raise ValueError(f"{path}: missing (`{command}` writes it)")
    return path


def _text(path: Path, limit: int = 20_000) -> str:
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise ValueError(f"{path}: cannot read ({exc.strerror or exc})") from None
    return text[:limit] + ("\n…" if len(text) > limit else "")


def _arrays(path: Path, kinds: dict[str, str], optional: dict[str, str] | None = None) -> dict[str, np.ndarray]:
    """The named arrays of the ``.npz`` file ``path``, each of a kind (``"f"`` numbers as float64, ``"i"``
    integers, ``"U"`` text), and those of ``optional`` it has; ValueError naming the file and the array."""
    optional = optional or {}
    try:
        with np.load(path, allow_pickle=False) as data:
            if not isinstance(data, np.lib.npyio.NpzFile):
                raise ValueError("not an .npz archive")
            missing = [k for k in kinds if k not in data.files]
            if missing:
                raise ValueError(f"no {', '.join(missing)}")
            raw = {k: data[k] for k in [*kinds, *optional] if k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, pickle.UnpicklingError) as exc:
        raise ValueError(f"{path}: cannot read ({' '.join(str(exc).split())})") from None
    out = {}
    for key, a in raw.items():
        kind = kinds.get(key) or optional[key]
        ok = {"f": a.dtype.kind in "fiu", "i": a.dtype.kind in "iu", "U": a.dtype.kind in "US"}[kind]
        if not ok or (kind != "f" and a.ndim != 1):
            what = {"f": "numbers", "i": "a list of integers", "U": "a list of names"}[kind]
            raise ValueError(f"{path}: {key} must be {what}, got {a.dtype} of shape {a.shape}")
        out[key] = a.astype(np.float64) if kind == "f" else a
    return out


def _shape(a: np.ndarray, shape: tuple, path: Path, key: str, against: str) -> None:
    if a.ndim != len(shape) or any(n is not None and m != n for m, n in zip(a.shape, shape)) or not len(a):
        want = "(" + ", ".join("F" if n is None else str(n) for n in shape) + ")"
        raise ValueError(f"{path}: {key} has shape {a.shape}, expected {want} with F ≥ 1 (from {against})")


def _fps(desc, path: Path) -> float:
    fps = desc.get("fps") if isinstance(desc, dict) else None
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"{path}: 'fps' must be a positive frame rate, got {fps!r}")
    return float(fps)


def _parents(parent_names: list, names: list[str], path: Path) -> list[int]:
    """Parent indices from parent names (None for the root); ValueError unless they form one tree."""
    index = {n: k for k, n in enumerate(names)}
    unknown = [p for p in parent_names if p is not None and p not in index]
    if unknown:
        raise ValueError(f"{path}: parent {unknown[0]!r} is not a segment or joint")
    parents = [-1 if p is None else index[p] for p in parent_names]
    if parents.count(-1) != 1:
        raise ValueError(f"{path}: {parents.count(-1)} roots (joints without a parent); expected one")
    for j in range(len(parents)):
        k, steps = j, 0
        while parents[k] >= 0:
            k, steps = parents[k], steps + 1
            if steps > len(parents):
                raise ValueError(f"{path}: the parents of {names[j]!r} form a cycle")
    return parents


def _extra_links(path: Path, bones: list[str], names: list[str], parents: list[int]) -> list[tuple[int, int]]:
    """The links of ``bones`` (``"a->b"``, from ``path``) that are not tree bones, as joint index pairs."""
    pairs = {f"{a}->{b}": (i, j) for i, a in enumerate(names) for j, b in enumerate(names) if i != j}
    tree = {(p, j) for j, p in enumerate(parents) if p >= 0}
    links = []
    for bone in bones:
        if bone not in pairs:
            raise ValueError(f"{path}: bone_names entry {bone!r} does not join two of the joints")
        if pairs[bone] not in tree:
            links.append(pairs[bone])
    return links


def _kcs_report(summary) -> str:
    """``report.json`` of ``bcmocap kcs`` as markdown: the solve and the bone lengths."""
    if not isinstance(summary, dict):
        return ""
    lines = []
    history = summary.get("reprojection_px")
    if isinstance(summary.get("iterations"), int):
        lines.append(f"{summary['iterations']} iterations"
                     + (" (converged)" if summary.get("converged") else " (stopped at the limit)"))
    if isinstance(history, list) and len(history) >= 2 and all(isinstance(h, (int, float)) for h in history):
        lines.append(f"reprojection error {history[0]:.3f} → {history[-1]:.3f} px RMS")
    bones, lengths = summary.get("bones"), summary.get("bone_lengths_m")
    text = "; ".join(lines)
    if isinstance(bones, list) and isinstance(lengths, list) and len(bones) == len(lengths):
        rows = "\n".join(f"| {b} | {100 * v:.1f} |" for b, v in zip(bones, lengths) if isinstance(v, (int, float)))
        text += "\n\n| bone | length (cm) |\n|---|---|\n" + rows
    return text
