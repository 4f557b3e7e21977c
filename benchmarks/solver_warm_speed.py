"""Warm solve speed of the paper's terms on the 10 s standard walk: the speed part of ``solver_speed.py`` alone,
repeated, with the summed cost and LM steps, to compare two commits on one machine.

Machine speed changes between sessions (the same code measured 111.6 frames/s on 2026-11-22 and 61–67 on
2026-11-26), so a regression is judged by running this script in two checkouts, alternately, in the same
conditions (e.g. ``git worktree add /tmp/old REV``; ``cd /tmp/old && python benchmarks/solver_warm_speed.py``):
the same cost and steps show that the two compute the same thing, the frames/s compare their speed.

    python benchmarks/solver_warm_speed.py [--repeats 3] [--json FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json  # noqa: E402

from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed solves after a first (compiling) one")
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args(argv)
    enable_float64()
    enable_compilation_cache()
    from bcmocap.sim import standard_capture
    from bcmocap.solver import SolverOptions, solve
    from bcmocap.solver.objective import paper_problem

    capture = standard_capture("walk", seconds=10, repeat=True)
    correspondences = capture.correspondences()
    initial = capture.initial_motion(correspondences)
    problem = paper_problem(correspondences, capture.skeleton, capture.rig)
    clock = time.perf_counter()
    solve(problem, initial, SolverOptions())
    first = time.perf_counter() - clock
    speeds = []
    for _ in range(args.repeats):
        clock = time.perf_counter()
        solution = solve(problem, initial, SolverOptions())
        speeds.append(capture.num_frames / (time.perf_counter() - clock))
    cost = sum(r.final_cost for r in solution.reports)
    steps = sum(r.num_steps for r in solution.reports)
    print(f"{capture.num_frames} frames: {', '.join(f'{s:.1f}' for s in speeds)} frames/s (first solve, compile "
          f"included, {first:.1f} s); cost {cost:.8f}, {steps} LM steps")
    write_json(args.json, {"frames": capture.num_frames, "frames_per_second": speeds, "first_solve_seconds": first,
                           "cost": cost, "lm_steps": steps, "machine": machine()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
