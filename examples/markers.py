"""The "Vicon side": a skeleton (segments, topology, joints, bone lengths) from optical marker trajectories alone.

``bcmocap.markers.fit_marker_skeleton`` (Kirk, O'Brien & Forsyth, CVPR 2005) groups the markers into rigid
segments, connects the segments into a tree at the joints that best keep constant distances to their
markers, fits a rigid skeleton with marker offsets and poses every frame by inverse kinematics.

With no arguments it reads the C3D file bundled with the tests: a c3d.org lower-body gait trial
(26 markers on pelvis, thighs, shanks and feet, 450 frames at 50 Hz), and finds the 7 segments by the
eigengap. ``--simulate walk|run|jump`` instead simulates a 45-marker full-body set on a bundled CMU
motion followed by a range-of-motion sequence (``bcmocap.sim``; 1 mm noise, jumps, occlusion gaps, marker
identities kept as in a labelled trial) and checks the topology found against the true skeleton.

    python examples/markers.py [FILE.c3d] [--groups N] [--frames A:B] [--out DIR]
    python examples/markers.py --simulate walk [--calibration-seconds 5]
"""

from __future__ import annotations

import argparse
import time
import warnings
from collections import Counter
from pathlib import Path

from bcmocap.compilation_cache import enable_compilation_cache
from bcmocap.precision import enable_float64
from bcmocap.io import read_c3d
from bcmocap.kinematics import Motion
from bcmocap.markers import MarkerOptions, MarkerTrajectories, fit_marker_skeleton
from bcmocap.sim import CMU_TRIALS, load_body_motion
from bcmocap.sim.markers import (
    MarkerNoise,
    calibration_motion,
    full_body_markers,
    simulate_markers,
)

BUNDLED_C3D = Path(__file__).resolve().parents[1] / "tests" / "data" / "c3d" / "BTKData_c3d.org_sample01_Eb015pr.c3d"
FPS = 60.0


def simulated_trajectories(motion_name: str, calibration_seconds: float, seed: int):
    """Labelled full-body markers on a CMU motion (+ range of motion) and the true segment of each marker."""
    skeleton, motion = load_body_motion(motion_name, fps=FPS)
    if calibration_seconds > 0:  # wrists, neck … barely move in walking: exercise every joint afterwards
        motion = Motion.concatenate([motion, calibration_motion(skeleton, motion[-1], calibration_seconds, FPS, seed=seed)])
    markers = full_body_markers(skeleton, jitter_m=0.01, seed=seed)
    noise = MarkerNoise(relabel_after_gap=0.0, label_break_rate_hz=0.0)  # identities kept: a labelled trial
    sim = simulate_markers(skeleton, motion, markers, FPS, noise, seed=seed)
    trajectories = MarkerTrajectories.from_array(sim.identified_positions(), FPS, sim.marker_names)
    return trajectories, {m.name: m.segment for m in markers}, sim.skeleton


def check_topology(result, segment_of_marker: dict[str, str], truth) -> None:
    """Name each found segment by the true segment of most of its markers; compare the trees."""
    skel = result.skeleton
    named = [Counter(segment_of_marker[m] for m in result.segment_markers(j)).most_common(1)[0][0]
             for j in range(skel.num_segments)]
    found = {frozenset((named[j], named[skel.parents[j]])) for j in range(1, skel.num_segments)}
    true = {frozenset((truth.names[j], truth.names[truth.parents[j]])) for j in range(1, truth.num_segments)}
    print("\nagainst the simulation's truth:")
    print("  segments found → true segment: " + ", ".join(f"{skel.names[j]} → {named[j]}" for j in range(skel.num_segments)))
    if found == true:
        print(f"  topology: correct ({len(true)} joints)")
    else:
        print(f"  topology: differs; missing {sorted(tuple(sorted(e)) for e in true - found)}, "
              f"extra {sorted(tuple(sorted(e)) for e in found - true)}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("file", nargs="?", type=Path, default=BUNDLED_C3D,
                        help="a .c3d marker file (default: the bundled c3d.org lower-body gait trial)")
    parser.add_argument("--simulate", choices=sorted(CMU_TRIALS), default=None,
                        help="simulate full-body markers on this bundled CMU motion instead of reading FILE")
    parser.add_argument("--calibration-seconds", type=float, default=5.0,
                        help="with --simulate: range-of-motion sequence after the motion (default: 5 s)")
    parser.add_argument("--groups", type=int, default=None, help="number of segments (default: chosen by the eigengap)")
    parser.add_argument("--frames", default=None, help="use only frames FIRST:LAST (0-based, LAST excluded)")
    parser.add_argument("--out", type=Path, default=None, help="also write skeleton.bvh, skeleton.json, poses.npz, report.txt here")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.groups is not None and args.groups < 1:
        parser.error("--groups must be at least 1")
    enable_float64()
    enable_compilation_cache()

    truth = None
    if args.simulate:
        trajectories, segment_of_marker, truth = simulated_trajectories(args.simulate, args.calibration_seconds, args.seed)
        source = f"simulated full-body markers on CMU '{args.simulate}' + {args.calibration_seconds:g} s range of motion"
        groups = args.groups or truth.num_segments
    else:
        try:
            data = read_c3d(args.file)  # metres, NaN gaps; computed/modelled points left out
        except (OSError, ValueError) as exc:
            parser.error(str(exc))
        trajectories = MarkerTrajectories.from_c3d(data)
        source = f"{args.file.name} ({data.units} → m)"
        groups = args.groups
    if args.frames:
        first, _, last = args.frames.partition(":")
        sel = slice(int(first) if first else None, int(last) if last else None)
        trajectories = MarkerTrajectories(trajectories.positions[sel], trajectories.labels, trajectories.fps)
    print(f"{source}: {trajectories.num_frames} frames at {trajectories.fps:g} Hz, {trajectories.num_markers} markers", flush=True)

    start = time.perf_counter()
    with warnings.catch_warnings(record=True):  # the same notes come back in result.notes and the report
        warnings.simplefilter("always")
        result = fit_marker_skeleton(trajectories, MarkerOptions(num_groups=groups, seed=args.seed))
    seconds = time.perf_counter() - start
    print(result.report())  # segments with their markers, topology, joints, segment lengths, IK residuals
    if truth is not None:
        check_topology(result, segment_of_marker, truth)
    if args.out is not None:
        paths = result.save(args.out)
        print("wrote " + ", ".join(str(p) for p in paths.values()))
    print(f"\nfitted in {seconds:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
