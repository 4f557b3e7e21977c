"""Monocular 3-D motion from 2-D joints in one camera: the kinematic chain space method (Wandt et al.).

A bundled CMU motion (19 joints of the CMU skeleton, ``bcmocap.kcs.CMU_JOINTS``) is filmed by one static
perspective camera (``bcmocap.cameras.PinholeCamera``, 1000 px focal length, a few metres away, looking
slightly down), optionally with pixel noise. ``bcmocap.kcs.reconstruct`` recovers the 3-D joints from
those 2-D joints alone: no training data, no calibration, no bone lengths; its only prior is a mean pose
``X0`` (here ``bcmocap.kcs.mean_pose`` of the *other* bundled trials), which fixes the scale. The error is
the paper's 3D error (3DPE: mean joint distance after rigidly aligning each frame to the truth) in mm.
Expect more than the paper's Table 1 (``benchmarks/kcs_table.py``: weak-perspective cameras, a mean pose
mostly of the same subject): a perspective camera at 5 m and another subject's proportions both cost
accuracy; ``--distance 30`` (nearly weak perspective) shows the first.

    python examples/monocular.py [--motion walk|run|jump] [--frames 240] [--noise-px 0] [--azimuth 60]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bcmocap.cameras import PinholeCamera
from bcmocap.compilation_cache import enable_compilation_cache
from bcmocap.precision import enable_float64
from bcmocap.io import load_cmu
from bcmocap.kcs import (
    CMU_JOINTS,
    KinematicChainSpace,
    aligned_joint_errors,
    joint_errors,
    mean_pose,
    reconstruct,
)
from bcmocap.kinematics import joint_positions
from bcmocap.sim import CMU_TRIALS
from bcmocap.sim.motions import cmu_trial_path

CMU_FPS = 120.0
#: The bundled trials used here: upright locomotion, so that the others' mean pose is a fair prior ("scoop" bends
#: double; "hop" is a BVH file without the ASF's joint names).
MOTIONS = ("jump", "run", "walk")


def cmu_joints(name: str) -> tuple[KinematicChainSpace, np.ndarray]:
    """The chain of CMU_JOINTS and a bundled trial's ``(F, 19, 3)`` joint positions (m, Z up)."""
    skeleton, motion = load_cmu(*cmu_trial_path(name), fps=CMU_FPS)
    keep = [skeleton.index(n) for n in CMU_JOINTS]
    return KinematicChainSpace.from_skeleton(skeleton, CMU_JOINTS), np.asarray(joint_positions(skeleton, motion))[:, keep]


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``camera_from_world`` rotation (rows: x right, y down, z forward; OpenCV) of a camera at ``centre``."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(forward, right), forward])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--motion", default="walk", choices=MOTIONS, help="bundled CMU trial (default: walk)")
    parser.add_argument("--frames", type=int, default=240, help="frames at 120 Hz from the start of the trial (default: 240 = 2 s)")
    parser.add_argument("--distance", type=float, default=5.0, help="camera distance from the motion's centre (m)")
    parser.add_argument("--azimuth", type=float, default=60.0, help="camera direction about the vertical (deg)")
    parser.add_argument("--elevation", type=float, default=15.0, help="camera height angle, looking down (deg)")
    parser.add_argument("--noise-px", type=float, default=0.0, help="Gaussian noise on the 2-D joints (px per coordinate)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.frames < 2:
        parser.error("--frames must be at least 2")
    if not args.distance > 0:
        parser.error("--distance must be positive")
    enable_float64()
    enable_compilation_cache()

    chain, truth = cmu_joints(args.motion)
    truth = truth[: args.frames]
    others = [cmu_joints(n)[1] for n in MOTIONS if n != args.motion]
    prior = mean_pose(others, chain)  # X0 from other trials: no knowledge of this subject's bone lengths

    # One static camera looking at the middle of the motion; 2-D joints by perspective projection.
    target = truth.reshape(-1, 3).mean(axis=0)
    az, el = np.deg2rad(args.azimuth), np.deg2rad(args.elevation)
    centre = target + args.distance * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
    rotation = look_at(centre, target)
    camera = PinholeCamera(1280, 720, focal=(1000.0, 1000.0), principal_point=(639.5, 359.5))
    pixels, valid = camera.project((truth - centre) @ rotation.T)
    joints_2d = np.array(pixels, dtype=np.float64)
    if args.noise_px > 0:
        joints_2d += np.random.default_rng(args.seed).normal(scale=args.noise_px, size=joints_2d.shape)
    joints_2d[~np.asarray(valid)] = np.nan  # a joint the camera cannot see is missing
    print(f"CMU '{args.motion}' ({CMU_TRIALS[args.motion][2]}): {len(truth)} frames, {chain.num_joints} joints, "
          f"{chain.num_bones} bones; camera {args.distance:g} m away, {args.noise_px:g} px noise; "
          f"mean pose from {', '.join(n for n in MOTIONS if n != args.motion)}", flush=True)

    start = time.perf_counter()
    result = reconstruct(chain, joints_2d, prior)
    estimate = np.asarray(result.joints)
    seconds = time.perf_counter() - start

    error_3d = np.asarray(aligned_joint_errors(estimate, truth)) * 1000  # (F,) mm
    similarity = np.asarray(aligned_joint_errors(estimate, truth, scale=True)) * 1000
    truth_camera = (truth - centre) @ rotation.T
    mpjpe = np.asarray(joint_errors(np.asarray(result.joints_camera), truth_camera)) * 1000
    history = np.asarray(result.reprojection_px)
    history = history[np.isfinite(history)]
    true_lengths = np.linalg.norm(chain.bones(truth), axis=-1).mean(axis=0)
    scale = float(np.median(np.asarray(result.bone_lengths) / true_lengths))
    print(f"{int(result.iterations)} iterations ({'converged' if bool(result.converged) else 'stopped at the limit'}), "
          f"reprojection {history[0]:.2f} → {history[-1]:.2f} px RMS, {seconds:.1f} s (compilation included)")
    print(f"3D error (rigid alignment per frame): {error_3d.mean():.1f} mm mean, {np.median(error_3d):.1f} mm median, "
          f"{error_3d.max():.1f} mm worst frame")
    print(f"with a scale too (similarity): {similarity.mean():.1f} mm; MPJPE in the camera frame: {mpjpe.mean():.1f} mm; "
          f"bone lengths {scale * 100:.1f} % of the truth (median)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
