"""Run the whole chain on a capture folder from a script, then read the solved motion back.

``bcmocap.pipeline.run_pipeline`` is what ``bcmocap run CAPTURE_DIR --out DIR`` calls: frontend (reference
model, sync, SIFT, registration, homographies) → metric Z-up world → skeleton and camera mounts from the
range-of-motion trial → initial motion → solver → outputs (BVH, PLY, COLMAP model, NPZ/CSV, pictures,
``metrics.json`` when the capture has ground truth). Every stage is saved as it finishes, so running the
script again resumes; changed settings redo the stages they affect. Settings are ``RunConfig`` defaults,
then ``--config FILE`` (TOML or JSON, see ``bcmocap.pipeline.config``), then the flags below.

CAPTURE_DIR has the layout ``bcmocap simulate`` writes (a rendered synthetic capture with ground truth:
``bcmocap simulate --out CAPTURE_DIR``) or that of a real recording. The frontend takes many minutes
on a full capture; ``--stop-after STAGE`` stops early (e.g. ``skeleton`` to check the model first).

    python examples/real_capture.py CAPTURE_DIR [--out DIR] [--config FILE] [--stop-after STAGE]
                                    [--stride N] [--window N] [--no-pictures]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bcmocap.compilation_cache import enable_compilation_cache
from bcmocap.precision import enable_float64
from bcmocap.kinematics import joint_positions
from bcmocap.pipeline import STAGES, load_config, load_model, load_motion, run_pipeline


def summarise(out: Path, stages_done: list[str]) -> None:
    """Print what the run found, read back from its output folder."""
    print(f"\nstages finished in {out}: {', '.join(stages_done) or 'none'}")
    if "skeleton" not in stages_done:
        return
    skeleton, rig = load_model(out)  # the estimated skeleton and camera mounts (DIR/model/)
    print(f"model: {skeleton.num_segments} segments, {len(rig.names)} cameras ({out / 'model'})")
    motion_path = out / "solve" / "motion.npz"
    if "solve" not in stages_done:
        print("no solved motion yet (run again without --stop-after to finish)")
        return
    motion = load_motion(motion_path)
    positions = np.asarray(joint_positions(skeleton, motion))  # (T, J, 3) m, metric Z-up world
    root = np.asarray(motion.root_position)
    path_length = float(np.linalg.norm(np.diff(root, axis=0), axis=-1).sum())
    extent = positions.reshape(-1, 3).max(0) - positions.reshape(-1, 3).min(0)
    print(f"motion: {motion.num_frames} frames, {skeleton.num_segments} joints, root path {path_length:.2f} m, "
          f"volume covered {extent[0]:.2f} × {extent[1]:.2f} × {extent[2]:.2f} m")
    for name, what in [("motion.bvh", "skeleton and motion (BVH)"), ("motion.npz", "arrays (NPZ)"),
                       ("joint_angles.csv", "joint angles (CSV)"), ("scene.ply", "scene points (PLY)"),
                       ("camera_paths.ply", "camera paths (PLY)"), ("pictures", "pictures (PNG)"),
                       ("metrics.json", "errors against the ground truth")]:
        if (out / name).exists():
            print(f"  {what:<32} {out / name}")
    if (out / "metrics.json").exists():
        import json

        solved = json.loads((out / "metrics.json").read_text())["solved"]
        print(f"ground truth: joint position {solved['joint_position_error_cm']['mean']:.2f} cm, "
              f"joint angle {solved['joint_angle_error_deg']['mean']:.2f} deg mean")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("capture", metavar="CAPTURE_DIR", type=Path, help="the capture folder (read only)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: CAPTURE_DIR-run next to it)")
    parser.add_argument("--config", type=Path, default=None, help="settings file (.toml or .json)")
    parser.add_argument("--stop-after", choices=STAGES, default=None, help="stop after this stage")
    parser.add_argument("--stride", type=int, default=None, help="use every n-th video frame of the capture trial")
    parser.add_argument("--window", type=int, default=None, help="frames per solver window")
    parser.add_argument("--no-pictures", action="store_true", help="skip the PNG pictures")
    args = parser.parse_args(argv)
    if not args.capture.is_dir():
        parser.error(f"capture folder {args.capture} does not exist (or is not a folder)")
    out = args.out if args.out is not None else args.capture.with_name(args.capture.name + "-run")
    if out.exists() and not out.is_dir():
        parser.error(f"--out {out} exists and is not a folder")

    overrides = {"frontend.stride": args.stride, "solver.window": args.window,
                 "outputs.pictures": False if args.no_pictures else None}
    try:
        config = load_config(args.config).with_overrides({k: v for k, v in overrides.items() if v is not None})
    except ValueError as exc:
        parser.error(str(exc))

    enable_float64()
    enable_compilation_cache()
    try:
        log = run_pipeline(args.capture, out, config, log=lambda line: print(line, flush=True),
                           stop_after=args.stop_after)
    except ValueError as exc:  # unreadable capture, missing subject description, bad settings: named
        print(f"{parser.prog}: {exc}", file=sys.stderr)
        return 2
    summarise(out, [s for s in STAGES if s in log["stages"]])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
