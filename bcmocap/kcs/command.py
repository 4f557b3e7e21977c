"""``bcmocap kcs INPUT --out DIR``: monocular 3-D reconstruction of a kinematic chain from 2-D joints.

Heavy modules (JAX, the solver) are imported inside :func:`run_kcs`, so ``bcmocap --help`` stays fast.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time

from ..atomic import write_json_atomic
from ..compilation_cache import enable_compilation_cache
from ..io.output_folder import output_folder
from . import files

_DESCRIPTION = """\
Reconstruct the 3-D motion of a kinematic chain (a person, an animal, a robot arm) from its 2-D joints in
one uncalibrated, (nearly) static camera, with no training data and no known bone lengths: the kinematic
chain space method of Wandt, Ackermann & Rosenhahn (nuclear norm in the KCS, per-frame weak-perspective
cameras, Algorithm 1).

INPUT is a .npz file (joints_2d (F,J,2) px with NaN for missing joints, names (J,), parents (J,),
rest (J,3) m; optional mask, links, fps) or a folder with topology.csv (joint,parent,x,y,z) and
joints_2d.csv (frame,joint,x,y; absent rows = missing joints) and optionally links.csv (joint_a,joint_b).
See bcmocap/kcs/inputs.py. With --keypoints, INPUT is a detector's 2-D keypoints (COCO-17, OpenPose BODY-25,
MediaPipe Pose 33) mapped onto the CMU chain with its mean walking pose (bcmocap/kcs/keypoints.py). Writes DIR/joints_3d.csv, DIR/result.npz, DIR/motion.bvh, DIR/report.json.
"""


def add_kcs_command(sub: argparse._SubParsersAction) -> None:
    """Register ``bcmocap kcs`` on the CLI's subparsers."""
    kcs = sub.add_parser(
        "kcs",
        help="3-D motion of a kinematic chain from 2-D joints in one camera (kinematic chain space)",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    kcs.add_argument("input", help=".npz file or folder with topology.csv and joints_2d.csv")
    kcs.add_argument("--out", required=True, help="output folder (created if needed)")
    kcs.add_argument("--keypoints", choices=["coco17", "body25", "mediapipe33"], default=None,
                     help="INPUT is a detector's keypoints (COCO JSON, OpenPose's JSON folder, MediaPipe landmarks "
                     "JSON), mapped onto the CMU chain (bcmocap/kcs/keypoints.py)")
    kcs.add_argument("--min-confidence", type=float, default=0.3,
                     help="with --keypoints: a keypoint below this confidence is missing (default 0.3)")
    kcs.add_argument("--fps", type=float, default=None, help="frame rate for the BVH (default: the input's, else 30)")
    kcs.add_argument("--max-iterations", type=int, default=None, help="outer iterations of Algorithm 1 (default 30)")
    kcs.add_argument("--nuclear-weight", type=float, default=None, help="nuclear-norm weight τ in metres (default 0.03)")
    kcs.add_argument(
        "--hinge-weight",
        type=float,
        default=None,
        help="weight of the anatomical hinges (knees, ankles, elbows) in the choice of limb depth signs (default 100)",
    )
    kcs.add_argument(
        "--keypoint-smoothing",
        type=float,
        default=None,
        help="σ (frames) of a Gaussian smoothing of the observed 2-D joints over time before the solve, for a "
        "detector's jitter (default 0: none; e.g. 3 at 30 frames/s)",
    )
    kcs.add_argument(
        "--free-scale",
        action="store_true",
        help="let the bone lengths' sum drift with the cameras' scales instead of holding it to the prior's "
        "(no effect with --no-bone-lengths)",
    )
    kcs.add_argument(
        "--no-bone-lengths",
        action="store_true",
        help="solve Eq. 21 as printed, without the constant-bone-length projection",
    )

    def run(args: argparse.Namespace) -> int:
        problem = _flag_problem(args)
        if problem:
            print(f"bcmocap kcs: {problem}", file=sys.stderr)
            return 2
        return run_kcs(args)

    kcs.set_defaults(run=run)


def _flag_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with the flags, or None."""
    if args.fps is not None and not (math.isfinite(args.fps) and args.fps > 0):
        return f"--fps must be a positive finite frame rate, got {args.fps}"
    if args.max_iterations is not None and args.max_iterations < 1:
        return f"--max-iterations must be at least 1, got {args.max_iterations}"
    if not (math.isfinite(args.min_confidence) and 0 <= args.min_confidence <= 1):
        return f"--min-confidence must be between 0 and 1, got {args.min_confidence}"
    for flag, value in (("--nuclear-weight", args.nuclear_weight), ("--hinge-weight", args.hinge_weight),
                        ("--keypoint-smoothing", args.keypoint_smoothing)):
        if value is not None and not (math.isfinite(value) and value >= 0):
            return f"{flag} must be a finite number ≥ 0, got {value}"
    return None


def run_kcs(args: argparse.Namespace) -> int:
    enable_compilation_cache()
    import numpy as np

    from ..io import write_bvh
    from .chain_space import KinematicChainSpace
    from .export import motion_from_joints
    from .inputs import read_input
    from .solve import KCSOptions, reconstruct

    out = output_folder("kcs", args.out)
    if out is None:
        return 2
    try:
        if args.keypoints:
            from .keypoints import keypoint_input

            data = keypoint_input(args.input, args.keypoints, min_confidence=args.min_confidence)
        else:
            data = read_input(args.input)
    except ValueError as exc:
        print(f"bcmocap kcs: {exc}", file=sys.stderr)
        return 2
    overrides = {}
    if args.max_iterations is not None:
        overrides["max_iterations"] = args.max_iterations
    if args.nuclear_weight is not None:
        overrides["nuclear_weight"] = args.nuclear_weight
    if args.hinge_weight is not None:
        overrides["hinge_weight"] = args.hinge_weight
    if args.keypoint_smoothing is not None:
        overrides["keypoint_smoothing"] = args.keypoint_smoothing
    if args.free_scale:
        overrides["prior_scale"] = False
    if args.no_bone_lengths:
        overrides["constant_bone_lengths"] = False
    options = KCSOptions(**overrides)
    chain = data.chain
    frames, joints = data.joints_2d.shape[:2]
    missing = float(np.mean(~np.isfinite(data.joints_2d).all(-1)))
    print(f"{frames} frames, {joints} joints, {chain.num_bones} bones ({len(chain.extra_links)} extra links), "
          f"{missing * 100:.1f} % joint observations missing", flush=True)
    start = time.perf_counter()
    try:
        result = reconstruct(chain, data.joints_2d, data.rest, options=options)
    except ValueError as exc:
        print(f"bcmocap kcs: {exc}", file=sys.stderr)
        return 2
    joints_3d = np.asarray(result.joints)
    seconds = time.perf_counter() - start
    history = np.asarray(result.reprojection_px)
    history = history[np.isfinite(history)]
    # BVH joint names may not contain whitespace or braces.
    safe = ["".join("_" if c.isspace() or c in "{}" else c for c in n) for n in chain.names]
    bvh_chain = KinematicChainSpace(safe, chain.parents) if len(set(safe)) == len(safe) else chain
    skeleton, motion = motion_from_joints(bvh_chain, joints_3d, rest_joints=data.rest)
    fps = args.fps or data.fps or 30.0

    out.mkdir(parents=True, exist_ok=True)
    with open(out / files.JOINTS_CSV, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(["frame", "joint", "x", "y", "z"])
        for k in range(frames):
            for j, name in enumerate(chain.names):
                writer.writerow([k, name, *(f"{v:.6f}" for v in joints_3d[k, j])])
    np.savez(
        out / files.RESULT,
        joints=joints_3d,
        joints_camera=np.asarray(result.joints_camera),
        camera_rotation=np.asarray(result.cameras.rotation),
        camera_scale=np.asarray(result.cameras.scale),
        bone_lengths=np.asarray(result.bone_lengths),
        bone_names=np.array(chain.bone_names),
        reprojection_px=history,
        names=np.array(chain.names),
        parents=np.array(chain.parents),
    )
    write_bvh(out / files.MOTION_BVH, skeleton, motion, 1.0 / fps)
    report = {
        "frames": frames,
        "joints": list(chain.names),
        "bones": list(chain.bone_names),
        "bone_lengths_m": np.asarray(result.bone_lengths).round(6).tolist(),
        "iterations": int(result.iterations),
        "converged": bool(result.converged),
        "reprojection_px": history.round(6).tolist(),
        "missing_fraction": missing,
        "seconds": seconds,
        "fps": fps,
        "options": options.__dict__,
    }
    write_json_atomic(out / files.REPORT, report)
    print(f"{int(result.iterations)} iterations ({'converged' if report['converged'] else 'stopped at the limit'}), "
          f"reprojection error {history[0]:.3f} -> {history[-1]:.3f} px RMS, {seconds:.1f} s")
    print(f"wrote {out / files.JOINTS_CSV}, {out / files.RESULT}, {out / files.MOTION_BVH} and {out / files.REPORT}")
    return 0
