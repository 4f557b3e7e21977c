"""Scale-out on Dask (issue 23): the same capture through ``bcmocap run`` with no cluster, ``local:1`` and
``local:2``, and a simulated schedule of a 10-minute capture on 8, 32 and 128 workers.

Renders a capture with the standard rig (or takes ``--capture``) and runs every stage three times into
fresh folders under ``--work``, with the same settings (``bcmocap demo``'s, in chunks of ``--chunk-frames``
processed frames and with ``solver.windows`` independent): only the cluster differs. Prints
per mode the wall time, the time the run spent waiting for tasks and the time it worked alone (the serial
part: reference model, sync, reading caches, world, skeleton, initial motion, joining windows, outputs);
the speedup of ``local:2`` over ``local:1`` (goal ≥ 1.7); whether the outputs are the same (largest
difference of the solved joint positions, and which arrays are bitwise equal); the tasks and the critical
path (the serial part plus, per phase, its longest task); and the projected wall time of a 10-minute
capture, from the measured task durations scaled to that length (per-camera tracking ∝ frames, chunks
and windows ∝ their count; the ROM trial and the reference model fixed) and list-scheduled on W workers
(a simulation of the schedule, stated as such).

    python benchmarks/scale_out.py --solve-run RUN_DIR --json benchmarks/results/scale_out.json
"""

from __future__ import annotations

import argparse
import heapq
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json  # noqa: E402

from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.pipeline.cluster import open_executor  # noqa: E402
from bcmocap.pipeline.config import RunConfig  # noqa: E402
from bcmocap.pipeline.run import run_pipeline  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.sim.studio import StudioSettings, write_capture  # noqa: E402

MODES = ("local:2", "local:1", "none")  # the speedup's two runs first
PROJECTED_WORKERS = (8, 32, 128)
PROJECTED_SECONDS = 600.0


def run_mode(capture: Path, out: Path, config: RunConfig, mode: str, stop_after: str | None = None,
             fresh: bool = True) -> dict:
    """One run (fresh: every stage; else resumed) on the cluster ``mode``; wall time, tasks and the run log."""
    enable_float64()
    enable_compilation_cache()
    if fresh:
        shutil.rmtree(out, ignore_errors=True)
    lines: list[str] = []

    def say(line: str) -> None:
        lines.append(line)
        print(f"  [{mode}] {line}", flush=True)

    clock = time.perf_counter()
    with open_executor(None if mode == "none" else mode, log=say) as executor:
        started = time.perf_counter()
        log = run_pipeline(capture, out, config, executor=executor, log=say, stop_after=stop_after)
        wall = time.perf_counter() - started
    waited = _union([(a, b) for _, a, b in executor.calls])
    return {"wall_seconds": wall, "with_cluster_start_seconds": time.perf_counter() - clock,
            "waiting_for_tasks_seconds": waited, "serial_seconds": wall - waited,
            "tasks": [list(t) for t in executor.tasks],
            "calls": [[label, a - started, b - started] for label, a, b in executor.calls],
            "stage_seconds": {stage: rec["seconds"] for stage, rec in log["stages"].items()}}


SOLVE_INPUTS = ("run.json", "config.json", "model", "world", "solve/initial.npz", "solve/correspondences",
                "frontend/rom/registration.json", "frontend/rom/correspondences",
                "frontend/capture/registration.json", "frontend/capture/correspondences")


def solve_mode(run_dir: Path, out: Path, mode: str) -> dict:
    """The solve stage of a finished run redone with independent windows on the cluster ``mode``, in a copy
    of what it needs; solved twice, the second timed (the window solve then comes from JAX's persistent
    compilation cache in every process, as in any run after the first)."""
    shutil.rmtree(out, ignore_errors=True)
    for name in SOLVE_INPUTS:
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree if (run_dir / name).is_dir() else shutil.copy2)(run_dir / name, out / name)
    base = json.loads((run_dir / "config.json").read_text())
    config = RunConfig.from_dict(base).with_overrides({"solver.windows": "independent", "outputs.pictures": False})
    capture = Path(json.loads((run_dir / "run.json").read_text())["capture"])
    for attempt in range(2):
        log = json.loads((out / "run.json").read_text())
        for stage in ("solve", "outputs"):
            log["stages"].pop(stage, None)
        (out / "run.json").write_text(json.dumps(log))
        result = run_mode(capture, out, config, mode, stop_after="solve", fresh=False)
    result["solve_seconds"] = result["stage_seconds"]["solve"]
    return result


def in_fresh_process(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` in a new Python process, as each ``bcmocap run`` is: no mode inherits another's
    warm state (imported modules, compiled programs, OpenCV's thread pool)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(fn, *args, **kwargs).result()


def _union(intervals: list[tuple[float, float]]) -> float:
    """Length of the union of ``[a, b)`` intervals (map calls of the two trials overlap)."""
    total, end = 0.0, -np.inf
    for a, b in sorted(intervals):
        if b > end:
            total += b - max(a, end)
            end = b
    return total


def compare(work: Path, reference: str, mode: str) -> dict:
    """The frontend's correspondence stores (bitwise) and the solved motions (largest joint position
    difference) of ``mode`` against ``reference``."""
    from bcmocap.correspondence_store import CorrespondenceStore
    from bcmocap.kinematics import joint_positions
    from bcmocap.pipeline.run import load_model, load_motion

    folder = {m: work / f"out-{m.replace(':', '')}" for m in (reference, mode)}
    stores = {}
    for trial in ("rom", "capture"):
        p, q = (CorrespondenceStore.open(folder[m] / "frontend" / trial / "correspondences").load()
                for m in (reference, mode))
        stores[trial] = all(np.array_equal(getattr(p, f), getattr(q, f), equal_nan=True)
                            for f in ("point_ids", "pixels", "weights", "registered", "world_from_camera", "points"))
    out = {"frontend_correspondences_bitwise_equal": stores, "max_joint_position_difference_cm": 0.0,
           "motion_arrays_bitwise_equal": []}
    solved = {m: work / f"solve-{m.replace(':', '')}" for m in (reference, mode)}
    if all((d / "solve" / "motion.npz").is_file() for d in solved.values()):
        skeleton, _ = load_model(solved[reference])
        a, b = (load_motion(solved[m] / "solve" / "motion.npz") for m in (reference, mode))
        joints = np.asarray(joint_positions(skeleton, a)) - np.asarray(joint_positions(skeleton, b))
        out["max_joint_position_difference_cm"] = float(np.max(np.abs(joints))) * 100.0
        out["motion_arrays_bitwise_equal"] = [f for f in ("root_position", "rotations")
                                              if np.array_equal(getattr(a, f), getattr(b, f))]
    return out


def _phases(tasks: list[list]) -> dict[str, list[float]]:
    out: dict[str, list[float]] = {}
    for label, seconds in tasks:
        out.setdefault(label, []).append(seconds)
    return out


#: Phases of a run in the order they depend on each other; per trial, cameras before chunks.
_CHAINS = {"rom": ("track rom", "sift rom", "register rom"), "capture": ("track capture", "sift capture", "register capture")}
_SOLVE = ("window", "seam")


def critical_path(result: dict) -> float:
    """The serial part plus, along the run's chain of phases, each phase's longest task (the two trials'
    chains side by side: the longer counts)."""
    phases = _phases(result["tasks"])
    longest = {k: max(v) for k, v in phases.items()}
    trials = max(sum(longest.get(p, 0.0) for p in chain) for chain in _CHAINS.values())
    return result["serial_seconds"] + trials + sum(longest.get(p, 0.0) for p in _SOLVE)


def simulate(tasks: dict[str, list[float]], serial: float, scale_frontend: float, scale_solve: float,
             workers: int) -> float:
    """Wall time of the run's phases list-scheduled on ``workers`` (longest task first, a phase after the
    one it depends on; the two trials' chains side by side), plus its serial part.

    ``tasks``: phase → measured durations; the capture trial's phases are scaled by ``scale_frontend``
    (tracking or SIFT: each camera's task that many times longer; chunks: that many times as many), the
    solve's by ``scale_solve`` (windows and seams: that many times as many); the ROM trial is unchanged.
    """
    def scaled(phase: str) -> list[float]:
        durations = tasks.get(phase, [])
        if phase in _SOLVE:
            scale = scale_solve
        elif phase.endswith("capture"):
            scale = scale_frontend
        else:
            return list(durations)  # the ROM trial has its own length
        if phase.startswith(("track", "sift")):
            return [d * scale for d in durations]
        count = int(round(len(durations) * scale))
        return [durations[i % len(durations)] for i in range(count)] if durations else []

    free = [0.0] * workers  # each worker's next free time
    heapq.heapify(free)
    ready = {"rom": 0.0, "capture": 0.0}
    pending = [(trial, list(chain)) for trial, chain in _CHAINS.items()]
    while any(chain for _, chain in pending):  # the two chains interleave, each phase after its trial's last
        for trial, chain in pending:
            if not chain:
                continue
            phase = chain.pop(0)
            ends = []
            for d in sorted(scaled(phase), reverse=True):
                start = max(heapq.heappop(free), ready[trial])
                heapq.heappush(free, start + d)
                ends.append(start + d)
            ready[trial] = max(ends, default=ready[trial])
    now = max(ready.values())
    for phase in _SOLVE:
        free = [now] * workers
        ends = []
        for d in sorted(scaled(phase), reverse=True):
            start = heapq.heappop(free)
            heapq.heappush(free, start + d)
            ends.append(start + d)
        now = max(ends, default=now)
    return now + serial


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--capture", type=Path, help="capture folder (default: render one into --work)")
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "bcmocap-scale-out",
                        help="folder for the rendered capture and the runs (default: bcmocap-scale-out in the temp folder)")
    parser.add_argument("--seconds", type=float, default=4.0, help="capture trial to render (s)")
    parser.add_argument("--rom-seconds", type=float, default=2.5, help="range-of-motion trial to render (s)")
    parser.add_argument("--chunk-frames", type=int, default=10, help="frontend.chunk_frames")
    parser.add_argument("--window", type=int, default=20, help="solver.window")
    parser.add_argument("--overlap", type=int, default=5, help="solver.overlap")
    parser.add_argument("--modes", nargs="+", default=list(MODES))
    parser.add_argument("--stop-after", default="frontend",
                        help="stage after which the runs on the rendered capture stop (default frontend: on so short a "
                             "range-of-motion trial the skeleton stage can fail; the solve is measured on --solve-run)")
    parser.add_argument("--solve-run", type=Path,
                        help="a finished `bcmocap run` folder (e.g. the 10 s walk's, made by benchmarks/custom_terms.py) "
                             "whose solve stage is redone per mode with independent windows (default: not measured)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    enable_float64()
    enable_compilation_cache()
    capture = args.capture
    if capture is None:
        capture = args.work / "capture"
        if not (capture / "capture.json").is_file():
            print(f"rendering a {args.seconds:g} s walk and a {args.rom_seconds:g} s ROM trial into {capture} ...",
                  flush=True)
            write_capture(capture, StudioSettings(seconds=args.seconds, rom_seconds=args.rom_seconds, fps=30.0,
                                                  reference_width=640, reference_height=480, seed=0), progress=False)
    config = RunConfig().with_overrides({  # bcmocap demo's settings, in chunks and independent windows
        "frontend.rom_stride": 2, "frontend.max_features": 3000, "frontend.chunk_frames": args.chunk_frames,
        "solver.windows": "independent", "solver.window": args.window, "solver.overlap": args.overlap,
        # as benchmarks/realism.py: a foot the short ROM trial turns about two axes only is fixed as a hinge
        "skeleton.degenerate": "hinge", "skeleton.max_centre_std_cm": 10.0})
    results = {}
    for mode in args.modes:
        print(f"{mode}: bcmocap run ...", flush=True)
        results[mode] = in_fresh_process(run_mode, capture, args.work / f"out-{mode.replace(':', '')}", config, mode,
                                         stop_after=args.stop_after or None)
        print(f"{mode}: {results[mode]['wall_seconds']:.1f} s", flush=True)
        if args.solve_run is not None:
            results[mode]["solve"] = in_fresh_process(solve_mode, args.solve_run,
                                                      args.work / f"solve-{mode.replace(':', '')}", mode)
            print(f"{mode}: solve stage {results[mode]['solve']['solve_seconds']:.1f} s", flush=True)
        if args.json:  # what is measured so far, in case a later mode is stopped
            write_json(args.json.with_suffix(".partial.json"), {"runs": results, "machine": machine()})
    reference = "none" if "none" in args.modes else args.modes[0]
    same = {m: compare(args.work, reference, m) for m in args.modes if m != reference}
    worst = max((s["max_joint_position_difference_cm"] for s in same.values()), default=0.0)
    base = results.get("local:2") or results[args.modes[-1]]
    solve_base = base.get("solve", {"tasks": [], "serial_seconds": 0.0, "calls": [], "stage_seconds": {}})
    phases = _phases(base["tasks"] + solve_base["tasks"])
    capture_seconds = json.loads((capture / "capture.json").read_text()).get("settings", {}).get("seconds", args.seconds)
    scale_frontend = PROJECTED_SECONDS / float(capture_seconds)
    scale_solve, fixed = 0.0, 0.0
    if args.solve_run is not None:
        log = json.loads((args.solve_run / "run.json").read_text())
        solve_frames = int(log["stages"]["frontend"]["capture"]["frames"])
        fps = float(np.load(args.solve_run / "motion.npz")["fps"])
        scale_solve = PROJECTED_SECONDS / (solve_frames / fps)
        fixed = sum(log["stages"][s]["seconds"] for s in ("world", "skeleton"))  # do not grow with the length
        grows = sum(log["stages"][s]["seconds"] for s in ("initial", "outputs"))  # grow with it
    else:
        grows = 0.0
    # Serial parts: the frontend's (sync, reference model, reading caches, writing stores) scaled with the length
    # (conservative: the reference model does not grow), the solve's (cutting windows, joining) likewise.
    serial = base["serial_seconds"] * scale_frontend + (solve_base["serial_seconds"] + grows) * scale_solve + fixed
    projected = {str(w): simulate(phases, serial, scale_frontend, scale_solve, w) for w in PROJECTED_WORKERS}
    wall = {m: r["wall_seconds"] + r.get("solve", {}).get("solve_seconds", 0.0) for m, r in results.items()}
    speedup = wall["local:1"] / wall["local:2"] if {"local:1", "local:2"} <= set(wall) else None
    print(f"\n{'mode':<10}{'frontend s':>11}{'waiting s':>11}{'serial s':>10}{'tasks':>7}{'solve s':>9}{'sum s':>8}")
    for m, r in results.items():
        print(f"{m:<10}{r['wall_seconds']:>11.1f}{r['waiting_for_tasks_seconds']:>11.1f}{r['serial_seconds']:>10.1f}"
              f"{len(r['tasks']):>7}{r.get('solve', {}).get('solve_seconds', float('nan')):>9.1f}{wall[m]:>8.1f}")
    if speedup is not None:
        front = results["local:1"]["wall_seconds"] / results["local:2"]["wall_seconds"]
        print(f"speedup of local:2 over local:1: {speedup:.2f} (goal ≥ 1.7); frontend alone {front:.2f}")
    print("same result: " + "; ".join(f"{m}: frontend stores bitwise equal {s['frontend_correspondences_bitwise_equal']}, "
                                       f"solved joints differ ≤ {s['max_joint_position_difference_cm']:.2e} cm "
                                       f"(bitwise equal arrays: {s['motion_arrays_bitwise_equal']})"
                                       for m, s in same.items()))
    critical = critical_path(base) + critical_path(solve_base) if "solve" in base else critical_path(base)
    print(f"critical path (local:2): {critical:.1f} s; tasks per phase: "
          + ", ".join(f"{k} {len(v)} (longest {max(v):.1f} s)" for k, v in phases.items()))
    print(f"projected wall time of a {PROJECTED_SECONDS / 60:.0f}-minute capture (simulated schedule): "
          + ", ".join(f"{w} workers {v / 60:.1f} min" for w, v in projected.items()))
    if args.json:
        write_json(args.json, {
            "wall_seconds": wall, "speedup_2_workers": speedup, "same_result": worst <= 0.01 and all(
                all(s["frontend_correspondences_bitwise_equal"].values()) for s in same.values()),
            "max_joint_position_difference_cm": worst, "comparison": same,
            "critical_path_seconds": critical, "task_count": len(base["tasks"]) + len(solve_base["tasks"]),
            "tasks_per_phase": {k: {"count": len(v), "seconds_total": sum(v), "seconds_longest": max(v)}
                                for k, v in phases.items()},
            "projected_seconds_10min_capture": projected,
            "projection": {"method": "list schedule of the measured tasks scaled to the length (a simulation)",
                           "scale_frontend": scale_frontend, "scale_solve": scale_solve,
                           "serial_seconds": serial, "fixed_world_skeleton_seconds": fixed},
            "runs": results, "config": config.to_dict(), "capture": str(capture),
            "solve_run": str(args.solve_run), "machine": machine()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
