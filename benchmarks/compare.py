"""One benchmark on two revisions of this repository, alternating runs, in one session on one machine.

Machines of one kind differ by 2-3x in speed, so a time measured on one says little on another; a ratio of two
revisions measured side by side does. Each revision is checked out as a git worktree (``WORKTREE`` names the working
tree as it is, uncommitted changes included) and the benchmark script of that revision runs in a fresh process
with that checkout first on ``PYTHONPATH``, its own persistent compilation cache (``--cache fresh``: empty for every
run, so compilation counts; ``shared``: one per revision, warm after its first run) and ``{out}`` and ``{json}`` in
the arguments replaced by a folder and a JSON file of that run. The revisions alternate (A B, B A, …) so that a
machine that slows down or warms up over the session does not favour one.

    python benchmarks/compare.py REV_A REV_B [--repeats 2] [--key total_seconds --key solve_frames_per_second] \\
        [--json benchmarks/results/FILE.json] -- benchmarks/end_to_end.py --capture CAPTURE --out {out} --json {json}

Reports for each ``--key`` (a dotted path into the benchmark's JSON, e.g. ``joint_position_error_cm.mean``) the
values of every run, their mean per revision and the ratio B / A (mean, min and max over the repeats, runs paired
in order), and the wall time of every run.
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

WORKTREE = "WORKTREE"


def _value(data, path: str):
    for part in path.split("."):
        if not isinstance(data, dict) or part not in data:
            return None
        data = data[part]
    return data if isinstance(data, (int, float)) and not isinstance(data, bool) else None


def _checkout(rev: str, folder: Path) -> Path:
    if rev == WORKTREE:
        return ROOT
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(folder), rev], check=True,
                   capture_output=True)
    return folder


def _run(tree: Path, script: str, arguments: list[str], run_dir: Path, cache: Path) -> tuple[dict, float]:
    run_dir.mkdir(parents=True)
    json_path = run_dir / "result.json"
    args = [a.replace("{out}", str(run_dir / "out")).replace("{json}", str(json_path)) for a in arguments]
    env = {**os.environ, "PYTHONPATH": str(tree), "BCMOCAP_CACHE_DIR": str(cache)}
    clock = time.perf_counter()
    with open(run_dir / "log.txt", "w") as log:
        done = subprocess.run([sys.executable, str(tree / script), *args], cwd=tree, env=env, stdout=log,
                              stderr=subprocess.STDOUT)
    seconds = time.perf_counter() - clock
    if done.returncode != 0:
        tail = (run_dir / "log.txt").read_text().splitlines()[-20:]
        raise RuntimeError(f"{script} at {tree} exited {done.returncode}:\n" + "\n".join(tail))
    return (json.loads(json_path.read_text()) if json_path.exists() else {}), seconds


def compare(rev_a: str, rev_b: str, script: str, arguments: list[str], keys: list[str], repeats: int, cache: str,
            keep: Path | None = None) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        base = keep or Path(tmp)
        trees = {"A": _checkout(rev_a, Path(tmp) / "A"), "B": _checkout(rev_b, Path(tmp) / "B")}
        runs: dict[str, list[dict]] = {"A": [], "B": []}
        try:
            for k in range(repeats):
                for name in ("A", "B") if k % 2 == 0 else ("B", "A"):
                    caches = base / "cache" / (f"{name}_{k}" if cache == "fresh" else name)
                    result, seconds = _run(trees[name], script, arguments, base / f"{name}_{k}", caches)
                    values = {key: _value(result, key) for key in keys}
                    runs[name].append({"wall_seconds": seconds, "values": values})
                    print(f"repeat {k} {name} ({rev_a if name == 'A' else rev_b}): {seconds:.1f} s, "
                          + ", ".join(f"{key} {v:.6g}" if v is not None else f"{key} -" for key, v in values.items()),
                          flush=True)
        finally:
            for name, rev in (("A", rev_a), ("B", rev_b)):
                if rev != WORKTREE:
                    subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(trees[name])],
                                   check=False, capture_output=True)
    summary = {}
    for key in ["wall_seconds", *keys]:
        get = (lambda r: r["wall_seconds"]) if key == "wall_seconds" else (lambda r, key=key: r["values"][key])
        a, b = [get(r) for r in runs["A"]], [get(r) for r in runs["B"]]
        if any(v is None for v in a + b):
            summary[key] = {"A": a, "B": b, "note": "missing in some run"}
            continue
        ratios = [y / x for x, y in zip(a, b) if x]
        summary[key] = {"A": a, "B": b, "mean_A": sum(a) / len(a), "mean_B": sum(b) / len(b),
                        "ratio_B_over_A": {"mean": sum(ratios) / len(ratios), "min": min(ratios), "max": max(ratios)}
                        if ratios else None}
    return {"rev_a": rev_a, "rev_b": rev_b, "script": script, "arguments": arguments, "repeats": repeats,
            "cache": cache, "runs": runs, "summary": summary}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--" not in argv:
        print("usage: compare.py REV_A REV_B [options] -- SCRIPT ARGS...", file=sys.stderr)
        return 2
    split = argv.index("--")
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rev_a", help=f"a git revision, or {WORKTREE} for the working tree as it is")
    parser.add_argument("rev_b")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each revision, alternating")
    parser.add_argument("--key", action="append", default=[], help="dotted path of a figure in the benchmark's JSON")
    parser.add_argument("--cache", choices=("fresh", "shared"), default="fresh",
                        help="compilation cache: empty for every run, or one per revision")
    parser.add_argument("--keep", type=Path, help="keep the runs' folders and logs here")
    parser.add_argument("--json", help="write the comparison to this file")
    args = parser.parse_args(argv[:split])
    script, *arguments = argv[split + 1:]
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    from _common import write_json

    result = compare(args.rev_a, args.rev_b, script, arguments, args.key, args.repeats, args.cache, args.keep)
    for key, s in result["summary"].items():
        r = s.get("ratio_B_over_A")
        print(f"{key}: A {s.get('mean_A', s['A'])}, B {s.get('mean_B', s['B'])}"
              + (f", B/A {r['mean']:.4f} (min {r['min']:.4f}, max {r['max']:.4f})" if r else ""))
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
