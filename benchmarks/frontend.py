"""Frontend figures (issue 5) for the parts built so far.

1. Audio synchronisation on a rendered capture: per-camera frame offsets from the claps against the
   studio's ground truth (``video_start_frame + clap_frames[0]``), per trial; the largest error in frames.
2. Reference reconstruction (OpenCV SIFT, FLANN + ratio test, F-RANSAC, pycolmap incremental mapping):
   registered photos and mean reprojection error on the real SceauxCastle photos (downscaled to
   ``--sceaux-width``) and on the rendered capture's reference photos; for the rendered ones also the
   photos' rotation and position errors against the truth after a similarity alignment (§5.1).
3. Absolute registration of the body-camera frames of the rendered capture's "capture" trial (every
   ``--register-stride``-th frame of every camera) to the rendered reference model: registered fraction,
   rotation and position errors of the registered frames against the truth after the same similarity
   alignment (photo centres), frames per second.

Not built yet, so not reported: relative registration, homographies, the end-to-end joint errors,
parallel throughput.

    python benchmarks/frontend.py --json benchmarks/results/frontend.json [--capture DIR]

Without ``--capture`` a small capture (0.1 s trials, ``--body-width`` x ``--body-height`` body cameras,
default 640x360 as the standard rig, 24 reference photos of 640x480) is rendered into a temporary folder
first (about a minute on 2 cores; the whole benchmark takes about 4 minutes).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_json  # noqa: E402

from bcmocap.frontend import read_capture, synchronize  # noqa: E402
from bcmocap.frontend.reference import build_reference  # noqa: E402
from bcmocap.frontend.register import reference_index, register_trial, similarity  # noqa: E402
from bcmocap.sim.studio import StudioSettings, load_ground_truth, write_capture  # noqa: E402

SCEAUX = Path("/work/shared/data/images/SceauxCastle/images")
NOT_BUILT = ["relative registration", "homographies", "correspondences output",
             "parallel throughput (images_per_second)", "end_to_end"]


def sync_figures(capture_dir: Path) -> dict:
    capture, truth = read_capture(capture_dir), load_ground_truth(capture_dir)
    out = {}
    for trial in capture.trials:
        clock = time.perf_counter()
        result = synchronize(capture, trial)
        seconds = time.perf_counter() - clock
        tt = truth.trials[trial]
        expected = tt.video_start_frame + tt.clap_frames[0]
        errors = np.abs(result.offsets - expected)
        out[trial] = {"cameras": len(result.offsets), "max_error_frames": int(errors.max()),
                      "exact": int((errors == 0).sum()), "clap_sample_max_error": int(np.abs(result.clap_samples - tt.clap_samples).max()),
                      "duration_s": result.duration_s, "seconds": seconds}
        print(f"sync {trial:8s} {len(errors)} cameras: max error {errors.max()} frames, {out[trial]['exact']} exact, "
              f"clap samples max error {out[trial]['clap_sample_max_error']}, {seconds:.2f} s")
    return out


def pose_errors(model, truth: dict[str, np.ndarray]) -> dict:
    """Registered photos against their true ``world_from_camera`` after a similarity alignment (§5.1)."""
    from bcmocap.geometry import matrix_from_quat

    rec = model.reconstruction
    images = [rec.image(i) for i in rec.reg_image_ids()]
    est_c = np.array([im.projection_center() for im in images])
    est_r = np.array([im.cam_from_world().rotation.matrix().T for im in images])  # world_from_camera
    poses = np.array([truth[im.name] for im in images])
    true_c, true_r = poses[:, 4:], np.asarray(matrix_from_quat(poses[:, :4]))
    scale, rot, shift = similarity(est_c, true_c)
    pos_cm = 100 * np.linalg.norm(scale * est_c @ rot.T + shift - true_c, axis=1)
    rel = np.einsum("nji,jk,nkl->nil", true_r, rot, est_r)
    rot_deg = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return {"rotation_error_deg": {"median": float(np.median(rot_deg)), "mean": float(rot_deg.mean())},
            "position_error_cm": {"median": float(np.median(pos_cm)), "mean": float(pos_cm.mean())}}


def registration_figures(model, capture, truth, stride: int) -> dict:
    """Absolute registration of the "capture" trial's frames of every camera (see the module docstring)."""
    from bcmocap.geometry import matrix_from_quat

    rec, poses = model.reconstruction, dict(zip(truth.reference_names, truth.reference_poses))
    images = [rec.image(i) for i in rec.reg_image_ids()]
    scale, rot, shift = similarity(np.array([im.projection_center() for im in images]),
                                   np.array([poses[im.name][4:] for im in images]))
    clock = time.perf_counter()
    index = reference_index(model)
    tt = truth.trials["capture"]
    total, rot_deg, pos_cm = 0, [], []
    for c, name in enumerate(capture.camera_names):
        start = int(tt.video_start_frame[c])
        out = register_trial(capture, "capture", name, index, stride=stride, start=start,
                             stop=start + len(tt.world_from_camera))
        total += len(out.frames)
        for frame, pose in zip(out.frames[out.registered], out.poses[out.registered]):
            true = tt.world_from_camera[frame - start, c]
            rel = np.asarray(matrix_from_quat(true[:4])).T @ rot @ np.asarray(matrix_from_quat(pose[:4]))
            rot_deg.append(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1))))
            pos_cm.append(100 * np.linalg.norm(scale * rot @ pose[4:] + shift - true[4:]))
    seconds = time.perf_counter() - clock
    rot_deg, pos_cm = np.array(rot_deg), np.array(pos_cm)
    stats = (lambda e: {"median": float(np.median(e)), "mean": float(e.mean())} if len(e) else None)
    row = {"frames": total, "registered": len(rot_deg), "registered_fraction": len(rot_deg) / max(total, 1),
           "rotation_error_deg": stats(rot_deg), "position_error_cm": stats(pos_cm), "stride": stride,
           "seconds": seconds, "frames_per_second": total / seconds, "index_descriptors": len(index.descriptors)}
    print(f"absolute registration: {row['registered']}/{total} body-camera frames registered "
          f"({100 * row['registered_fraction']:.1f} %), {row['frames_per_second']:.1f} frames/s")
    if len(rot_deg):
        print(f"absolute registration: rotation error median {np.median(rot_deg):.3f}° mean {rot_deg.mean():.3f}°, "
              f"position error median {np.median(pos_cm):.2f} cm mean {pos_cm.mean():.2f} cm")
    return row


def reference_figures(label: str, image_dir: Path, names, camera, truth: dict | None = None,
                      use_model=None) -> dict:
    import pycolmap

    pycolmap.logging.minloglevel = 2
    with tempfile.TemporaryDirectory() as work:
        clock = time.perf_counter()
        model = build_reference(image_dir, names, camera=camera, workdir=work)
        seconds = time.perf_counter() - clock
        used = use_model(model) if use_model is not None else None
    row = {"registered": model.num_registered, "total": len(model.image_names),
           "mean_reprojection_error_px": model.mean_reprojection_error_px, "points3D": model.num_points3D,
           "verified_pairs": len(model.pair_inliers), "seconds": seconds,
           "stage_seconds": model.seconds}
    if truth is not None and model.num_registered >= 3:
        row.update(pose_errors(model, truth))
    print(f"reference {label:9s} registered {row['registered']}/{row['total']}, mean reprojection error "
          f"{row['mean_reprojection_error_px']:.3f} px, {row['points3D']} points, {row['verified_pairs']} verified pairs, "
          f"{seconds:.1f} s")
    if "rotation_error_deg" in row:
        print(f"reference {label:9s} photo poses after similarity alignment: rotation error median "
              f"{row['rotation_error_deg']['median']:.3f}°, position error median {row['position_error_cm']['median']:.2f} cm")
    if used is not None:
        row["used_model"] = used
    return row


def sceaux_copies(folder: Path, width: int) -> tuple[list[str], object]:
    import pycolmap

    names = []
    for path in sorted(SCEAUX.glob("*.JPG")):
        image = cv2.imread(str(path))
        h, w = image.shape[:2]
        scale = width / w
        small = cv2.resize(image, (width, round(h * scale)), interpolation=cv2.INTER_AREA)
        names.append(path.stem + ".jpg")
        cv2.imwrite(str(folder / names[-1]), small, [cv2.IMWRITE_JPEG_QUALITY, 90])
    K = np.loadtxt(SCEAUX / "K.txt")
    # SIMPLE_RADIAL (f, cx, cy, k) in COLMAP's convention, started from K.txt; BA refines f and k.
    camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=width, height=small.shape[0],
                             params=[K[0, 0] * scale, (K[0, 2] + 0.5) * scale, (K[1, 2] + 0.5) * scale, 0.0])
    return names, camera


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--capture", type=Path, help="a rendered capture folder (default: render a small one)")
    parser.add_argument("--sceaux-width", type=int, default=640)
    parser.add_argument("--body-width", type=int, default=640, help="body-camera width of the rendered capture")
    parser.add_argument("--body-height", type=int, default=360)
    parser.add_argument("--register-stride", type=int, default=1, help="register every n-th frame")
    args = parser.parse_args(argv)

    print("frontend benchmark: built so far = capture reading, audio sync, reference reconstruction, "
          "absolute registration")
    print("not built, so not reported: " + ", ".join(NOT_BUILT))
    with tempfile.TemporaryDirectory() as tmp:
        capture_dir = args.capture
        if capture_dir is None:
            capture_dir = Path(tmp) / "capture"
            clock = time.perf_counter()
            write_capture(capture_dir, StudioSettings(seconds=0.1, rom_seconds=0.1, width=args.body_width, height=args.body_height,
                                                      reference_photos=24, reference_width=640,
                                                      reference_height=480, seed=5), progress=False)
            print(f"rendered a small capture in {time.perf_counter() - clock:.0f} s")
        sync = sync_figures(capture_dir)
        capture, truth = read_capture(capture_dir), load_ground_truth(capture_dir)
        poses = dict(zip(truth.reference_names, truth.reference_poses))
        rendered = reference_figures("rendered", capture.path / "reference", [p.name for p in capture.reference_photos],
                                     capture.reference_camera, poses,
                                     lambda model: registration_figures(model, capture, truth, args.register_stride))
        absolute = rendered.pop("used_model")
        sceaux_dir = Path(tmp) / "sceaux"
        sceaux_dir.mkdir()
        names, camera = sceaux_copies(sceaux_dir, args.sceaux_width)
        real = reference_figures("sceaux", sceaux_dir, names, camera)
        settings = dict(capture.manifest.get("settings", {}))

    payload = {
        "sync_max_error_frames": max(row["max_error_frames"] for row in sync.values()),
        "sync": sync,
        "real_photos": {**real, "dataset": "SceauxCastle", "width_px": args.sceaux_width},
        "rendered_reference": {**rendered, "capture_settings": settings},
        "absolute_registration": absolute,
        "not_built": NOT_BUILT,
    }
    write_json(args.json, payload)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
