"""User residual terms through ``bcmocap run`` (issue 19): accuracy with the paper's terms and with the
wearable-sensor terms of ``examples/wearable_sensors`` added by a config file, and the banded solver's
speed with a three-frame term.

1. ``bcmocap run`` on a rendered capture with the paper's terms (``DIR/paper``), then the same run with
   the gyroscope, foot-contact and accelerometer terms named by import path in
   ``examples/wearable_sensors/config.toml`` (``DIR/with_imu_and_contact``: a copy of the first run, so
   only the solve and outputs stages run again). The capture gets its synthetic sensor files from its
   ground truth first if it has none (``bcmocap simulate CAPTURE --sensors-only``).
2. The standard 10 s walk (18 cameras, ~330 measurements per camera-frame) solved with the paper's terms
   (block-tridiagonal system) and with a three-frame term added (an accelerometer-like second difference
   of every camera centre: bandwidth 2, two fixed frames before each window), compiled code only.

    python benchmarks/custom_terms.py --capture CAPTURE --out DIR [--config benchmarks/configs/tracking.toml] \\
        --json benchmarks/results/custom_terms.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "examples" / "wearable_sensors"))  # the user terms' module, as PYTHONPATH would

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from _common import write_json  # noqa: E402
from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.io.sensors import CONTACTS_FILE, IMU_FILE  # noqa: E402
from bcmocap.kinematics import camera_poses  # noqa: E402
from bcmocap.pipeline import RunConfig, run_pipeline  # noqa: E402
from bcmocap.pipeline.config import load_config  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.residuals import MultiFrameTerm  # noqa: E402
from bcmocap.sim import standard_capture  # noqa: E402
from bcmocap.sim.sensors import write_sensor_data  # noqa: E402
from bcmocap.solver import Problem, SolverOptions, solve  # noqa: E402
from bcmocap.solver.objective import paper_terms  # noqa: E402

TERMS_CONFIG = ROOT / "examples" / "wearable_sensors" / "config.toml"


def with_user_terms(config: RunConfig, path: Path) -> RunConfig:
    """``config`` plus the ``[[solver.user_terms]]`` of the TOML file at ``path``."""
    data = config.to_dict()
    data["solver"]["user_terms"] = tomllib.loads(path.read_text())["solver"]["user_terms"]
    return RunConfig.from_dict(data)


def run(capture: Path, out: Path, config: RunConfig) -> dict:
    """``bcmocap run`` (resumed where finished) and its accuracy and stage times."""
    log = run_pipeline(capture, out, config, log=lambda line: print(line, flush=True))
    metrics = json.loads((out / "metrics.json").read_text())
    reports = json.loads((out / "solve" / "reports.json").read_text())["windows"]
    keys = ("joint_position_error_cm", "joint_angle_error_deg", "camera_centre_error_cm")
    return {**{k: metrics["solved"][k] for k in keys},
            "initial": {k: metrics["initial"][k] for k in keys},
            "solve_seconds": log["stages"]["solve"]["seconds"],
            "windows_converged": sum(r["converged"] for r in reports), "windows": len(reports),
            "user_terms": [u["factory"] for u in config.to_dict()["solver"]["user_terms"]]}


class CameraCentreSecondDifference(MultiFrameTerm):
    """Every camera centre's second difference over frames t−2…t equals ``data`` (m per frame²)."""

    span = 3

    def residual(self, states, data, variables):
        c = states.world_from_camera.translation()  # (3, C, 3)
        return c[2] - 2.0 * c[1] + c[0] - data, jnp.ones(data.shape[0], bool)


def banded_speed(seconds: float) -> dict:
    """Frames per second on the standard walk with the paper's terms and with a three-frame term added."""
    capture = standard_capture("walk", seconds=seconds, repeat=True)
    corr = capture.correspondences()
    initial = capture.initial_motion(corr)
    centres = np.asarray(camera_poses(capture.skeleton, capture.rig, capture.motion).translation())
    second = np.zeros_like(centres)
    second[2:] = centres[2:] - 2.0 * centres[1:-1] + centres[:-2]
    second += np.random.default_rng(0).normal(scale=0.002, size=second.shape)  # 2 mm per frame²
    paper = paper_terms(corr, capture.skeleton)
    problems = {"tridiagonal": Problem(capture.skeleton, capture.rig, paper),
                "banded": Problem(capture.skeleton, capture.rig,
                                  [*paper, CameraCentreSecondDifference(second, weight=1e4, name="second difference")])}
    out = {"frames": capture.num_frames}
    for name, problem in problems.items():
        solve(problem, initial, SolverOptions())  # compile every window shape
        start = time.perf_counter()
        solution = solve(problem, initial, SolverOptions())
        elapsed = time.perf_counter() - start
        steps = float(np.mean([r.num_steps for r in solution.reports]))
        out[name] = {"frames_per_second": capture.num_frames / elapsed, "seconds": elapsed, "lm_steps_per_window": steps,
                     "converged": solution.converged}
        print(f"{name}: {capture.num_frames} frames in {elapsed:.1f} s = {capture.num_frames / elapsed:.1f} frames/s, "
              f"{steps:.1f} LM steps per window")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capture", type=Path, required=True, help="a rendered capture folder (bcmocap simulate)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the two runs (resumed if there)")
    parser.add_argument("--config", type=Path, help="base run settings (e.g. benchmarks/configs/tracking.toml)")
    parser.add_argument("--terms", type=Path, default=TERMS_CONFIG, help="the [[solver.user_terms]] to add")
    parser.add_argument("--speed-seconds", type=float, default=10.0, help="length of the banded-solver speed run")
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args(argv)
    enable_float64()
    enable_compilation_cache()
    trial = args.capture / "trials" / "capture"
    if not ((trial / IMU_FILE).is_file() and (trial / CONTACTS_FILE).is_file()):
        print(f"{trial}: no sensor files; writing them from the ground truth", flush=True)
        write_sensor_data(args.capture)
    base = load_config(args.config)
    paper = run(args.capture, args.out / "paper", base)
    sensors_out = args.out / "with_imu_and_contact"
    if not sensors_out.exists():  # the same frontend, world, skeleton and initial motion: only the solve differs
        shutil.copytree(args.out / "paper", sensors_out, ignore=shutil.ignore_patterns("run.lock"))
    sensors = run(args.capture, sensors_out, with_user_terms(base, args.terms))
    for name, r in (("paper terms", paper), ("with IMU and contact", sensors)):
        print(f"{name}: joint position {r['joint_position_error_cm']['mean']:.3f} cm, joint angle "
              f"{r['joint_angle_error_deg']['mean']:.3f}°, camera centre {r['camera_centre_error_cm']['mean']:.3f} cm, "
              f"solve {r['solve_seconds']:.0f} s")
    speed = banded_speed(args.speed_seconds)
    write_json(args.json, {
        "capture": str(args.capture), "config": str(args.config), "terms": str(args.terms),
        "paper_terms": paper, "with_imu_and_contact": sensors,
        "banded_frames_per_second": speed["banded"]["frames_per_second"],
        "tridiagonal_frames_per_second": speed["tridiagonal"]["frames_per_second"], "speed": speed,
    })
    return 0


if __name__ == "__main__":
    sys.exit(main())
