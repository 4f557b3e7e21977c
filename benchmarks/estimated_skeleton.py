"""The full chain with an estimated skeleton: range-of-motion trial → skeleton + rig → initial poses → solver.

For each motion NAME (walk 35_01, run 02_03, jump 02_04):

1. simulate the range-of-motion trial of NAME's CMU subject with the standard 18-camera rig, camera
   poses as SfM gives them (1° rotation and 1 cm position noise, 10 % missing);
2. estimate the skeleton and the camera mounts from it (:func:`bcmocap.kinematics.skeleton_from_range_of_motion`);
3. simulate the standard capture of NAME — its measurements are generated with the TRUE skeleton and
   rig — and initialise the motion from its noisy registered camera poses through the ESTIMATED rig;
4. solve Eq. (1) with the ESTIMATED skeleton and rig; compare with the ground truth.

What is compared, since the two skeletons differ. The estimated segment frames follow the truth's
convention (origin at the joint, all frames parallel to the world in the rest pose that starts the
range-of-motion trial, the root at the lower-back joint as in the CMU skeletons), so local joint
rotations are directly comparable: the joint angle error is the geodesic angle between estimated and
true local rotations (root excluded, as in :func:`bcmocap.eval.evaluate_motion`); it includes the
small error of the estimated rest orientation of each segment. Joint positions are each skeleton's own
forward kinematics in the world, joint by joint (same names), root included; camera centres each
rig's. Lengths and centres are never copied from the truth.

    python benchmarks/estimated_skeleton.py [--json FILE] [--seconds S] [--motions walk run jump]
    python benchmarks/estimated_skeleton.py --refine [--rounds N] --json benchmarks/results/estimated_skeleton_refined.json

``--refine`` (issue 3, item 6, beyond the paper) runs the same chain and then refines the bone
offsets, camera mounts and hinge axes in the final optimisation
(:func:`bcmocap.solver.solve_with_refinement`): per motion it prints round 0 (no refinement, as above)
and each refinement round, with the skeleton errors (joint centres in the cameras' frames, bone
lengths, mount rotations, hinge axes) of that round's model.

Goal (issue 3): mean joint position error ≤ 1.5 cm and mean joint angle error ≤ 2.5° (paper: 1.76 cm, 3.01°).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import solve_summary, write_json  # noqa: E402

from bcmocap.eval import ErrorStats  # noqa: E402
from bcmocap.geometry import rotation_angle  # noqa: E402
from bcmocap.kinematics import Motion, Rig, Skeleton, camera_poses, joint_positions, motion_from_camera_poses  # noqa: E402
from bcmocap.sim import range_of_motion_trial, skeleton_errors, standard_capture  # noqa: E402
from bcmocap.solver import SolverOptions, solve, solve_with_refinement  # noqa: E402
from bcmocap.solver.objective import paper_problem  # noqa: E402

GOAL_POSITION_CM = 1.5
GOAL_ANGLE_DEG = 2.5


def compare_motions(truth: Skeleton, truth_rig: Rig, truth_motion: Motion, skeleton: Skeleton, rig: Rig, motion: Motion) -> dict:
    """Joint position (cm), joint angle (°) and camera-centre (cm) errors of a motion of another skeleton.

    Both skeletons must share names and topology and use the same segment-frame convention.
    """
    if skeleton.names != truth.names or rig.names != truth_rig.names:
        raise ValueError("compare_motions: the estimate and the truth have different segments or cameras")
    pos = np.linalg.norm(np.asarray(joint_positions(skeleton, motion)) - np.asarray(joint_positions(truth, truth_motion)), axis=-1)
    ang = np.asarray(rotation_angle(motion.rotations[..., 1:, :], truth_motion.rotations[..., 1:, :]))
    cams = np.linalg.norm(
        np.asarray(camera_poses(skeleton, rig, motion).translation())
        - np.asarray(camera_poses(truth, truth_rig, truth_motion).translation()),
        axis=-1,
    )
    return {
        "joint_position_error_cm": ErrorStats.of(100.0 * pos).as_dict(),
        "joint_angle_error_deg": ErrorStats.of(np.rad2deg(ang)).as_dict(),
        "camera_centre_error_cm": ErrorStats.of(100.0 * cams).as_dict(),
    }


def skeleton_summary(errors: dict) -> dict:
    """``{"joint_centre_error_cm", "bone_length_error_pct", "mount_rotation_error_deg"}`` → mean/max."""
    def stats(values, scale=1.0):
        v = scale * np.asarray(list(values.values()), dtype=float)
        return {"mean": float(v.mean()), "max": float(v.max())}

    return {
        "joint_centre_error_cm": stats(errors["joint_centre_m"], 100.0),
        "bone_length_error_pct": stats(errors["bone_length_pct"]),
        "mount_rotation_error_deg": stats(errors["mount_rotation_deg"]),
    }


def _chain(name: str, seconds: float | None, seed: int):
    """Capture, range-of-motion estimate (and its time), correspondences and initial motion of one motion."""
    capture = standard_capture(name, seconds=seconds, seed=seed)
    start = time.perf_counter()
    trial = range_of_motion_trial(capture.skeleton, capture.rig, seed=seed + 1000)
    estimate = trial.estimate()
    rom_seconds = time.perf_counter() - start
    correspondences = capture.correspondences()
    initial = motion_from_camera_poses(
        estimate.skeleton, estimate.rig, correspondences.world_from_camera, correspondences.registered, robust=True
    )
    return capture, trial, estimate, rom_seconds, correspondences, initial


def run_motion(name: str, seconds: float | None = None, seed: int = 0) -> dict:
    """The "estimated skeleton" row of ``benchmarks/accuracy.py`` for one motion (same per-motion layout)."""
    capture, trial, estimate, rom_seconds, correspondences, initial = _chain(name, seconds, seed)
    start = time.perf_counter()
    solution = solve(paper_problem(correspondences, estimate.skeleton, estimate.rig), initial, SolverOptions())
    elapsed = time.perf_counter() - start
    truth = (capture.skeleton, capture.rig, capture.motion)
    return {
        **compare_motions(*truth, estimate.skeleton, estimate.rig, solution.motion),
        "initial": compare_motions(*truth, estimate.skeleton, estimate.rig, initial),
        "skeleton": skeleton_summary(skeleton_errors(capture.skeleton, capture.rig, estimate.skeleton, estimate.segment_from_camera)),
        "rom_frames": trial.num_frames,
        "rom_seconds": rom_seconds,
        **solve_summary(solution, correspondences, elapsed, capture.num_frames),
    }


def run_refined(name: str, seconds: float | None = None, seed: int = 0, rounds: int = 1) -> dict:
    """The same chain with bone offsets and mounts refined in the final optimisation (issue 3, item 6).

    Round 0 is :func:`run_motion`'s solve; each later round refines the skeleton and mounts
    (:func:`bcmocap.solver.refine_skeleton_and_rig`, prior: the range-of-motion estimate) and solves again.
    Top-level figures are those of the last round; ``"rounds"`` has each round's.
    """
    capture, trial, estimate, rom_seconds, correspondences, initial = _chain(name, seconds, seed)
    truth = (capture.skeleton, capture.rig, capture.motion)
    per_round: list[dict] = []

    def record(k, skeleton, rig, solution):
        errors = skeleton_errors(capture.skeleton, capture.rig, skeleton, rig.segment_from_camera)
        hinge = np.asarray(list(errors["hinge_axis_deg"].values()))
        per_round.append({
            "round": k,
            **compare_motions(*truth, skeleton, rig, solution.motion),
            "skeleton": {**skeleton_summary(errors), "hinge_axis_error_deg": {"mean": float(hinge.mean()), "max": float(hinge.max())}},
        })

    start = time.perf_counter()
    result = solve_with_refinement(
        correspondences, estimate.skeleton, estimate.rig, initial, rounds=rounds, solver_options=SolverOptions(), callback=record
    )
    elapsed = time.perf_counter() - start
    for row, report in zip(per_round, result.rounds):
        row["reprojection_cost"] = report.reprojection_cost
        row["solve_seconds"] = report.solve_seconds
        if report.refinement is not None:
            row["refinement"] = dataclasses.asdict(report.refinement)
    last = {k: v for k, v in per_round[-1].items() if k not in ("round", "refinement")}
    return {
        **last,
        "without_refinement": {k: v for k, v in per_round[0].items() if k != "round"},
        "initial": compare_motions(*truth, estimate.skeleton, estimate.rig, initial),
        "rom_skeleton": per_round[0]["skeleton"],
        "rounds": per_round,
        "rom_frames": trial.num_frames,
        "rom_seconds": rom_seconds,
        **solve_summary(result.solution, correspondences, elapsed, capture.num_frames),
    }


def _print_row(label: str, r: dict) -> None:
    p, a, s = r["joint_position_error_cm"], r["joint_angle_error_deg"], r["skeleton"]
    print(f"{label:<12}{r.get('frames', ''):>7}{p['mean']:>13.3f}{p['median']:>8.3f}{p['max']:>8.3f}{a['mean']:>12.3f}"
          f"{a['median']:>8.3f}{a['max']:>8.3f}{r['camera_centre_error_cm']['mean']:>11.3f}"
          f"{s['joint_centre_error_cm']['mean']:>11.3f}{s['bone_length_error_pct']['mean']:>8.2f}"
          f"{s['mount_rotation_error_deg']['mean']:>9.3f}{s['hinge_axis_error_deg']['mean']:>9.3f}", flush=True)


def main_refined(args) -> int:
    """``--refine``: each motion without and with refinement, per round."""
    results = {}
    print(f"{'motion/round':<12}{'frames':>7}{'pos mean cm':>13}{'median':>8}{'max':>8}{'ang mean °':>12}{'median':>8}{'max':>8}"
          f"{'cam cm':>11}{'centre cm':>11}{'bone %':>8}{'mount °':>9}{'hinge °':>9}")
    for name in args.motions:
        r = results[name] = run_refined(name, args.seconds, args.seed, args.rounds)
        for row in r["rounds"]:
            _print_row(f"{name} r{row['round']}", {**row, "frames": r["frames"] if row["round"] == 0 else ""})
        print(f"{'':<12}refine+solve {r['solve_seconds']:.0f} s; reprojection cost per round: "
              + ", ".join(f"{row['reprojection_cost']:.6g}" for row in r["rounds"]), flush=True)
    ok = all(r["joint_position_error_cm"]["mean"] <= GOAL_POSITION_CM and r["joint_angle_error_deg"]["mean"] <= GOAL_ANGLE_DEG
             for r in results.values())
    mean_cm = lambda r: r["joint_position_error_cm"]["mean"]  # noqa: E731
    helped = {n: mean_cm(r) < mean_cm(r["without_refinement"]) for n, r in results.items()}
    print(f"goal (≤ {GOAL_POSITION_CM} cm and ≤ {GOAL_ANGLE_DEG}° mean on each motion): {'met' if ok else 'NOT met'}; "
          f"refinement lowers the mean joint position error: {helped}")
    write_json(args.json, {"estimated_skeleton_refined": results, "rounds": args.rounds, "goal_met": ok, "refinement_helps": helped})
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--seconds", type=float, default=None, help="length per motion (default: the whole trial)")
    parser.add_argument("--motions", nargs="+", default=["walk", "run", "jump"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--refine", action="store_true", help="also refine bone offsets and mounts (issue 3, item 6)")
    parser.add_argument("--rounds", type=int, default=1, help="refinement rounds with --refine (a second one moved nothing on walk)")
    args = parser.parse_args(argv)
    from bcmocap.compilation_cache import enable_compilation_cache
    from bcmocap.precision import enable_float64

    enable_float64()
    enable_compilation_cache()
    if args.refine:
        return main_refined(args)
    results = {}
    print(f"{'motion':<8}{'frames':>7}{'pos mean cm':>13}{'median':>8}{'max':>8}{'ang mean °':>12}{'median':>8}{'max':>8}"
          f"{'init pos cm':>13}{'init ang °':>12}{'centre cm':>11}{'bone %':>8}{'mount °':>9}")
    for name in args.motions:
        r = run_motion(name, args.seconds, args.seed)
        results[name] = r
        p, a, s = r["joint_position_error_cm"], r["joint_angle_error_deg"], r["skeleton"]
        print(f"{name:<8}{r['frames']:>7}{p['mean']:>13.3f}{p['median']:>8.3f}{p['max']:>8.3f}{a['mean']:>12.3f}{a['median']:>8.3f}"
              f"{a['max']:>8.3f}{r['initial']['joint_position_error_cm']['mean']:>13.3f}"
              f"{r['initial']['joint_angle_error_deg']['mean']:>12.3f}{s['joint_centre_error_cm']['mean']:>11.3f}"
              f"{s['bone_length_error_pct']['mean']:>8.2f}{s['mount_rotation_error_deg']['mean']:>9.3f}", flush=True)
    ok = all(r["joint_position_error_cm"]["mean"] <= GOAL_POSITION_CM and r["joint_angle_error_deg"]["mean"] <= GOAL_ANGLE_DEG
             for r in results.values())
    print(f"goal (≤ {GOAL_POSITION_CM} cm and ≤ {GOAL_ANGLE_DEG}° mean on each motion): {'met' if ok else 'NOT met'}")
    write_json(args.json, {"estimated_skeleton": results, "goal_met": ok})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
