"""What ``bcmocap run`` leaves in ``DIR`` for the user (the ``outputs`` stage).

=========================  ==========================================================================
``motion.bvh``             the estimated skeleton and motion (Y up, metres; any BVH reader)
``motion.npz``             ``root_position`` (T, 3) m, ``rotations`` (T, J, 4) wxyz local, ``joint_positions``
                           (T, J, 3) m, ``joint_angles_deg`` (T, J−1, 3) rotation vectors, ``names``, ``fps``
``joint_angles.csv``       per frame: time (s), per joint the local rotation as a rotation vector (deg)
``joint_positions.csv``    per frame: time (s), per joint x, y, z (m)
``scene.ply``              the sparse scene: every 3D point the solver used (m)
``camera_paths.ply``       each camera's centre per frame after optimisation, joined by edges
``reference_colmap/``      the reference model in COLMAP's binary format, in the metric world
``pictures/*.png``         joint angles (Fig. 7a), joint positions (Fig. 7b), camera centres before and
                           after optimisation (Fig. 6), the root path over the scene from above (Fig. 9),
                           a few skeleton poses over the scene
``metrics.json``           with ground truth in the capture: errors after the §5.1 similarity (camera
                           centres aligned to the true ones), before and after optimisation
=========================  ==========================================================================

Coordinates are the run's metric world (``DIR/world/similarity.json``): Z up, metres.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from ..atomic import atomic_path, write_json_atomic
from ..correspondence_store import CorrespondenceStore
from ..geometry import quat_log, rotation_angle, similarity
from ..io import write_bvh
from ..io.ply import write_camera_paths_ply, write_ply_pieces
from ..io.run_folder import load_model, load_motion
from ..kinematics.fk import joint_positions
from ..kinematics.rig import camera_poses
from ..native_crashes import load_pycolmap
from .world import Similarity, load_similarity, transform_model


def rotation_vectors_deg(rotations: np.ndarray) -> np.ndarray:
    """``(..., 4)`` wxyz unit quaternions → ``(..., 3)`` rotation vectors in degrees."""
    return np.rad2deg(quat_log(np.asarray(rotations, np.float64)))


def _write_csv(path: Path, header: list[str], rows: np.ndarray) -> None:
    with atomic_path(path, suffix=".csv") as tmp:
        np.savetxt(tmp, rows, delimiter=",", header=",".join(header), comments="", fmt="%.6f")


def _camera_centres(skeleton, rig, motion) -> np.ndarray:

    return np.asarray(camera_poses(skeleton, rig, motion).translation())


_PICTURE_POINTS = 200_000  # about this many scene points are kept for the pictures


def write_outputs(ctx) -> dict:
    """Write every output of a finished solve; returns a summary for the run log."""
    out = ctx.out
    skeleton, rig = load_model(out, "solve")  # refined in the solve, if it was
    motion = load_motion(out / "solve" / "motion.npz")
    initial = load_motion(out / "solve" / "initial.npz")
    corr = CorrespondenceStore.open(out / "solve" / "correspondences")
    fps = corr.fps
    t = np.arange(motion.num_frames) / fps
    names = list(skeleton.names)

    write_bvh(out / "motion.bvh", skeleton, motion, 1.0 / fps)
    positions = np.asarray(joint_positions(skeleton, motion))
    angles = rotation_vectors_deg(np.asarray(motion.rotations)[:, 1:])
    with atomic_path(out / "motion.npz", suffix=".npz") as tmp:
        np.savez(tmp, root_position=np.asarray(motion.root_position), rotations=np.asarray(motion.rotations),
                 joint_positions=positions, joint_angles_deg=angles, names=np.array(names), fps=fps)
    _write_csv(out / "joint_angles.csv", ["time_s"] + [f"{n}.{a}_deg" for n in names[1:] for a in "xyz"],
               np.column_stack([t, angles.reshape(len(t), -1)]))
    _write_csv(out / "joint_positions.csv", ["time_s"] + [f"{n}.{a}_m" for n in names for a in "xyz"],
               np.column_stack([t, positions.reshape(len(t), -1)]))


    used = corr.used_mask()
    step = max(1, -(-int(used.sum()) // _PICTURE_POINTS))
    sample = []

    def pieces():  # one pass over the points: written whole, every step-th kept for the pictures
        for piece in corr.iter_points(used):
            sample.append(piece[::step])
            yield piece

    write_ply_pieces(out / "scene.ply", int(used.sum()), pieces())
    scene = np.concatenate(sample or [np.zeros((0, 3))]).reshape(-1, 3)
    after = _camera_centres(skeleton, rig, motion)
    write_camera_paths_ply(out / "camera_paths.ply", after)
    _write_reference(ctx, load_similarity(out))

    summary = {"frames": int(motion.num_frames), "scene_points": int(used.sum())}
    truth = _truth(ctx, corr)
    metrics = aligned = None
    if truth is not None:
        metrics, aligned = evaluate_run(skeleton, rig, {"initial": initial, "solved": motion}, corr, truth)
        write_json_atomic(out / "metrics.json", metrics)
        s = metrics["solved"]
        ctx.log(f"metrics (after the §5.1 similarity, {metrics['frames_evaluated']} frames): joint position "
                f"{s['joint_position_error_cm']['mean']:.2f} cm, joint angle {s['joint_angle_error_deg']['mean']:.2f}°, "
                f"camera centre {s['camera_centre_error_cm']['mean']:.2f} cm mean "
                f"(initial: {metrics['initial']['joint_position_error_cm']['mean']:.2f} cm, "
                f"{metrics['initial']['joint_angle_error_deg']['mean']:.2f}°)")
        summary["joint_position_error_cm"] = s["joint_position_error_cm"]["mean"]
        summary["joint_angle_error_deg"] = s["joint_angle_error_deg"]["mean"]
    if ctx.config.outputs.pictures:
        summary["pictures"] = _pictures(out / "pictures", skeleton, motion, positions, t, corr, scene, after, truth, aligned)
    return summary


def _write_reference(ctx, sim) -> None:
    pycolmap = load_pycolmap()

    source = ctx.path("frontend", "reference", "model")
    target = ctx.path("reference_colmap")
    recon = pycolmap.Reconstruction(str(source))
    recon.transform(pycolmap.Sim3d(np.column_stack([sim.scale * sim.rotation, sim.translation])))
    tmp = target.with_name(target.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    recon.write(str(tmp))
    shutil.rmtree(target, ignore_errors=True)
    tmp.rename(target)


# ---- ground truth ---------------------------------------------------------------------------------
def _truth(ctx, corr):
    """The capture trial's ground truth resampled to the run's frames, or None without ground truth."""
    return capture_truth(ctx.capture.path, corr)


def capture_truth(capture_path: Path, corr):
    """:func:`_truth` of the capture folder ``capture_path`` (also read by ``bcmocap view``)."""
    if not (Path(capture_path) / "ground_truth").is_dir():
        return None
    from ..io.capture_folder import load_ground_truth

    gt = load_ground_truth(capture_path)
    trial = gt.trials["capture"]
    stride = int(round(trial.fps / corr.fps))
    frames = int(trial.clap_frames[0]) + stride * np.arange(corr.num_frames)
    valid = (frames >= 0) & (frames < trial.motion.num_frames)
    idx = np.clip(frames, 0, trial.motion.num_frames - 1)
    return {"skeleton": gt.skeleton, "rig": gt.rig, "motion": trial.motion[idx],
            "joint_positions": trial.joint_positions[idx],
            "world_from_camera": trial.world_from_camera[idx], "valid": valid}


def evaluate_run(skeleton, rig, motions: dict, corr, truth: dict):
    """Errors against ground truth after the §5.1 similarity (registered camera centres → true ones).

    Returns:
        The metrics (JSON-ready; cm and degrees, mean/median/max per motion) and the similarity.

    Args:
        skeleton, rig: the estimated model; motions: name → estimated :class:`Motion` over the run's frames.
        corr: the run's (metric) correspondences (a store or ``Correspondences``), whose registered
            poses are aligned.
        truth: from :func:`_truth`.
    """

    valid = truth["valid"]
    sim, residual = align_to_truth(corr, truth)
    s = sim.scale
    true_sk, true_rig, true_motion = truth["skeleton"], truth["rig"], truth["motion"][np.flatnonzero(valid)]
    true_joints = np.asarray(joint_positions(true_sk, true_motion))
    true_cams = _camera_centres(true_sk, true_rig, true_motion)
    out = {"frames_evaluated": int(valid.sum()),
           "alignment": {"scale": s, "camera_centre_residual_cm": _stats(100 * residual),
                         "method": "Umeyama similarity of registered camera centres onto the true ones (§5.1)"},
           "units": {"position": "cm", "angle": "degrees"}}
    for name, motion in motions.items():
        sk2, rig2, m2 = transform_model(skeleton, rig, motion[np.flatnonzero(valid)], sim)
        joints = np.asarray(joint_positions(sk2, m2))
        angles = np.rad2deg(np.asarray(rotation_angle(np.asarray(m2.rotations)[:, 1:], np.asarray(true_motion.rotations)[:, 1:])))
        cams = _camera_centres(sk2, rig2, m2)
        out[name] = {"joint_position_error_cm": _stats(100 * np.linalg.norm(joints - true_joints, axis=-1)),
                     "joint_angle_error_deg": _stats(angles),
                     "camera_centre_error_cm": _stats(100 * np.linalg.norm(cams - true_cams, axis=-1))}
    return out, sim


def align_to_truth(corr, truth: dict):
    """The §5.1 similarity (run world → true world: Umeyama of the registered camera centres onto the true
    ones, over the frames the truth covers) and its ``(N,)`` residuals (m)."""

    reg = corr.registered & truth["valid"][:, None]
    src = corr.world_from_camera[reg][:, 4:]
    dst = np.asarray(truth["world_from_camera"])[reg][:, 4:]
    sim = Similarity(*similarity(src, dst))
    return sim, np.linalg.norm(sim.points(src) - dst, axis=-1)


def _stats(x: np.ndarray) -> dict:
    from ..eval import ErrorStats

    return ErrorStats.of(x).as_dict()


# ---- pictures ---------------------------------------------------------------------------------------
def _pictures(folder: Path, skeleton, motion, positions, t, corr, scene, after, truth, aligned) -> list[str]:
    from ..eval import plots

    folder.mkdir(parents=True, exist_ok=True)
    names = list(skeleton.names)
    angles = np.rad2deg(np.linalg.norm(np.deg2rad(rotation_vectors_deg(np.asarray(motion.rotations)[:, 1:])), axis=-1))
    true_angles = true_positions = true_root = true_cams = None
    if truth is not None and aligned is not None:
        back = aligned.inverse()
        valid = truth["valid"]

        tm = truth["motion"]
        true_angles = np.rad2deg(np.linalg.norm(np.deg2rad(rotation_vectors_deg(np.asarray(tm.rotations)[:, 1:])), axis=-1))
        true_positions = back.points(np.asarray(joint_positions(truth["skeleton"], tm)))
        true_cams = back.points(np.asarray(truth["world_from_camera"])[..., 4:])
        for arr in (true_angles, true_positions, true_cams):
            arr[~valid] = np.nan
        if truth["skeleton"].names == skeleton.names:
            true_root = true_positions[:, 0]
        else:
            true_positions = None
    before = np.where(corr.registered[..., None], corr.world_from_camera[..., 4:], np.nan)
    written = [
        plots.plot_joint_angles(folder / "joint_angles.png", t, angles, names[1:], true_angles),
        plots.plot_joint_positions(folder / "joint_positions.png", t, positions, names, true_positions,
                                    parents=list(skeleton.parents)),
        plots.plot_camera_centres(folder / "camera_centres.png", before, after, true_cams),
        plots.plot_top_view(folder / "top_view.png", scene, positions[:, 0], after, true_root),
        plots.plot_skeleton_poses(folder / "skeleton_poses.png", positions, np.asarray(skeleton.parents),
                                  np.linspace(0, len(t) - 1, min(5, len(t))).astype(int), scene),
    ]
    return [str(Path(p).relative_to(folder.parent)) for p in written]

