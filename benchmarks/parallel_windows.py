"""Independent windows (for a cluster) against the sequential sliding-window solve, on the standard walk.

On the standard simulated capture (CMU walk, 18-camera rig, ~300 points per camera-frame, 1 px noise, 10 %
outliers; 10 s by default, as in ``solver_speed.py``) the paper's problem is solved three ways from the same
initial motion (from the registered cameras):

- ``sequential``: :func:`bcmocap.solver.solve`, each window starting from the previous window's result;
- ``independent``: :func:`bcmocap.solver.solve_windows_independently` without the seam pass: every window
  from the initial motion, blended across the overlaps;
- ``independent + seams``: the same with the seam pass (a window centred on each seam, from the joined motion).

For each: mean joint position error (cm) and joint angle error (deg) against the ground truth, the total cost
½ Σ r² of Eq. (1) over the whole sequence at the result (:func:`bcmocap.solver.sequence_cost`, every frame and
pair counted once), the number of window-solves, the largest frame-to-frame joint position change at the
seams (cm) against elsewhere, and the time on this machine (all run one after the other here: the time says
nothing of a cluster's, where the independent windows run at once).

    python benchmarks/parallel_windows.py [--seconds 10] [--json FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from _common import write_json  # noqa: E402

from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.eval import evaluate_motion  # noqa: E402
from bcmocap.kinematics import joint_positions  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.sim import standard_capture  # noqa: E402
from bcmocap.solver import SolverOptions, sequence_cost, solve, solve_windows_independently, window_starts  # noqa: E402
from bcmocap.solver.objective import paper_problem  # noqa: E402


def seam_jumps(skeleton, motion, starts, window) -> tuple[float, float]:
    """Largest frame-to-frame joint position change (cm, over joints) at frames where windows meet (the shared
    frames and one either side), and the 99th percentile of it elsewhere."""
    positions = np.asarray(joint_positions(skeleton, motion))  # (T, J, 3)
    change = 100.0 * np.linalg.norm(np.diff(positions, axis=0), axis=-1).max(axis=1)  # (T - 1,) between t and t + 1
    seam = np.zeros(len(change), bool)
    for a, b in zip(starts, starts[1:]):
        seam[max(b - 2, 0):min(a + window + 1, len(change))] = True
    return float(change[seam].max()), float(np.percentile(change[~seam], 99))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="length of the walk (s)")
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args(argv)
    enable_float64()
    enable_compilation_cache()
    capture = standard_capture("walk", seconds=args.seconds, repeat=True)
    correspondences = capture.correspondences()
    initial = capture.initial_motion(correspondences)
    problem = paper_problem(correspondences, capture.skeleton, capture.rig)
    options = SolverOptions()
    window = min(options.window, capture.num_frames)
    starts = window_starts(capture.num_frames, window, options.overlap)
    print(f"{capture.num_frames} frames, {capture.rig.num_cameras} cameras, {len(starts)} windows of {window} "
          f"(overlap {options.overlap})")

    clock = time.perf_counter()
    solve(problem, initial, options)  # compiles every window shape (camera slots too): the times below are compiled code's
    print(f"first (compiling) sequential solve: {time.perf_counter() - clock:.1f} s")
    runs = {
        "sequential": lambda: solve(problem, initial, options),
        "independent": lambda: solve_windows_independently(problem, initial, options, seam_pass=False),
        "independent + seams": lambda: solve_windows_independently(problem, initial, options, seam_pass=True),
    }
    rows = {}
    initial_errors = evaluate_motion(capture.skeleton, initial, capture.motion)
    for name, run in runs.items():
        clock = time.perf_counter()
        solution = run()
        seconds = time.perf_counter() - clock
        errors = evaluate_motion(capture.skeleton, solution.motion, capture.motion)
        at_seams, elsewhere = seam_jumps(capture.skeleton, solution.motion, starts, window)
        rows[name] = {
            "joint_position_error_cm": errors["joint_position_error_cm"],
            "joint_angle_error_deg": errors["joint_angle_error_deg"],
            "total_cost": sequence_cost(problem, solution.motion, chunk=window),
            "window_solves": len(solution.reports),
            "lm_steps": sum(r.num_steps for r in solution.reports),
            "converged": solution.converged,
            "max_joint_step_at_seams_cm": at_seams,
            "p99_joint_step_elsewhere_cm": elsewhere,
            "seconds": seconds,
        }
    base = rows["sequential"]
    print(f"initial motion: joint position error {initial_errors['joint_position_error_cm']['mean']:.3f} cm, "
          f"joint angle error {initial_errors['joint_angle_error_deg']['mean']:.3f} deg (mean)")
    print(f"{'':22s} {'pos err cm':>10s} {'angle err °':>11s} {'total cost':>16s} {'Δcost rel.':>11s} {'solves':>6s} "
          f"{'LM steps':>8s} {'seam step cm':>12s} {'p99 step cm':>11s} {'time s':>7s}")
    for name, row in rows.items():
        row["cost_change_vs_sequential_relative"] = row["total_cost"] / base["total_cost"] - 1.0
        print(f"{name:22s} {row['joint_position_error_cm']['mean']:10.5f} {row['joint_angle_error_deg']['mean']:11.5f} "
              f"{row['total_cost']:16.4f} {row['cost_change_vs_sequential_relative']:11.2e} {row['window_solves']:6d} "
              f"{row['lm_steps']:8d} {row['max_joint_step_at_seams_cm']:12.4f} {row['p99_joint_step_elsewhere_cm']:11.4f} "
              f"{row['seconds']:7.1f}")
    print("times: one process on this machine, windows one after the other (a cluster runs the independent ones at once)")
    write_json(args.json, {
        "frames": capture.num_frames,
        "windows": len(starts),
        "window": window,
        "overlap": options.overlap,
        "initial": {k: initial_errors[k] for k in ("joint_position_error_cm", "joint_angle_error_deg")},
        "runs": rows,
    })
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
