"""Rendering speed with the studio's time and sensor effects: plain, motion blur, rolling shutter, the preset.

Seconds per 640x360 frame of the ray-cast renderer (bcmocap.sim.render) on the standard capture (CMU walk,
FOV cameras of the standard rig, textured room, body capsules), frames rendered 4 at a time as the studio
does, compilation timed apart:

- ``plain``: ``RenderOptions()`` (the path ``bcmocap simulate`` takes without degradations);
- ``blur``: motion blur, 4 sub-exposures over the preset's exposure (8 ms at 60 fps);
- ``rolling``: rolling shutter, the preset's readout (15 ms at 60 fps), one pose per row;
- ``preset``: the render options of ``preset_settings("realistic")`` (blur + rolling shutter + vignetting +
  shot noise) with per-frame gains (exposure and white balance).

``--before FILE`` also times a saved copy of ``render.py`` (loaded as a module of ``bcmocap.sim``) in the same
run, alternating old and new camera by camera, and compares their images (max level difference, share of
identical bytes): the A/B of a change to the renderer.

    python benchmarks/render_blur_speed.py --json benchmarks/results/render_blur_speed.json [--before /tmp/render_before.py]

Wall-clock figures depend on the machine's load (printed): run on a quiet machine for the real speed.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_json  # noqa: E402

from bcmocap.cameras import camera_at  # noqa: E402
from bcmocap.kinematics import camera_poses  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.sim import load_body_motion, standard_rig  # noqa: E402
from bcmocap.sim import render as render_now  # noqa: E402
from bcmocap.sim.scene import make_textured_scene  # noqa: E402
from bcmocap.sim.studio import capsule_ends, preset_settings  # noqa: E402

BATCH = 4  # frames per render call, as the studio's


def load_render_module(path: str):
    """A saved copy of render.py as the module ``bcmocap.sim._render_before`` (its relative imports resolve)."""
    spec = importlib.util.spec_from_file_location("bcmocap.sim._render_before", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def mode_options(module, width: int, height: int) -> dict:
    preset = preset_settings("realistic", width=width, height=height).render_options()
    opts = module.RenderOptions
    return {
        "plain": (opts(), False),
        "blur": (opts(motion_blur=True, blur_samples=preset.blur_samples, exposure_frames=preset.exposure_frames), False),
        "rolling": (opts(rolling_shutter=True, readout_frames=preset.readout_frames), False),
        "preset": (opts(motion_blur=preset.motion_blur, blur_samples=preset.blur_samples,
                        exposure_frames=preset.exposure_frames, rolling_shutter=preset.rolling_shutter,
                        readout_frames=preset.readout_frames, noise_dn=preset.noise_dn,
                        full_scale_electrons=preset.full_scale_electrons, vignetting=preset.vignetting), True),
    }


def render_camera(module, options, with_gains: bool, scene, camera, poses, capsules, frames) -> tuple[list, float, float]:
    """Images of ``frames`` of one camera, wall and CPU seconds (the renderer built outside the timing)."""
    ends, radii, colors = capsules
    renderer = module.Renderer(scene, camera, options)
    images = []
    w0, c0 = time.perf_counter(), time.process_time()
    for first in range(0, len(frames), BATCH):
        batch = frames[first: first + BATCH]
        rot, org = renderer.poses_at(poses, batch)
        gains = None
        if with_gains:  # exposure and white balance drifting over the batch
            gains = np.stack([1.0 + 0.02 * np.sin(batch), 1.0 + 0.01 * np.cos(batch), 0.97 + 0.0 * batch], 1)
        images.extend(renderer.render(rot, org, renderer.capsules_at(ends, batch), radii, colors, keys=batch,
                                      gains=gains))
    return images, time.perf_counter() - w0, time.process_time() - c0


def main() -> int:
    enable_float64()
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--before", help="a saved copy of render.py to time and compare against")
    parser.add_argument("--modes", default="plain,blur,rolling,preset", help="comma-separated modes")
    parser.add_argument("--cameras", default="0,4,9,14", help="camera indices of the standard rig")
    parser.add_argument("--frames", type=int, default=8, help="frames per camera (a multiple of 4)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--label", default="after", help="name of the current renderer's rows in the JSON")
    args = parser.parse_args()

    versions = {args.label: render_now}
    if args.before:
        versions = {"before": load_render_module(args.before), args.label: render_now}
    skeleton, motion = load_body_motion("walk", seconds=2.0)
    rig = standard_rig(skeleton, args.width, args.height)
    scene = make_textured_scene(np.asarray(motion.root_position)[:, :2], seed=0)
    poses = np.asarray(camera_poses(skeleton, rig, motion).wxyz_xyz)
    capsules = capsule_ends(skeleton, motion)
    cameras = [int(c) for c in args.cameras.split(",")]
    frames = np.arange(args.frames) + 40
    load_start = os.getloadavg()
    print(f"load average at start: {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f} on {os.cpu_count()} CPUs",
          flush=True)

    results: dict = {name: {} for name in versions}
    comparison: dict = {}
    for mode in args.modes.split(","):
        totals = {name: {"wall": 0.0, "cpu": 0.0, "frames": 0, "compile_s": 0.0} for name in versions}
        diffs = []
        for i, c in enumerate(cameras):
            camera = camera_at(rig.intrinsics, c)
            images = {}
            order = list(versions) if i % 2 == 0 else list(versions)[::-1]  # alternate who goes first
            for name in order:
                module = versions[name]
                options, gains = mode_options(module, args.width, args.height)[mode]
                if i == 0:  # compile (one compilation serves every camera of this size)
                    start = time.perf_counter()
                    render_camera(module, options, gains, scene, camera, poses[:, c], capsules, frames[:BATCH])
                    totals[name]["compile_s"] = time.perf_counter() - start
                imgs, wall, cpu = render_camera(module, options, gains, scene, camera, poses[:, c], capsules, frames)
                images[name] = np.stack(imgs)
                totals[name]["wall"] += wall
                totals[name]["cpu"] += cpu
                totals[name]["frames"] += len(frames)
            if len(images) == 2:
                a, b = (images[n].astype(np.int16) for n in versions)
                diffs.append((int(np.abs(a - b).max()), int((a != b).sum()), a.size))
        for name, t in totals.items():
            results[name][mode] = {
                "wall_s_per_frame": t["wall"] / t["frames"],
                "cpu_s_per_frame": t["cpu"] / t["frames"],
                "compile_s": t["compile_s"],
                "frames": t["frames"],
            }
        line = "  ".join(f"{name} {results[name][mode]['wall_s_per_frame']:.3f} s/frame "
                         f"(CPU {results[name][mode]['cpu_s_per_frame']:.3f})" for name in versions)
        if diffs:
            comparison[mode] = {"max_level_difference": max(d[0] for d in diffs),
                                "differing_bytes": sum(d[1] for d in diffs), "bytes": sum(d[2] for d in diffs)}
            cmp = comparison[mode]
            line += (f"  | max diff {cmp['max_level_difference']} level(s), "
                     f"{cmp['differing_bytes'] / cmp['bytes']:.2e} of bytes differ")
        print(f"{mode:>8}: {line}  [load {os.getloadavg()[0]:.2f}]", flush=True)

    load_end = os.getloadavg()
    print(f"load average at end: {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f}")
    write_json(args.json, {
        "size": f"{args.width}x{args.height}",
        "cameras": cameras,
        "frames_per_camera": args.frames,
        "batch": BATCH,
        "seconds_per_frame": results,
        "comparison_with_before": comparison,
        "load_average_start": list(load_start),
        "load_average_end": list(load_end),
        "note": "2 shared CPUs: wall-clock figures depend on what else runs; 'before' and the current renderer "
                "alternate camera by camera in the same run",
    })
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
