"""Scale-out on Dask (issue 23): the same capture through ``bcmocap run`` with no cluster, ``local:1`` and
``local:2``, and a simulated schedule of a 10-minute capture on 8, 32 and 128 workers.

Renders a capture with the standard rig (or takes ``--capture``) and runs every stage once per mode, each
in a fresh process and a fresh folder under ``--work``, with the same settings (``bcmocap demo``'s, in chunks
of ``--chunk-frames`` processed frames and with ``solver.windows`` independent): only the cluster differs.
Prints per mode the wall time, the time the run spent waiting for tasks and the time it worked alone (the
serial part: reference model, sync, reading caches, writing stores, world, skeleton, initial motion, joining
windows, outputs) and its accuracy against the capture's ground truth; the speedup of ``local:2`` over
``local:1`` (goal ≥ 1.7); whether the outputs are the same (frontend stores bitwise, largest difference of
the solved joint positions); the tasks and the critical path (the serial part plus, per phase, its longest
task); and the projected wall time of a 10-minute capture, from the measured task durations scaled to that
length (per-camera tracking or SIFT ∝ frames, chunks and windows ∝ their count; the ROM trial, world and
skeleton fixed; the rest of the serial part ∝ length) and list-scheduled on W workers (a simulation of the
schedule, stated as such).

    python benchmarks/scale_out.py --json benchmarks/results/scale_out.json
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


def run_mode(capture: Path, out: Path, config: RunConfig, mode: str, stop_after: str | None = None) -> dict:
    """One run, every stage into an emptied ``out``, on the cluster ``mode``; wall time, tasks and the run log."""
    enable_float64()
    enable_compilation_cache()
    shutil.rmtree(out, ignore_errors=True)
    lines: list[str] = []

    def say(line: str) -> None:
        lines.append(line)
        print(f"  [{mode}] {line}", flush=True)

    clock = time.perf_counter()
    with open_executor(None if mode == "none" else mode, log=say) as executor:
        started, cpu = time.perf_counter(), time.process_time()
        log = run_pipeline(capture, out, config, executor=executor, log=say, stop_after=stop_after)
        wall, cpu = time.perf_counter() - started, time.process_time() - cpu
    waited = _union([(a, b) for _, a, b in executor.calls])
    return {"wall_seconds": wall, "with_cluster_start_seconds": time.perf_counter() - clock,
            "this_process_cpu_seconds": cpu,  # with a local cluster: the run's serial part, the scheduler, the client
            "waiting_for_tasks_seconds": waited, "serial_seconds": wall - waited,
            "tasks": [list(t) for t in executor.tasks],
            "calls": [[label, a - started, b - started] for label, a, b in executor.calls],
            "stage_seconds": {stage: rec["seconds"] for stage, rec in log["stages"].items()}}


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
    out = {"frontend_correspondences_bitwise_equal": stores, "max_joint_position_difference_cm": None,
           "motion_arrays_bitwise_equal": []}
    if all((folder[m] / "solve" / "motion.npz").is_file() for m in folder):
        joints, motions = [], []
        for m in (reference, mode):
            skeleton, _ = load_model(folder[m])
            motions.append(load_motion(folder[m] / "solve" / "motion.npz"))
            joints.append(np.asarray(joint_positions(skeleton, motions[-1])))
        out["max_joint_position_difference_cm"] = float(np.max(np.abs(joints[0] - joints[1]))) * 100.0
        out["motion_arrays_bitwise_equal"] = [f for f in ("root_position", "rotations")
                                              if np.array_equal(getattr(motions[0], f), getattr(motions[1], f))]
    return out


def accuracy(out: Path) -> dict | None:
    """Mean joint position (cm) and angle (°) errors of a finished run against the ground truth (its
    ``metrics.json``, after the §5.1 similarity); None if the run did not reach its outputs."""
    path = out / "metrics.json"
    if not path.is_file():
        return None
    solved = json.loads(path.read_text())["solved"]
    return {key: solved[key]["mean"] for key in ("joint_position_error_cm", "joint_angle_error_deg")}


def _phases(tasks: list[list]) -> dict[str, list[float]]:
    out: dict[str, list[float]] = {}
    for label, seconds, *_ in tasks:
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


def simulate(tasks: dict[str, list[float]], serial: float, scale: float, workers: int) -> float:
    """Wall time of the run's phases list-scheduled on ``workers`` (longest task first, a phase after the
    one it depends on; the two trials' chains side by side), plus its serial part.

    ``tasks``: phase → measured durations; the capture trial's and the solve's phases are scaled by ``scale``
    (the capture's length: tracking or SIFT, each camera's task that many times longer; chunks, windows and
    seams, that many times as many); the ROM trial is unchanged.
    """
    def scaled(phase: str) -> list[float]:
        durations = tasks.get(phase, [])
        if phase not in _SOLVE and not phase.endswith("capture"):
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
    parser.add_argument("--rom-seconds", type=float, default=3.0, help="range-of-motion trial to render (s)")
    parser.add_argument("--seed", type=int, default=3, help="the rendered capture's seed")
    parser.add_argument("--chunk-frames", type=int, default=5, help="frontend.chunk_frames")
    parser.add_argument("--window", type=int, default=20, help="solver.window")
    parser.add_argument("--overlap", type=int, default=5, help="solver.overlap")
    parser.add_argument("--modes", nargs="+", default=list(MODES))
    parser.add_argument("--stop-after", default="", help="stage after which the runs stop (default: none, every stage)")
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
                                                  reference_width=640, reference_height=480, seed=args.seed),
                          progress=False)
    config = RunConfig().with_overrides({  # bcmocap demo's settings, in chunks and independent windows
        "frontend.rom_stride": 2, "frontend.max_features": 3000, "frontend.chunk_frames": args.chunk_frames,
        "solver.windows": "independent", "solver.window": args.window, "solver.overlap": args.overlap,
        # as benchmarks/realism.py: a foot the short ROM trial turns about two axes only is fixed as a hinge
        "skeleton.degenerate": "hinge", "skeleton.max_centre_std_cm": 10.0})
    results = {}
    for mode in args.modes:
        print(f"{mode}: bcmocap run ...", flush=True)
        out = args.work / f"out-{mode.replace(':', '')}"
        results[mode] = in_fresh_process(run_mode, capture, out, config, mode, stop_after=args.stop_after or None)
        results[mode]["accuracy"] = accuracy(out)
        print(f"{mode}: {results[mode]['wall_seconds']:.1f} s", flush=True)
        if args.json:  # what is measured so far, in case a later mode is stopped
            write_json(args.json.with_suffix(".partial.json"), {"runs": results, "machine": machine()})
    reference = "none" if "none" in args.modes else args.modes[0]
    same = {m: compare(args.work, reference, m) for m in args.modes if m != reference}
    differences = [s["max_joint_position_difference_cm"] for s in same.values()]
    worst = None if None in differences else max(differences, default=0.0)
    base = results.get("local:2") or results[args.modes[-1]]
    phases = _phases(base["tasks"])
    capture_seconds = json.loads((capture / "capture.json").read_text()).get("settings", {}).get("seconds", args.seconds)
    scale = PROJECTED_SECONDS / float(capture_seconds)
    stages = base["stage_seconds"]
    # The serial part scaled with the length (conservative: the reference model and the ROM trial's share do
    # not grow), except the world and skeleton stages, which depend on the reference model and the ROM trial only.
    fixed = sum(stages.get(stage, 0.0) for stage in ("world", "skeleton"))
    serial = (base["serial_seconds"] - fixed) * scale + fixed
    projected = {str(w): simulate(phases, serial, scale, w) for w in PROJECTED_WORKERS}
    wall = {m: r["wall_seconds"] for m, r in results.items()}
    speedup = wall["local:1"] / wall["local:2"] if {"local:1", "local:2"} <= set(wall) else None
    print(f"\n{'mode':<10}{'wall s':>9}{'waiting s':>11}{'serial s':>10}{'tasks':>7}{'frontend s':>12}{'solve s':>9}"
          f"{'joints cm':>11}{'angles °':>10}")
    for m, r in results.items():
        acc = r["accuracy"] or {"joint_position_error_cm": float("nan"), "joint_angle_error_deg": float("nan")}
        print(f"{m:<10}{r['wall_seconds']:>9.1f}{r['waiting_for_tasks_seconds']:>11.1f}{r['serial_seconds']:>10.1f}"
              f"{len(r['tasks']):>7}{r['stage_seconds'].get('frontend', float('nan')):>12.1f}"
              f"{r['stage_seconds'].get('solve', float('nan')):>9.1f}{acc['joint_position_error_cm']:>11.3f}"
              f"{acc['joint_angle_error_deg']:>10.3f}")
    for m, r in results.items():
        wall_sum, cpu_sum = sum(t[1] for t in r["tasks"]), sum(t[2] for t in r["tasks"])
        print(f"{m}: tasks {wall_sum:.1f} s wall, {cpu_sum:.1f} s CPU; this process {r['this_process_cpu_seconds']:.1f} s CPU")
    if speedup is not None:
        front = results["local:1"]["stage_seconds"]["frontend"] / results["local:2"]["stage_seconds"]["frontend"]
        print(f"speedup of local:2 over local:1: {speedup:.2f} (goal ≥ 1.7); frontend stage alone {front:.2f}")
    print("same result: " + "; ".join(f"{m}: frontend stores bitwise equal {s['frontend_correspondences_bitwise_equal']}, "
                                       f"solved joints differ ≤ {s['max_joint_position_difference_cm']} cm "
                                       f"(bitwise equal arrays: {s['motion_arrays_bitwise_equal']})"
                                       for m, s in same.items()))
    critical = critical_path(base)
    print(f"critical path (local:2): {critical:.1f} s; tasks per phase: "
          + ", ".join(f"{k} {len(v)} (longest {max(v):.1f} s)" for k, v in phases.items()))
    print(f"projected wall time of a {PROJECTED_SECONDS / 60:.0f}-minute capture (simulated schedule): "
          + ", ".join(f"{w} workers {v / 60:.1f} min" for w, v in projected.items()))
    if args.json:
        write_json(args.json, {
            "wall_seconds": wall, "speedup_2_workers": speedup,
            "same_result": worst is not None and worst <= 0.01 and all(
                all(s["frontend_correspondences_bitwise_equal"].values()) for s in same.values()),
            "max_joint_position_difference_cm": worst, "comparison": same,
            "accuracy": {m: r["accuracy"] for m, r in results.items()},
            "critical_path_seconds": critical, "task_count": len(base["tasks"]),
            "tasks_per_phase": {k: {"count": len(v), "seconds_total": sum(v), "seconds_longest": max(v)}
                                for k, v in phases.items()},
            "projected_seconds_10min_capture": projected,
            "projection": {"method": "list schedule of the measured tasks scaled to the length (a simulation)",
                           "scale": scale, "serial_seconds": serial, "fixed_world_skeleton_seconds": fixed},
            "runs": results, "config": config.to_dict(), "capture": str(capture), "machine": machine()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
