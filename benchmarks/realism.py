"""Realism (issue 20): the chain from pixels on a short capture with each degradation of a real shoot alone, all
of them together (the studio's ``realistic`` preset), and all of them with the solver terms that model them.

Each condition renders one capture with the standard rig (``--seconds`` of the CMU walk and a ``--rom-seconds``
range-of-motion trial, seed 3, 640×360 at 60 fps; ``bcmocap.sim.studio``) and runs ``bcmocap run`` on it
(``--config``, by default the tracking frontend of ``benchmarks/configs/tracking.toml``, without pictures).
Rows:

- ``clean``: the default studio (no degradation);
- one row per degradation, at the preset's value (``bcmocap.sim.studio.REALISTIC`` says where each comes from):
  ``mount_wobble``, ``rolling_shutter``, ``motion_blur``, ``exposure`` (auto exposure and white balance),
  ``vignetting``, ``sensor_noise`` (shot noise), ``compression`` (H.264 at an action camera's bit rate),
  ``calibration`` (focal length and centre errors in the intrinsics given);
- ``realistic``: all of them (the preset), the paper's terms only;
- ``realistic+terms``: the same capture with ``[solver] rolling_shutter_readout`` (the rendered readout),
  ``estimate_readout``, ``self_calibration`` and ``mount_compliance`` (the preset's wobble RMS) on.

It reports the joint position and joint angle errors (mean, median, max, after the §5.1 similarity alignment,
from the run's ``metrics.json``) and the registered fraction of frames per trial, and writes JSON
``{"conditions": {NAME: {...}}, "preset": "realistic", "modelled": "realistic+terms"}``. Everything is kept in
``--out`` (``captures/NAME``, ``runs/NAME``): a condition whose run finished is read back, not run again; an
interrupted one resumes (the studio and ``bcmocap run`` both resume).

    python benchmarks/realism.py --out /tmp/realism --json benchmarks/results/realism.json \\
        [--conditions clean,mount_wobble] [--seconds 2] [--rom-seconds 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, peak_rss_mb, write_json  # noqa: E402

from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.pipeline import RunConfig, run_pipeline  # noqa: E402
from bcmocap.pipeline.config import load_config  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.sim.studio import REALISTIC, StudioSettings, preset_settings, write_capture  # noqa: E402

PRESET = "realistic"
MODELLED = "realistic+terms"
#: Degradation rows: the preset's settings each one takes.
DEGRADATIONS = {
    "mount_wobble": ("mount_wobble_mm", "mount_wobble_deg"),
    "rolling_shutter": ("rolling_shutter", "readout_ms"),
    "motion_blur": ("motion_blur", "exposure_ms"),
    "exposure": ("auto_exposure", "white_balance"),
    "vignetting": ("vignetting",),
    "sensor_noise": ("full_scale_electrons", "read_noise_dn"),
    "compression": ("container", "video_bitrate_mbps"),
    "calibration": ("focal_error_pct", "centre_error_px"),
}
CONDITIONS = ("clean", *DEGRADATIONS, PRESET, MODELLED)


def capture_settings(condition: str, base: StudioSettings) -> StudioSettings:
    """The studio settings of a condition's capture (``MODELLED`` shares the preset's)."""
    preset = preset_settings(PRESET, **{k: v for k, v in dataclasses.asdict(base).items() if k not in REALISTIC})
    if condition == "clean":
        return base
    if condition in (PRESET, MODELLED):
        return preset
    return dataclasses.replace(base, **{k: getattr(preset, k) for k in DEGRADATIONS[condition]})


def run_config(condition: str, base: RunConfig, settings: StudioSettings) -> RunConfig:
    """The run settings of a condition: the base's, without pictures; with the modelling terms for ``MODELLED``."""
    data = base.to_dict()
    data["outputs"]["pictures"] = False
    if condition == MODELLED:
        data["solver"].update({
            "rolling_shutter_readout": settings.readout_ms / 1000.0,
            "estimate_readout": True,
            "self_calibration": True,
            "mount_compliance": [settings.mount_wobble_mm / 1000.0, settings.mount_wobble_deg],
        })
    return RunConfig.from_dict(data)


def finished(run: Path) -> bool:
    """True when ``run`` holds a run whose every stage finished (its metrics are written)."""
    try:
        log = json.loads((run / "run.json").read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return "outputs" in log.get("stages", {}) and (run / "metrics.json").is_file()


def row(run: Path) -> dict:
    """A condition's figures from its finished run folder."""
    metrics = json.loads((run / "metrics.json").read_text())
    log = json.loads((run / "run.json").read_text())
    registered = {t: json.loads((run / "frontend" / t / "registration.json").read_text())["registered_fraction"]
                  for t in ("rom", "capture")}
    return {
        "joint_position_error_cm": metrics["solved"]["joint_position_error_cm"],
        "joint_angle_error_deg": metrics["solved"]["joint_angle_error_deg"],
        "camera_centre_error_cm": metrics["solved"].get("camera_centre_error_cm"),
        "initial": {k: metrics["initial"][k] for k in ("joint_position_error_cm", "joint_angle_error_deg")},
        "registered_fraction": registered,
        "frames_evaluated": metrics.get("frames_evaluated"),
        "stage_seconds": {stage: rec["seconds"] for stage, rec in log["stages"].items()},
    }


def condition(name: str, out: Path, base: StudioSettings, config: RunConfig) -> dict:
    """Render (or resume) the condition's capture and run (or resume, or read back) ``bcmocap run`` on it."""
    settings = capture_settings(name, base)
    capture = out / "captures" / (PRESET if name == MODELLED else name)
    run = out / "runs" / name
    timings: dict = {}
    if finished(run):
        print(f"{name}: finished run in {run}, read back", flush=True)
        result = row(run)
        result["render_seconds"] = json.loads((run / "benchmark.json").read_text()).get("render_seconds") \
            if (run / "benchmark.json").is_file() else None
        return result
    clock = time.perf_counter()
    write_capture(capture, settings, progress=False, timings=timings)
    render_seconds = time.perf_counter() - clock
    print(f"{name}: capture {capture} ready in {render_seconds:.0f} s", flush=True)
    run_pipeline(capture, run, run_config(name, config, settings), log=lambda line: print(f"  [{name}] {line}", flush=True))
    result = row(run)
    result["render_seconds"] = render_seconds
    run.joinpath("benchmark.json").write_text(json.dumps({"render_seconds": render_seconds,
                                                         "render_timings": timings}, indent=1) + "\n")
    return result


def print_table(rows: dict[str, dict]) -> None:
    print(f"\n{'condition':<18}{'joint pos. cm mean / median / max':>36}{'joint angle deg mean / median / max':>38}"
          f"{'registered rom / capture':>27}{'run s':>8}")
    for name, r in rows.items():
        p, a, reg = r["joint_position_error_cm"], r["joint_angle_error_deg"], r["registered_fraction"]
        seconds = sum(r["stage_seconds"].values())
        print(f"{name:<18}{p['mean']:>14.3f} / {p['median']:6.3f} / {p['max']:7.3f}"
              f"{a['mean']:>16.3f} / {a['median']:6.3f} / {a['max']:7.3f}"
              f"{100 * reg['rom']:>15.1f} % / {100 * reg['capture']:5.1f} %{seconds:>8.0f}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of the captures and runs (resumed)")
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--conditions", default=",".join(CONDITIONS),
                        help=f"comma-separated rows to run (default all: {','.join(CONDITIONS)})")
    parser.add_argument("--seconds", type=float, default=2.0, help="length of the capture trial (s, default 2)")
    parser.add_argument("--rom-seconds", type=float, default=3.0, help="length of the ROM trial (s, default 3)")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--config", type=Path, default=ROOT / "benchmarks" / "configs" / "tracking.toml",
                        help="bcmocap run settings (TOML or JSON; default the tracking frontend)")
    args = parser.parse_args(argv)
    wanted = [c.strip() for c in args.conditions.split(",") if c.strip()]
    unknown = [c for c in wanted if c not in CONDITIONS]
    if unknown or not wanted:
        parser.error(f"--conditions: unknown {unknown or wanted}; choose from {','.join(CONDITIONS)}")
    enable_float64()
    enable_compilation_cache()
    base = StudioSettings(seconds=args.seconds, rom_seconds=args.rom_seconds, seed=args.seed,
                          reference_width=640, reference_height=480)
    config = load_config(args.config)
    rows, seconds = {}, {}
    for name in wanted:
        clock = time.perf_counter()
        rows[name] = condition(name, args.out, base, config)
        seconds[name] = time.perf_counter() - clock
        print_table({name: rows[name]})
    print_table(rows)
    write_json(args.json, {
        "conditions": rows, "preset": PRESET, "modelled": MODELLED,
        "capture_settings": {name: capture_settings(name, base).to_dict() for name in rows},
        "run_config": {name: run_config(name, config, capture_settings(name, base)).to_dict() for name in rows},
        "this_run_seconds": seconds, "machine": machine(), "peak_rss_mb": peak_rss_mb(),
    })
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
