"""`bcmocap init` then `bcmocap run` against `bcmocap run` on the studio's own folder (issue 21, item 4).

The studio renders a small capture the way cameras record it (``--container mp4-aac``: H.264 with the soundtrack
as AAC inside each MP4, no WAV beside); `bcmocap init` assembles a second capture folder from those camera
files, the template rig file with the subject's rest pose, the studio's intrinsics files and its reference
photos, as a user would from a shoot; `bcmocap run` then runs on both folders with the same settings. The
figure is how the two runs' outputs compare (files bitwise equal, the largest difference of those that are
not; the init folder has no ground truth, so only the studio's run writes metrics.json and the error pictures)
and the studio run's errors against the ground truth.

    python benchmarks/init_equivalence.py --out DIR [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json  # noqa: E402
from reliability import PIXELS_RUN_CONFIG, PIXELS_SIMULATE, compare  # noqa: E402

BCMOCAP = str(Path(sys.executable).parent / "bcmocap")


def _bcmocap(*args: str) -> float:
    start = time.perf_counter()
    done = subprocess.run([BCMOCAP, *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"bcmocap {' '.join(args)} failed: {done.stderr.strip()[-2000:]}")
    return time.perf_counter() - start


def _rig_file(studio: Path) -> str:
    """The template rig (the studio's cameras and segments) with the studio's subject."""
    from bcmocap.frontend.rig_file import TEMPLATE, RigFile, format_rig_file

    subject = json.loads((studio / "capture.json").read_text())["subject"]
    return format_rig_file(RigFile(TEMPLATE.segments, TEMPLATE.cameras, rest=subject["rest"],
                                   measurements=tuple(subject["measurements"])))


def _errors(run: Path) -> dict:
    solved = json.loads((run / "metrics.json").read_text())["solved"]
    return {k: solved[k] for k in ("joint_position_error_cm", "joint_angle_error_deg")}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder of the captures and runs (kept; reused if there)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    studio, ours, config = out / "studio", out / "init", out / "run.toml"
    seconds = {}
    if not (studio / "capture.json").is_file() or not json.loads((studio / "capture.json").read_text()).get("complete"):
        seconds["render"] = _bcmocap("simulate", str(studio), *PIXELS_SIMULATE, "--container", "mp4-aac")
    if not ours.exists():
        (out / "rig.toml").write_text(_rig_file(studio))
        seconds["init"] = _bcmocap("init", str(ours), "--videos", str(studio / "trials"), "--rig", str(out / "rig.toml"),
                                   "--calibration", str(studio / "intrinsics"), "--reference-photos",
                                   str(studio / "reference"))
    config.write_text(PIXELS_RUN_CONFIG)
    runs = {}
    for label, capture in (("studio", studio), ("init", ours)):
        run = out / f"run_{label}"
        seconds[f"run_{label}"] = _bcmocap("run", str(capture), "--out", str(run), "--config", str(config))
        runs[label] = run
    result = compare(runs["studio"], runs["init"], 0.0)
    payload = {
        "capture": {"simulate": PIXELS_SIMULATE + ["--container", "mp4-aac"], "config": PIXELS_RUN_CONFIG},
        "bitwise_equal": result["bitwise_equal"],
        "equal_but_timings": result["equal_but_timings"],
        "differing": result["differing"],
        "only_in_one": [m["file"] for m in result["mismatches"] if m["why"].startswith("only in")],
        "studio_errors": _errors(runs["studio"]),
        "seconds_this_invocation": seconds,  # finished steps found in --out are resumed (seconds, not minutes)
        "machine": machine(),
    }
    print(f"outputs: {result['bitwise_equal']} files bitwise equal, {len(result['equal_but_timings'])} equal but their "
          f"timings, {len(result['differing'])} differing")
    for d in result["differing"][:20]:
        print(f"  {d['file']}: {'not comparable' if d['max_difference'] is None else d['max_difference']}")
    print(f"only in one run: {payload['only_in_one']}")
    print("studio run: " + ", ".join(f"{k} {v['mean']:.4f}" for k, v in payload["studio_errors"].items()
                                     if isinstance(v, dict)))
    if args.json:
        write_json(args.json, payload)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
