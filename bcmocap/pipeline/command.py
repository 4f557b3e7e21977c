"""``bcmocap run CAPTURE_DIR --out DIR``: the whole chain from a capture folder to a motion.

Stages: frontend (reference model, sync, SIFT, registration, homographies) → world (metric, Z up) →
skeleton and camera mounts from the range-of-motion trial → initial motion → solver → outputs (BVH, PLY,
COLMAP model, NPZ/CSV, pictures, metrics.json with ground truth). Run it again to resume: finished
stages are reused, the solver continues at its next window; changed settings redo the stages they
affect. Settings: a TOML or JSON file (``--config``), then the flags below; the settings used are saved
in ``DIR/config.json``.

``bcmocap batch CAPTURE... --out DIR`` runs many captures the same way, each into ``DIR/<name>/``, on one
cluster, and prints a summary table.

Heavy modules are imported inside the command, so ``bcmocap --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys

from ..compilation_cache import enable_compilation_cache
from ..io.output_folder import output_folder

#: flag → dotted setting (see :mod:`bcmocap.pipeline.config`).
FLAGS = {
    "stride": ("frontend.stride", int, "use every n-th video frame of the capture trial"),
    "rom_stride": ("frontend.rom_stride", int, "the same for the range-of-motion trial"),
    "max_features": ("frontend.max_features", int, "SIFT features per image"),
    "frames": ("frontend.frames", int, "at most this many frames per camera and trial (0: all)"),
    "registration": ("frontend.registration", str, "tracking (default: KLT + PnP, SIFT at keyframes) or global "
                                                   "(SIFT of every frame matched against the reference; slower)"),
    "max_measurements": ("frontend.max_measurements", int, "measurements per camera-frame kept for the solver "
                                                           "(default 300; 0: all)"),
    "window": ("solver.window", int, "frames per solver window"),
    "overlap": ("solver.overlap", int, "frames shared by consecutive windows"),
    "root_smoothness": ("solver.root_smoothness", float, "λ_O (px² per m² of frame-to-frame root change)"),
    "joint_smoothness": ("solver.joint_smoothness", float, "λ_A (px² per rad² of joint-angle change)"),
    "loss": ("solver.loss", str, "robust loss: none, huber or cauchy"),
    "windows": ("solver.windows", str, "sequential (default: each window from the one before) or independent "
                                       "(windows solved at once on a cluster, joined, seams solved again)"),
    "cluster": ("cluster.address", str, "local:N (N worker processes on this machine) or tcp://HOST:PORT (a running "
                                        "Dask scheduler): the frontend's cameras and chunks, and independent "
                                        "windows, run as tasks there (default: this process)"),
}


def add_run_command(sub: argparse._SubParsersAction) -> None:
    """Register ``bcmocap run`` on the CLI's subparsers."""
    cmd = sub.add_parser("run", help="capture folder → motion (BVH, PLY, pictures, metrics), resumable",
                         description=__doc__.split("\n\n", 1)[1].rsplit("\n\nHeavy", 1)[0])
    cmd.add_argument("capture", help="capture folder (the layout `bcmocap simulate` writes)")
    cmd.add_argument("--out", required=True, help="output folder (created; a run found there is resumed)")
    _add_settings(cmd, "settings file (.toml or .json), see bcmocap.pipeline.config", "stop after this stage")

    def run(args: argparse.Namespace) -> int:
        return run_command(args)

    cmd.set_defaults(run=run)


def add_batch_command(sub: argparse._SubParsersAction) -> None:
    """Register ``bcmocap batch`` on the CLI's subparsers."""
    from .batch import __doc__ as batch_doc

    cmd = sub.add_parser("batch", help="many capture folders through `bcmocap run` on one cluster, with a summary",
                         description=batch_doc.split("\n\n", 1)[1])
    cmd.add_argument("captures", nargs="+", metavar="CAPTURE", help="capture folders")
    cmd.add_argument("--out", required=True, help="output folder: one run folder per capture in it, and batch.json")
    _add_settings(cmd, "settings file (.toml or .json) for every capture, see bcmocap.pipeline.config",
                  "stop each capture's run after this stage")
    cmd.set_defaults(run=batch_command)


def _add_settings(cmd: argparse.ArgumentParser, config_help: str, stop_help: str) -> None:
    """``--config``, the setting flags, ``--no-pictures`` and ``--stop-after`` of run and batch."""
    cmd.add_argument("--config", help=config_help)
    for flag, (_, kind, text) in FLAGS.items():
        cmd.add_argument(f"--{flag.replace('_', '-')}", dest=flag, type=kind, default=None, help=text)
    cmd.add_argument("--no-pictures", action="store_true", help="skip the PNG pictures")
    cmd.add_argument("--stop-after", choices=["frontend", "world", "skeleton", "initial", "solve", "outputs"],
                     help=stop_help)


def _out_and_config(command: str, args: argparse.Namespace):
    """``(out, config)``: ``--out`` and the config file overridden by the flags; None after saying on stderr
    what is wrong with them. Turns on JAX's compilation cache."""
    from .config import load_config

    out = output_folder(command, args.out)
    if out is None:
        return None
    try:
        config = load_config(args.config)
        overrides = {key: getattr(args, flag) for flag, (key, _, _) in FLAGS.items() if getattr(args, flag) is not None}
        if args.no_pictures:
            overrides["outputs.pictures"] = False
        config = config.with_overrides(overrides)
    except ValueError as exc:
        print(f"bcmocap {command}: {exc}", file=sys.stderr)
        return None
    enable_compilation_cache()
    return out, config


def batch_command(args: argparse.Namespace) -> int:
    from .batch import run_batch, summary_table
    from .cluster import open_executor

    prepared = _out_and_config("batch", args)
    if prepared is None:
        return 2
    out, config = prepared
    with open_executor(config.cluster.address, log=lambda line: print(line, flush=True)) as executor:
        rows = run_batch(args.captures, out, config, executor, log=lambda line: print(line, flush=True),
                         stop_after=args.stop_after)
    print(summary_table(rows))
    failed = sum(not r["ok"] for r in rows)
    print(f"{len(rows) - failed} of {len(rows)} captures done; summary in {out / 'batch.json'}", flush=True)
    return 1 if failed else 0


def run_command(args: argparse.Namespace) -> int:
    from .run import run_pipeline

    prepared = _out_and_config("run", args)
    if prepared is None:
        return 2
    out, config = prepared
    try:
        run_pipeline(args.capture, out, config, log=lambda line: print(line, flush=True), stop_after=args.stop_after)
    except ValueError as exc:
        print(f"bcmocap run: {exc}", file=sys.stderr)
        return 2
    print(f"outputs in {out}", flush=True)
    return 0
