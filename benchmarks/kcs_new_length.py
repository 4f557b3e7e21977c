"""A sequence of a new length in a fresh process (issue 47): how long before ``bcmocap.kcs.reconstruct`` starts
iterating, with the persistent compilation cache warm from earlier sequences.

Each measurement is a fresh Python process (``--child``) with one compilation cache folder for the whole run
(new, or ``--cache``): the bundled CMU walk 35_01 (120 Hz) projected by one near-static camera path
(``benchmarks/kcs_table.py``'s), its prior the walk's own mean pose. In order:

1. **first user**: 300 frames, in an empty cache: compiles its bucket's program (384 frames) and stores it;
2. **new length, padded** (today's ``reconstruct``): 333 frames, never seen, in the bucket of 1;
3. **new length, unpadded** (``pad=False``, as before issue 47): 333 frames, compiled for its own length;
4. **new length, padded, new bucket**: 420 frames (bucket 512), which nothing compiled yet.

For each: the first call's wall time, a second call's in the same process (the iterations alone), and their
difference, the time before the first iteration (compiling or loading the program, tracing, transfers).

    python benchmarks/kcs_new_length.py --json benchmarks/results/kcs_new_length.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_json  # noqa: E402

CASES = (("first user", 300, True), ("new length, padded", 333, True), ("new length, unpadded", 333, False),
         ("new length, padded, new bucket", 420, True))


def child(frames: int, pad: bool) -> dict:
    started = time.perf_counter()
    import numpy as np
    from importlib import resources

    from bcmocap.compilation_cache import enable_compilation_cache
    from bcmocap.io import read_amc, read_asf
    from bcmocap.kcs import CMU_JOINTS, KinematicChainSpace, mean_pose, reconstruct
    from bcmocap.kcs.solve import padded_length
    from bcmocap.kinematics import joint_positions
    from bcmocap.precision import enable_float64
    from kcs_table import camera_paths, project

    enable_float64()
    enable_compilation_cache()
    base = resources.files("bcmocap") / "data" / "cmu"
    with resources.as_file(base / "35.asf") as asf_path, resources.as_file(base / "35_01.amc") as amc_path:
        asf = read_asf(asf_path)
        motion = read_amc(amc_path, asf)
    chain = KinematicChainSpace.from_skeleton(asf.skeleton, CMU_JOINTS)
    joints = np.asarray(joint_positions(asf.skeleton, motion))[:, [asf.skeleton.index(n) for n in CMU_JOINTS]]
    truth = joints[:frames]
    rng = np.random.default_rng(0)
    rotation, scale = camera_paths(len(truth), 1, rng)
    images = project(truth, rotation, scale, 0.0, rng)[0]
    prior = mean_pose(joints, chain)
    ready = time.perf_counter()
    times = []
    for _ in range(2):
        start = time.perf_counter()
        result = reconstruct(chain, images, prior, pad=pad)
        np.asarray(result.joints)
        times.append(time.perf_counter() - start)
    return {"frames": frames, "pad": pad, "solved_length": padded_length(frames) if pad else frames,
            "setup_seconds": ready - started, "first_call_seconds": times[0], "second_call_seconds": times[1],
            "before_first_iteration_seconds": times[0] - times[1], "iterations": int(result.iterations)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--cache", help="compilation cache folder (default: a new one, removed after)")
    ap.add_argument("--child", nargs=2, metavar=("FRAMES", "PAD"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(int(args.child[0]), args.child[1] == "1")))
        return 0
    with tempfile.TemporaryDirectory() as scratch:
        cache = args.cache or scratch
        env = {**os.environ, "BCMOCAP_CACHE_DIR": cache}
        rows = {}
        for name, frames, pad in CASES:
            out = subprocess.run([sys.executable, __file__, "--child", str(frames), "1" if pad else "0"], env=env,
                                 capture_output=True, text=True, check=True)
            rows[name] = json.loads(out.stdout.strip().splitlines()[-1])
            r = rows[name]
            print(f"{name}: {frames} frames (solved as {r['solved_length']}): first call {r['first_call_seconds']:.1f} s, "
                  f"second {r['second_call_seconds']:.1f} s: {r['before_first_iteration_seconds']:.1f} s before the "
                  f"first iteration", flush=True)
    write_json(args.json, {"cases": rows, "goal_seconds": 10.0})
    return 0


if __name__ == "__main__":
    sys.exit(main())
