"""The solve stage of a finished run, again: its time, LM steps and accuracy, and the time of one window's normal
equations, to compare two revisions of the solver on a real run (``benchmarks/compare.py``).

The run folder ``--run`` (e.g. one of ``benchmarks/suite.py``'s realistic runs) is copied into ``--out`` (its
frontend's large folders hard-linked, read only by the solve), its ``solve`` and ``outputs`` stages are forgotten,
and ``bcmocap run`` redoes them with the run's own config (``DIR/config.json``; ``--config`` another, e.g. with
another solver setting) on its capture. Reported:

- ``solve_seconds``: the stage's time (compilation included unless the compilation cache is warm);
- ``steps``, ``seconds_per_step``: the LM steps of all windows and the stage's seconds per step;
- ``normal_equations_seconds``: one assembly of the first window's normal equations, compiled (mean of 3);
- ``residuals_seconds``: one evaluation of its residuals, compiled (mean of 3);
- the run's metrics after the solve (joint position and angle errors, initial and solved).

    python benchmarks/compare.py HEAD WORKTREE --key solve_seconds --key normal_equations_seconds \\
        --key solved.joint_angle_error_deg -- benchmarks/solve_stage.py --run RUN --out {out} --json {json}
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json  # noqa: E402

LINKED = ("frontend", "reference_colmap")  # large, and only read after the frontend stage


def copy_run(run: Path, out: Path) -> None:
    """``run`` into ``out`` without its solve and outputs stages (the initial stage's files in ``solve/`` kept)."""
    if out.exists():
        raise SystemExit(f"{out}: exists; give a new --out")
    out.mkdir(parents=True)
    for item in run.iterdir():
        if item.name in LINKED:
            shutil.copytree(item, out / item.name, copy_function=os.link)
        elif item.name == "solve":
            (out / "solve").mkdir()
            for kept in ("correspondences", "initial.npz"):
                source = item / kept
                if source.is_dir():
                    shutil.copytree(source, out / "solve" / kept)
                elif source.exists():
                    shutil.copy2(source, out / "solve" / kept)
        elif item.name != "run.lock":
            (shutil.copytree if item.is_dir() else shutil.copy2)(item, out / item.name)
    log = json.loads((out / "run.json").read_text())
    for stage in ("solve", "outputs"):
        log["stages"].pop(stage, None)
    (out / "run.json").write_text(json.dumps(log, indent=1))


def time_window(out: Path, capture, config, frames: int) -> tuple[float, float]:
    """Seconds of one compiled assembly of the first window's normal equations and of its residuals (mean of 3)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    from bcmocap.io.run_folder import load_motion
    from bcmocap.kinematics.skeleton import Motion
    from bcmocap.pipeline.run import RunContext, solve_problem
    from bcmocap.solver.solve import window_terms, with_start_values
    from bcmocap.solver.window import make_window_problem, normal_equations, residuals, window_history

    problem, options = solve_problem(RunContext(capture, config, out, lambda line: None))
    frames = min(frames, options.window, problem.num_frames)
    initial = load_motion(out / "solve" / "initial.npz")
    terms = window_terms(problem, 0, frames)
    extended = np.concatenate([np.zeros(window_history(terms), int), np.arange(frames)])
    values = with_start_values({}, terms, problem.num_frames)
    wp = make_window_problem(problem.skeleton, problem.rig, terms,
                             Motion(np.asarray(initial.root_position)[extended], np.asarray(initial.rotations)[extended]),
                             0, {}, None, {k: v[extended] for k, v in values.items()})
    y, z = jnp.zeros((wp.num_frames, wp.frame_size)), jnp.zeros(wp.num_statics)
    system = eqx.filter_jit(lambda wp, y, z: normal_equations(wp, y, z if z.size else None))
    evaluate = eqx.filter_jit(lambda wp, y, z: residuals(wp, y, z if z.size else None))
    out_times = []
    for fn in (system, evaluate):
        jax.block_until_ready(fn(wp, y, z))
        clock = time.perf_counter()
        for _ in range(3):
            jax.block_until_ready(fn(wp, y, z))
        out_times.append((time.perf_counter() - clock) / 3)
    return out_times[0], out_times[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", required=True, help="a finished run folder (its capture must be where run.json says)")
    ap.add_argument("--out", required=True, help="a new folder for the copy")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--window-frames", type=int, default=60, help="frames of the timed window (default 60)")
    ap.add_argument("--config", help="solve with this config instead of the run's own (its frontend, world, skeleton "
                                     "and initial settings must be the run's, or those stages are redone)")
    args = ap.parse_args()

    from bcmocap.compilation_cache import enable_compilation_cache
    from bcmocap.frontend import read_capture
    from bcmocap.pipeline.config import RunConfig
    from bcmocap.pipeline.run import run_pipeline
    from bcmocap.precision import enable_float64

    enable_float64()
    enable_compilation_cache()
    run, out = Path(args.run), Path(args.out)
    copy_run(run, out)
    if args.config:
        from bcmocap.pipeline.config import load_config

        config = load_config(args.config)
    else:
        config = RunConfig.from_dict(json.loads((out / "config.json").read_text()), where=str(out / "config.json"))
    capture = read_capture(json.loads((out / "run.json").read_text())["capture"])
    clock = time.perf_counter()
    run_pipeline(capture, out, config, log=lambda line: print(line, flush=True))
    total = time.perf_counter() - clock
    stages = json.loads((out / "run.json").read_text())["stages"]
    reports = json.loads((out / "solve" / "reports.json").read_text())["windows"]
    metrics = json.loads((out / "metrics.json").read_text())
    steps = sum(r["num_steps"] for r in reports)
    normal_seconds, residual_seconds = time_window(out, capture, config, args.window_frames)
    result = {
        "run": str(run), "solve_seconds": stages["solve"]["seconds"], "seconds": round(total, 1),
        "steps": steps, "seconds_per_step": stages["solve"]["seconds"] / max(steps, 1),
        "windows": [{k: r[k] for k in ("start", "stop", "num_steps", "converged", "final_cost", "seconds")}
                    for r in reports],
        "normal_equations_seconds": normal_seconds, "residuals_seconds": residual_seconds,
        "window_frames": args.window_frames,
        **{which: {k: metrics[which][k]["mean"] for k in ("joint_position_error_cm", "joint_angle_error_deg")}
           for which in ("initial", "solved")},
        "machine": machine(),
    }
    print(json.dumps({k: v for k, v in result.items() if k not in ("windows", "machine")}, indent=1))
    if args.json:
        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
