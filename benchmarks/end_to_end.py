"""End to end (issues 5, 8 and 18): rendered pixels → ``bcmocap run`` → motion, against the ground truth.

Renders a capture with the standard rig (or takes ``--capture``), runs every stage of ``bcmocap run``
in one process (``--out``; rerunning resumes and reports the stages it still had to do), and prints the
wall time of each stage and the accuracy of the result after the §5.1 similarity alignment: mean joint
position and joint angle errors before and after the optimisation (goal of issue 5: ≤ 2.0 cm and
≤ 3.0°; the paper: 1.76 cm, 3.01°).

    python benchmarks/end_to_end.py --seconds 10 --out /tmp/e2e --json benchmarks/results/end_to_end.json \
        --baseline-json benchmarks/results/end_to_end_global.json

It also prints the frontend's images per second, the solve stage's frames per second and the whole run's
seconds against the goals of issue 18 (≥ 20 images/s, ≥ 60 frames/s, ≤ 6 minutes), and with
``--baseline-json`` stores the same figures of an earlier run with ``frontend.registration = "global"``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, peak_rss_mb, write_json  # noqa: E402

from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.pipeline import RunConfig, run_pipeline  # noqa: E402
from bcmocap.sim.studio import StudioSettings, write_capture  # noqa: E402


def end_to_end(capture: Path, out: Path, config: RunConfig) -> dict:
    """Run (or resume) ``bcmocap run`` and collect its stage times, registration and accuracy."""
    clock = time.perf_counter()
    log = run_pipeline(capture, out, config, log=lambda line: print(line, flush=True))
    metrics = json.loads((out / "metrics.json").read_text())
    registration = {t: json.loads((out / "frontend" / t / "registration.json").read_text()) for t in ("rom", "capture")}
    images = sum(r["frames"] * len(r["cameras"]) for r in registration.values())
    stage_seconds = {stage: rec["seconds"] for stage, rec in log["stages"].items()}
    solve_frames = registration["capture"]["frames"]
    total = sum(stage_seconds.values())
    return {
        "images_per_second": images / stage_seconds["frontend"] if stage_seconds.get("frontend") else None,
        "solve_frames": solve_frames,
        "solve_frames_per_second": solve_frames / stage_seconds["solve"] if stage_seconds.get("solve") else None,
        "registration": registration["capture"].get("registration", "global"),
        "registered_how": {t: {k: r.get(k) for k in ("registered_absolute", "registered_tracked",
                                                     "registered_relocalised", "registered_relative",
                                                     "tracked_after_rounds")}
                           for t, r in registration.items()},
        "joint_position_error_cm": metrics["solved"]["joint_position_error_cm"],
        "joint_angle_error_deg": metrics["solved"]["joint_angle_error_deg"],
        "camera_centre_error_cm": metrics["solved"]["camera_centre_error_cm"],
        "initial": metrics["initial"],
        "alignment": metrics["alignment"],
        "frames_evaluated": metrics["frames_evaluated"],
        "registered_fraction": {t: r["registered_fraction"] for t, r in registration.items()},
        "images": images,
        "stage_seconds": stage_seconds,
        "total_seconds": total,
        "this_run_seconds": time.perf_counter() - clock,
        "config": config.to_dict(),
    }


def baseline(path: Path, settings: dict) -> dict:
    """The figures of an earlier run of this script with global registration on a capture rendered with the
    same ``settings``, in this run's keys (the rates derived from its stage times where it lacks them)."""
    data = json.loads(path.read_text())
    # settings added to the studio since are at their defaults in a capture rendered before them
    defaults = json.loads(json.dumps(StudioSettings().to_dict()))
    if {**defaults, **data.get("capture_settings", {})} != {**defaults, **settings}:
        raise SystemExit(f"{path}: rendered with other settings ({data.get('capture_settings')}), not {settings}")
    if data.get("config", {}).get("frontend", {}).get("registration", "global") != "global":
        raise SystemExit(f"{path}: not a run with frontend.registration = 'global'")
    stages = data["stage_seconds"]
    keys = ("total_seconds", "stage_seconds", "joint_position_error_cm", "joint_angle_error_deg",
            "camera_centre_error_cm", "registered_fraction", "images")
    out = {k: data[k] for k in keys}
    out["images_per_second"] = data.get("images_per_second", data["images"] / stages["frontend"])
    # An older JSON does not record how many frames the solve stage solved; then the frames evaluated (the
    # capture's frames with ground truth, 300 of 315 in the 10 s walk) stand for them: slightly fewer.
    out["solve_frames_per_second"] = data.get("solve_frames_per_second",
                                              data["frames_evaluated"] / stages["solve"])
    out["source"] = f"{path.name}: {data.get('source', 'benchmarks/end_to_end.py')}"
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--capture", type=Path, help="a rendered capture folder (default: render one into OUT/capture)")
    parser.add_argument("--out", type=Path, required=True, help="run folder (resumed if it holds a run)")
    parser.add_argument("--seconds", type=float, default=10.0, help="length of the rendered capture trial (s)")
    parser.add_argument("--rom-seconds", type=float, default=3.0, help="length of the rendered ROM trial (s)")
    parser.add_argument("--motion", default="walk", choices=["walk", "run", "jump"])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--config", type=Path, help="bcmocap run settings (TOML or JSON)")
    parser.add_argument("--baseline-json", type=Path,
                        help="an earlier end_to_end.py JSON of the same capture run with frontend.registration = "
                             "'global' (SIFT and reference matching of every frame): stored beside this run as "
                             "baseline_global_registration, after checking its capture settings match")
    args = parser.parse_args(argv)
    enable_float64()
    enable_compilation_cache()

    from bcmocap.pipeline.config import load_config

    config = load_config(args.config)
    capture = args.capture
    render_seconds = None
    if capture is None:
        capture = args.out / "capture"
        clock = time.perf_counter()
        write_capture(capture, StudioSettings(motion=args.motion, seconds=args.seconds, rom_seconds=args.rom_seconds,
                                              seed=args.seed, reference_width=640, reference_height=480))
        render_seconds = time.perf_counter() - clock
    result = end_to_end(capture, args.out, config)
    result["render_seconds"] = render_seconds
    settings = json.loads((capture / "capture.json").read_text())["settings"]
    s, i = result, result["initial"]
    print(f"\ncapture {settings['motion']} {settings['seconds']} s + ROM {settings['rom_seconds']} s, "
          f"{result['images']} images processed")
    for stage, sec in result["stage_seconds"].items():
        print(f"  {stage:<10}{sec:>9.1f} s")
    print(f"  {'total':<10}{result['total_seconds']:>9.1f} s")
    print(f"joint position error cm mean: {s['joint_position_error_cm']['mean']:.3f} "
          f"(initial {i['joint_position_error_cm']['mean']:.3f}); goal ≤ 2.0")
    print(f"joint angle error deg mean:   {s['joint_angle_error_deg']['mean']:.3f} "
          f"(initial {i['joint_angle_error_deg']['mean']:.3f}); goal ≤ 3.0")
    print(f"frontend images/s: {result['images_per_second']:.2f} (goal ≥ 20); solve frames/s: "
          f"{result['solve_frames_per_second']:.1f} (goal ≥ 60); whole run {result['total_seconds']:.0f} s (goal ≤ 360)")
    print("registered: " + ", ".join(f"{t} {100 * f:.2f} %" for t, f in result["registered_fraction"].items()))
    if args.baseline_json is not None:
        result["baseline_global_registration"] = baseline(args.baseline_json, settings)
        b = result["baseline_global_registration"]
        print(f"baseline (global registration): {b['total_seconds']:.0f} s, {b['images_per_second']:.2f} images/s, "
              f"solve {b['solve_frames_per_second']:.1f} frames/s, {b['joint_position_error_cm']['mean']:.3f} cm, "
              f"{b['joint_angle_error_deg']['mean']:.3f} deg")
    write_json(args.json, {**result, "capture_settings": settings, "machine": machine(), "peak_rss_mb": peak_rss_mb()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
