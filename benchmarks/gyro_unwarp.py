"""How much of a rolling shutter the gyro correction of the frames removes (issue 20; bcmocap.frontend.rolling_shutter).

On a studio capture rendered with a rolling shutter, for every ``--every``-th frame of a trial and every camera, the
scene points in view are projected twice with the true camera poses: as a global shutter at the frame time, and as
the rolling shutter the studio renders (each point in the row whose time's pose sees it there, the poses between
frames interpolated; translation included). The correction's map (:meth:`GyroUnwarp.source_pixels`, from the
capture's gyro with its noise and bias) sends each global-shutter pixel to where the rolling-shutter frame shows it;
the script reports how far the rolling shutter moved the points (px) and how far the map is from where they are,
overall and for camera-frames turning faster than 120°/s. It also times the correction of the trial's first
``--timed-frames`` video frames of every camera (decoded beforehand; after one frame to warm up), as the frontend
reads them: each frame once, then again (the frontend reads most frames more than once).

    python benchmarks/gyro_unwarp.py --capture CAPTURE [--trial rom] [--every 7] [--timed-frames 40] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json  # noqa: E402

from bcmocap.frontend.capture import read_capture  # noqa: E402
from bcmocap.frontend.rolling_shutter import gyro_unwarp  # noqa: E402
from bcmocap.geometry import matrix_from_quat, slerp  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.io.capture_folder import load_ground_truth  # noqa: E402

FAST_DEG_S = 120.0


def _pose_at(world_from_camera: np.ndarray, frame: float, camera: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and centre of a camera at a fractional trial frame (slerp and linear between frames)."""
    f0 = int(np.floor(frame))
    a = frame - f0
    q = slerp(world_from_camera[f0, camera, :4], world_from_camera[f0 + 1, camera, :4], np.array(a))
    return matrix_from_quat(q), (1 - a) * world_from_camera[f0, camera, 4:] + a * world_from_camera[f0 + 1, camera, 4:]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--capture", type=Path, required=True, help="a studio capture rendered with a rolling shutter")
    parser.add_argument("--trial", default="rom")
    parser.add_argument("--every", type=int, default=7, help="every n-th frame of the trial (default 7)")
    parser.add_argument("--points", type=int, default=200, help="scene points per camera-frame at most (default 200)")
    parser.add_argument("--timed-frames", type=int, default=40, help="video frames per camera timed (default 40)")
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args(argv)
    enable_float64()
    capture = read_capture(args.capture)
    settings = json.loads((args.capture / "capture.json").read_text())["settings"]
    if not settings.get("rolling_shutter"):
        parser.error(f"{args.capture}: rendered without a rolling shutter")
    readout = settings["readout_ms"] / 1000.0
    truth = load_ground_truth(args.capture).trials[args.trial]
    world_from_camera = np.asarray(truth.world_from_camera)
    with np.load(args.capture / "ground_truth" / "world_points.npz") as data:
        scene = np.asarray(data[data.files[0]], np.float64).reshape(-1, 3)
    clap = int(truth.clap_frames[0])
    cameras = world_from_camera.shape[1]
    unwarp = gyro_unwarp(capture, args.trial, [clap] * cameras, readout)  # trial frame f is video frame f here
    rows = []
    # The accuracy figures read trial frame f as every camera's video frame f: cameras that start together (the
    # studio's default). With the realistic preset's own starts and clocks only the timing below is measured.
    together = not (settings.get("start_subframe") or settings.get("clock_ppm"))
    for f in range(clap + 1, world_from_camera.shape[0] - 2, args.every) if together else ():
        for c in range(cameras):
            lens = capture.cameras[c].intrinsics
            rot, centre = _pose_at(world_from_camera, f, c)
            pixels, ok = lens.project((scene - centre) @ rot)
            pixels, ok = np.asarray(pixels), np.asarray(ok) & np.asarray(lens.in_image(pixels))
            chosen = np.flatnonzero(ok)[: args.points]
            if len(chosen) < 20:
                continue
            global_shutter = pixels[chosen]
            rolling = global_shutter.copy()
            for _ in range(5):  # the row each point is seen in, and the pose at that row's time
                rows_time = (rolling[:, 1] / (lens.height - 1) - 0.5) * readout * capture.fps
                local = []
                for k, i in enumerate(chosen):
                    r, t = _pose_at(world_from_camera, f + rows_time[k], c)
                    local.append((scene[i] - t) @ r)
                rolling = np.asarray(lens.project(np.array(local))[0])
            source = unwarp.source_pixels(c, f)
            near = np.round(global_shutter).astype(int)
            near[:, 0] = np.clip(near[:, 0], 0, lens.width - 1)
            near[:, 1] = np.clip(near[:, 1], 0, lens.height - 1)
            mapped = source[near[:, 1], near[:, 0]] + (global_shutter - near)  # the map is smooth: a pixel's shift
            speed = np.degrees(np.linalg.norm(unwarp.angular_velocity(c, f)))
            rows.append((np.linalg.norm(rolling - global_shutter, axis=1).mean(),
                         np.linalg.norm(rolling - mapped, axis=1).mean(), speed))
    result = _accuracy(args, settings, np.array(rows).reshape(-1, 3)) if together else {
        "capture": str(args.capture), "trial": args.trial, "readout_ms": settings["readout_ms"],
        "accuracy": "not measured: the cameras start at their own times (start_subframe, clock_ppm)"}
    result["correction_ms_per_camera_frame"] = _correction_ms(capture, args.trial, max(clap, 0), cameras, readout,
                                                              args.timed_frames)
    result["machine"] = machine()
    print(f"correction of a video frame: {result['correction_ms_per_camera_frame']['first']:.2f} ms the first time, "
          f"{result['correction_ms_per_camera_frame']['again']:.2f} ms again")
    write_json(args.json, result)
    return 0


def _accuracy(args, settings: dict, rows: np.ndarray) -> dict:
    """The figures of the module docstring from ``rows`` ``(N, 3)``: shift, miss (px) and speed (deg/s) per
    camera-frame (printed too)."""
    fast = rows[:, 2] > FAST_DEG_S
    result = {
        "capture": str(args.capture), "trial": args.trial, "readout_ms": settings["readout_ms"],
        "camera_frames": int(len(rows)), "fast_camera_frames": int(fast.sum()),
        "rolling_shutter_shift_px": {"all": float(rows[:, 0].mean()), "fast": float(rows[fast, 0].mean())},
        "after_correction_px": {"all": float(rows[:, 1].mean()), "fast": float(rows[fast, 1].mean())},
        "worst_camera_frame_px": {"shift": float(rows[:, 0].max()), "after": float(rows[np.argmax(rows[:, 0]), 1])},
    }
    print(f"{args.trial}: {len(rows)} camera-frames: the rolling shutter moves the scene points by "
          f"{result['rolling_shutter_shift_px']['all']:.3f} px on average, the gyro map misses them by "
          f"{result['after_correction_px']['all']:.3f} px; above {FAST_DEG_S:g} deg/s ({int(fast.sum())} camera-frames): "
          f"{result['rolling_shutter_shift_px']['fast']:.3f} -> {result['after_correction_px']['fast']:.3f} px; worst "
          f"camera-frame {result['worst_camera_frame_px']['shift']:.2f} -> {result['worst_camera_frame_px']['after']:.2f} px")
    return result


def _correction_ms(capture, trial: str, clap: int, cameras: int, readout: float, count: int) -> dict:
    """Mean ms of :class:`GyroUnwarp` on ``count`` decoded video frames of each camera from the first clap: the first
    correction of each frame, and a second one."""
    unwarp = gyro_unwarp(capture, trial, [clap] * cameras, readout)
    names = [c.name for c in capture.cameras]
    frames = [list(capture.frames(trial, names[c], start=clap, stop=clap + count + 1, gray=True)) for c in range(cameras)]
    unwarp(0, int(frames[0][0][0]), frames[0][0][1])  # warm-up (compilation, first calls)
    timed = {}
    for label in ("first", "again"):
        clock, calls = time.perf_counter(), 0
        for c in range(cameras):
            for index, image in frames[c][1:]:
                unwarp(c, int(index), image)
                calls += 1
        timed[label] = 1e3 * (time.perf_counter() - clock) / max(calls, 1)
    return timed


if __name__ == "__main__":
    raise SystemExit(main())
