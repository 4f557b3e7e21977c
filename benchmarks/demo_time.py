"""Wall time of ``bcmocap demo`` with its defaults (issue 18: ≤ 2 minutes with a warm compilation cache).

Runs the command in fresh processes, each into an empty output folder: ``--warm N`` times with the user's
caches (``BCMOCAP_CACHE_DIR`` or ``~/.cache/bcmocap/jax``; the first run of a new code version stores its
programs, so the last of them is the warm figure), and with ``--cold`` once more with an empty cache folder.
Prints and stores each run's wall time (process start to exit), its stage seconds and its accuracy.

    python benchmarks/demo_time.py [--warm 2] [--cold] [--json benchmarks/results/demo_time.json]
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json  # noqa: E402

BCMOCAP = str(Path(sys.executable).parent / "bcmocap")


def one_run(cache: str | None) -> dict:
    """``bcmocap demo --out`` an empty folder; ``cache``: the cache folder to use (None: the user's)."""
    env = dict(os.environ)
    if cache is not None:
        env["BCMOCAP_CACHE_DIR"] = cache
    with tempfile.TemporaryDirectory(prefix="bcmocap_demo_time_") as tmp:
        out = Path(tmp) / "demo"
        clock = time.perf_counter()
        done = subprocess.run([BCMOCAP, "demo", "--out", str(out)], env=env, capture_output=True, text=True)
        wall = time.perf_counter() - clock
        if done.returncode != 0:
            raise SystemExit(f"bcmocap demo failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
        stages = {k: v["seconds"] for k, v in json.loads((out / "run.json").read_text())["stages"].items()}
        solved = json.loads((out / "metrics.json").read_text())["solved"]
    return {"wall_seconds": wall, "stage_seconds": stages,
            "joint_position_error_cm": solved["joint_position_error_cm"]["mean"],
            "joint_angle_error_deg": solved["joint_angle_error_deg"]["mean"]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--warm", type=int, default=2, help="runs with the user's caches (the last is the figure)")
    parser.add_argument("--cold", action="store_true", help="one more run with an empty cache folder")
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args(argv)
    runs = {}
    for k in range(args.warm):
        runs[f"warm_{k + 1}"] = one_run(None)
    if args.cold:
        with tempfile.TemporaryDirectory(prefix="bcmocap_cold_cache_") as cache:
            runs["cold"] = one_run(cache)
    for name, r in runs.items():
        print(f"{name:<8} {r['wall_seconds']:6.1f} s  (" + ", ".join(f"{s} {v:.0f} s" for s, v in r["stage_seconds"].items())
              + f")  {r['joint_position_error_cm']:.2f} cm, {r['joint_angle_error_deg']:.2f}°")
    write_json(args.json, {"runs": runs, "goal_seconds": 120.0, "machine": machine()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
