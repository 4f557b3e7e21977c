"""``bcmocap markers FILE --out DIR``: a skeleton and its motion from a C3D file (or a ``.npy`` array)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _load(args: argparse.Namespace):
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
    from ..cli import enable_compilation_cache, output_folder

    enable_compilation_cache()
    from .pipeline import MarkerOptions, fit_marker_skeleton
    from .preprocess import MarkerTrajectories

    out = output_folder("markers", args.out)
    if out is None:
        return 2
    try:
        trajectories, note = _load(args)
    except (OSError, ValueError) as exc:
        print(f"bcmocap markers: {exc}", file=sys.stderr)
        return 2
    if args.frames:
        first, _, last = args.frames.partition(":")
        sel = slice(int(first) if first else None, int(last) if last else None)
        trajectories = MarkerTrajectories(trajectories.positions[sel], trajectories.labels, trajectories.fps)
    print(note, flush=True)
    options = MarkerOptions(num_groups=args.groups, merge=args.merge, num_markers=args.num_markers, seed=args.seed)
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
    p.add_argument("--keep-modelled", action="store_true", help="keep points that look modelled (Plug-in Gait bone axes, centres of mass)")
    p.add_argument("--merge", choices=["auto", "yes", "no"], default="auto", help="merge broken marker labels (default: auto)")
    p.add_argument("--num-markers", type=int, default=None, help="physical markers when merging labels")
    p.add_argument("--frames", default=None, help="frame range FIRST:LAST (0-based, LAST excluded)")
    p.add_argument("--fps", type=float, default=None, help="frame rate of a .npy input (Hz)")
    p.add_argument("--seed", type=int, default=0)

    def run(args: argparse.Namespace) -> int:
        if args.groups is not None and args.groups < 1:
            p.error("--groups must be at least 1")
        return run_markers(args)

    p.set_defaults(run=run)
