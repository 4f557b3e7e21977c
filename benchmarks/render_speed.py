"""Rendering speed of the synthetic capture studio, and whether SIFT can track its images.

1. Frames per second of the ray-cast renderer on the standard capture (CMU walk, 18 FOV cameras,
   textured room, body capsules) at 640x360 and 1280x720: steady state (compilation timed apart),
   wall clock and CPU time per frame.
2. ``write_capture`` of the standard 2-second capture at 640x360 (``bcmocap simulate``): wall clock per
   phase, the capture trial (18 cameras x 120 frames) separately.
3. OpenCV SIFT + ratio test (0.8) + RANSAC on the essential matrix of bearing vectors (threshold 1 px)
   between consecutive frames of each camera while walking: inliers per pair, median and min, on the
   rendered frames and after the MP4 (mp4v) round trip.

    python benchmarks/render_speed.py --json benchmarks/results/render_speed.json

Wall-clock figures depend on the machine's load: run on a quiet machine for the real speed.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_json  # noqa: E402

from bcmocap.cameras import camera_at  # noqa: E402
from bcmocap.kinematics import camera_poses  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.sim import load_body_motion, standard_rig  # noqa: E402
from bcmocap.sim.render import Renderer  # noqa: E402
from bcmocap.sim.scene import make_textured_scene  # noqa: E402
from bcmocap.io.capture_folder import load_ground_truth  # noqa: E402
from bcmocap.sim.studio import StudioSettings, capsule_ends, write_capture  # noqa: E402


def sift_inliers(camera, image_a, image_b, sift) -> int:
    """Inliers of SIFT + ratio test + RANSAC essential matrix on bearing vectors (rays < 78° off-axis)."""
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) if im.ndim == 3 else im for im in (image_a, image_b)]
    (ka, da), (kb, db) = (sift.detectAndCompute(g, None) for g in grey)
    if da is None or db is None or len(ka) < 8 or len(kb) < 8:
        return 0
    matches = [m[0] for m in cv2.BFMatcher().knnMatch(da, db, k=2) if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    if len(matches) < 8:
        return 0
    ra = np.asarray(camera.unproject(np.float64([ka[m.queryIdx].pt for m in matches])))
    rb = np.asarray(camera.unproject(np.float64([kb[m.trainIdx].pt for m in matches])))
    ok = (ra[:, 2] > 0.2) & (rb[:, 2] > 0.2)
    if ok.sum() < 8:
        return 0
    _, mask = cv2.findEssentialMat(ra[ok, :2] / ra[ok, 2:], rb[ok, :2] / rb[ok, 2:], np.eye(3), method=cv2.RANSAC,
                                   prob=0.999, threshold=1.0 / float(camera.focal[0]))
    return 0 if mask is None else int(mask.sum())


def render_speed(width: int, height: int, frames_per_camera: int, pairs: list[int]) -> dict:
    skeleton, motion = load_body_motion("walk", seconds=2.0)
    rig = standard_rig(skeleton, width, height)
    scene = make_textured_scene(np.asarray(motion.root_position)[:, :2], seed=0)
    poses = np.asarray(camera_poses(skeleton, rig, motion).wxyz_xyz)
    ends, radii, colors = capsule_ends(skeleton, motion)
    sift = cv2.SIFT_create()
    compile_s, wall, cpu, count, inliers = 0.0, 0.0, 0.0, 0, []
    frames = np.arange(frames_per_camera) + 20
    for c in range(rig.num_cameras):
        camera = camera_at(rig.intrinsics, c)
        renderer = Renderer(scene, camera)
        if c == 0:  # the first call compiles (one compilation serves all cameras of this size)
            start = time.perf_counter()
            rot, org = renderer.poses_at(poses[:, c], frames[:4])
            renderer.render(rot, org, renderer.capsules_at(ends, frames[:4]), radii, colors)
            compile_s = time.perf_counter() - start
        w0, c0 = time.perf_counter(), time.process_time()
        images = []
        for first in range(0, len(frames), 4):
            batch = frames[first: first + 4]
            rot, org = renderer.poses_at(poses[:, c], batch)
            images.extend(renderer.render(rot, org, renderer.capsules_at(ends, batch), radii, colors))
        wall += time.perf_counter() - w0
        cpu += time.process_time() - c0
        count += len(frames)
        for k in pairs:
            inliers.append(sift_inliers(camera, images[k], images[k + 1], sift))
    return {
        "frames": count,
        "frames_per_second": count / wall,
        "wall_ms_per_frame": 1000 * wall / count,
        "cpu_ms_per_frame": 1000 * cpu / count,
        "compile_s": compile_s,
        "sift_inliers": inliers,
    }


def capture_run(folder: Path) -> dict:
    timings: dict = {}
    start = time.perf_counter()
    write_capture(folder, StudioSettings(), progress=False, timings=timings)
    total = time.perf_counter() - start
    gt = load_ground_truth(folder)
    trial = gt.trials["capture"]
    sift = cv2.SIFT_create()
    inliers = []
    for c, name in enumerate(gt.rig.names):
        video = cv2.VideoCapture(str(folder / "trials" / "capture" / f"{name}.mp4"))
        wanted = {int(trial.video_start_frame[c]) + k for k in (30, 31, 60, 61, 90, 91)}
        decoded, i = {}, 0
        while len(decoded) < len(wanted):
            ok, image = video.read()
            if not ok:
                break
            if i in wanted:
                decoded[i] = image[..., ::-1]
            i += 1
        camera = camera_at(gt.rig.intrinsics, c)
        for k in (30, 60, 90):
            first = int(trial.video_start_frame[c]) + k
            inliers.append(sift_inliers(camera, decoded[first], decoded[first + 1], sift))
    size_mb = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 1e6
    return {"total_s": total, "timings_s": timings, "folder_mb": size_mb, "sift_inliers_mp4": inliers}


def stats(values) -> dict:
    v = np.asarray(values, float)
    return {"median": float(np.median(v)), "min": float(v.min()), "mean": float(v.mean())}


def main() -> int:
    enable_float64()
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--frames", type=int, default=24, help="frames per camera at 640x360 (1280x720: a third)")
    parser.add_argument("--keep", help="write the 2-second capture here instead of a temporary folder")
    args = parser.parse_args()

    load = os.getloadavg()[0]
    print(f"load average at start: {load:.2f} on {os.cpu_count()} CPUs", flush=True)
    small = render_speed(640, 360, args.frames, pairs=[2, 10, 18])
    print(f"640x360: {small['frames_per_second']:.1f} frames/s", flush=True)
    large = render_speed(1280, 720, max(args.frames // 3, 4), pairs=[2])
    print(f"1280x720: {large['frames_per_second']:.1f} frames/s", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep) if args.keep else Path(tmp) / "capture"
        run = capture_run(folder)
    t = run["timings_s"]
    frames = t.get("frames:capture", 0)
    sift_640 = stats(small["sift_inliers"])
    sift_mp4 = stats(run["sift_inliers_mp4"])

    rows = [
        ("renderer 640x360, frames/s (wall)", f"{small['frames_per_second']:.1f}"),
        ("renderer 640x360, ms/frame wall / CPU", f"{small['wall_ms_per_frame']:.1f} / {small['cpu_ms_per_frame']:.1f}"),
        ("renderer 1280x720, frames/s (wall)", f"{large['frames_per_second']:.1f}"),
        ("renderer 1280x720, ms/frame wall / CPU", f"{large['wall_ms_per_frame']:.1f} / {large['cpu_ms_per_frame']:.1f}"),
        ("compile 640x360 / 1280x720 (s)", f"{small['compile_s']:.1f} / {large['compile_s']:.1f}"),
        ("simulate 2 s walk: total (s)", f"{run['total_s']:.1f}"),
        ("  setup / reference photos (s)", f"{t.get('setup', 0):.1f} / {t.get('reference_photos', 0):.1f}"),
        ("  ROM trial, 18 x 120 frames (s)", f"{t.get('trial:rom', 0):.1f}"),
        (f"  capture trial, {frames} frames (s)", f"{t.get('trial:capture', 0):.1f}"),
        ("  capture trial frames/s", f"{frames / max(t.get('trial:capture', 1e-9), 1e-9):.1f}"),
        ("  folder size (MB)", f"{run['folder_mb']:.0f}"),
        ("SIFT inliers, rendered 640x360: median / min", f"{sift_640['median']:.0f} / {sift_640['min']:.0f}"),
        ("SIFT inliers, after mp4v: median / min", f"{sift_mp4['median']:.0f} / {sift_mp4['min']:.0f}"),
        ("SIFT inliers, rendered 1280x720: median / min", f"{np.median(large['sift_inliers']):.0f} / {min(large['sift_inliers'])}"),
    ]
    width = max(len(r[0]) for r in rows)
    print()
    for name, value in rows:
        print(f"{name:<{width}}  {value}")
    write_json(args.json, {
        "frames_per_second": {"640x360": small["frames_per_second"], "1280x720": large["frames_per_second"]},
        "sift_inliers_consecutive": {"median": sift_640["median"], "min": sift_640["min"]},
        "sift_inliers_consecutive_after_mp4": {"median": sift_mp4["median"], "min": sift_mp4["min"]},
        "renderer": {"640x360": {k: v for k, v in small.items() if k != "sift_inliers"},
                     "1280x720": {k: v for k, v in large.items() if k != "sift_inliers"}},
        "simulate_2s_walk": {"total_s": run["total_s"], **{k.replace(":", "_"): v for k, v in t.items()},
                             "capture_trial_frames_per_second": frames / max(t.get("trial:capture", 1e-9), 1e-9),
                             "folder_mb": run["folder_mb"]},
        "sift_inliers_per_pair": {"rendered_640x360": small["sift_inliers"], "after_mp4": run["sift_inliers_mp4"],
                                  "rendered_1280x720": large["sift_inliers"]},
        "load_average_at_start": load,
        "note": "2 shared CPUs: wall-clock figures depend on what else runs; CPU ms/frame is the steadier figure",
    })
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
