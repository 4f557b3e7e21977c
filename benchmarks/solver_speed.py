"""Speed and memory of the whole-sequence optimisation on the standard rig.

- frames per second of the windowed structured LM on a 10 s walk (18 cameras, ~300 points per
  camera-frame), compiled code only; compile time reported apart;
- the same residuals solved by scipy.optimize.least_squares (method "trf", finite differences with the
  sparse Jacobian pattern, as a reference implementation would) on a short sequence, and our solver
  on the same sequence, measured in this run: ``speedup_vs_scipy`` is the ratio of their times;
- peak resident memory of a fresh process solving 10 s and 60 s sequences whose measurements are
  simulated window by window (the CMU walk played back and forth to reach 60 s).

    python benchmarks/solver_speed.py [--json FILE] [--seconds 10] [--scipy-seconds 1] [--rss 10 60]

Goals (issue 2): ≥ 60 frames/s, ≥ 10× scipy, peak memory that does not grow with sequence length.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.optimize  # noqa: E402
import scipy.sparse  # noqa: E402
from _common import peak_rss_mb, write_json  # noqa: E402

from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.residuals import CameraPairTerm, PairTerm  # noqa: E402
from bcmocap.sim import standard_capture  # noqa: E402
from bcmocap.solver import SolverOptions, solve, whole_sequence_residual_function  # noqa: E402
from bcmocap.solver.objective import paper_problem  # noqa: E402
from bcmocap.solver.window import WindowProblem, residuals  # noqa: E402


def jacobian_sparsity(problem, num_frames: int) -> scipy.sparse.csr_matrix:
    """Which residual rows depend on which frame's variables, in the order of the residual vector."""
    d = problem.skeleton.num_dofs
    terms = tuple(problem.window(0, num_frames))
    reference = problem.skeleton.rest_motion(num_frames + 1)  # only shapes matter here
    wp = WindowProblem(problem.skeleton, problem.rig, terms, reference, jnp.asarray(False))
    shapes = jax.eval_shape(lambda y: residuals(wp, y), jnp.zeros((num_frames, d)))
    rows, cols, offset = [], [], 0
    for term, shape in zip(terms, shapes):
        per_frame = int(np.prod(shape.shape[1:]))
        frames = np.repeat(np.arange(num_frames), per_frame)
        r = offset + np.arange(num_frames * per_frame)
        lags = (0, 1) if isinstance(term, (PairTerm, CameraPairTerm)) else (0,)
        for lag in lags:
            keep = frames - lag >= 0
            rows.append(np.repeat(r[keep], d))
            cols.append(((frames[keep] - lag)[:, None] * d + np.arange(d)).ravel())
        offset += num_frames * per_frame
    data = np.ones(sum(len(x) for x in rows), bool)
    return scipy.sparse.csr_matrix((data, (np.concatenate(rows), np.concatenate(cols))), shape=(offset, num_frames * d))


def timed_solve(problem, initial, options):
    start = time.perf_counter()
    solution = solve(problem, initial, options)
    return solution, time.perf_counter() - start


def measure_speed(seconds: float, scipy_seconds: float) -> dict:
    capture = standard_capture("walk", seconds=seconds, repeat=True)
    correspondences = capture.correspondences()
    initial = capture.initial_motion(correspondences)
    problem = paper_problem(correspondences, capture.skeleton, capture.rig)
    options = SolverOptions()
    obs = float((correspondences.weights > 0).sum() / correspondences.registered.sum())
    print(f"{capture.num_frames} frames, {capture.rig.num_cameras} cameras, {obs:.0f} point measurements per registered camera-frame")

    # compile time: the first solve of the whole sequence minus the same solve once compiled (the timed
    # one), so every window shape, camera slots included, is compiled before timing
    _, cold = timed_solve(problem, initial, options)
    solution, elapsed = timed_solve(problem, initial, options)
    warm = elapsed
    steps = [r.num_steps for r in solution.reports]
    fps = capture.num_frames / elapsed
    print(f"bcmocap: {elapsed:.1f} s for {capture.num_frames} frames = {fps:.1f} frames/s "
          f"({len(steps)} windows of {options.window}, overlap {options.overlap}, {np.mean(steps):.1f} LM steps per window); "
          f"compile {cold - warm:.1f} s")

    # scipy reference on a short sequence, and ours on the same frames
    n = int(round(scipy_seconds * capture.fps))
    short = paper_problem(correspondences.frames(0, n), capture.skeleton, capture.rig)
    ours_short, ours_seconds = timed_solve(short, initial[:n], SolverOptions(window=n, overlap=0))
    _, ours_seconds = timed_solve(short, initial[:n], SolverOptions(window=n, overlap=0))  # compiled
    fn = whole_sequence_residual_function(short, initial[:n])
    fn_np = lambda y: np.asarray(fn(jnp.asarray(y)))
    fn_np(np.zeros(n * capture.skeleton.num_dofs))  # compile
    pattern = jacobian_sparsity(short, n)
    start = time.perf_counter()
    ref = scipy.optimize.least_squares(fn_np, np.zeros(n * capture.skeleton.num_dofs), jac_sparsity=pattern, method="trf")
    scipy_seconds_taken = time.perf_counter() - start
    ours_cost = ours_short.reports[0].final_cost
    print(f"scipy trf (sparse FD Jacobian) on {n} frames: {scipy_seconds_taken:.1f} s, {ref.nfev} evaluations, cost {ref.cost:.6g}; "
          f"bcmocap on the same frames: {ours_seconds:.2f} s, cost {ours_cost:.6g} → {scipy_seconds_taken / ours_seconds:.1f}× faster")
    return {
        "frames": capture.num_frames,
        "frames_per_second": fps,
        "solve_seconds": elapsed,
        "compile_seconds": cold - warm,
        "lm_steps_per_window": float(np.mean(steps)),
        "observations_per_camera_frame": obs,
        "scipy": {"frames": n, "seconds": scipy_seconds_taken, "cost": float(ref.cost), "nfev": int(ref.nfev),
                  "bcmocap_seconds": ours_seconds, "bcmocap_cost": ours_cost},
        "speedup_vs_scipy": scipy_seconds_taken / ours_seconds,
    }


def rss_child(seconds: float) -> None:
    """Solve a sequence whose measurements are simulated window by window; print peak RSS as JSON."""
    enable_float64()
    enable_compilation_cache()
    capture = standard_capture("walk", seconds=seconds, repeat=True)
    initial = capture.initial_motion()
    start = time.perf_counter()
    solution = solve(capture.lazy_problem(), initial, SolverOptions())
    print(json.dumps({"frames": capture.num_frames, "seconds": time.perf_counter() - start,
                      "peak_rss_mb": peak_rss_mb(), "converged": solution.converged}))


def measure_rss(seconds: float) -> dict:
    out = subprocess.run([sys.executable, __file__, "--rss-child", str(seconds)], check=True, capture_output=True, text=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    print(f"{seconds:g} s sequence ({result['frames']} frames, measurements simulated per window): "
          f"peak RSS {result['peak_rss_mb']:.0f} MB, {result['seconds']:.0f} s (simulation included)")
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--seconds", type=float, default=10.0, help="length of the speed run")
    parser.add_argument("--scipy-seconds", type=float, default=1.0, help="length of the scipy comparison")
    parser.add_argument("--rss", type=float, nargs="*", default=[10.0, 60.0], help="lengths for the memory runs")
    parser.add_argument("--rss-child", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.rss_child is not None:
        rss_child(args.rss_child)
        return 0
    enable_float64()
    enable_compilation_cache()
    result = measure_speed(args.seconds, args.scipy_seconds)
    rss = {f"{s:g}s": measure_rss(s) for s in args.rss}
    result["peak_rss_mb"] = {k: v["peak_rss_mb"] for k, v in rss.items()}
    result["memory_runs"] = rss
    goals = {
        "frames_per_second >= 60": result["frames_per_second"] >= 60,
        "speedup_vs_scipy >= 10": result["speedup_vs_scipy"] >= 10,
    }
    if len(rss) >= 2:
        sizes = [v["peak_rss_mb"] for v in rss.values()]
        goals["peak memory flat (largest ≤ 1.1 × smallest)"] = max(sizes) <= 1.1 * min(sizes)
    for goal, met in goals.items():
        print(f"goal {goal}: {'met' if met else 'NOT met'}")
    result["goals"] = goals
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
