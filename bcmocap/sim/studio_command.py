"""``bcmocap simulate CAPTURE_DIR``: render a synthetic capture folder and its ground truth."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..compilation_cache import enable_compilation_cache

PRESETS = ("realistic",)  # bcmocap.sim.studio.PRESETS (not imported here: the CLI starts without JAX)
ROOMS = ("textured", "sparse", "repeated", "passerby")  # bcmocap.sim.studio.ROOMS
ROM_PROTOCOLS = ("together", "feet_after")  # bcmocap.sim.studio.ROM_PROTOCOLS


def add_simulate_command(sub: argparse._SubParsersAction) -> None:
    """Add the ``simulate`` subcommand (heavy imports happen when it runs)."""
    cmd = sub.add_parser(
        "simulate",
        help="render a synthetic capture folder (fisheye videos with audio, reference photos, intrinsics, rig) and its ground truth",
        description="Render the standard 18-camera capture of a CMU motion in a textured room: one MP4 and one WAV "
        "(clapper-board claps, random start per camera; --container mp4-aac: one MP4 with the audio inside) per "
        "body camera for a range-of-motion trial and the capture trial, hand-held reference photos, calibration "
        "files, the rig, and ground truth beside it (layout: bcmocap.sim.studio). The same arguments write the "
        "same files; running again resumes. Clean by default; --preset realistic adds what a real shoot has (mount "
        "wobble, rolling shutter, motion blur, auto exposure and white balance, vignetting, shot noise, H.264 at an "
        "action camera's bit rate, calibration error, a lens unit per camera; sources in "
        "bcmocap.sim.studio.REALISTIC), and each "
        "degradation has its own option (which overrides the preset's value).",
    )
    _add_capture_arguments(cmd)
    _add_degradation_arguments(cmd.add_argument_group("degradations (off unless given or set by --preset)"))
    _add_mode_arguments(cmd)

    def run(args: argparse.Namespace) -> int:
        # "--motion run DIR": --motion takes one or two values, so it swallowed the folder; give it back.
        if args.capture_dir is None and len(args.motion) > 1 and not args.motion[-1].lower().endswith(".amc"):
            args.capture_dir = args.motion.pop()
        if args.capture_dir is None:
            print("bcmocap simulate: CAPTURE_DIR is required (the folder to write)", file=sys.stderr)
            return 2
        if args.board_videos:
            return _add_board_videos(args)
        if args.gopro_files:
            return _add_gopro_files(args)
        if args.sensors_only:
            return _add_sensor_files(args)
        return _simulate_capture(cmd, args)

    cmd.set_defaults(run=run)


def _add_capture_arguments(cmd: argparse.ArgumentParser) -> None:
    """The capture folder, the motion, the trials' lengths and the rendering (cameras, reference photos, preset)."""
    cmd.add_argument("capture_dir", metavar="CAPTURE_DIR", nargs="?",
                     help="new or empty folder, or an unfinished capture to resume")
    cmd.add_argument("--motion", nargs="+", default=["walk"], metavar="MOTION",
                     help="the capture's motion: a bundled CMU trial (walk, run, jump, scoop, hop; default walk; "
                          "bcmocap.sim.motions.CMU_TRIALS), a BVH file, or an "
                          "ASF file and an AMC file (bones found by their usual names: bcmocap.sim.motions.BONE_ALIASES)")
    cmd.add_argument("--motion-fps", type=float, default=0.0,
                     help="frame rate of a motion file (Hz; default: a BVH file's Frame Time, 120 for AMC)")
    cmd.add_argument("--motion-unit-m", type=float, default=0.0,
                     help="metres per length unit of a motion file (default: guessed for BVH, the ASF's :units)")
    cmd.add_argument("--seconds", type=float, default=2.0, help="length of the capture trial (s, default 2, at most 600)")
    cmd.add_argument("--rom-seconds", type=float, default=2.0,
                     help="length of the range-of-motion trial (s, default 2, at most 600)")
    cmd.add_argument("--rom-tempo", type=float, default=1.0,
                     help="speed of the range-of-motion trial's sweeps (default 1: 0.6-1.4 Hz; 0.5: half as fast)")
    cmd.add_argument("--rom-protocol", default="together", choices=list(ROM_PROTOCOLS),
                     help="what the subject does in the range-of-motion trial: together (default: every joint at "
                          "once) or feet_after (the ankles turned on still legs after the rest has swung, so the foot "
                          "cameras register while the ankles move)")
    cmd.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    cmd.add_argument("--fps", type=float, default=60.0, help="frame rate (default 60, at most 240)")
    cmd.add_argument("--width", type=int, default=640, help="body-camera image width (px, default 640)")
    cmd.add_argument("--height", type=int, default=360, help="body-camera image height (px, default 360)")
    cmd.add_argument("--lens", default="fov", choices=["fov", "opencv_fisheye"],
                     help="lens model rendered: the paper's FOV model or its cv2.fisheye fit (default fov)")
    cmd.add_argument("--room", default="textured", choices=list(ROOMS),
                     help="textured (default: rich, non-repeating texture everywhere); sparse (weak texture, a blank "
                          "wall, less clutter); repeated (floor tiles of 8 faces; identical ceiling panels, bricks and "
                          "windows); passerby (the textured room and a second person walking across it in the "
                          "videos, not in the reference photos; truth in ground_truth/passerby/)")
    cmd.add_argument("--reference-photos", type=int, default=24, help="number of reference photos (default 24)")
    cmd.add_argument("--reference-size", default="1024x768", metavar="WxH", help="reference photo size (default 1024x768)")
    cmd.add_argument("--preset", choices=list(PRESETS),
                     help="realistic: every degradation below on, at values from camera data sheets and the literature "
                          "(bcmocap.sim.studio.REALISTIC)")


def _add_degradation_arguments(deg) -> None:
    """The degradations' options (group ``deg``), each overriding the preset's value."""
    deg.add_argument("--motion-blur", action=argparse.BooleanOptionalAction, default=None,
                     help="render motion blur over the exposure (default: no blur)")
    deg.add_argument("--exposure-ms", type=float, help="shutter time for motion blur (ms; default half a frame period)")
    deg.add_argument("--blur-samples", type=int, help="sub-exposures averaged for motion blur (default 4)")
    deg.add_argument("--rolling-shutter", action=argparse.BooleanOptionalAction, default=None,
                     help="expose rows one after another (default: all at once)")
    deg.add_argument("--readout-ms", type=float, help="rolling-shutter readout, first row to last (ms; default 0.8 frames)")
    deg.add_argument("--mount-wobble-mm", type=float,
                     help="RMS translation of each camera on its strap (mm, times 0.5-1.5 per camera; default 0)")
    deg.add_argument("--mount-wobble-deg", type=float, help="RMS rotation of each camera on its strap (deg; default 0)")
    deg.add_argument("--auto-exposure", action=argparse.BooleanOptionalAction, default=None,
                     help="exposure follows the view (default: fixed)")
    deg.add_argument("--white-balance", action=argparse.BooleanOptionalAction, default=None,
                     help="grey-world auto white balance (default: fixed)")
    deg.add_argument("--vignetting", type=float, help="share of light lost at the image's most oblique ray (default 0)")
    deg.add_argument("--read-noise-dn", type=float, help="read noise σ in 8-bit levels (default 1)")
    deg.add_argument("--full-scale-electrons", type=float,
                     help="electrons per rendered pixel at level 255: photon shot noise (default 0: none)")
    deg.add_argument("--container", choices=["mp4v-wav", "mp4-aac"],
                     help="mp4v-wav (default): an mp4v video and a WAV soundtrack beside it; mp4-aac: H.264 video with "
                          "the soundtrack as an AAC track in the same MP4, as a real camera writes it (through PyAV)")
    deg.add_argument("--video-bitrate-mbps", type=float,
                     help="H.264 bit rate (Mbit/s; needs --container mp4-aac; default: constant quality, CRF 16)")
    deg.add_argument("--focal-error-pct", type=float,
                     help="calibration given to the user: focal lengths off by 0.3-1 times this (%%; default 0)")
    deg.add_argument("--centre-error-px", type=float,
                     help="calibration given to the user: centres off by 0.3-1 times this (px; default 0)")
    deg.add_argument("--start-subframe", action=argparse.BooleanOptionalAction, default=None,
                     help="each camera starts at a random sub-frame time (default: on whole frames)")
    deg.add_argument("--clock-ppm", type=float,
                     help="each camera's clock runs fast or slow by up to this much (ppm; default 0: perfect clocks)")
    deg.add_argument("--audio-latency-ms", type=float,
                     help="each camera's audio lags its video by 0 to this much (ms; default 0)")
    deg.add_argument("--imu-offset-ms", type=float,
                     help="the IMU's timestamps are off from the video clock by up to +- this much per trial (ms; default 0)")
    deg.add_argument("--lens-units", action=argparse.BooleanOptionalAction, default=None,
                     help="each camera renders through its own manufactured unit of one lens design (focal length, "
                          "centre, radial, decentering and thin-prism terms off the design, on a tilted sensor: "
                          "bcmocap.sim.lens_units), "
                          "kept in the ground truth; intrinsics/ holds the design's nominal lens (default: every "
                          "camera the one --lens)")


def _add_mode_arguments(cmd: argparse.ArgumentParser) -> None:
    """No progress bar, and the modes that only add files to an existing capture."""
    cmd.add_argument("--no-progress", action="store_true", help="no progress bar")
    cmd.add_argument("--board-videos", action="store_true",
                     help="only add calibration videos to the existing capture CAPTURE_DIR: calibration/lens_K.mp4, a "
                     "ChArUco board moved in front of each distinct rendered lens, and calibration/lenses.json (the "
                     "board and which cameras have each lens), for bcmocap calibrate; the other options are ignored")
    cmd.add_argument("--gopro-files", metavar="DIR",
                     help="only write the existing capture CAPTURE_DIR's camera files as GoPro cameras write them into "
                     "the new folder DIR: DIR/<trial>/<camera>.mp4, each trial's video and audio with the camera's IMU "
                     "in a GPMF track on the camera's own clock, for bcmocap init (the capture must have been written "
                     "with --container mp4-aac; the other options are ignored)")
    cmd.add_argument("--sensors-only", action="store_true",
                     help="only add trials/<trial>/imu.npz and contacts.npz to the existing capture CAPTURE_DIR from its "
                     "ground truth (nothing rendered; the other options are ignored)")


def _file_mode(work, report) -> int:
    """An add-files mode: ``work()`` (a ValueError is one line on stderr, exit code 2), then ``report(its result,
    seconds)``; the exit code."""
    start = time.perf_counter()
    try:
        result = work()
    except ValueError as err:
        print(f"bcmocap simulate: {err}", file=sys.stderr)
        return 2
    report(result, time.perf_counter() - start)
    return 0


def _add_board_videos(args: argparse.Namespace) -> int:
    """``--board-videos``: add the calibration board videos to the capture ``args.capture_dir``; the exit code."""
    from .board_video import write_board_videos

    def report(lenses, seconds):
        for name, cameras in lenses.items():
            print(f"{Path(args.capture_dir) / 'calibration' / name}.mp4: {', '.join(cameras)}")
        print(f"wrote {len(lenses)} calibration videos in {seconds:.1f} s")

    return _file_mode(lambda: write_board_videos(args.capture_dir, progress=lambda name: print(
        f"rendering {name} ...", flush=True)), report)


def _add_gopro_files(args: argparse.Namespace) -> int:
    """``--gopro-files DIR``: the capture's camera files as GoPro files (:mod:`.gopro_files`); the exit code."""
    from .gopro_files import write_gopro_files

    out = Path(args.gopro_files)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        print(f"bcmocap simulate: {out} exists and is not an empty folder; --gopro-files writes into a new one",
              file=sys.stderr)
        return 2

    def report(written, seconds):
        for trial, files in written.items():
            print(f"{trial}: {len(files)} GoPro files in {out / trial}")
        print(f"wrote the GoPro files of {len(written)} trials in {seconds:.1f} s")

    return _file_mode(lambda: write_gopro_files(args.capture_dir, out), report)


def _add_sensor_files(args: argparse.Namespace) -> int:
    """``--sensors-only``: add the IMU and contact files to the capture ``args.capture_dir``; the exit code."""
    from .sensors import write_sensor_data

    def report(written, seconds):
        for trial, paths in written.items():
            print(f"{trial}: " + ", ".join(str(p) for p in paths))
        print(f"wrote the sensor files of {len(written)} trials in {seconds:.1f} s")

    return _file_mode(lambda: write_sensor_data(args.capture_dir), report)


def _simulate_capture(cmd: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """Render (or resume) the capture ``args.capture_dir`` with the settings the options give; the exit code."""
    from .studio import MAX_FPS, MAX_SECONDS, StudioSettings, preset_settings, write_capture

    try:
        ref_w, ref_h = (int(x) for x in args.reference_size.lower().split("x"))
    except ValueError:
        cmd.error(f"--reference-size must look like 1024x768, got {args.reference_size!r}")
    for flag, value, most in (("--seconds", args.seconds, MAX_SECONDS),
                              ("--rom-seconds", args.rom_seconds, MAX_SECONDS), ("--fps", args.fps, MAX_FPS)):
        if not 0 < value <= most:  # also refuses NaN
            print(f"bcmocap simulate: {flag} must be in (0, {most:g}], got {value}", file=sys.stderr)
            return 2
    motion = _motion_argument(args.motion)
    if isinstance(motion, ValueError):
        print(f"bcmocap simulate: {motion}", file=sys.stderr)
        return 2
    fields = dict(
        motion=motion, motion_fps=args.motion_fps, motion_unit_m=args.motion_unit_m, seconds=args.seconds,
        rom_seconds=args.rom_seconds, rom_tempo=args.rom_tempo, rom_protocol=args.rom_protocol, seed=args.seed, fps=args.fps, width=args.width, height=args.height,
        lens=args.lens, room=args.room, reference_photos=args.reference_photos, reference_width=ref_w, reference_height=ref_h,
    )
    fields.update({name: getattr(args, name) for name in DEGRADATIONS if getattr(args, name) is not None})
    try:
        settings = preset_settings(args.preset, **fields) if args.preset else StudioSettings(**fields)
    except ValueError as err:
        print(f"bcmocap simulate: {_flag_names(str(err))}", file=sys.stderr)
        return 2
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


#: Settings with an option of the same name that --preset may set.
DEGRADATIONS = ("motion_blur", "exposure_ms", "blur_samples", "rolling_shutter", "readout_ms", "mount_wobble_mm",
                "mount_wobble_deg", "auto_exposure", "white_balance", "vignetting", "read_noise_dn",
                "full_scale_electrons", "container", "video_bitrate_mbps", "focal_error_pct", "centre_error_px",
                "start_subframe", "clock_ppm", "audio_latency_ms", "imu_offset_ms", "lens_units")


def _motion_argument(values: list[str]) -> str | tuple[str, str] | ValueError:
    """``--motion``'s value for the settings: a bundled name, a BVH path or an (ASF, AMC) pair (absolute paths, so
    that the capture resumes from anywhere), or the error to print."""
    from pathlib import Path

    from .motions import CMU_TRIALS

    if len(values) == 1 and values[0] in CMU_TRIALS:
        return values[0]
    if len(values) == 1 and values[0].lower().endswith(".bvh"):
        return str(Path(values[0]).resolve())
    if len(values) == 2 and values[0].lower().endswith(".asf") and values[1].lower().endswith(".amc"):
        return tuple(str(Path(v).resolve()) for v in values)
    return ValueError(f"--motion must be one of {sorted(CMU_TRIALS)}, a .bvh file, or an .asf file and an .amc file; "
                      f"got {' '.join(values)!r}")


def _flag_names(message: str) -> str:
    """A settings error with each ``StudioSettings.<field>`` written as its option ``--<field>``."""
    import re

    return re.sub(r"StudioSettings\.(\w+)", lambda m: "--" + m.group(1).replace("_", "-"), message)
