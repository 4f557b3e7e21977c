"""Monocular reconstruction from COCO-17 keypoints with a detector's noise (issue 47): the error against noise level.

For each of subject 35's walks 35_02 … 35_05 (the prior, the bundled walk 35_01's mean pose, is what ``bcmocap kcs
--keypoints coco17`` starts from, so 35_01 itself is left out) and five near-static camera paths
(``benchmarks/kcs_table.py``'s, with the scale set so that the walker fits a 640 × 480 image: 80–120 px/m, the body
300–400 px tall at 4–6 m and a 500 px focal length), the CMU joints are projected and written as a COCO keypoint
results file (``[x, y, score] × 17`` per frame: hips, knees, ankles, shoulders, elbows, wrists from the CMU joints
they map to (``bcmocap.kcs.keypoints``), the ears 8 cm either side of the CMU head joint along the shoulders' line,
the nose and eyes absent), then read back by ``bcmocap.kcs.keypoint_input`` as the command reads it and reconstructed.

**Noise.** Gaussian, per keypoint in proportion to COCO's per-keypoint standard deviations (the OKS constants of
the COCO keypoint evaluation, cocodataset.org/#keypoints-eval: nose .026, eyes .025, ears .035, shoulders .079,
elbows .072, wrists .062, hips .107, knees .087, ankles .089, as fractions of the object's scale: a detector errs
most where annotators disagree most), scaled so that their mean over the 12 body keypoints is the row's σ: 0, 5, 10,
20 px. **Dropouts**: each keypoint of each frame is missing (score 0, below ``--min-confidence``) with probability
5 % at σ = 5 px, 10 % at 10 and 20 % at 20 (none without noise): a detector loses the joints it is least sure of.

The figures: the 3D error (3DPE: per-frame rigid alignment; mean over frames, paths and walks) over the 15 CMU joints
COCO gives (the root, lower neck and head as midpoints), and over all 19 (the thorax, the head's top and the toes
placed from the others); each without and with ``KCSOptions.keypoint_smoothing`` (``--keypoint-smoothing``).

    python benchmarks/kcs_coco.py --json benchmarks/results/kcs_coco.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_json  # noqa: E402

WALKS = ("35_02", "35_03", "35_04", "35_05")
NOISE_PX = (0.0, 5.0, 10.0, 20.0)
DROPOUT = {0.0: 0.0, 5.0: 0.05, 10.0: 0.10, 20.0: 0.20}
#: COCO's per-keypoint OKS standard deviations (cocodataset.org/#keypoints-eval), in COCO-17 order.
COCO_SIGMAS = np.array([.26, .25, .25, .35, .35, .79, .79, .72, .72, .62, .62, 1.07, 1.07, .87, .87, .89, .89]) / 10.0
#: COCO-17 keypoint -> the CMU joint it is made from (the ears from the head joint, the face not given).
FROM_CMU = {"left_shoulder": "lhumerus", "right_shoulder": "rhumerus", "left_elbow": "lradius", "right_elbow": "rradius",
            "left_wrist": "lwrist", "right_wrist": "rwrist", "left_hip": "lfemur", "right_hip": "rfemur",
            "left_knee": "ltibia", "right_knee": "rtibia", "left_ankle": "lfoot", "right_ankle": "rfoot"}
SEEN = ("root", "lfemur", "ltibia", "lfoot", "rfemur", "rtibia", "rfoot", "lowerneck", "head", "lhumerus", "lradius",
        "lwrist", "rhumerus", "rradius", "rwrist")  # the CMU joints COCO-17 gives (root, neck, head as midpoints)


def coco_keypoints(joints: np.ndarray, names, rotation: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``(F, 17, 2)`` pixel positions (NaN where COCO-17 is not made from CMU joints) of one camera path."""
    from bcmocap.kcs.keypoints import KEYPOINT_NAMES

    index = {n: i for i, n in enumerate(names)}
    lateral = joints[:, index["lhumerus"]] - joints[:, index["rhumerus"]]
    lateral /= np.linalg.norm(lateral, axis=1, keepdims=True)
    points = np.full((len(joints), 17, 3), np.nan)
    for k, name in enumerate(KEYPOINT_NAMES["coco17"]):
        if name in FROM_CMU:
            points[:, k] = joints[:, index[FROM_CMU[name]]]
        elif name in ("left_ear", "right_ear"):
            points[:, k] = joints[:, index["head"]] + (0.08 if name == "left_ear" else -0.08) * lateral
    centred = points - np.nanmean(joints, axis=1, keepdims=True)
    return scale[:, None, None] * np.einsum("fij,fkj->fki", rotation[:, :2, :], centred) + np.array([320.0, 240.0])


def write_coco_results(path: Path, pixels: np.ndarray, rng: np.random.Generator, noise_px: float) -> None:
    """A COCO keypoint results file: a detection per frame, the keypoints with the row's noise and dropouts."""
    sigma = COCO_SIGMAS / COCO_SIGMAS[5:].mean() * noise_px  # mean over the 12 body keypoints: noise_px
    noisy = pixels + rng.normal(size=pixels.shape) * sigma[None, :, None]
    score = np.where(np.isfinite(pixels).all(-1), 0.9, 0.0)
    score[rng.random(score.shape) < DROPOUT[noise_px]] = 0.0
    rows = []
    for frame in range(len(pixels)):
        triplets = [[float(x), float(y), float(c)] if c > 0 else [0.0, 0.0, 0.0]
                    for (x, y), c in zip(noisy[frame], score[frame])]
        rows.append({"image_id": frame, "category_id": 1, "keypoints": sum(triplets, []), "score": 0.9})
    path.write_text(json.dumps(rows))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--paths", type=int, default=5, help="camera paths per walk (default 5)")
    ap.add_argument("--keypoint-smoothing", type=float, default=10.0, help="the smoothed rows' KCSOptions.keypoint_smoothing "
                    "(frames at 120 Hz; default 10: σ 83 ms, as 2.5 frames at 30 frames/s)")
    args = ap.parse_args()

    from kcs_table import camera_paths, load_trials

    from bcmocap.compilation_cache import enable_compilation_cache
    from bcmocap.kcs import KCSOptions, aligned_joint_distances, reconstruct
    from bcmocap.kcs.keypoints import keypoint_input
    from bcmocap.precision import enable_float64

    enable_float64()
    enable_compilation_cache()
    clock = time.perf_counter()
    chain, trials = load_trials(ROOT.parent / "shared" / "data" / "cmu" / "amc")
    names = list(chain.names)
    seen = [names.index(n) for n in SEEN]
    rows = {}
    with tempfile.TemporaryDirectory() as scratch:
        for noise in NOISE_PX:
            per_walk = {}
            for w, walk in enumerate(WALKS):
                truth = trials[walk]
                rng = np.random.default_rng([47, w, int(noise)])
                rotation, scale = camera_paths(len(truth), args.paths, rng)
                scale = scale / 2.0  # a 500 px focal length: the walker fits 640 x 480
                images = []
                for p in range(args.paths):
                    path = Path(scratch) / f"{walk}-{p}-{noise:g}.json"
                    write_coco_results(path, coco_keypoints(truth, names, rotation[p], scale[p]), rng, noise)
                    data = keypoint_input(path, "coco17")
                    images.append(data.joints_2d)
                per_walk[walk] = {"missing_fraction": float(np.mean(~np.isfinite(np.stack(images)).all(-1)))}
                for label, sigma in (("raw", 0.0), ("smoothed", args.keypoint_smoothing)):
                    result = reconstruct(data.chain, np.stack(images), data.rest,
                                         options=KCSOptions(keypoint_smoothing=sigma))
                    distances = np.asarray(aligned_joint_distances(np.asarray(result.joints),
                                                                   np.broadcast_to(truth, result.joints.shape)))
                    per_walk[walk][label] = {"all_joints_mm": float(distances.mean() * 1000),
                                             "coco_joints_mm": float(distances[..., seen].mean() * 1000)}
            row = {"noise_px": noise, "dropout": DROPOUT[noise], "walks": per_walk}
            for label in ("raw", "smoothed"):
                row[label] = {k: float(np.mean([r[label][k] for r in per_walk.values()]))
                              for k in ("all_joints_mm", "coco_joints_mm")}
            rows[f"{noise:g}px"] = row
            print(f"σ {noise:g} px, dropout {DROPOUT[noise]:.0%}: over COCO's joints {row['raw']['coco_joints_mm']:.1f} mm "
                  f"(smoothed {row['smoothed']['coco_joints_mm']:.1f}), over all 19 {row['raw']['all_joints_mm']:.1f} mm "
                  f"(smoothed {row['smoothed']['all_joints_mm']:.1f})", flush=True)
    write_json(args.json, {"rows": rows, "walks": list(WALKS), "paths": args.paths, "image": [640, 480],
                           "keypoint_smoothing_frames": args.keypoint_smoothing,
                           "sigmas": "COCO OKS per-keypoint constants, scaled to the row's mean over the body keypoints",
                           "seconds": round(time.perf_counter() - clock, 1)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
