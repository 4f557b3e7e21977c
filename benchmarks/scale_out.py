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

    python benchmarks/scale_out.py --json benchmarks/results/scale_out.json
"""

from __future__ import annotations

import argparse
import heapq
import json
import shutil
import sys
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

MODES = ("none", "local:1", "local:2")
PROJECTED_WORKERS = (8, 32, 128)
PROJECTED_SECONDS = 600.0


def run_mode(capture: Path, out: Path, config: RunConfig, mode: str) -> dict:
    """One fresh run of every stage on the cluster ``mode``; wall time, tasks and the run log."""
    shutil.rmtree(out, ignore_errors=True)
    lines: list[str] = []

    def say(line: str) -> None:
        lines.append(line)
        print(f"  [{mode}] {line}", flush=True)

    clock = time.perf_counter()
    with open_executor(None if mode == "none" else mode, log=say) as executor:
        started = time.perf_counter()
        log = run_pipeline(capture, out, config, executor=executor, log=say)
        wall = time.perf_counter() - started
    waited = _union([(a, b) for _, a, b in executor.calls])
    return {"wall_seconds": wall, "with_cluster_start_seconds": time.perf_counter() - clock,
            "waiting_for_tasks_seconds": waited, "serial_seconds": wall - waited,
            "tasks": [list(t) for t in executor.tasks],
            "calls": [[label, a - started, b - started] for label, a, b in executor.calls],
            "stage_seconds": {stage: rec["seconds"] for stage, rec in log["stages"].items()}}


def _union(intervals: list[tuple[float, float]]) -> float:
    """Length of the union of ``[a, b)`` intervals (map calls of the two trials overlap)."""
    total, end = 0.0, -np.inf
    for a, b in sorted(intervals):
        if b > end:
            total += b - max(a, end)
            end = b
    return total


def compare(a: Path, b: Path) -> dict:
    """Largest differences between two runs' solved motions and which output arrays are bitwise equal."""
    with np.load(a / "motion.npz") as x, np.load(b / "motion.npz") as y:
        joints = float(np.max(np.abs(x["joint_positions"] - y["joint_positions"]))) * 100.0
        equal = sorted(k for k in x.files if k in y.files and np.array_equal(x[k], y[k]))
    stores = {}
    for trial in ("rom", "capture"):
        from bcmocap.correspondence_store import CorrespondenceStore

        p, q = (CorrespondenceStore.open(r / "frontend" / trial / "correspondences").load() for r in (a, b))
        stores[trial] = all(np.array_equal(getattr(p, f), getattr(q, f), equal_nan=True)
                            for f in ("point_ids", "pixels", "weights", "registered", "world_from_camera", "points"))
    return {"max_joint_position_difference_cm": joints, "motion_arrays_bitwise_equal": equal,
            "frontend_correspondences_bitwise_equal": stores}


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


def simulate(tasks: dict[str, list[float]], serial_fixed: float, serial_scaled: float, scale: float,
             workers: int) -> float:
    """Wall time of the run's phases list-scheduled on ``workers`` (longest task first, a phase after the
    one it depends on; the two trials' chains side by side), plus its serial part.

    ``tasks``: phase → measured durations of the short capture; capture phases are scaled by ``scale``
    (tracking: each camera's task ``scale`` × longer; chunks, windows, seams: ``scale`` × as many, as long).
    """
    def scaled(phase: str) -> list[float]:
        durations = tasks.get(phase, [])
        if not phase.endswith("capture") and phase not in _SOLVE:
            return list(durations)  # the ROM trial has its own length
        if phase.startswith(("track", "sift")):
            return [d * scale for d in durations]
        count = int(round(len(durations) * scale))
        return [durations[i % len(durations)] for i in range(count)] if durations else []

    free = [0.0] * workers  # each worker's next free time
    heapq.heapify(free)
    ready = {"rom": 0.0, "capture": 0.0}
    pending = [(trial, list(chain)) for trial, chain in _CHAINS.items()]
    # The two chains interleave: schedule phase by phase, each after its trial's previous phase ends.
    while any(chain for _, chain in pending):
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
    return now + serial_fixed + serial_scaled * scale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--capture", type=Path, help="capture folder (default: render one into --work)")
    parser.add_argument("--work", type=Path, default=Path("/tmp/bcmocap-scale-out"))
    parser.add_argument("--seconds", type=float, default=4.0, help="capture trial to render (s)")
    parser.add_argument("--rom-seconds", type=float, default=2.5, help="range-of-motion trial to render (s)")
    parser.add_argument("--chunk-frames", type=int, default=10, help="frontend.chunk_frames")
    parser.add_argument("--window", type=int, default=20, help="solver.window")
    parser.add_argument("--overlap", type=int, default=5, help="solver.overlap")
    parser.add_argument("--modes", nargs="+", default=list(MODES))
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
        "solver.windows": "independent", "solver.window": args.window, "solver.overlap": args.overlap})
    results = {}
    for mode in args.modes:
        print(f"{mode}: bcmocap run ...", flush=True)
        results[mode] = run_mode(capture, args.work / f"out-{mode.replace(':', '')}", config, mode)
        print(f"{mode}: {results[mode]['wall_seconds']:.1f} s", flush=True)
    outs = {m: args.work / f"out-{m.replace(':', '')}" for m in args.modes}
    same = {m: compare(outs[args.modes[0]], outs[m]) for m in args.modes[1:]}
    worst = max((s["max_joint_position_difference_cm"] for s in same.values()), default=0.0)
    base = results.get("local:2") or results[args.modes[-1]]
    phases = _phases(base["tasks"])
    capture_seconds = json.loads((capture / "capture.json").read_text()).get("settings", {}).get("seconds", args.seconds)
    scale = PROJECTED_SECONDS / float(capture_seconds)
    scaled_stages = ("initial", "solve", "outputs")  # their serial work grows with the capture's length
    serial_scaled = min(base["serial_seconds"], sum(base["stage_seconds"].get(s, 0.0) for s in scaled_stages)
                        - sum(b - a for label, a, b in base["calls"] if label in _SOLVE))
    serial_fixed = base["serial_seconds"] - serial_scaled
    projected = {str(w): simulate(phases, serial_fixed, serial_scaled, scale, w) for w in PROJECTED_WORKERS}
    wall = {m: r["wall_seconds"] for m, r in results.items()}
    speedup = wall["local:1"] / wall["local:2"] if {"local:1", "local:2"} <= set(wall) else None
    print(f"\n{'mode':<10}{'wall s':>9}{'waiting s':>11}{'serial s':>10}{'tasks':>7}")
    for m, r in results.items():
        print(f"{m:<10}{r['wall_seconds']:>9.1f}{r['waiting_for_tasks_seconds']:>11.1f}{r['serial_seconds']:>10.1f}"
              f"{len(r['tasks']):>7}")
    if speedup is not None:
        print(f"speedup of local:2 over local:1: {speedup:.2f} (goal ≥ 1.7)")
    print(f"same result: largest joint position difference {worst:.2e} cm; "
          + "; ".join(f"{m}: bitwise equal {s['motion_arrays_bitwise_equal']}, frontend stores "
                      f"{s['frontend_correspondences_bitwise_equal']}" for m, s in same.items()))
    print(f"critical path (local:2): {critical_path(base):.1f} s; tasks per phase: "
          + ", ".join(f"{k} {len(v)} (longest {max(v):.1f} s)" for k, v in phases.items()))
    print(f"projected wall time of a {PROJECTED_SECONDS / 60:.0f}-minute capture (simulated schedule): "
          + ", ".join(f"{w} workers {s / 60:.1f} min" for w, s in projected.items()))
    if args.json:
        write_json(args.json, {
            "wall_seconds": wall, "speedup_2_workers": speedup, "same_result": worst <= 0.01,
            "max_joint_position_difference_cm": worst, "comparison": same,
            "critical_path_seconds": critical_path(base), "task_count": len(base["tasks"]),
            "tasks_per_phase": {k: {"count": len(v), "seconds_total": sum(v), "seconds_longest": max(v)}
                                for k, v in phases.items()},
            "projected_seconds_10min_capture": projected,
            "projection": {"method": "list schedule of the measured tasks scaled to the length (simulation)",
                           "scale": scale, "serial_fixed_seconds": serial_fixed,
                           "serial_scaled_seconds_per_capture": serial_scaled},
            "runs": results, "config": config.to_dict(), "capture": str(capture), "machine": machine()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
