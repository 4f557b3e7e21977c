"""Synthetic benchmark: simulate the standard capture, solve Eq. (1) and score it against the ground truth.

The standard synthetic capture (``bcmocap.sim.standard_capture``) plays a bundled CMU motion through the
paper's 18-camera rig: ~300 scene-point measurements per camera-frame with 1 px noise and 10 % outliers,
5 % of the camera-frames unregistered, and SfM-like noise on the registered camera poses. The solver
starts from the motion fitted to those noisy camera poses (``capture.initial_motion``) and minimises
Eq. (1) in overlapping windows (``bcmocap.solver``); ``bcmocap.eval.evaluate_motion`` gives the
paper's figures (§5.1) before and after. This is ``bcmocap demo --simulated-measurements`` /
``benchmarks/accuracy.py`` in a few lines of the public API.

    python examples/synthetic_benchmark.py [--motion walk|run|jump] [--seconds 1.0] [--window 60] [--seed 0]
"""

from __future__ import annotations

import argparse
import time

from bcmocap.compilation_cache import enable_compilation_cache
from bcmocap.precision import enable_float64
from bcmocap.eval import evaluate_motion
from bcmocap.sim import CMU_TRIALS, standard_capture
from bcmocap.solver import SolverOptions, solve
from bcmocap.solver.objective import paper_problem

METRICS = {
    "joint_position_error_cm": "joint position (cm)",
    "joint_angle_error_deg": "joint angle (deg)",
    "camera_centre_error_cm": "camera centre (cm)",
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--motion", default="walk", choices=sorted(CMU_TRIALS), help="bundled CMU trial (default: walk)")
    parser.add_argument("--seconds", type=float, default=1.0, help="length of motion to simulate (default: 1 s = 60 frames)")
    parser.add_argument("--window", type=int, default=60, help="frames per solver window (default: 60)")
    parser.add_argument("--overlap", type=int, default=10, help="frames shared by consecutive windows (default: 10)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the scene and the measurements")
    args = parser.parse_args(argv)
    if not args.seconds > 0:
        parser.error("--seconds must be positive")
    if not 0 <= args.overlap < args.window:
        parser.error("--overlap must be in [0, --window)")
    enable_float64()
    enable_compilation_cache()  # later runs skip most of the XLA compilation

    start = time.perf_counter()
    capture = standard_capture(args.motion, seconds=args.seconds, seed=args.seed)
    correspondences = capture.correspondences()
    initial = capture.initial_motion(correspondences)  # IK from the noisy registered camera poses
    print(f"simulated {capture.num_frames} frames of CMU '{args.motion}' ({CMU_TRIALS[args.motion][2]}) at "
          f"{capture.fps:g} fps: {capture.rig.num_cameras} cameras, {len(capture.world.points)} scene points, "
          f"{int((correspondences.weights > 0).sum())} point measurements, "
          f"{(~correspondences.registered).mean() * 100:.1f} % camera-frames unregistered", flush=True)

    problem = paper_problem(correspondences, capture.skeleton, capture.rig)
    options = SolverOptions(window=args.window, overlap=args.overlap)  # one window if the capture is shorter
    solve_start = time.perf_counter()
    solution = solve(problem, initial, options)
    solve_seconds = time.perf_counter() - solve_start

    before = evaluate_motion(capture.skeleton, initial, capture.motion, capture.rig)
    after = evaluate_motion(capture.skeleton, solution.motion, capture.motion, capture.rig)
    steps = sum(r.num_steps for r in solution.reports)
    print(f"solved in {solve_seconds:.1f} s ({len(solution.reports)} window(s), {steps} Levenberg–Marquardt steps, "
          f"{'converged' if solution.converged else 'NOT converged'})\n")
    print(f"{'mean error':<22}{'before':>10}{'after':>10}   (after: median / max)")
    for key, label in METRICS.items():
        b, a = before[key], after[key]
        print(f"{label:<22}{b['mean']:>10.3f}{a['mean']:>10.3f}   ({a['median']:.3f} / {a['max']:.3f})")
    print(f"\ntotal {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
