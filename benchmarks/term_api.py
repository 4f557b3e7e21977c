"""The term API against the code before it (issue 41 item 2), old and new alternating in one run.

Each run is a fresh process on one checkout (this tree, or ``--rev`` checked out as a git worktree) that solves the
standard walk (18 cameras, ~330 measurements per camera-frame, ``--seconds`` long) with the paper's terms plus the
three wearable-sensor terms of that checkout's ``examples/wearable_sensors`` (a gyroscope pair term, a foot-contact
pair term, a three-frame accelerometer term, so the system is block banded with bandwidth 2), their exact sensor
files simulated from the walk. Without the persistent compilation cache, so each run compiles:

- ``first_solve_s``: the first solve, compilation included; ``solve_s``: the same solve again, compiled;
  ``compile_s``: their difference;
- the solved motion and every window's final cost, compared between the two checkouts.

    python benchmarks/term_api.py --rev REV [--seconds 3] [--repeats 3] [--json benchmarks/results/term_api.json]

Figures: the largest difference of the solved root positions (m) and joint rotations (quaternion components) and of
the windows' final costs (relative), old against new; the ratio new/old of compile and solve times with their spread
over the alternating repeats.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))


def child(out: Path, seconds: float) -> None:
    """One run on the checkout this process imports bcmocap from (its cwd)."""
    import numpy as np

    from bcmocap.io.sensors import write_contacts, write_imu
    from bcmocap.precision import enable_float64
    from bcmocap.sim import standard_capture
    from bcmocap.sim.sensors import simulate_contacts, simulate_imu
    from bcmocap.solver import SolverOptions, solve
    from bcmocap.solver.objective import UserTerms, paper_problem

    enable_float64()
    sys.path.insert(0, str(Path.cwd() / "examples" / "wearable_sensors"))
    import sensor_terms

    capture = standard_capture("walk", seconds=seconds, repeat=True)
    corr = capture.correspondences()
    initial = capture.initial_motion(corr)
    trial = out.parent / f"{out.stem}_trial"
    trial.mkdir(parents=True, exist_ok=True)
    claps = np.array([0, capture.num_frames - 1])
    exact = dict(gyro_noise=0.0, gyro_bias=0.0, accel_noise=0.0, accel_bias=0.0)
    write_imu(trial / "imu.npz", simulate_imu(capture.skeleton, capture.rig, capture.motion, capture.fps, claps, **exact))
    write_contacts(trial / "contacts.npz", simulate_contacts(capture.skeleton, capture.motion, capture.fps, claps))
    factories = [UserTerms(f, {}, f.__name__) for f in (sensor_terms.gyroscope, sensor_terms.foot_contact,
                                                        sensor_terms.accelerometer)]
    problem = paper_problem(corr, capture.skeleton, capture.rig, extra_terms=factories, trial_folder=trial)
    options = SolverOptions(window=40, overlap=10)
    start = time.perf_counter()
    solve(problem, initial, options)
    first = time.perf_counter() - start
    start = time.perf_counter()
    solution = solve(problem, initial, options)
    again = time.perf_counter() - start
    np.savez(out, root_position=np.asarray(solution.motion.root_position), rotations=np.asarray(solution.motion.rotations),
             final_cost=np.array([r.final_cost for r in solution.reports]))
    out.with_suffix(".json").write_text(json.dumps({"first_solve_s": first, "solve_s": again, "frames": capture.num_frames,
                                                    "converged": all(r.converged for r in solution.reports)}))


def run_once(tree: Path, out: Path, seconds: float) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    env.pop("BCMOCAP_CACHE_DIR", None)
    subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", str(out), "--seconds", str(seconds)],
                   cwd=tree, env=env, check=True)
    return json.loads(out.with_suffix(".json").read_text())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rev", help="the code before the change (a git revision of this repository)")
    parser.add_argument("--seconds", type=float, default=3.0, help="length of the walk (s)")
    parser.add_argument("--repeats", type=int, default=3, help="alternating runs of each checkout")
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(args.child, args.seconds)
        return 0
    if not args.rev:
        parser.error("--rev is required")
    import numpy as np

    from _common import machine, write_json

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        old_tree = tmp / "old"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old_tree), args.rev], check=True,
                       capture_output=True)
        try:
            runs = {"old": [], "new": []}
            for k in range(args.repeats):
                for name, tree in (("old", old_tree), ("new", ROOT)) if k % 2 == 0 else (("new", ROOT), ("old", old_tree)):
                    runs[name].append(run_once(tree, tmp / f"{name}_{k}.npz", args.seconds))
                    print(f"repeat {k} {name}: first solve {runs[name][-1]['first_solve_s']:.1f} s, "
                          f"compiled {runs[name][-1]['solve_s']:.1f} s", flush=True)
            old, new = np.load(tmp / "old_0.npz"), np.load(tmp / "new_0.npz")
            difference = {
                "root_position_m": float(np.abs(old["root_position"] - new["root_position"]).max()),
                "rotations": float(np.abs(old["rotations"] - new["rotations"]).max()),
                "final_cost_relative": float((np.abs(old["final_cost"] - new["final_cost"]) / old["final_cost"]).max()),
            }
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old_tree)], check=False)

    def ratio(key: str) -> dict:
        values = [n[key] / o[key] if key != "compile_s" else (n["first_solve_s"] - n["solve_s"]) / (o["first_solve_s"] - o["solve_s"])
                  for o, n in zip(runs["old"], runs["new"])]
        return {"mean": float(np.mean(values)), "min": float(np.min(values)), "max": float(np.max(values))}

    result = {"rev": args.rev, "seconds": args.seconds, "repeats": args.repeats, "frames": runs["new"][0]["frames"],
              "difference_old_new": difference, "new_over_old": {k: ratio(k) for k in ("compile_s", "solve_s")},
              "runs": runs, "converged": all(r["converged"] for rs in runs.values() for r in rs), "machine": machine()}
    print(json.dumps({k: result[k] for k in ("difference_old_new", "new_over_old", "converged")}, indent=2))
    if args.json:
        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
