"""bcmocap's inverse kinematics side by side with Meta's Momentum on one shared problem (issue 44, item 4).

The problem: a real CMU motion (subject 35's walk 35_02, 406 frames at 120 Hz, read from the ASF/AMC files in
``../shared/data/cmu/amc``) on its skeleton with the hands, fingers, thumbs and end sites left out and every joint
made a ball joint (the ASF's fixed hips and its hinges too: 25 segments, a free root and 24 ball joints, 78 unknowns
per frame); three markers fixed on each segment (random offsets around
the middle of the bone, seed 0) observed with 2 mm of Gaussian noise per coordinate. Each frame is posed from the
same start — every joint at rest, the root at the frame's marker centroid — by

* bcmocap: :func:`bcmocap.markers.solve_ik` (the project's Levenberg–Marquardt, analytic Jacobian, frames vmapped
  in one chunk, float64; prior weight towards the start 1e-6 so that the two solve the same least squares);
* Momentum: ``pymomentum.solver.solve_ik`` (Levenberg–Marquardt on position constraints, the frames as one batch,
  float32), with the same tree, rest offsets and marker offsets, in a Python of its own (``_momentum_side.py``).

Both solve the problem at each iteration limit of ``--max-steps`` (default 10, 20, 30, 40, 60, 80 and 100: from the
rest pose neither has converged at 30); Momentum's convergence threshold is lowered so that, like bcmocap (relative
tolerance 1e-6), it stops on the limit or at its minimum. Each solve runs ``--repeats`` + 1 times in one process; the median
time of the calls after the first is the figure (their min and max beside it), and the first call's extra time (bcmocap: tracing and compiling, or loading the compiled program from
the persistent cache) is reported apart. Only the solver's call is timed. Figures per row: wall milliseconds per
frame, mean joint position error against the true motion (mm, all 25 joints) and its 90th percentile
over frames, the share of frames more than 5 cm off (a local minimum), the RMS marker residual (mm; the noise is 3.46 mm in 3-D,
and a least-squares fit of 78 unknowns to 225 coordinates per frame leaves 3.46·√(1 − 78/225) = 2.80 mm of it), and
at the last limit the ratio of the times. ``equal_error`` compares the two at one error: the larger of the two
solvers' best errors, plus 5 %; for each, the fastest limit that reaches it. Run alone on the machine.

Momentum needs Python 3.12 or newer (``pymomentum-cpu`` has no wheel for 3.11), so it lives in an environment of
its own, installed once (about 7 GB with the torch it pulls)::

    python3.12 -m venv ~/momentum && ~/momentum/bin/pip install 'pymomentum-cpu>=0.1.114,<0.2'
    python benchmarks/peer_momentum.py --momentum-python ~/momentum/bin/python [--json FILE]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json  # noqa: E402

from bcmocap.compilation_cache import enable_compilation_cache  # noqa: E402
from bcmocap.io import read_amc, read_asf  # noqa: E402
from bcmocap.kinematics import Motion, Skeleton, joint_positions  # noqa: E402
from bcmocap.markers.ik import marker_model_positions, solve_ik  # noqa: E402
from bcmocap.markers.rigid import RigidSkeleton  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: Segments left out of the CMU skeleton: hands, fingers, thumbs and end sites (leaves without a marker set of
#: their own in a usual full-body marker protocol).
LEFT_OUT = ("ltoes_end", "rtoes_end", "head_end", "lhand", "lfingers", "lfingers_end", "lthumb", "lthumb_end",
            "rhand", "rfingers", "rfingers_end", "rthumb", "rthumb_end")


def shared_problem(cmu_dir: Path, trial: str, noise_m: float, seed: int):
    """The skeleton, true motion, markers and their noisy observations (see the module docstring)."""
    asf = read_asf(cmu_dir / trial.split("_")[0] / f"{trial.split('_')[0]}.asf")
    full = asf.skeleton
    motion = read_amc(cmu_dir / trial.split("_")[0] / f"{trial}.amc", asf)
    keep = [k for k, n in enumerate(full.names) if n not in LEFT_OUT]
    index = {k: i for i, k in enumerate(keep)}
    parents = [-1] + [index[full.parents[k]] for k in keep[1:]]
    offsets = np.asarray(full.offsets)[keep]
    skeleton = Skeleton([full.names[k] for k in keep], parents, offsets)  # free root, ball joints
    truth = Motion(np.asarray(motion.root_position), np.asarray(motion.rotations)[:, keep])
    rng = np.random.default_rng(seed)
    segment, offset = [], []
    for j in range(len(keep)):
        children = [c for c in range(len(keep)) if parents[c] == j]
        along = offsets[children[0]] if children else np.zeros(3)
        for _ in range(3):
            segment.append(j)
            offset.append(0.5 * along + rng.normal(scale=0.05, size=3))
    segment, offset = np.array(segment), np.array(offset)
    markers = np.asarray(marker_model_positions(skeleton, truth, segment, offset))
    observed = markers + rng.normal(scale=noise_m, size=markers.shape)
    return skeleton, truth, segment, offset, observed


def errors(solved: np.ndarray, true: np.ndarray, markers: np.ndarray, observed: np.ndarray) -> dict:
    per_frame = np.linalg.norm(solved - true, axis=-1).mean(axis=-1)
    return {"marker_rms_mm": float(np.sqrt(np.mean(np.sum((markers - observed) ** 2, axis=-1))) * 1000),
            "joint_position_error_mm": float(per_frame.mean() * 1000),
            "joint_position_error_p90_mm": float(np.percentile(per_frame, 90) * 1000),
            "frames_over_5cm": float(np.mean(per_frame > 0.05))}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--momentum-python", required=True, help="a Python with pymomentum-cpu (3.12 or newer)")
    parser.add_argument("--cmu-dir", type=Path, default=ROOT.parent / "shared" / "data" / "cmu" / "amc")
    parser.add_argument("--trial", default="35_02")
    parser.add_argument("--noise-mm", type=float, default=2.0)
    parser.add_argument("--max-steps", type=int, nargs="+", default=[10, 20, 30, 40, 60, 80, 100],
                        help="iteration limits, each solved by both (ascending; the last is the headline row)")
    parser.add_argument("--momentum-threshold", type=float, default=0.1,
                        help="Momentum's convergence threshold (SolverOptions.threshold, its default 10; 0.1 lets it run "
                             "to the iteration limit as bcmocap's tolerance does)")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per solver and limit (the median is the figure)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args(argv)
    enable_float64()
    enable_compilation_cache()
    skeleton, truth, segment, offset, observed = shared_problem(args.cmu_dir, args.trial, args.noise_mm / 1000, args.seed)
    frames, joints = observed.shape[0], skeleton.num_segments
    true_joints = np.asarray(joint_positions(skeleton, truth))
    centroid = observed.mean(axis=1)
    start = Motion(centroid, np.tile(np.array([1.0, 0, 0, 0]), (frames, joints, 1)))
    rigid = RigidSkeleton(skeleton, np.arange(joints), segment, offset, np.zeros(joints), 0)

    ours = {}
    for steps in args.max_steps:
        t0 = time.perf_counter()
        solve_ik(rigid, observed, start, prior_weight=1e-6, chunk=frames, max_steps=steps)
        first = time.perf_counter() - t0
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            result = solve_ik(rigid, observed, start, prior_weight=1e-6, chunk=frames, max_steps=steps)  # numpy: done
            times.append(time.perf_counter() - t0)
        ours[steps] = (np.asarray(joint_positions(skeleton, result.motion)), result.marker_positions, first, times)

    with tempfile.TemporaryDirectory() as tmp:
        problem, result = Path(tmp) / "problem.npz", Path(tmp) / "result.npz"
        np.savez(problem, parents=np.array(skeleton.parents), offsets=np.asarray(skeleton.offsets), targets=observed,
                 seen=np.ones(observed.shape[:2]), marker_segment=segment, marker_offsets=offset,
                 initial_root=centroid, max_steps=np.array(args.max_steps), threshold=args.momentum_threshold,
                 repeats=args.repeats)
        side = Path(__file__).resolve().parent / "_momentum_side.py"
        done = subprocess.run([args.momentum_python, str(side), str(problem), str(result)], capture_output=True, text=True)
        if done.returncode != 0:
            last = (done.stderr.strip().splitlines() or ["(no message)"])[-1]
            raise SystemExit(f"peer_momentum: the Momentum side ({args.momentum_python}) failed: {last}")
        with np.load(result) as r:
            theirs = {k: (r[f"joint_positions_{k}"], r[f"marker_positions_{k}"], float(r[f"first_seconds_{k}"]),
                          list(r[f"seconds_{k}"])) for k in args.max_steps}
            momentum_threads = int(r["threads"])

    rows = []
    for steps in args.max_steps:
        for name, (joints_, markers_, first, times) in (("bcmocap", ours[steps]), ("momentum", theirs[steps])):
            seconds = float(np.median(times))
            row = {"solver": name, "max_steps": steps, "ms_per_frame": 1000 * seconds / frames,
                   "ms_per_frame_min_max": [1000 * min(times) / frames, 1000 * max(times) / frames],
                   "first_call_extra_seconds": first - seconds, **errors(joints_, true_joints, markers_, observed)}
            rows.append(row)
            print(f"{name:8s} ≤{steps:3d} steps: {row['ms_per_frame']:8.3f} ms/frame ({row['ms_per_frame_min_max'][0]:.2f}–{row['ms_per_frame_min_max'][1]:.2f}; first call +{row['first_call_extra_seconds']:.1f} s); joint error "
                  f"{row['joint_position_error_mm']:.2f} mm (p90 {row['joint_position_error_p90_mm']:.2f}), frames over "
                  f"5 cm {100 * row['frames_over_5cm']:.1f} %; marker rms {row['marker_rms_mm']:.3f} mm", flush=True)
    last = args.max_steps[-1]
    mine, peer = rows[-2], rows[-1]
    ratio = peer["ms_per_frame"] / mine["ms_per_frame"]
    print(f"at ≤{last} steps, Momentum's time over bcmocap's: {ratio:.2f}")
    target = 1.05 * max(min(r["joint_position_error_mm"] for r in rows if r["solver"] == n) for n in ("bcmocap", "momentum"))
    fastest = {n: min((r for r in rows if r["solver"] == n and r["joint_position_error_mm"] <= target),
                      key=lambda r: r["ms_per_frame"]) for n in ("bcmocap", "momentum")}
    equal = {"target_error_mm": target, **{f"{n}_{k}": r[k] for n, r in fastest.items()
                                          for k in ("max_steps", "ms_per_frame", "joint_position_error_mm")},
             "momentum_over_bcmocap_time": fastest["momentum"]["ms_per_frame"] / fastest["bcmocap"]["ms_per_frame"]}
    print(f"at one error (≤ {target:.2f} mm): bcmocap {equal['bcmocap_ms_per_frame']:.2f} ms/frame (≤{equal['bcmocap_max_steps']} "
          f"steps), Momentum {equal['momentum_ms_per_frame']:.2f} (≤{equal['momentum_max_steps']}); Momentum's time over "
          f"bcmocap's {equal['momentum_over_bcmocap_time']:.2f}")
    write_json(args.json, {
        "momentum": {"bcmocap_ms_per_frame": mine["ms_per_frame"], "momentum_ms_per_frame": peer["ms_per_frame"],
                     "bcmocap_error": mine["joint_position_error_mm"], "momentum_error": peer["joint_position_error_mm"],
                     "momentum_over_bcmocap_time": ratio, "max_steps": last},
        "equal_error": equal,
        "rows": rows,
        "momentum_torch_threads": momentum_threads,
        "problem": {"trial": args.trial, "frames": frames, "segments": joints, "unknowns_per_frame": 6 + 3 * (joints - 1),
                    "markers": len(segment), "noise_mm": args.noise_mm, "seed": args.seed,
                    "momentum_threshold": args.momentum_threshold,
                    "start": "rest pose, root at the frame's marker centroid"},
    })
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
