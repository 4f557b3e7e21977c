"""Skeletons from real optical-marker files (Kirk et al. §3–4 on ``../shared/data/c3d``).

Each C3D file is read as ``bcmocap markers FILE`` reads it (modelled points left out) and fitted with the
pipeline's defaults (the eigengap chooses the number of segments). There is no ground truth: the script
records what a reader of ``bcmocap markers``' report judges — the segments with their markers, the tree,
the joints left unexercised, the warnings — and the time per stage, wall and CPU (other jobs may share the
machine's two cores).

    python benchmarks/markers_real.py [--data ../shared/data] [--json FILE] [--files NAME ...]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import cpu_seconds, machine, peak_rss_mb, write_json  # noqa: E402

from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.io.c3d import read_c3d  # noqa: E402
from bcmocap.markers import MarkerOptions, MarkerTrajectories, fit_marker_skeleton  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402

#: The full-body sets of ``../shared/data/c3d`` (the README's table); the others are partial-body trials.
FULL_BODY = (
    "MocapRecovery_85_02.c3d",
    "MocapRecovery_HDM_bd_05-01_01_120.c3d",
    "ezc3d-testFiles_Qualisys.c3d",
    "BTKData_PiG_PiG_Motion-FlatFoot-Full.c3d",
    "BTKData_PiG_PiG_Motion-FlatFoot-Hole.c3d",
)



def fit_file(path: Path) -> dict:
    """Fit one file with the defaults; the report's figures, its tree and its warnings."""
    data = read_c3d(path)
    trajectories = MarkerTrajectories.from_c3d(data)
    wall, cpu = time.perf_counter(), cpu_seconds()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the same warnings are in result.notes
        result = fit_marker_skeleton(trajectories, MarkerOptions())
    wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
    frames = int(data.positions.shape[0])
    unexercised = [f"{j['parent']}–{j['child']}" for j in result.to_dict()["joints"] if j["free_directions"] >= 2]
    return {
        "frames": frames,
        "fps": float(data.frame_rate_hz),
        "seconds_of_capture": frames / float(data.frame_rate_hz),
        "labels": len(trajectories.labels),
        "markers_used": int(result.trajectories.num_markers),
        "segments": int(result.skeleton.num_segments),
        "segments_chosen_by": result.segmentation.chosen_by,
        "tree": result.tree_lines(),
        "joints_not_exercised": unexercised,
        "notes": list(result.notes),
        "ik_rms_mm": float(result.to_dict()["ik_rms_m"] * 1000),
        "seconds": wall,
        "cpu_seconds": cpu,
        "seconds_per_1000_frames": wall / frames * 1000,
        "stage_seconds": dict(result.seconds),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data",
                        help="the shared data folder (its c3d/ subfolder is read)")
    parser.add_argument("--files", nargs="+", default=list(FULL_BODY), help="C3D files in DATA/c3d")
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args(argv)
    folder = args.data / "c3d"
    missing = [name for name in args.files if not (folder / name).is_file()]
    if missing:
        parser.error(f"not found in {folder}: {', '.join(missing)}")
    enable_float64()
    enable_compilation_cache()
    rows = {}
    for name in args.files:
        row = rows[name] = fit_file(folder / name)
        print(f"\n{name}: {row['frames']} frames ({row['seconds_of_capture']:.1f} s), {row['labels']} labels, "
              f"{row['segments']} segments ({row['segments_chosen_by']}), {row['seconds']:.1f} s "
              f"(CPU {row['cpu_seconds']:.1f} s)")
        print("\n".join("  " + line for line in row["tree"]))
        for note in row["notes"]:
            print(f"  warning: {note}")
    write_json(args.json, {"files": rows, "machine": machine(), "peak_rss_mb": peak_rss_mb()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
