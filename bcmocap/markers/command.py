"""``bcmocap markers FILE --out DIR``: a skeleton and its motion from a C3D file (or a ``.npy`` array)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..compilation_cache import enable_compilation_cache
from ..io.output_folder import output_folder


def _frame_range(text: str | None) -> slice:
    """``--frames FIRST:LAST`` as a slice (either end may be left out); ValueError naming the flag."""
    if text is None:
        return slice(None)
    first, colon, last = text.partition(":")
    try:
        bounds = [int(end) if end.strip() else None for end in (first, last)]
    except ValueError:
        bounds = None
    if not colon or bounds is None:
        raise ValueError(f"--frames must be FIRST:LAST with whole frame numbers, got {text!r}")
    return slice(*bounds)


def _load(args: argparse.Namespace):
    """The trajectories of the frames ``args`` select and a line describing the file; ValueError naming it."""
    from .preprocess import MarkerTrajectories

    frames = _frame_range(args.frames)
    trajectories, note = _read(args)
    total = len(trajectories.positions)
    kept = len(range(total)[frames])
    if kept < 2:
        raise ValueError(f"--frames {args.frames} leaves {kept} of the {total} frames of {args.file}; at least 2 are needed")
    if kept < total:
        trajectories = MarkerTrajectories(trajectories.positions[frames], trajectories.labels, trajectories.fps)
    if args.drop:
        unknown = [label for label in args.drop if label not in trajectories.labels]
        if unknown:
            raise ValueError(f"--drop {' '.join(unknown)}: no such marker in {args.file} (its markers: "
                             f"{', '.join(trajectories.labels[:12])}{' …' if len(trajectories.labels) > 12 else ''})")
        keep = [k for k, label in enumerate(trajectories.labels) if label not in set(args.drop)]
        if len(keep) < 2:
            raise ValueError(f"--drop leaves {len(keep)} markers of {args.file}")
        trajectories = trajectories.select(keep)
        note += f"; dropped {len(args.drop)} markers (--drop)"
    return trajectories, note


def _read(args: argparse.Namespace):
    from .preprocess import MarkerTrajectories

    path = Path(args.file)
    if path.suffix.lower() == ".npy":
        import numpy as np

        if args.fps is None:
            raise ValueError(f"{path}: a .npy array of shape (frames, markers, 3) in metres needs --fps")
        return MarkerTrajectories.from_array(np.load(path), args.fps), f"{path} (array)"
    from ..io.c3d import read_c3d

    data = read_c3d(path, markers=args.markers, keep_modelled=args.keep_modelled)
    frames, markers, _ = data.positions.shape
    note = f"{path}: {frames} frames at {data.frame_rate_hz:g} Hz, {markers} markers ({data.units} → m)"
    if data.excluded:
        note += f"; left out {len(data.excluded)} computed/modelled points"
    return MarkerTrajectories.from_c3d(data), note


def run_markers(args: argparse.Namespace) -> int:
    enable_compilation_cache()
    from .pipeline import MarkerOptions, fit_marker_skeleton

    out = output_folder("markers", args.out)
    if out is None:
        return 2
    try:
        trajectories, note = _load(args)
    except (OSError, ValueError) as exc:
        print(f"bcmocap markers: {exc}", file=sys.stderr)
        return 2
    print(note, flush=True)
    options = MarkerOptions(num_groups=args.groups, merge=args.merge, num_markers=args.num_markers, seed=args.seed,
                            label_prior=MarkerOptions.label_prior if args.names else 0.0)
    try:
        result = fit_marker_skeleton(trajectories, options)
    except ValueError as exc:
        print(f"bcmocap markers: {exc}", file=sys.stderr)
        return 2
    paths = result.save(out)
    print(result.report())
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


def add_markers_command(sub: argparse._SubParsersAction) -> None:
    """Register ``bcmocap markers`` (heavy modules are imported only when it runs)."""
    p = sub.add_parser(
        "markers",
        help="skeleton, topology, joints and motion from optical marker data (C3D)",
        description="Estimate a skeleton (marker groups, topology, joints, marker offsets) and per-frame poses "
        "from marker trajectories, after Kirk, O'Brien & Forsyth (CVPR 2005). Writes skeleton.bvh, "
        "skeleton.json, poses.npz and report.txt.",
    )
    p.add_argument("file", help="a .c3d file (or a .npy array (frames, markers, 3) in metres with --fps)")
    p.add_argument("--out", default="bcmocap-markers", help="output folder (default: ./bcmocap-markers)")
    p.add_argument("--groups", type=int, default=None, help="number of segments (default: chosen by the eigengap)")
    p.add_argument("--markers", nargs="+", default=None, help="use only these marker labels")
    p.add_argument("--drop", nargs="+", default=None, help="leave these marker labels out (the report suggests some "
                   "where the tree is not a body)")
    p.add_argument("--keep-modelled", action="store_true", help="keep points that look modelled (Plug-in Gait bone axes, centres of mass)")
    p.add_argument("--merge", choices=["auto", "yes", "no"], default="auto", help="merge broken marker labels (default: auto)")
    p.add_argument("--num-markers", type=int, default=None, help="physical markers when merging labels")
    p.add_argument("--frames", default=None, help="frame range FIRST:LAST (0-based, LAST excluded)")
    p.add_argument("--fps", type=float, default=None, help="frame rate of a .npy input (Hz)")
    p.add_argument("--ignore-names", dest="names", action="store_false",
                   help="do not use the markers' names (by default, names that follow a known marker set, such as "
                        "Plug-in Gait's LTHI, RKNE, are a soft prior on the segments and the tree)")
    p.add_argument("--seed", type=int, default=0)

    def run(args: argparse.Namespace) -> int:
        if args.groups is not None and args.groups < 1:
            p.error("--groups must be at least 1")
        return run_markers(args)

    p.set_defaults(run=run)
