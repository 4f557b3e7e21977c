"""Joint centres from the range-of-motion trial alone, or from it and the capture together (``[skeleton]
centre_trials``): how much the capture's motion adds when the ROM trial's camera poses are poor.

For the walk's subject (CMU 35) and the standard 18-camera rig, the studio's range-of-motion trial
(``bcmocap.sim.studio.studio_range_of_motion``: a rest hold, then every joint swinging about all its axes at once;
``--rom-seconds``) and ``--seconds`` of the CMU walk are observed as structure-from-motion would
(``bcmocap.sim.sfm_like_poses``) at three levels of pose noise and missing camera-frames, the last two of the order
of what a tracked frontend gives under the realistic studio preset (74 % of its ROM camera-frames registered).
Per level and seed the skeleton is estimated from the ROM trial alone and from both trials (the rest pose and
the virtual cameras from the ROM trial in both), with ``bcmocap run``'s thresholds (5 cm standard error; with
``--loose``: 10 cm and degenerate ball joints as hinges, the realism benchmark's); a row gives the joint-centre error
(mean over joints and seeds, and the worst joint), the mount translation error, the worst joint's standard error
and how many estimates stopped on an undetermined joint.

    python benchmarks/centre_trials.py [--json benchmarks/results/centre_trials.json] [--seeds 5]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json  # noqa: E402

from bcmocap.kinematics.rig import camera_poses  # noqa: E402
from bcmocap.kinematics.rom import RomOptions, skeleton_from_range_of_motion  # noqa: E402
from bcmocap.precision import enable_float64  # noqa: E402
from bcmocap.sim import load_body_motion, sfm_like_poses, skeleton_errors, standard_rig  # noqa: E402
from bcmocap.sim.studio import rom_rest_frames, studio_range_of_motion  # noqa: E402

#: (rotation σ deg, position σ m, missing share of the ROM trial); the capture misses 10 % at every level.
LEVELS = {"1 deg, 1 cm, 10 % missing": (1.0, 0.01, 0.1),
          "2 deg, 2 cm, 30 % missing": (2.0, 0.02, 0.3),
          "3 deg, 3 cm, 40 % missing": (3.0, 0.03, 0.4)}
CAPTURE_MISSING = 0.1


def estimate(skeleton, rig, rom, walk, rest, more: bool, options: RomOptions) -> dict:
    cams = [(name, skeleton.names[s]) for name, s in zip(rig.names, rig.segments)]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est = skeleton_from_range_of_motion(skeleton, cams, *rom, rest_frames=rest, options=options,
                                                more_trials=[walk] if more else ())
    except ValueError as exc:
        return {"failed": str(exc).split(":")[0]}
    err = skeleton_errors(skeleton, rig, est.skeleton, est.segment_from_camera)
    centre = err["joint_centre_m"]
    return {"centre_cm": {k: 100 * v for k, v in centre.items()},
            "mount_cm": 100 * float(np.mean(list(err["mount_translation_m"].values()))),
            "worst_std_cm": 100 * max(j.std_m for j in est.joints.values())}


def summarise(runs: list[dict]) -> dict:
    ok = [r for r in runs if "failed" not in r]
    out = {"estimates": len(runs), "failed": len(runs) - len(ok), "failures": [r["failed"] for r in runs if "failed" in r]}
    if ok:
        per_joint = {k: float(np.nanmean([r["centre_cm"][k] for r in ok])) for k in ok[0]["centre_cm"]}
        worst = max(per_joint, key=per_joint.get)
        out.update({
            "joint_centre_error_cm": float(np.nanmean([np.nanmean(list(r["centre_cm"].values())) for r in ok])),
            "worst_joint": worst, "worst_joint_error_cm": per_joint[worst],
            "mount_translation_error_cm": float(np.mean([r["mount_cm"] for r in ok])),
            "worst_standard_error_cm": float(np.mean([r["worst_std_cm"] for r in ok])),
        })
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--rom-seconds", type=float, default=3.0)
    parser.add_argument("--seconds", type=float, default=2.0, help="length of the capture (walk) trial (s)")
    parser.add_argument("--loose", action="store_true", help="10 cm limit and degenerate ball joints as hinges")
    args = parser.parse_args(argv)
    enable_float64()
    fps = 60.0
    skeleton, walk_motion = load_body_motion("walk", fps=fps, seconds=args.seconds)
    rig = standard_rig(skeleton)
    options = RomOptions(max_centre_std_m=0.10, degenerate="hinge") if args.loose else RomOptions(max_centre_std_m=0.05)
    rows = {}
    print(f"{'level':<28}{'centres from':<15}{'failed':>7}{'centre cm':>11}{'worst joint cm':>24}{'mount cm':>10}"
          f"{'worst std cm':>14}")
    for level, (rot, pos, missing) in LEVELS.items():
        runs = {"rom": [], "rom+capture": []}
        for seed in range(args.seeds):
            rng = np.random.default_rng([seed, 1])
            rom_motion = studio_range_of_motion(skeleton, walk_motion, args.rom_seconds, fps, rng)
            noise = dict(rotation_sigma_deg=rot, position_sigma_m=pos)
            rom = sfm_like_poses(camera_poses(skeleton, rig, rom_motion), rng, missing_fraction=missing, **noise)[:2]
            walk = sfm_like_poses(camera_poses(skeleton, rig, walk_motion), rng, missing_fraction=CAPTURE_MISSING,
                                  **noise)[:2]
            rest = rom_rest_frames(rom_motion.num_frames, fps)
            for label in runs:
                runs[label].append(estimate(skeleton, rig, rom, walk, rest, label != "rom", options))
        rows[level] = {label: summarise(r) for label, r in runs.items()}
        for label, r in rows[level].items():
            if "joint_centre_error_cm" in r:
                print(f"{level:<28}{label:<15}{r['failed']:>7}{r['joint_centre_error_cm']:>11.2f}"
                      f"{r['worst_joint']:>15} {r['worst_joint_error_cm']:>7.2f}{r['mount_translation_error_cm']:>10.2f}"
                      f"{r['worst_standard_error_cm']:>14.2f}")
            else:
                print(f"{level:<28}{label:<15}{r['failed']:>7}  (every estimate stopped: {r['failures'][0]})")
    write_json(args.json, {"levels": rows, "seeds": args.seeds, "rom_seconds": args.rom_seconds,
                           "capture_seconds": args.seconds, "loose": args.loose, "machine": machine()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
