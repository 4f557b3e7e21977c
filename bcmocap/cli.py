"""The ``bcmocap`` command."""

from __future__ import annotations

import argparse
import os
import sys
import time

from .atomic import write_json_atomic
from .calibrate.command import add_calibrate_command
from .compilation_cache import enable_compilation_cache
from .frontend.command import add_frontend_command
from .frontend.init_command import add_init_command
from .io.messages import one_line_error
from .io.output_folder import output_folder
from .kcs.command import add_kcs_command
from .markers.command import add_markers_command
from .pipeline.command import add_batch_command, add_run_command
from .pipeline.view_command import add_view_command
from .precision import enable_float64
from .sim.studio_command import add_simulate_command


def _table(rows: list[tuple[str, dict]]) -> str:
    lines = [f"{'metric':<28}{'mean':>10}{'median':>10}{'max':>10}"]
    for name, stats in rows:
        lines.append(f"{name:<28}{stats['mean']:>10.3f}{stats['median']:>10.3f}{stats['max']:>10.3f}")
    return "\n".join(lines)


def run_demo(args: argparse.Namespace) -> int:
    """The full chain on a small rendered capture: pixels → frontend → skeleton → solver → outputs."""
    if args.simulated_measurements:
        return run_measurement_demo(args)
    enable_compilation_cache()
    from .pipeline.config import RunConfig
    from .pipeline.run import run_pipeline
    from .sim.studio import StudioSettings, write_capture

    out = output_folder("demo", args.out)
    if out is None:
        return 2
    start = time.perf_counter()
    settings = StudioSettings(motion=args.motion, seconds=args.seconds, rom_seconds=args.rom_seconds, seed=args.seed,
                              fps=args.fps, reference_photos=args.reference_photos, reference_width=640,
                              reference_height=480)
    print(f"rendering a {args.seconds:g} s '{args.motion}' capture and a {args.rom_seconds:g} s range-of-motion "
          f"trial at {args.fps:g} frames/s through the 18-camera rig into {out / 'capture'} ...", flush=True)
    try:
        write_capture(out / "capture", settings)
        config = RunConfig().with_overrides({"frontend.stride": args.stride, "frontend.rom_stride": args.rom_stride,
                                             "frontend.max_features": args.max_features,
                                             "solver.window": args.window, "solver.overlap": args.overlap})
        log = run_pipeline(out / "capture", out, config, log=lambda line: print(line, flush=True))
    except (FileExistsError, ValueError) as exc:
        print(f"bcmocap demo: {exc}", file=sys.stderr)
        return 2
    seconds = {stage: rec["seconds"] for stage, rec in log["stages"].items()}
    print(f"\ndone in {time.perf_counter() - start:.0f} s (stages this run: "
          + ", ".join(f"{k} {v:.0f} s" for k, v in seconds.items()) + f"); outputs in {out}")
    return 0


def run_measurement_demo(args: argparse.Namespace) -> int:
    """The solver alone on simulated measurements (no pixels): seconds instead of minutes."""
    enable_compilation_cache()
    from .eval import evaluate_motion
    from .io import write_bvh
    from .sim import standard_capture
    from .solver import SolverOptions, solve
    from .solver.objective import paper_problem

    out = output_folder("demo", args.out)
    if out is None:
        return 2
    start = time.perf_counter()
    print(f"simulating {args.seconds:g} s of CMU '{args.motion}' through the 18-camera rig ...", flush=True)
    capture = standard_capture(args.motion, seconds=args.seconds, seed=args.seed)
    correspondences = capture.correspondences()
    initial = capture.initial_motion(correspondences)
    n_obs = int((correspondences.weights > 0).sum())
    print(
        f"  {capture.num_frames} frames, {capture.rig.num_cameras} cameras, {len(capture.world.points)} scene points, "
        f"{n_obs / capture.num_frames / capture.rig.num_cameras:.0f} point measurements per camera-frame, "
        f"{(~correspondences.registered).mean() * 100:.1f} % camera-frames unregistered",
        flush=True,
    )
    problem = paper_problem(correspondences, capture.skeleton, capture.rig)
    solve_start = time.perf_counter()
    solution = solve(problem, initial, SolverOptions(window=args.window, overlap=args.overlap), progress=True)
    solve_seconds = time.perf_counter() - solve_start
    before = evaluate_motion(capture.skeleton, initial, capture.motion, capture.rig)
    after = evaluate_motion(capture.skeleton, solution.motion, capture.motion, capture.rig)
    print("\nbefore optimisation (IK from noisy registered cameras):")
    print(_table([(k.replace("_", " "), v) for k, v in before.items()]))
    print("\nafter optimisation:")
    print(_table([(k.replace("_", " "), v) for k, v in after.items()]))
    total = time.perf_counter() - start
    metrics = {
        **after,
        "initial": before,
        "frames": capture.num_frames,
        "seconds": total,
        "solve_seconds": solve_seconds,
        "motion": args.motion,
        "windows": [r.__dict__ for r in solution.reports],
        "converged": solution.converged,
    }
    write_json_atomic(out / "metrics.json", metrics)
    write_bvh(out / "motion.bvh", capture.skeleton, solution.motion, 1.0 / capture.fps)
    print(f"\nwrote {out / 'metrics.json'} and {out / 'motion.bvh'} ({total:.1f} s in all, solve {solve_seconds:.1f} s)")
    return 0


def add_demo_command(sub: argparse._SubParsersAction) -> None:
    demo = sub.add_parser(
        "demo", help="render a short capture and run the whole chain on its pixels (--simulated-measurements: "
                     "the solver alone)",
        description="Render a short capture (a 1 s CMU walk and a 2.5 s range-of-motion trial at 30 frames/s through "
                    "the 18-camera rig, as bcmocap simulate does) into OUT/capture and run `bcmocap run` on its "
                    "pixels: reference model, sync, SIFT, registration, skeleton from the range-of-motion trial, "
                    "solver, outputs, pictures and metrics.json against the rendered truth in OUT (about 2 minutes "
                    "on 2 cores; rerunning resumes). --simulated-measurements instead simulates the measurements "
                    "directly (1 px noise, 10 % outliers, 5 % unregistered camera-frames, SfM-like pose noise), "
                    "optimises them with the true skeleton and reports the solver's accuracy (about a minute).")
    demo.add_argument("--out", default="bcmocap-demo", help="output folder (default: ./bcmocap-demo)")
    demo.add_argument("--motion", default="walk", choices=["walk", "run", "jump"])
    demo.add_argument("--seconds", type=float, default=None,
                      help="length of the capture (s; default 1, or 2 with --simulated-measurements)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--window", type=int, default=60, help="frames per solver window")
    demo.add_argument("--overlap", type=int, default=10, help="frames shared by consecutive windows")
    demo.add_argument("--simulated-measurements", action="store_true",
                      help="skip pixels: simulate the measurements and run the solver alone")
    full = demo.add_argument_group("the full chain (default)")
    full.add_argument("--rom-seconds", type=float, default=2.5, help="length of the range-of-motion trial (s)")
    full.add_argument("--fps", type=float, default=30.0, help="frame rate of the rendered videos")
    full.add_argument("--reference-photos", type=int, default=24, help="reference photos of the room")
    full.add_argument("--stride", type=int, default=2, help="use every n-th frame of the capture trial")
    full.add_argument("--rom-stride", type=int, default=3,
                      help="use every n-th frame of the range-of-motion trial (3, as bcmocap run)")
    full.add_argument("--max-features", type=int, default=3000, help="SIFT features per image")

    def run(args: argparse.Namespace) -> int:
        if args.seconds is None:
            args.seconds = 2.0 if args.simulated_measurements else 1.0
        if args.seconds <= 0 or args.rom_seconds <= 0 or args.fps <= 0:
            demo.error("--seconds, --rom-seconds and --fps must be positive")
        if args.reference_photos < 4:
            demo.error("--reference-photos must be at least 4")
        return run_demo(args)

    demo.set_defaults(run=run)


# Each subcommand registers itself: ``add(subparsers)`` adds its parser and sets ``run=callable(args) -> int``.
# Modules are imported lazily inside their ``run`` so that ``bcmocap --help`` stays fast.
COMMANDS = [
    add_demo_command,
    add_markers_command,
    add_simulate_command,
    add_kcs_command,
    add_frontend_command,
    add_run_command,
    add_batch_command,
    add_view_command,
    add_calibrate_command,
    add_init_command,
]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bcmocap", description="Motion capture from body-mounted cameras.")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in COMMANDS:
        add(sub)
    args = parser.parse_args(argv)
    enable_float64()
    try:
        return int(args.run(args))
    except KeyboardInterrupt:
        print(f"bcmocap {args.command}: interrupted (rerun the same command to resume)", file=sys.stderr)
        return 130
    except (ValueError, OSError, MemoryError, FloatingPointError) as exc:
        # Expected failures of any stage (bad input files, a full disk, an impossible allocation, a solve
        # gone non-finite) end in one line naming what failed; BCMOCAP_TRACEBACK=1 shows where.
        if os.environ.get("BCMOCAP_TRACEBACK"):
            raise
        print(f"bcmocap {args.command}: {one_line_error(exc, getattr(args, 'out', None))}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
