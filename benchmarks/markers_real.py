"""Skeletons from real optical-marker files, judged by the human template (Kirk et al. §3–4; issue 46).

The files: the full-body trials of ``../shared/data/c3d`` and the public files of ``benchmarks/c3d_files.py``
(fetched into ``--fetched``, checked against their SHA-256; their terms in ``benchmarks/data/c3d_licences``). Each
is read as ``bcmocap markers FILE`` reads it (modelled points left out), fitted with the pipeline's defaults (the
eigengap chooses the number of segments), saved into ``--out/NAME`` and reported: the verdict of the human template
and each limb's segments with their labels, the tree, the seconds per 1000 frames (wall, and CPU: other jobs may
share the machine), the marker-frames filled and the marker RMS. ``human_share`` is the share of human verdicts.

Each verdict is checked by eye once, on the picture ``bcmocap view`` shows of the saved folder (``--pictures DIR``
writes one per file, with headless Chromium): what was seen is kept in ``benchmarks/markers_real_eye.json``
(``{NAME: {"human": bool, "seen": text}}``), and a file's ``confirmed_by_eye`` is whether that look agrees with
the verdict (None where the file was never looked at).

    python benchmarks/c3d_files.py --out ~/.cache/bcmocap/c3d
    python benchmarks/markers_real.py --json benchmarks/results/markers_real.json [--out DIR] [--pictures DIR]
        [--files NAME ...] [--label-prior 0]
    python benchmarks/markers_real.py --json benchmarks/results/markers_real.json --eye-only
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import cpu_seconds, machine, peak_rss_mb, write_json  # noqa: E402

from c3d_files import FILES, ensure_files  # noqa: E402

from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.io.c3d import read_c3d  # noqa: E402
from bcmocap.markers import MarkerOptions, MarkerTrajectories, fit_marker_skeleton  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402

EYE = Path(__file__).resolve().parent / "markers_real_eye.json"
#: The full-body sets of ``../shared/data/c3d`` (the README's table); the others are partial-body trials.
FULL_BODY = (
    "MocapRecovery_85_02.c3d",
    "MocapRecovery_HDM_bd_05-01_01_120.c3d",
    "ezc3d-testFiles_Qualisys.c3d",
    "BTKData_PiG_PiG_Motion-FlatFoot-Full.c3d",
    "BTKData_PiG_PiG_Motion-FlatFoot-Hole.c3d",
)



def fit_file(path: Path, out: Path | None, options: MarkerOptions = MarkerOptions()) -> dict:
    """Fit one file with ``options`` (saved into ``out`` if given); the verdict, the report's figures, the tree."""
    data = read_c3d(path)
    trajectories = MarkerTrajectories.from_c3d(data)
    wall, cpu = time.perf_counter(), cpu_seconds()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the same warnings are in result.notes
        result = fit_marker_skeleton(trajectories, options)
    wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
    if out is not None:
        result.save(out)
    frames = int(data.positions.shape[0])
    description = result.to_dict()
    unexercised = [f"{j['parent']}–{j['child']}" for j in description["joints"] if j["free_directions"] >= 2]
    names, anatomy = result.skeleton.names, result.anatomy
    return {
        "human": anatomy.human,
        "wrong_limbs": anatomy.wrong_limbs,
        "limbs": {limb: [f"{names[j]} ({anatomy.labels[j]})" for j in chain] for limb, chain in anatomy.limbs.items()},
        "labels": {names[j]: {"label": anatomy.labels[j], "confidence": round(float(anatomy.confidence[j]), 3)}
                   for j in range(len(names))},
        "verdict_notes": list(anatomy.notes),
        "frames": frames,
        "fps": float(data.frame_rate_hz),
        "seconds_of_capture": frames / float(data.frame_rate_hz),
        "input_labels": len(trajectories.labels),
        "markers_used": int(result.trajectories.num_markers),
        "segments": int(result.skeleton.num_segments),
        "segments_chosen_by": result.segmentation.chosen_by,
        "tree": result.tree_lines(),
        "joints_not_exercised": unexercised,
        "notes": list(result.notes),
        "gaps_filled_marker_frames": int((~np.isfinite(result.trajectories.positions[..., 0])).sum()),
        "ik_rms_mm": float(description["ik_rms_m"] * 1000),
        "seconds": wall,
        "cpu_seconds": cpu,
        "seconds_per_1000_frames": wall / frames * 1000,
        "stage_seconds": dict(result.seconds),
    }


def take_pictures(folders: dict[str, Path], pictures: Path) -> None:
    """``pictures/NAME.png``: what ``bcmocap view`` shows of each saved folder (headless Chromium)."""
    from bcmocap.pipeline.view_tracks import load_track_folder
    from bcmocap.viewer.app import BONE
    from bcmocap.viewer.browser import Browser, colour_pixels, free_port
    from bcmocap.viewer.server import start_server
    from bcmocap.viewer.tracks import TrackViewer

    pictures.mkdir(parents=True, exist_ok=True)
    for name, folder in folders.items():
        port = free_port()
        server = start_server("127.0.0.1", port)
        viewer = TrackViewer(load_track_folder(folder), server)
        try:
            with Browser(1400, 900) as browser:
                browser.open(f"http://127.0.0.1:{port}/")
                deadline = time.perf_counter() + 90
                while time.perf_counter() < deadline:
                    png = browser.screenshot()
                    if colour_pixels(png, BONE, left_fraction=0.7) > 40:
                        break
                    time.sleep(0.5)
                time.sleep(2.0)
                browser.dismiss_notifications()
                browser.screenshot(pictures / f"{Path(name).stem}.png")
        finally:
            viewer.close()
            server.stop()


def confirm_by_eye(results: Path) -> int:
    """Fill ``confirmed_by_eye`` and ``seen_by_eye`` of a results file from :data:`EYE`, the verdicts unchanged."""
    figures = json.loads(results.read_text())
    eye = json.loads(EYE.read_text()) if EYE.is_file() else {}
    for name, row in figures["files"].items():
        look = eye.get(name)
        row["confirmed_by_eye"] = None if look is None else bool(look["human"]) == row["human"]
        row["seen_by_eye"] = None if look is None else look["seen"]
    figures["confirmed_by_eye"] = sum(bool(r["confirmed_by_eye"]) for r in figures["files"].values())
    write_json(str(results), figures)
    print(f"{figures['confirmed_by_eye']} of {len(figures['files'])} verdicts confirmed by eye")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data",
                        help="the shared data folder (its c3d/ subfolder is read)")
    parser.add_argument("--fetched", type=Path, default=Path.home() / ".cache" / "bcmocap" / "c3d",
                        help="where benchmarks/c3d_files.py put (or puts) the public files")
    parser.add_argument("--files", nargs="+", help="only these files (names of either set)")
    parser.add_argument("--out", type=Path, help="save each file's markers folder here (OUT/NAME)")
    parser.add_argument("--pictures", type=Path, help="write the picture bcmocap view shows of each (needs --out)")
    parser.add_argument("--label-prior", type=float, default=MarkerOptions.label_prior,
                        help="MarkerOptions.label_prior: the weight of the markers' names (0: the names unused)")
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--eye-only", action="store_true",
                        help="fit nothing: fill the --json file's confirmed_by_eye from markers_real_eye.json (after "
                             "looking at the pictures of the run that wrote it)")
    args = parser.parse_args(argv)
    if args.eye_only:
        if not args.json:
            parser.error("--eye-only needs --json")
        return confirm_by_eye(Path(args.json))
    if args.pictures and not args.out:
        parser.error("--pictures needs --out")
    shared = {name: args.data / "c3d" / name for name in FULL_BODY}
    missing = [str(p) for p in shared.values() if not p.is_file()]
    if missing:
        parser.error(f"not found: {', '.join(missing)}")
    try:
        fetched = {p.name: p for p in ensure_files(args.fetched)}
    except ValueError as exc:
        parser.error(str(exc))
    paths = {**shared, **fetched}
    source = {**{n: "shared data (" + n.split("_")[0] + ")" for n in shared},
              **{f.name: f"{f.repo}@{f.commit[:12]}: {f.path}" for f in FILES}}
    names = args.files or list(paths)
    unknown = [n for n in names if n not in paths]
    if unknown:
        parser.error(f"unknown files {unknown}; the set: {', '.join(paths)}")
    eye = json.loads(EYE.read_text()) if EYE.is_file() else {}
    enable_float64()
    enable_compilation_cache()
    options = MarkerOptions(label_prior=args.label_prior)
    rows, folders = {}, {}
    for name in names:
        out = args.out / Path(name).stem if args.out else None
        try:
            row = rows[name] = {"source": source[name], **fit_file(paths[name], out, options)}
        except ValueError as exc:  # the file or the pipeline refused it: a failed file, never a dropped one
            rows[name] = {"source": source[name], "human": False, "error": str(exc), "confirmed_by_eye": None}
            print(f"\n{name}: FAILED {exc}", flush=True)
            continue
        if out is not None:
            folders[name] = out
        look = eye.get(name)
        row["confirmed_by_eye"] = None if look is None else bool(look["human"]) == row["human"]
        row["seen_by_eye"] = None if look is None else look["seen"]
        verdict = "human" if row["human"] else "NOT human: " + "; ".join(f"{k}: {v}" for k, v in row["wrong_limbs"].items())
        print(f"\n{name}: {verdict}\n  {row['frames']} frames ({row['seconds_of_capture']:.1f} s), {row['input_labels']} "
              f"labels, {row['segments']} segments ({row['segments_chosen_by']}), {row['seconds_per_1000_frames']:.1f} s "
              f"per 1000 frames (CPU {row['cpu_seconds']:.1f} s), eye: {row['confirmed_by_eye']}", flush=True)
        print("\n".join("  " + line for line in row["tree"]))
    share = sum(r["human"] for r in rows.values()) / len(rows)
    print(f"\nhuman verdicts: {sum(r['human'] for r in rows.values())} of {len(rows)} ({100 * share:.0f} %)")
    if args.pictures:
        take_pictures(folders, args.pictures)
    write_json(args.json, {"files": rows, "human_share": share, "label_prior": args.label_prior,
                           "confirmed_by_eye": sum(bool(r["confirmed_by_eye"]) for r in rows.values()),
                           "machine": machine(), "peak_rss_mb": peak_rss_mb()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
