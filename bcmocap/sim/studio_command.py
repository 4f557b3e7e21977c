"""``bcmocap simulate CAPTURE_DIR``: render a synthetic capture folder and its ground truth."""

from __future__ import annotations

import argparse
import sys
import time

from ..compilation_cache import enable_compilation_cache


def add_simulate_command(sub: argparse._SubParsersAction) -> None:
    """Add the ``simulate`` subcommand (heavy imports happen when it runs)."""
    cmd = sub.add_parser(
        "simulate",
        help="render a synthetic capture folder (fisheye videos with audio, reference photos, intrinsics, rig) and its ground truth",
        description="Render the standard 18-camera capture of a CMU motion in a textured room: one MP4 and one WAV "
        "(clapper-board claps, random start per camera; --container mp4-aac: one MP4 with the audio inside) per "
        "body camera for a range-of-motion trial and the capture trial, hand-held reference photos, calibration "
        "files, the rig, and ground truth beside it (layout: bcmocap.sim.studio). The same arguments write the "
        "same files; running again resumes.",
    )
    cmd.add_argument("capture_dir", metavar="CAPTURE_DIR", help="new or empty folder, or an unfinished capture to resume")
    cmd.add_argument("--motion", default="walk", choices=["walk", "run", "jump"], help="bundled CMU trial (default walk)")
    cmd.add_argument("--seconds", type=float, default=2.0, help="length of the capture trial (s, default 2, at most 600)")
    cmd.add_argument("--rom-seconds", type=float, default=2.0,
                     help="length of the range-of-motion trial (s, default 2, at most 600)")
    cmd.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    cmd.add_argument("--fps", type=float, default=60.0, help="frame rate (default 60, at most 240)")
    cmd.add_argument("--width", type=int, default=640, help="body-camera image width (px, default 640)")
    cmd.add_argument("--height", type=int, default=360, help="body-camera image height (px, default 360)")
    cmd.add_argument("--lens", default="fov", choices=["fov", "opencv_fisheye"],
                     help="lens model rendered: the paper's FOV model or its cv2.fisheye fit (default fov)")
    cmd.add_argument("--reference-photos", type=int, default=24, help="number of reference photos (default 24)")
    cmd.add_argument("--reference-size", default="1024x768", metavar="WxH", help="reference photo size (default 1024x768)")
    cmd.add_argument("--motion-blur", action="store_true", help="render motion blur (4 sub-exposures, half-frame shutter)")
    cmd.add_argument("--rolling-shutter", action="store_true", help="expose rows one after another (0.8 frame readout)")
    cmd.add_argument("--container", default="mp4v-wav", choices=["mp4v-wav", "mp4-aac"],
                     help="mp4v-wav (default): an mp4v video and a WAV soundtrack beside it; mp4-aac: H.264 video with "
                          "the soundtrack as an AAC track in the same MP4, as a real camera writes it (through PyAV)")
    cmd.add_argument("--no-progress", action="store_true", help="no progress bar")
    cmd.add_argument("--sensors-only", action="store_true",
                     help="only add trials/<trial>/imu.npz and contacts.npz to the existing capture CAPTURE_DIR from its "
                     "ground truth (nothing rendered; the other options are ignored)")

    def run(args: argparse.Namespace) -> int:
        from .studio import MAX_FPS, MAX_SECONDS, StudioSettings, write_capture

        if args.sensors_only:
            from .sensors import write_sensor_data

            start = time.perf_counter()
            try:
                written = write_sensor_data(args.capture_dir)
            except ValueError as err:
                print(f"bcmocap simulate: {err}", file=sys.stderr)
                return 2
            for trial, paths in written.items():
                print(f"{trial}: " + ", ".join(str(p) for p in paths))
            print(f"wrote the sensor files of {len(written)} trials in {time.perf_counter() - start:.1f} s")
            return 0

        try:
            ref_w, ref_h = (int(x) for x in args.reference_size.lower().split("x"))
        except ValueError:
            cmd.error(f"--reference-size must look like 1024x768, got {args.reference_size!r}")
        for flag, value, most in (("--seconds", args.seconds, MAX_SECONDS),
                                  ("--rom-seconds", args.rom_seconds, MAX_SECONDS), ("--fps", args.fps, MAX_FPS)):
            if not 0 < value <= most:  # also refuses NaN
                print(f"bcmocap simulate: {flag} must be in (0, {most:g}], got {value}", file=sys.stderr)
                return 2
        try:
            settings = StudioSettings(
                motion=args.motion, seconds=args.seconds, rom_seconds=args.rom_seconds, seed=args.seed, fps=args.fps,
                width=args.width, height=args.height, lens=args.lens, reference_photos=args.reference_photos,
                reference_width=ref_w, reference_height=ref_h,
                motion_blur=args.motion_blur, rolling_shutter=args.rolling_shutter, container=args.container,
            )
        except ValueError as err:
            cmd.error(str(err))
        enable_compilation_cache()
        start = time.perf_counter()
        try:
            folder = write_capture(args.capture_dir, settings, progress=not args.no_progress)
        except FileExistsError as err:
            print(f"bcmocap simulate: {err}", file=sys.stderr)
            return 2
        print(f"wrote {folder} in {time.perf_counter() - start:.1f} s "
              f"(ground truth: bcmocap.sim.studio.load_ground_truth('{folder}'))")
        return 0

    cmd.set_defaults(run=run)
