"""Where a finished run's error lies: per joint and per camera, against the capture's ground truth.

``metrics.json`` gives one mean per run; this splits it. For a run folder of ``bcmocap run`` (or of the suite's
grid) and the studio capture it ran on, after the run's own §5.1 similarity (its registered camera centres onto
the true ones, :func:`bcmocap.pipeline.outputs.align_to_truth`):

- per joint: the mean position error (cm) of the initial and the solved motion, the mean joint angle error (deg)
  of both (the root has no angle), and the bone ending at the joint: its estimated length (scaled by the
  similarity) against the true one (cm);
- per camera: its share of registered frames in the capture trial and the mean error of its centre (cm), solved.

    python benchmarks/run_breakdown.py RUN_DIR [CAPTURE_DIR] [--json FILE]

``CAPTURE_DIR`` defaults to the capture the run's ``run.json`` names. Nothing is run again: the script reads the
run's ``solve/`` and ``model/`` folders and the capture's ``ground_truth/``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_json  # noqa: E402


def breakdown(run: Path, capture: Path) -> dict:
    """The per-joint and per-camera errors of ``run`` against ``capture``'s ground truth (module docstring)."""
    from bcmocap.correspondence_store import CorrespondenceStore
    from bcmocap.geometry import rotation_angle
    from bcmocap.io.run_folder import load_model, load_motion
    from bcmocap.kinematics.fk import joint_positions
    from bcmocap.pipeline.outputs import _camera_centres, align_to_truth, capture_truth
    from bcmocap.pipeline.world import transform_model

    skeleton, rig = load_model(run, "solve")
    corr = CorrespondenceStore.open(run / "solve" / "correspondences")
    truth = capture_truth(capture, corr)
    if truth is None:
        raise SystemExit(f"{capture}: no ground_truth/ folder")
    valid = np.flatnonzero(truth["valid"])
    sim, _ = align_to_truth(corr, truth)
    true_sk, true_motion = truth["skeleton"], truth["motion"][valid]
    if tuple(true_sk.names) != tuple(skeleton.names):
        raise SystemExit(f"{run}: its skeleton's segments {list(skeleton.names)} are not the truth's "
                         f"{list(true_sk.names)}")
    true_joints = np.asarray(joint_positions(true_sk, true_motion))
    true_cams = _camera_centres(true_sk, truth["rig"], true_motion)
    names = list(skeleton.names)
    out = {"run": str(run), "capture": str(capture), "frames_evaluated": int(len(valid)), "similarity_scale": sim.scale,
           "joints": {n: {} for n in names}}
    for stage, path in (("initial", run / "solve" / "initial.npz"), ("solved", run / "solve" / "motion.npz")):
        sk2, rig2, m2 = transform_model(skeleton, rig, load_motion(path)[valid], sim)
        position = 100 * np.linalg.norm(np.asarray(joint_positions(sk2, m2)) - true_joints, axis=-1).mean(axis=0)
        angle = np.rad2deg(np.asarray(rotation_angle(np.asarray(m2.rotations)[:, 1:],
                                                     np.asarray(true_motion.rotations)[:, 1:]))).mean(axis=0)
        for j, n in enumerate(names):
            out["joints"][n][f"{stage}_position_cm"] = round(float(position[j]), 3)
            if j:
                out["joints"][n][f"{stage}_angle_deg"] = round(float(angle[j - 1]), 3)
        if stage == "solved":
            cams = _camera_centres(sk2, rig2, m2)
            centre = 100 * np.linalg.norm(cams - true_cams, axis=-1).mean(axis=0)
            registered = np.asarray(corr.registered)[valid].mean(axis=0)
            out["cameras"] = {c: {"registered": round(float(r), 4), "centre_cm": round(float(e), 3)}
                              for c, r, e in zip(rig.names, registered, centre)}
    for j, n in enumerate(names):
        if j:
            out["joints"][n]["bone_cm"] = round(float(100 * sim.scale * np.linalg.norm(np.asarray(skeleton.offsets)[j])), 3)
            out["joints"][n]["true_bone_cm"] = round(float(100 * np.linalg.norm(np.asarray(true_sk.offsets)[j])), 3)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a finished run folder (bcmocap run --out)")
    ap.add_argument("capture", type=Path, nargs="?", help="its studio capture (default: the one run.json names)")
    ap.add_argument("--json", help="write the breakdown here")
    args = ap.parse_args(argv)

    from bcmocap.precision import enable_float64

    enable_float64()
    capture = args.capture or Path(json.loads((args.run / "run.json").read_text())["capture"])
    result = breakdown(args.run, capture)
    print(f"{args.run}: {result['frames_evaluated']} frames, similarity scale {result['similarity_scale']:.4f}")
    print(f"{'joint':18s} {'pos init':>8s} {'pos cm':>7s} {'ang init':>8s} {'ang deg':>7s} {'bone cm':>7s} {'true':>6s}")
    for n, row in result["joints"].items():
        print(f"{n:18s} {row['initial_position_cm']:8.2f} {row['solved_position_cm']:7.2f} "
              f"{row.get('initial_angle_deg', float('nan')):8.2f} {row.get('solved_angle_deg', float('nan')):7.2f} "
              f"{row.get('bone_cm', float('nan')):7.2f} {row.get('true_bone_cm', float('nan')):6.2f}")
    print(f"{'camera':18s} {'registered':>10s} {'centre cm':>9s}")
    for c, row in result["cameras"].items():
        print(f"{c:18s} {100 * row['registered']:9.1f}% {row['centre_cm']:9.2f}")
    if args.json:
        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
