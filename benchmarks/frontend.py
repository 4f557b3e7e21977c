"""Frontend figures (issue 5).

1. Audio synchronisation on a rendered capture: per-camera frame offsets from the claps against the
   studio's ground truth (``video_start_frame + clap_frames[0]``), per trial; the largest error in frames.
2. Reference reconstruction (OpenCV SIFT, FLANN + ratio test, F-RANSAC, pycolmap incremental mapping):
   registered photos and mean reprojection error on the real SceauxCastle photos (downscaled to
   ``--sceaux-width``) and on the rendered capture's reference photos; for the rendered ones also the
   photos' rotation and position errors against the truth after a similarity alignment (§5.1).
3. Registration of the body-camera frames of the rendered capture's "capture" trial (every
   ``--register-stride``-th frame of every camera; ``bcmocap.frontend.register_capture``): absolute
   registration to the rendered reference model, then rounds of new points, bundle adjustment with the
   reference fixed and relative registration. Registered fraction (goal ≥ 95 %), rotation and position
   errors of the registered frames against the truth after the same similarity alignment (photo centres;
   goals: median ≤ 0.5° and ≤ 2 cm), images per second (feature extraction + registration; cameras and
   frame pairs in threads).

   Features are streamed to a temporary folder and read back memory-mapped, as ``bcmocap frontend`` does;
   the peak private memory (``RssAnon``) during extraction and registration is reported beside the size of
   the feature files, to show that a long capture does not have to fit in memory.

   Frames left unregistered get orientations from homographies (``fill_with_homographies``); their
   count and errors are reported too.

4. With ``--end-to-end RUN_DIR``: ``bcmocap run`` on the same capture (``benchmarks/end_to_end.py``;
   the capture needs a range-of-motion trial of a few seconds, e.g. ``bcmocap simulate --rom-seconds 2.5``):
   mean joint position and joint angle errors after the §5.1 similarity (goals ≤ 2.0 cm, ≤ 3.0°).
   That run takes about 40 minutes for the 10 s capture; ``--end-to-end-json FILE`` instead takes the
   figures of an earlier ``benchmarks/end_to_end.py --json FILE`` run, after checking that it rendered a
   capture with the same settings, and records where they came from.

    python benchmarks/frontend.py --json benchmarks/results/frontend.json [--capture DIR] [--end-to-end RUN_DIR]

Without ``--capture`` a small capture (0.1 s trials, ``--body-width`` x ``--body-height`` body cameras,
default 640x360 as the standard rig, 24 reference photos of 640x480) is rendered into a temporary folder
first (about a minute on 2 cores; the whole benchmark takes about 4 minutes).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_json  # noqa: E402

from bcmocap.frontend import read_capture, synchronize  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.frontend.reference import build_reference  # noqa: E402
from bcmocap.frontend.register import reference_index  # noqa: E402
from bcmocap.geometry import similarity  # noqa: E402
from bcmocap.frontend.homography import fill_with_homographies  # noqa: E402
from bcmocap.frontend.relative import extract_trial_features, register_capture  # noqa: E402
from bcmocap.io.capture_folder import load_ground_truth  # noqa: E402
from bcmocap.sim.studio import StudioSettings, write_capture  # noqa: E402

SCEAUX = Path(__file__).resolve().parents[2] / "shared" / "data" / "images" / "SceauxCastle" / "images"
NOT_BUILT: list[str] = []


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


def _pose_error(align, pose: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    from bcmocap.geometry import matrix_from_quat

    scale, rot, shift = align
    rel = np.asarray(matrix_from_quat(true[:4])).T @ rot @ np.asarray(matrix_from_quat(pose[:4]))
    return (float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))),
            float(100 * np.linalg.norm(scale * rot @ pose[4:] + shift - true[4:])))


class MemoryPeak:
    """Peak resident memory of this process while the block runs, sampled from ``/proc/self/status`` every
    0.1 s: ``VmRSS`` (all resident pages, including memory-mapped feature files the kernel may drop) and
    ``RssAnon`` (private memory, what a long capture must not grow without bound). Zero where /proc is missing."""

    def __enter__(self):
        import threading

        self.rss_mb = self.anon_mb = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _sample(self) -> None:
        try:
            fields = dict(line.split(":", 1) for line in Path("/proc/self/status").read_text().splitlines())
        except OSError:
            return
        kb = (lambda key: float(fields.get(key, "0 kB").split()[0]))
        self.rss_mb = max(self.rss_mb, kb("VmRSS") / 1024)
        self.anon_mb = max(self.anon_mb, kb("RssAnon") / 1024)

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            self._sample()

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self._sample()


def registration_figures(model, capture, truth, stride: int, features_dir: Path) -> dict:
    """Registration of the "capture" trial's frames of every camera (see the module docstring); features are
    cached memory-mapped under ``features_dir`` as ``bcmocap frontend`` does."""
    rec, poses = model.reconstruction, dict(zip(truth.reference_names, truth.reference_poses))
    images = [rec.image(i) for i in rec.reg_image_ids()]
    align = similarity(np.array([im.projection_center() for im in images]),
                       np.array([poses[im.name][4:] for im in images]))
    tt = truth.trials["capture"]
    clock = time.perf_counter()
    with MemoryPeak() as before:
        pass
    with MemoryPeak() as memory:
        index = reference_index(model)
        features = extract_trial_features(capture, "capture", stride=stride, starts=np.asarray(tt.video_start_frame),
                                          num_frames=len(tt.world_from_camera), cache_dir=features_dir)
        feature_seconds = time.perf_counter() - clock
        clock = time.perf_counter()
        out = register_capture(features, [c.intrinsics for c in capture.cameras], index)
        fill = fill_with_homographies(out, [c.intrinsics for c in capture.cameras])
        register_seconds = time.perf_counter() - clock
    feature_bytes = sum(f.stat().st_size for f in features_dir.rglob("*") if f.is_file())
    keypoints = sum(len(k) for row in features for k, _ in row)
    filled = [_pose_error(align, fill.world_from_camera[t, c], tt.world_from_camera[t * stride, c])
              for t, c in zip(*np.nonzero(fill.filled))]
    errors = {"absolute": ([], []), "relative": ([], [])}
    for t, row in enumerate(out.states):
        for c, state in enumerate(row):
            if state.registered:
                rot_deg, pos_cm = _pose_error(align, state.world_from_camera, tt.world_from_camera[t * stride, c])
                errors[state.how][0].append(rot_deg)
                errors[state.how][1].append(pos_cm)
    stats = (lambda e: {"median": float(np.median(e)), "mean": float(np.mean(e)), "max": float(np.max(e))}
             if len(e) else None)
    every = (errors["absolute"][0] + errors["relative"][0], errors["absolute"][1] + errors["relative"][1])
    total = out.registered.size
    images = total / (feature_seconds + register_seconds)
    row = {"frames": total, "registered": int(out.registered.sum()), "registered_fraction": out.registered_fraction,
           "registered_absolute": len(errors["absolute"][0]), "registered_relative": len(errors["relative"][0]),
           "rounds": out.rounds, "new_points": len(out.new_point_ids),
           "rotation_error_deg": stats(every[0]), "position_error_cm": stats(every[1]),
           "absolute": {"rotation_error_deg": stats(errors["absolute"][0]), "position_error_cm": stats(errors["absolute"][1])},
           "relative": {"rotation_error_deg": stats(errors["relative"][0]), "position_error_cm": stats(errors["relative"][1])},
           "filled_by_homographies": len(filled),
           "filled": {"rotation_error_deg": stats([e[0] for e in filled]), "position_error_cm": stats([e[1] for e in filled])},
           "stride": stride, "feature_seconds": feature_seconds, "register_seconds": register_seconds,
           "images_per_second": images, "index_descriptors": len(index.descriptors),
           "memory": {"keypoints": keypoints, "feature_files_mb": feature_bytes / 2**20,
                      "rss_before_mb": before.rss_mb, "anon_before_mb": before.anon_mb,
                      "peak_rss_mb": memory.rss_mb, "peak_anon_mb": memory.anon_mb}}
    print(f"registration: {row['registered']}/{total} body-camera frames ({100 * row['registered_fraction']:.1f} %): "
          f"{row['registered_absolute']} absolute, {row['registered_relative']} relative in {len(out.rounds) - 1} rounds, "
          f"{row['new_points']} new points; {images:.2f} images/s (features {feature_seconds:.0f} s, "
          f"registration {register_seconds:.0f} s)")
    print(f"  memory: {keypoints} features ({feature_bytes / 2**20:.0f} MB memory-mapped from disk); peak private "
          f"memory {memory.anon_mb:.0f} MB (before {before.anon_mb:.0f} MB), peak resident {memory.rss_mb:.0f} MB")
    for how in ("absolute", "relative"):
        if errors[how][0]:
            print(f"  {how}: rotation error median {np.median(errors[how][0]):.3f}° max {np.max(errors[how][0]):.3f}°, "
                  f"position error median {np.median(errors[how][1]):.2f} cm max {np.max(errors[how][1]):.2f} cm")
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


def print_end_to_end(figures: dict, source: str = "") -> None:
    print(f"end to end{source}: joint position {figures['joint_position_error_cm']['mean']:.3f} cm, "
          f"joint angle {figures['joint_angle_error_deg']['mean']:.3f} deg (goals 2.0 / 3.0)")


def earlier_end_to_end(path: Path, settings: dict) -> dict:
    """End-to-end figures from an earlier ``benchmarks/end_to_end.py --json`` file, if it rendered a
    capture with the same studio ``settings`` as the one measured here."""
    try:
        earlier = json.loads(path.read_text())
        earlier_settings = earlier["capture_settings"]
        earlier["joint_position_error_cm"]["mean"], earlier["joint_angle_error_deg"]["mean"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(f"--end-to-end-json {path}: not an end_to_end.py result ({exc!r})") from None
    differ = sorted(k for k in set(settings) | set(earlier_settings) if settings.get(k) != earlier_settings.get(k))
    if differ:
        raise SystemExit(f"--end-to-end-json {path}: its capture was rendered with other settings ({', '.join(differ)})")
    print_end_to_end(earlier, f" (from {path})")
    return {**earlier, "source": f"{path} (benchmarks/end_to_end.py, an earlier run on a capture with the same settings)"}


def main(argv=None) -> int:
    enable_float64()
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--capture", type=Path, help="a rendered capture folder (default: render a small one)")
    parser.add_argument("--sceaux-width", type=int, default=640)
    parser.add_argument("--body-width", type=int, default=640, help="body-camera width of the rendered capture")
    parser.add_argument("--body-height", type=int, default=360)
    parser.add_argument("--register-stride", type=int, default=1, help="register every n-th frame")
    parser.add_argument("--end-to-end", type=Path, metavar="RUN_DIR",
                        help="also run bcmocap run on the capture into RUN_DIR (resumed if it holds a run)")
    parser.add_argument("--run-config", type=Path, help="bcmocap run settings for --end-to-end (TOML or JSON)")
    parser.add_argument("--end-to-end-json", type=Path, metavar="FILE",
                        help="take the end-to-end figures from an earlier benchmarks/end_to_end.py --json FILE "
                             "on a capture with the same settings instead of running bcmocap run")
    args = parser.parse_args(argv)
    if args.end_to_end is not None and args.capture is None:
        parser.error("--end-to-end needs --capture (a capture with a range-of-motion trial of a few seconds)")
    if args.end_to_end is not None and args.end_to_end_json is not None:
        parser.error("give --end-to-end or --end-to-end-json, not both")

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
                                     lambda model: registration_figures(model, capture, truth, args.register_stride,
                                                                        Path(tmp) / "features"))
        registration = rendered.pop("used_model")
        sceaux_dir = Path(tmp) / "sceaux"
        sceaux_dir.mkdir()
        names, camera = sceaux_copies(sceaux_dir, args.sceaux_width)
        real = reference_figures("sceaux", sceaux_dir, names, camera)
        settings = dict(capture.manifest.get("settings", {}))
        end_to_end = None
        if args.end_to_end is not None:
            from end_to_end import end_to_end as run_end_to_end

            from bcmocap.pipeline.config import load_config

            end_to_end = run_end_to_end(capture_dir, args.end_to_end, load_config(args.run_config))
            print_end_to_end(end_to_end)
        elif args.end_to_end_json is not None:
            end_to_end = earlier_end_to_end(args.end_to_end_json, settings)

    payload = {
        "registered_fraction": registration["registered_fraction"],
        "rotation_error_deg": registration["rotation_error_deg"],
        "position_error_cm": registration["position_error_cm"],
        "images_per_second": registration["images_per_second"],
        "memory": registration["memory"],
        "sync_max_error_frames": max(row["max_error_frames"] for row in sync.values()),
        "sync": sync,
        "real_photos": {**real, "dataset": "SceauxCastle", "width_px": args.sceaux_width},
        "rendered_reference": {**rendered, "capture_settings": settings},
        "registration": registration,
        "end_to_end": end_to_end,
        "not_built": NOT_BUILT + ([] if end_to_end is not None else ["end_to_end (pass --end-to-end RUN_DIR or --end-to-end-json FILE)"]),
    }
    write_json(args.json, payload)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
