"""``bcmocap init CAPTURE_DIR --videos DIR --rig rig.toml``: a capture folder from a shoot's camera files
(:mod:`.assemble`); ``bcmocap init --template FILE`` writes a rig file to start from (:mod:`.rig_file`)."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path


def add_init_command(sub: argparse._SubParsersAction) -> None:
    """Register ``bcmocap init`` on the CLI's subparsers."""
    cmd = sub.add_parser(
        "init", help="assemble a capture folder from camera files (audio inside), a rig file and calibrations",
        description="Assemble a capture folder (the layout bcmocap frontend and run read) from a shoot: one video per "
                    "camera (MP4/MOV… with its own audio track; all trials in one file, cut by the claps or by given "
                    "times, or one file per trial), rig.toml (camera -> body segment, mount, lens; the trials and the "
                    "subject), the calibration files of each camera or lens model (what bcmocap calibrate writes) and "
                    "the reference photos. Videos and photos are linked, not copied (--copy copies them). Nothing "
                    "given is overwritten; CAPTURE_DIR must be new or empty. `bcmocap init --template rig.toml` "
                    "writes the paper-like 18-camera rig file to edit.")
    cmd.add_argument("capture_dir", nargs="?", metavar="CAPTURE_DIR", help="the capture folder to write (new or empty)")
    cmd.add_argument("--videos", metavar="DIR", help="the camera files: CAMERA.mp4 (every trial in one file), "
                     "TRIAL/CAMERA.mp4, or as rig.toml names them")
    cmd.add_argument("--rig", metavar="RIG_TOML", help="the rig file (bcmocap init --template writes one)")
    cmd.add_argument("--calibration", metavar="DIR",
                     help="calibration files CAMERA.json|.yml or LENS.json|.yml (default: the rig file's folder)")
    cmd.add_argument("--reference-photos", metavar="DIR", help="reference photos of the scene (and camera.json)")
    cmd.add_argument("--copy", action="store_true", help="copy the videos and photos instead of linking to them")
    cmd.add_argument("--trials", metavar="NAMES", help="comma-separated trial names in recording order "
                     "(overrides [trials] names)")
    cmd.add_argument("--times", metavar="TRIAL=START:END,…",
                     help="cut the trials at these seconds of each video's clock instead of by the claps")
    cmd.add_argument("--margin", type=float, metavar="SECONDS",
                     help="video kept before a trial's first clap and after its second (overrides trials.margin_s)")
    cmd.add_argument("--template", metavar="FILE", help="write a rig file template (18 cameras, 15 segments) and stop")
    cmd.set_defaults(run=run_init)


def _fail(message: str) -> int:
    print(f"bcmocap init: {' '.join(message.split())}", file=sys.stderr)
    return 2


def parse_times(text: str, trials) -> dict[str, tuple[float, float]]:
    """``"rom=5:60,capture=70:130"`` as ``{trial: (start_s, end_s)}``; ValueError naming ``--times``."""
    from ..io.names import checked_name

    out = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, sep, span = part.partition("=")
        start, colon, end = span.partition(":")
        try:
            if not sep or not colon:
                raise ValueError
            values = float(start), float(end)
        except ValueError:
            raise ValueError(f"--times: {part!r} is not TRIAL=START:END (seconds)") from None
        name = checked_name(name.strip(), "a trial name", "--times")
        if name not in trials:
            raise ValueError(f"--times: no trial {name!r} (trials: {', '.join(trials)})")
        if not 0 <= values[0] < values[1]:
            raise ValueError(f"--times: {part!r} needs 0 <= START < END")
        out[name] = values
    if not out:
        raise ValueError(f"--times: {text!r} gives no trial")
    return out


def run_init(args: argparse.Namespace) -> int:
    from ..atomic import atomic_path
    from ..io.names import checked_name
    from .rig_file import TEMPLATE, format_rig_file, read_rig_file

    if args.template:
        target = Path(args.template)
        if target.exists() or target.is_symlink():
            return _fail(f"{target} exists; bcmocap init --template overwrites nothing")
        with atomic_path(target, suffix=".toml") as tmp:
            tmp.write_text(format_rig_file(TEMPLATE))
        print(f"wrote {target}: the 18-camera rig on 15 segments; edit the cameras, lenses, trials and subject")
        return 0
    missing = [flag for flag, value in (("CAPTURE_DIR", args.capture_dir), ("--videos", args.videos),
                                        ("--rig", args.rig)) if not value]
    if missing:
        return _fail(f"{', '.join(missing)} missing: bcmocap init CAPTURE_DIR --videos DIR --rig rig.toml "
                     "(or bcmocap init --template rig.toml)")
    from .assemble import assemble_capture

    rig = read_rig_file(args.rig)
    if args.trials:
        names = tuple(checked_name(t.strip(), f"--trials[{i}]", "--trials") for i, t in enumerate(args.trials.split(",")))
        if len(set(names)) != len(names):
            return _fail(f"--trials names a trial twice: {args.trials}")
        unknown = sorted({t for c in rig.cameras for t in c.times} - set(names))
        rig = dataclasses.replace(rig, trials=names, times={t: s for t, s in rig.times.items() if t in names})
        if unknown:
            return _fail(f"{rig.path}: camera times name trials {unknown} that --trials does not list")
        if rig.rest is not None and rig.rest["trial"] not in names:
            return _fail(f"{rig.path}: subject.rest.trial {rig.rest['trial']!r} is not one of --trials {list(names)}")
    if args.times:
        rig = dataclasses.replace(rig, split="times", times=parse_times(args.times, rig.trials))
    if args.margin is not None:
        if not args.margin >= 0:
            return _fail(f"--margin must be >= 0 s, got {args.margin}")
        rig = dataclasses.replace(rig, margin_s=args.margin)
    calibration = Path(args.calibration) if args.calibration else Path(args.rig).parent
    folder = assemble_capture(args.capture_dir, args.videos, rig, calibration=calibration,
                              reference_photos=args.reference_photos, copy=args.copy)
    notes = []
    if rig.rest is None or not rig.measurements:
        notes.append("the rig file gives no subject rest time or measurements; bcmocap run needs both "
                     "(capture.json → subject)")
    if not {"rom", "capture"} <= set(rig.trials):
        notes.append("bcmocap run processes trials named 'rom' and 'capture'")
    if not args.reference_photos:
        notes.append(f"no reference photos: put them in {folder / 'reference'} before bcmocap frontend")
    for note in notes:
        print(f"note: {note}")
    return 0
