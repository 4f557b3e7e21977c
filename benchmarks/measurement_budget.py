"""Measurement budget (issue 18, item 3): how accuracy and solve speed change with N, the measurements per
camera-frame that reach the solver (``frontend.max_measurements``), on the rendered 10 s walk.

For each N the capture goes through ``bcmocap run`` with its defaults but N, into ``OUT/N<N>/``. N only
decides which of a registration's measurements the store keeps, so the tracking passes (cached per camera
in ``frontend/tracks/``) are the same for every N: they are hard-linked from ``--tracks RUN`` (e.g. the run
folder of ``end_to_end.py`` on the same capture with the same frontend settings) or from the first N's run.
Per N: joint position and joint angle errors after the §5.1 similarity, the measurements per registered
camera-frame, and two solve speeds — the solve stage as run (a new N has new array shapes, so its first
window compiles a program) and the same solve again in the same process (compiled: the windows' own speed,
without a process's one-off loading of the program).

    python benchmarks/measurement_budget.py --capture CAPTURE --out DIR [--tracks RUN] [--values 200,300,400,600,0]
        [--json benchmarks/results/measurement_budget.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json  # noqa: E402

from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402


def link_tracks(source: Path, run: Path) -> None:
    """Hard-link ``source/frontend/tracks`` into ``run`` (the tracking passes' cache; never written in place)."""
    tracks = source / "frontend" / "tracks"
    if tracks.is_dir() and not (run / "frontend" / "tracks").exists():
        shutil.copytree(tracks, run / "frontend" / "tracks", copy_function=os.link)


def measure(capture: Path, run: Path, config) -> dict:
    """Run (or resume) ``bcmocap run`` into ``run``, then solve its problem again in this process."""
    from bcmocap.frontend import read_capture
    from bcmocap.pipeline import run_pipeline
    from bcmocap.pipeline.run import RunContext, load_motion, solve_problem
    from bcmocap.solver import solve

    log = run_pipeline(capture, run, config, log=lambda line: print(line, flush=True))
    metrics = json.loads((run / "metrics.json").read_text())
    ctx = RunContext(read_capture(capture), config, run, print)
    problem, options = solve_problem(ctx)
    initial = load_motion(run / "solve" / "initial.npz")
    solve(problem, initial, options)  # compiled here if the run's solve stage was reused
    clock = time.perf_counter()
    solve(problem, initial, options)
    warm = time.perf_counter() - clock
    store = problem.store
    counts = []
    for start in range(0, store.num_frames, 50):
        corr = store.frames(start, min(start + 50, store.num_frames))
        per = (corr.point_ids >= 0).sum(axis=-1)
        counts.append(per[per > 0])
    counts = np.concatenate(counts)
    frames = store.num_frames
    stage = log["stages"]["solve"]["seconds"]
    return {
        "joint_position_error_cm": metrics["solved"]["joint_position_error_cm"],
        "joint_angle_error_deg": metrics["solved"]["joint_angle_error_deg"],
        "initial": metrics["initial"],
        "measurements_per_camera_frame": {"mean": float(counts.mean()), "max": int(counts.max())},
        "solve_frames": frames,
        "solve_stage_seconds": stage,
        "solve_stage_frames_per_second": frames / stage,
        "warm_solve_seconds": warm,
        "warm_solve_frames_per_second": frames / warm,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--capture", type=Path, required=True, help="a rendered capture (end_to_end.py renders one)")
    parser.add_argument("--out", type=Path, required=True, help="one run folder per N goes here (resumed)")
    parser.add_argument("--tracks", type=Path, help="a run folder of the same capture whose tracking passes to reuse")
    parser.add_argument("--values", default="200,300,400,600,0", help="the N to compare (0: every measurement)")
    parser.add_argument("--config", type=Path, help="settings besides N (default: bcmocap run's defaults)")
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args(argv)
    enable_float64()
    enable_compilation_cache()
    from bcmocap.pipeline.config import load_config

    base = load_config(args.config)
    values = [int(v) for v in args.values.split(",")]
    rows = {}
    for n in values:
        run = args.out / f"N{n}"
        run.mkdir(parents=True, exist_ok=True)
        source = args.tracks or (args.out / f"N{values[0]}")
        if source != run:
            link_tracks(source, run)
        rows[str(n)] = measure(args.capture, run, base.with_overrides({"frontend.max_measurements": n}))
    print(f"\n{'N':>5} {'meas/frame':>11} {'joints cm':>10} {'angles °':>9} {'solve stage':>12} {'warm solve':>11}")
    for n, r in rows.items():
        print(f"{n:>5} {r['measurements_per_camera_frame']['mean']:>11.0f} "
              f"{r['joint_position_error_cm']['mean']:>10.3f} {r['joint_angle_error_deg']['mean']:>9.3f} "
              f"{r['solve_stage_frames_per_second']:>8.1f} f/s {r['warm_solve_frames_per_second']:>7.1f} f/s")
    write_json(args.json, {"capture": str(args.capture), "config": base.to_dict(), "values": rows,
                           "machine": machine()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
