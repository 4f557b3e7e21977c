"""A run's registered camera poses against the studio's truth, per trial and camera: how many camera-frames the
frontend placed far from where the camera was (a repeated pattern's copy, a wrong relocalisation).

The registrations are in the reference model's frame (``DIR/world/registered/TRIAL.npz`` where the world stage
re-fitted them, else the frontend's store). They are put in the true world by the similarity that carries the
reference photos' centres onto their true ones (Umeyama; independent of the registrations it then judges), and
camera ``c``'s registration at solver frame ``k`` is compared with the truth at trial frame
``clap_frames[0] + stride · k``, as ``metrics.json`` compares the motion (each camera's sub-frame start is not taken
into account: up to half a frame, 4 cm for a limb camera of the run, under the 10 cm counted as off). A reference
model far from the truth (``reference_photo_residual_cm``) makes every registration look off.

    python benchmarks/registration_truth.py RUN_DIR CAPTURE_DIR [--json F]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_json  # noqa: E402

#: A registration this far (m) from the truth is counted as off: several times the frontend's error on a right
#: registration (about 1 cm on the realistic studio), far below a repeated pattern's period.
OFF_M = 0.10


def _photo_similarity(run_dir: Path, truth) -> tuple[float, np.ndarray, np.ndarray, float]:
    """``(s, R, t, median residual m)`` taking the reference model's frame to the true world (photo centres)."""
    from bcmocap.frontend.reference import load_reference
    from bcmocap.geometry import similarity

    rec = load_reference(run_dir / "frontend" / "reference").reconstruction
    names = list(truth.reference_names)
    est, true = [], []
    for image in rec.images.values():
        if image.name in names:
            est.append(np.asarray(image.projection_center(), float))
            true.append(np.asarray(truth.reference_poses[names.index(image.name)][4:7], float))
    if len(est) < 3:
        raise ValueError(f"{run_dir}: {len(est)} reference photos of the model are in the truth; the similarity needs 3")
    est, true = np.array(est), np.array(true)
    s, r, t = similarity(est, true)
    residual = np.linalg.norm(s * est @ np.asarray(r).T + t - true, axis=1)
    return float(s), np.asarray(r), np.asarray(t), float(np.median(residual))


def _registered(run_dir: Path, trial: str) -> tuple[np.ndarray, np.ndarray, int]:
    """``(world_from_camera (T, C, 7), registered (T, C), stride)`` of a trial in the reference model's frame."""
    from bcmocap.correspondence_store import CorrespondenceStore

    report = json.loads((run_dir / "frontend" / trial / "registration.json").read_text())
    refit = run_dir / "world" / "registered" / f"{trial}.npz"
    if refit.is_file():
        with np.load(refit) as data:
            return data["world_from_camera"], data["registered"].astype(bool), int(report["stride"])
    store = CorrespondenceStore.open(run_dir / "frontend" / trial / "correspondences")
    return np.asarray(store.world_from_camera), np.asarray(store.registered, bool), int(report["stride"])


def registration_errors(run_dir: str | Path, capture_dir: str | Path) -> dict:
    """Per trial and camera: registered camera-frames, how many lie more than :data:`OFF_M` from the truth, and
    the median and worst centre errors (cm); and per trial the totals. Centre errors only (a copy of a pattern
    keeps the rotation)."""
    from bcmocap.sim.studio import load_ground_truth

    run_dir, capture_dir = Path(run_dir), Path(capture_dir)
    truth = load_ground_truth(capture_dir)
    s, r, t, photo_residual = _photo_similarity(run_dir, truth)
    out = {"reference_photo_residual_cm": 100 * photo_residual, "off_threshold_cm": 100 * OFF_M, "trials": {}}
    for trial in ("rom", "capture"):
        if not (run_dir / "frontend" / trial / "registration.json").exists():
            continue
        poses, registered, stride = _registered(run_dir, trial)
        cameras = json.loads((run_dir / "frontend" / trial / "registration.json").read_text())["cameras"]
        gt = truth.trials[trial]
        frames = int(gt.clap_frames[0]) + stride * np.arange(len(poses))
        valid = (frames >= 0) & (frames < len(gt.world_from_camera))
        true = np.asarray(gt.world_from_camera)[np.clip(frames, 0, len(gt.world_from_camera) - 1)][..., 4:7]
        centres = s * poses[..., 4:7] @ r.T + t
        error = np.linalg.norm(centres - true, axis=-1)
        rows = {}
        for c, name in enumerate(cameras):
            e = error[registered[:, c] & valid, c]
            rows[name] = {"registered": int(len(e)), "off": int((e > OFF_M).sum()),
                          "median_cm": float(100 * np.median(e)) if len(e) else None,
                          "max_cm": float(100 * e.max()) if len(e) else None}
        counted = registered & valid[:, None]
        out["trials"][trial] = {"registered": int(counted.sum()), "off": int((error[counted] > OFF_M).sum()),
                                "cameras_with_off": sorted(n for n, row in rows.items() if row["off"]), "cameras": rows}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a run's folder (bcmocap run --out)")
    ap.add_argument("capture", help="its studio capture folder (with ground_truth/)")
    ap.add_argument("--json", help="write the result here")
    args = ap.parse_args()
    from bcmocap.precision import enable_float64

    enable_float64()
    result = registration_errors(args.run, args.capture)
    print(f"reference photos: {result['reference_photo_residual_cm']:.2f} cm median residual")
    for trial, row in result["trials"].items():
        print(f"{trial}: {row['off']} of {row['registered']} registered camera-frames more than "
              f"{result['off_threshold_cm']:.0f} cm off")
        for name, cam in row["cameras"].items():
            if cam["registered"]:
                print(f"  {name:16s} {cam['registered']:4d} registered, {cam['off']:4d} off, median "
                      f"{cam['median_cm']:7.2f} cm, max {cam['max_cm']:7.2f} cm")
            else:
                print(f"  {name:16s}    0 registered")
    if args.json:
        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
