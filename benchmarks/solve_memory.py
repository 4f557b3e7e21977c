"""Memory of `bcmocap run`'s solve stage against the trial's length, on real frontend measurements.

Takes a finished run (``bcmocap run`` or ``benchmarks/end_to_end.py``'s run folder) and tiles its
capture trial's metric correspondences (``RUN/solve/correspondences/``, measured by the frontend on
rendered pixels) k times end to end, each copy with its own points, into a new store; the initial
motion (``RUN/solve/initial.npz``) is tiled alike. Each tiled trial is solved with the run's solver
settings in a fresh process, two ways:

- ``stored``: :class:`~bcmocap.solver.objective.StoredProblem`, what the solve stage does: each
  window's measurements are read from the store on disk when the solver reaches it;
- ``in_memory``: the whole trial's dense ``Correspondences`` loaded and one ``Problem`` built from it
  (what the solve stage did before the store).

Printed and written: peak resident memory of the process (VmHWM), the dense measurement arrays'
size, seconds and the summed final cost (the two ways must agree). The seams between copies are
jumps in the motion, which the smoothness term sees; they do not change what is measured here.

    python benchmarks/solve_memory.py --run RUN_DIR [--repeats 1 2 4 8] [--in-memory-repeats 1 2 4] [--json FILE]

Goal (issue 5, item 8): a long capture never has to fit in memory at once: peak memory of the
stored solve flat in the trial's length.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from _common import peak_rss_mb, write_json  # noqa: E402

from bcmocap.correspondence_store import CorrespondenceStore, write_store  # noqa: E402


def tile(run: Path, repeats: int, folder: Path) -> CorrespondenceStore:
    """``repeats`` copies of the run's metric store end to end (block by block: one copy's block in
    memory at a time), and the tiled initial motion as ``folder/initial.npz``."""
    from bcmocap.pipeline.run import load_motion, save_motion
    from bcmocap.kinematics.skeleton import Motion

    source = CorrespondenceStore.open(run / "solve" / "correspondences")

    def parts():
        for _ in range(repeats):
            for block in source.blocks:
                yield source.frames(block.start, block.stop)

    store = write_store(folder / "correspondences", parts(), block_frames=max(b.stop - b.start for b in source.blocks))
    initial = load_motion(run / "solve" / "initial.npz")
    save_motion(folder / "initial.npz", Motion(np.tile(initial.root_position, (repeats, 1)),
                                               np.tile(initial.rotations, (repeats, 1, 1))))
    return store


def child(mode: str, run: Path, folder: Path) -> dict:
    """Solve the tiled trial in ``folder`` (this process only), return the figures."""
    from bcmocap.compilation_cache import enable_compilation_cache
    from bcmocap.precision import enable_float64
    from bcmocap.pipeline.config import load_config
    from bcmocap.pipeline.run import load_model, load_motion, objective_weights
    from bcmocap.solver import Problem, SolverOptions, solve
    from bcmocap.solver.objective import StoredProblem, paper_terms

    enable_float64()
    enable_compilation_cache()
    config = load_config(run / "config.json" if (run / "config.json").is_file() else None)
    s = config.solver
    weights, homography = objective_weights(s), "homography" in s.terms and None
    skeleton, rig = load_model(run)
    store = CorrespondenceStore.open(folder / "correspondences")
    initial = load_motion(folder / "initial.npz")
    before = peak_rss_mb()
    t0 = time.perf_counter()
    if mode == "stored":
        problem = StoredProblem(store, skeleton, rig, weights, include_homography=homography)
    else:
        corr = store.load()
        problem = Problem(skeleton, rig, paper_terms(corr, skeleton, weights, include_homography=homography))
    solution = solve(problem, initial, SolverOptions(window=s.window, overlap=s.overlap))
    return {"mode": mode, "frames": store.num_frames, "seconds": time.perf_counter() - t0,
            "peak_rss_mb": peak_rss_mb(), "peak_rss_before_solve_mb": before,
            "final_cost": float(sum(r.final_cost for r in solution.reports)), "windows": len(solution.reports),
            "converged_windows": int(sum(r.converged for r in solution.reports))}


def dense_megabytes(store: CorrespondenceStore) -> float:
    """Size of the dense ``(T, C, N)`` measurement arrays of :class:`Correspondences` for this store."""
    t, c, n, m = store.num_frames, store.num_cameras, store.slots, store.homography_slots
    return t * c * (n * (4 + 16 + 8) + m * (16 + 16 + 8)) / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="a finished bcmocap run folder")
    parser.add_argument("--repeats", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--in-memory-repeats", type=int, nargs="*", default=[1, 2, 4],
                        help="lengths also solved with the whole trial in memory (dense arrays)")
    parser.add_argument("--json")
    parser.add_argument("--child", choices=["stored", "in_memory"], help=argparse.SUPPRESS)
    parser.add_argument("--folder", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.run, args.folder)))
        return
    if not (args.run / "solve" / "correspondences" / "index.json").is_file():
        sys.exit(f"{args.run}: no solve/correspondences/ store (run bcmocap run up to the initial stage)")
    rows = []
    for repeats in sorted(set(args.repeats) | set(args.in_memory_repeats)):
        with tempfile.TemporaryDirectory(prefix="solve_memory_") as tmp:
            folder = Path(tmp)
            store = tile(args.run, repeats, folder)
            disk_mb = sum(f.stat().st_size for f in (folder / "correspondences").iterdir()) / 1e6
            for mode in ("stored", "in_memory"):
                if repeats not in (args.repeats if mode == "stored" else args.in_memory_repeats):
                    continue
                out = subprocess.run([sys.executable, __file__, "--run", str(args.run), "--child", mode,
                                      "--folder", str(folder)], capture_output=True, text=True)
                if out.returncode:
                    sys.exit(f"{mode} × {repeats} failed:\n{out.stderr[-3000:]}")
                row = {"repeats": repeats, "seconds_of_capture": store.num_frames / store.fps,
                       "dense_measurements_mb": dense_megabytes(store), "store_on_disk_mb": disk_mb,
                       **json.loads(out.stdout.strip().splitlines()[-1])}
                rows.append(row)
                print(f"{mode:9s} ×{repeats}: {row['frames']} frames ({row['seconds_of_capture']:.0f} s of capture), "
                      f"dense arrays {row['dense_measurements_mb']:.0f} MB, store {disk_mb:.0f} MB on disk; "
                      f"peak RSS {row['peak_rss_mb']:.0f} MB, {row['seconds']:.0f} s, "
                      f"cost {row['final_cost']:.6g}, {row['converged_windows']}/{row['windows']} windows converged",
                      flush=True)
            shutil.rmtree(folder / "correspondences", ignore_errors=True)
    stored = [r for r in rows if r["mode"] == "stored"]
    growth = stored[-1]["peak_rss_mb"] / stored[0]["peak_rss_mb"] if len(stored) > 1 else None
    if growth is not None:
        print(f"stored: peak RSS ×{growth:.2f} from {stored[0]['frames']} to {stored[-1]['frames']} frames")
    write_json(args.json, {"run": str(args.run), "rows": rows, "stored_peak_rss_growth": growth})


if __name__ == "__main__":
    main()
