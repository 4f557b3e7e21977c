"""How a room's repeated patterns fool the reference photos' pairs, measured against the studio's truth (issue 42).

For each room and seed the studio renders only the reference photos of a capture (``bcmocap.sim.studio``: the
loop of hand-held photos around the capture area, half looking out and half in), and the frontend builds its
reference from them as ``bcmocap run`` does (:func:`bcmocap.frontend.reference.build_reference`, with the photos'
pinhole camera and the rotation check). Against the truth it reports:

- **pairs**: every verified pair (SIFT, Lowe's ratio, F-RANSAC at 1.5 px), called *right* when at least half of
  its inliers lie within 3 px (Sampson distance) of the true epipolar geometry, else an *alias*; with their inliers;
- **distinctive pairs**: those verified on their coarse features' geometry
  (:func:`~bcmocap.frontend.reference.verify_distinctive`), labelled the same way;
- **rotation check**: the distinctive pairs the check keeps (consistent with one set of absolute rotations) and
  how many of those are aliases, and the photos they connect;
- **model**: the photos the reference registers, the check's verdict, and the camera centres' distance from the
  truth after the best similarity (median, max, how many photos more than 10 cm off).

    python benchmarks/reference_aliases.py --out /tmp/aliases --json benchmarks/results/reference_aliases.json \
        [--rooms repeated textured] [--motions walk run] [--seeds 0 1 2] [--photos 24]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json  # noqa: E402

RIGHT_PX = 3.0  # an inlier within this Sampson distance of the true epipolar geometry is a true match
RIGHT_FRACTION = 0.5  # a pair with at least this fraction of true matches is right
OFF_M = 0.10  # a photo further than this from the truth (after the similarity) is misplaced


def render_photos(folder: Path, room: str, seed: int, photos: int, motion: str):
    """The reference photos of the studio capture ``(motion, room, seed)`` in ``folder/reference``; returns their
    names, the ``(N, 7)`` true world_from_camera and the photos' camera."""
    from bcmocap.sim.studio import (
        StudioSettings,
        _plan,
        _write_reference_photos,
        reference_photo_path,
    )

    plan = _plan(StudioSettings(motion=motion, room=room, seed=seed, reference_photos=photos))
    (folder / "reference").mkdir(parents=True, exist_ok=True)
    _write_reference_photos(folder, plan, list(range(photos)), lambda done: None)
    names = tuple(reference_photo_path(folder, i).name for i in range(photos))
    return names, np.asarray(plan.reference_poses, np.float64), plan.reference_camera


def _camera_from_world(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from bcmocap.geometry import matrix_from_quat

    rotation = np.asarray(matrix_from_quat(pose[:4]), np.float64)  # world_from_camera
    return rotation.T, pose[4:]


def true_match_fraction(keypoints_a, keypoints_b, matches, pose_a, pose_b, camera) -> float:
    """Fraction of ``matches`` ``(M, 2)`` within :data:`RIGHT_PX` (Sampson) of the true epipolar geometry."""
    ray_a = np.asarray(camera.unproject(np.asarray(keypoints_a[matches[:, 0], :2], np.float64)))
    ray_b = np.asarray(camera.unproject(np.asarray(keypoints_b[matches[:, 1], :2], np.float64)))
    (ra, ca), (rb, cb) = _camera_from_world(pose_a), _camera_from_world(pose_b)
    rotation, t = rb @ ra.T, rb @ (ca - cb)  # x_b = R x_a + t
    essential = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ rotation
    pa, pb = ray_a / ray_a[:, 2:], ray_b / ray_b[:, 2:]
    ea, eb = pa @ essential.T, pb @ essential
    focal = float(np.mean(np.asarray(camera.focal)))
    sampson = np.abs(np.sum(pb * ea, 1)) / np.sqrt(ea[:, 0] ** 2 + ea[:, 1] ** 2 + eb[:, 0] ** 2 + eb[:, 1] ** 2)
    return float(np.mean(focal * sampson < RIGHT_PX))


def centre_errors(model, names, truth) -> np.ndarray:
    """Distances (m) of the model's camera centres from the truth's after the best similarity (Umeyama's)."""
    from bcmocap.geometry import similarity

    rec = model.reconstruction
    index = {n: i for i, n in enumerate(names)}
    found = [(rec.image(i).name, np.asarray(rec.image(i).projection_center(), np.float64)) for i in rec.reg_image_ids()]
    a = np.array([c for _, c in found])
    b = np.array([truth[index[n], 4:] for n, _ in found])
    scale, rotation, shift = similarity(a, b)
    return np.linalg.norm(b - (scale * a @ rotation.T + shift), axis=1)


def one_room(out: Path, room: str, seed: int, photos: int, motion: str, log) -> dict:
    import cv2

    from bcmocap.frontend import reference

    folder = out / f"{motion}-{room}-s{seed}"
    if folder.exists():
        shutil.rmtree(folder)
    clock = time.perf_counter()
    names, truth, camera = render_photos(folder, room, seed, photos, motion)
    # The pairs as build_reference verifies them (same SIFT, ratio, threshold, minimum inliers), labelled by the truth.
    features = {n: reference.extract_sift(cv2.imread(str(folder / "reference" / n), cv2.IMREAD_GRAYSCALE))
                for n in names}
    size = {n: reference.DISTINCTIVE_SIZE * max(camera.width, camera.height) for n in names}
    verified, distinctive = reference._match_pairs(names, features, ratio=0.8, threshold_px=1.5, min_inliers=15,
                                                   distinctive_px=size)
    index = {n: i for i, n in enumerate(names)}

    def labels(pairs):
        return {pair: true_match_fraction(features[pair[0]][0], features[pair[1]][0], m, truth[index[pair[0]]],
                                          truth[index[pair[1]]], camera) >= RIGHT_FRACTION for pair, m in pairs.items()}

    right, right_distinctive = labels(verified), labels(distinctive)
    _, kept = reference._rotation_consistent(names, features, distinctive, camera, 1.5, 1.5)  # as build_reference
    model = reference.build_reference(folder / "reference", names, camera=camera, workdir=folder / "work")
    errors = centre_errors(model, names, truth)
    row = {
        "room": room, "seed": seed, "photos": photos, "motion": motion,
        "pairs_verified": len(verified), "pairs_right": int(sum(right.values())),
        "inliers_right": int(sum(len(m) for p, m in verified.items() if right[p])),
        "inliers_alias": int(sum(len(m) for p, m in verified.items() if not right[p])),
        "pairs_distinctive": len(distinctive), "distinctive_right": int(sum(right_distinctive.values())),
        "rotation_kept": len(kept), "rotation_kept_aliases": int(sum(not right_distinctive[p] for p in kept)),
        "rotation_kept_right_of_right": int(sum(right_distinctive[p] for p in kept)),
        "rotation_kept_photos": len({n for p in kept for n in p}),
        "model_registered": model.num_registered, "model_check": model.rotation_check,
        "model_inconsistent_pairs": model.inconsistent_pairs,
        "model_error_px": round(model.mean_reprojection_error_px, 3),
        "centre_error_m_median": float(np.median(errors)), "centre_error_m_max": float(errors.max()),
        "photos_off": int((errors > OFF_M).sum()), "seconds": round(time.perf_counter() - clock, 1),
    }
    log(f"{motion} {room} s{seed}: {row['pairs_right']} of {row['pairs_verified']} verified pairs right "
        f"({row['inliers_alias']} alias inliers against {row['inliers_right']}), {row['distinctive_right']} of "
        f"{row['pairs_distinctive']} distinctive ones; the rotation check keeps "
        f"{row['rotation_kept']} ({row['rotation_kept_aliases']} aliases) over {row['rotation_kept_photos']} photos; "
        f"model: {row['model_registered']} photos, check {row['model_check']}, centres {row['centre_error_m_median']:.3f} m "
        f"median, {row['centre_error_m_max']:.2f} m max, {row['photos_off']} off by more than {OFF_M:g} m")
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="working folder (each room's photos and model; rewritten)")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--rooms", nargs="+", default=["repeated", "textured"], choices=["textured", "sparse", "repeated"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--photos", type=int, default=24, help="reference photos per room (the studio's default 24)")
    ap.add_argument("--motions", nargs="+", default=["walk"],
                    help="the captures' motions (each room is built around its motion's path)")
    args = ap.parse_args()

    from bcmocap.precision import enable_float64

    enable_float64()
    clock = time.perf_counter()
    rows = [one_room(Path(args.out), room, seed, args.photos, motion, lambda text: print(text, flush=True))
            for room in args.rooms for motion in args.motions for seed in args.seeds]
    if args.json:
        write_json(args.json, {"rows": rows, "settings": {k: v for k, v in vars(args).items() if k not in ("out", "json")},
                               "seconds": round(time.perf_counter() - clock, 1), "machine": machine()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
