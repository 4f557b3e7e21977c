"""Accuracy of the solver on the standard synthetic capture (known skeleton and camera mounts).

For each bundled CMU motion (walking 35_01, running 02_03, jumping 02_04), simulate the standard
capture (18 FOV fisheyes at 640×360, ~300 points per camera-frame, 1 px noise, 10 % outliers, 5 %
unregistered camera-frames, 1° / 2 cm SfM-like camera-pose noise), initialise from the noisy
registered camera poses, solve Eq. (1), and compare with the ground truth.

The row "estimated skeleton" runs the full chain of issue 3 on the same captures: skeleton and
mounts from a simulated range-of-motion trial (benchmarks/estimated_skeleton.py), initial poses from
the registered cameras through the estimated rig, the same solver; measurements come from the true
model.

    python benchmarks/accuracy.py [--json FILE] [--seconds S] [--motions walk run jump] [--known-skeleton-only]

Goals: known skeleton (issue 2) mean joint position error ≤ 1.0 cm and mean joint angle error ≤ 1.5° on
each motion; estimated skeleton (issue 3) ≤ 1.5 cm and ≤ 2.5°.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import solve_summary, write_json  # noqa: E402
from estimated_skeleton import GOAL_ANGLE_DEG, GOAL_POSITION_CM  # noqa: E402
from estimated_skeleton import run_motion as run_estimated_skeleton  # noqa: E402

from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.eval import evaluate_motion  # noqa: E402
from bcmocap.sim import standard_capture  # noqa: E402
from bcmocap.solver import SolverOptions, solve  # noqa: E402
from bcmocap.solver.objective import paper_problem  # noqa: E402


def run_motion(name: str, seconds: float | None, seed: int) -> dict:
    capture = standard_capture(name, seconds=seconds, seed=seed)
    correspondences = capture.correspondences()
    initial = capture.initial_motion(correspondences)
    start = time.perf_counter()
    solution = solve(paper_problem(correspondences, capture.skeleton, capture.rig), initial, SolverOptions())
    elapsed = time.perf_counter() - start
    return {
        **evaluate_motion(capture.skeleton, solution.motion, capture.motion, capture.rig),
        "initial": evaluate_motion(capture.skeleton, initial, capture.motion, capture.rig),
        **solve_summary(solution, correspondences, elapsed, capture.num_frames),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--seconds", type=float, default=None, help="length per motion (default: the whole trial)")
    parser.add_argument("--motions", nargs="+", default=["walk", "run", "jump"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--known-skeleton-only", action="store_true", help="skip the estimated-skeleton row")
    args = parser.parse_args(argv)
    enable_float64()
    enable_compilation_cache()
    results = {}
    print("known skeleton and mounts:")
    print(f"{'motion':<8}{'frames':>7}{'pos mean cm':>13}{'median':>8}{'max':>8}{'ang mean °':>12}{'median':>8}{'max':>8}{'init pos cm':>13}{'init ang °':>12}")
    for name in args.motions:
        r = run_motion(name, args.seconds, args.seed)
        results[name] = r
        p, a = r["joint_position_error_cm"], r["joint_angle_error_deg"]
        print(f"{name:<8}{r['frames']:>7}{p['mean']:>13.3f}{p['median']:>8.3f}{p['max']:>8.3f}{a['mean']:>12.3f}{a['median']:>8.3f}"
              f"{a['max']:>8.3f}{r['initial']['joint_position_error_cm']['mean']:>13.3f}{r['initial']['joint_angle_error_deg']['mean']:>12.3f}",
              flush=True)
    ok = all(r["joint_position_error_cm"]["mean"] <= 1.0 and r["joint_angle_error_deg"]["mean"] <= 1.5 for r in results.values())
    print(f"goal (≤ 1.0 cm and ≤ 1.5° mean on each motion): {'met' if ok else 'NOT met'}")
    payload = {"motions": results, "goal_met": ok}
    if not args.known_skeleton_only:
        estimated = {}
        print("\nestimated skeleton (range-of-motion trial → skeleton + mounts → initial poses → solver):")
        for name in args.motions:
            r = estimated[name] = run_estimated_skeleton(name, args.seconds, args.seed)
            p, a = r["joint_position_error_cm"], r["joint_angle_error_deg"]
            print(f"{name:<8}{r['frames']:>7}{p['mean']:>13.3f}{p['median']:>8.3f}{p['max']:>8.3f}{a['mean']:>12.3f}"
                  f"{a['median']:>8.3f}{a['max']:>8.3f}{r['initial']['joint_position_error_cm']['mean']:>13.3f}"
                  f"{r['initial']['joint_angle_error_deg']['mean']:>12.3f}", flush=True)
        est_ok = all(r["joint_position_error_cm"]["mean"] <= GOAL_POSITION_CM and r["joint_angle_error_deg"]["mean"] <= GOAL_ANGLE_DEG
                     for r in estimated.values())
        print(f"goal (≤ {GOAL_POSITION_CM} cm and ≤ {GOAL_ANGLE_DEG}° mean on each motion): {'met' if est_ok else 'NOT met'}")
        payload.update(estimated_skeleton=estimated, estimated_skeleton_goal_met=est_ok)
    write_json(args.json, payload)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
