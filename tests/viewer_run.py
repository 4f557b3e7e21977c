"""A small ``bcmocap run`` folder made without running the pipeline (for the viewer's tests and screenshot).

The true model of a bundled CMU walk with the 18-camera rig; the "estimate" is the truth with every joint
offset and camera mount moved by a few millimetres, so that errors are not zero. The correspondence store
holds ~20 simulated measurements (0.5 px noise) of scene points on the walls per camera-frame. Beside the
run, ``<run>-capture/`` is a capture folder the run names in ``run.json``: manifest, rig, intrinsics and
each camera's video of the scene points as bright dots (two frames before the first clap, stride 1).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

STAGES = ("frontend", "world", "skeleton", "initial", "solve", "outputs")


def make_run_folder(out: Path, seconds: float = 1.0, fps: float = 30.0, seed: int = 0):
    """Write a run folder at ``out``; returns ``(skeleton, rig, motion, true_joints)`` (the truth)."""
    import cv2

    from bcmocap.atomic import write_json_atomic
    from bcmocap.cameras import camera_at
    from bcmocap.correspondence_store import write_store
    from bcmocap.correspondences import Correspondences
    from bcmocap.io.model_json import rig_to_dict, skeleton_to_dict
    from bcmocap.kinematics import Rig, Skeleton
    from bcmocap.sim.motions import load_body_motion
    from bcmocap.sim.rig import standard_rig
    from bcmocap.viewer.posing import Posing

    rng = np.random.default_rng(seed)
    out = Path(out)
    truth_skeleton, motion = load_body_motion("walk", fps=fps, seconds=seconds)
    truth_rig = standard_rig(truth_skeleton, 160, 90)
    posing = Posing(truth_skeleton.parents, motion.root_position, motion.rotations)
    true_joints = posing.joint_positions(np.asarray(truth_skeleton.offsets))
    offsets = np.asarray(truth_skeleton.offsets) + rng.normal(0, 0.004, (len(truth_skeleton.names), 3))
    skeleton = Skeleton(truth_skeleton.names, truth_skeleton.parents, offsets, truth_skeleton.joint_types,
                        truth_skeleton.hinge_axes)
    mounts = np.array(truth_rig.segment_from_camera)
    mounts[:, 4:] += rng.normal(0, 0.003, (len(mounts), 3))
    rig = Rig(truth_rig.names, truth_rig.segments, mounts, truth_rig.intrinsics)
    cameras = posing.camera_poses(true_joints, truth_rig.segments, truth_rig.segment_from_camera)

    centre = true_joints[:, 0].mean(axis=0)
    angle = rng.uniform(0, 2 * np.pi, 600)
    points = np.column_stack([centre[0] + 4 * np.cos(angle), centre[1] + 4 * np.sin(angle), rng.uniform(0, 2.5, 600)])
    points = np.concatenate([points, np.column_stack([centre[:2] + rng.uniform(-4, 4, (200, 2)), np.zeros(200)])])
    t, c, n = motion.num_frames, rig.num_cameras, 20
    ids = np.full((t, c, n), -1, np.int32)
    pixels = np.zeros((t, c, n, 2))
    weights = np.zeros((t, c, n))
    for k in range(c):
        camera = camera_at(rig.intrinsics, k)
        uv_all, ok_all = _project(camera, cameras[:, k], points)
        for f in range(t):
            uv, ok = uv_all[f], ok_all[f]
            seen = np.flatnonzero(ok)[:n]
            ids[f, k, :len(seen)] = seen
            pixels[f, k, :len(seen)] = uv[seen] + rng.normal(0, 0.5, (len(seen), 2))
            weights[f, k, :len(seen)] = 1.0
    registered = rng.random((t, c)) > 0.05
    corr = Correspondences(points=points, point_ids=ids, pixels=pixels, weights=weights,
                           homography_pixels=np.zeros((t, c, 0, 2)), homography_pixels_prev=np.zeros((t, c, 0, 2)),
                           homography_weights=np.zeros((t, c, 0)), world_from_camera=cameras, registered=registered,
                           fps=fps)
    write_store(out / "solve" / "correspondences", [corr], block_frames=10)
    write_json_atomic(out / "model" / "skeleton.json", skeleton_to_dict(skeleton))
    write_json_atomic(out / "model" / "rig.json", rig_to_dict(rig, skeleton))
    for name, m in (("motion.npz", motion), ("initial.npz", motion), ("checkpoint.npz", motion)):
        np.savez(out / "solve" / name, root_position=np.asarray(m.root_position), rotations=np.asarray(m.rotations))
    write_json_atomic(out / "solve" / "checkpoint.json", {"fingerprint": "x", "reports": []})
    capture = out.parent / f"{out.name}-capture"
    _write_capture(capture, rig, cameras, points, fps)
    write_json_atomic(out / "frontend" / "capture" / "registration.json", {
        "trial": "capture", "cameras": list(rig.names), "first_clap_frames": [2] * c, "stride": 1, "frames": t})
    stages = {s: {"fingerprint": f"{i:016x}", "seconds": 1.0, "finished": "2026-01-01T00:00:00"}
              for i, s in enumerate(STAGES)}
    write_json_atomic(out / "run.json", {"format": "bcmocap-run", "capture": str(capture.resolve()), "stages": stages})
    (out / "pictures").mkdir(parents=True, exist_ok=True)
    gradient = np.tile(np.linspace(0, 255, 320, dtype=np.uint8), (120, 1))
    cv2.imwrite(str(out / "pictures" / "joint_angles.png"), cv2.applyColorMap(gradient, cv2.COLORMAP_VIRIDIS))
    (out / "metrics.json").write_text(json.dumps({"frames_evaluated": t, "solved": {
        "joint_position_error_cm": {"mean": 0.6, "median": 0.5, "max": 1.2}}}))
    return truth_skeleton, truth_rig, motion, true_joints


def _write_capture(folder: Path, rig, cameras: np.ndarray, points: np.ndarray, fps: float) -> None:
    """A capture folder with one video per camera: every scene point in view drawn as a dot."""
    import cv2

    from bcmocap.atomic import write_json_atomic
    from bcmocap.cameras import camera_at
    from bcmocap.io.model_json import camera_to_dict

    write_json_atomic(folder / "capture.json", {"format": "bcmocap-capture", "fps": fps, "trials": ["capture"],
                                                "cameras": list(rig.names)})
    write_json_atomic(folder / "rig.json", {"cameras": [{"name": n, "segment": "x"} for n in rig.names]})
    (folder / "trials" / "capture").mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(rig.names):
        camera = camera_at(rig.intrinsics, k)
        write_json_atomic(folder / "intrinsics" / f"{name}.json", camera_to_dict(camera))
        rows = np.linspace(60, 110, camera.height, dtype=np.uint8)[:, None, None]
        background = np.broadcast_to(rows, (camera.height, camera.width, 3)).copy()
        uv, ok = _project(camera, cameras[:, k], points)
        writer = cv2.VideoWriter(str(folder / "trials" / "capture" / f"{name}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"),
                                 fps, (camera.width, camera.height))
        for f in range(-2, len(cameras)):
            image = background.copy()
            if f >= 0:
                for u, v in uv[f][ok[f]]:
                    cv2.circle(image, (int(round(u)), int(round(v))), 2, (235, 235, 235), -1, cv2.LINE_AA)
            writer.write(image)
        writer.release()


def _project(camera, poses: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(T, P, 2)`` pixels of ``points`` ``(P, 3)`` in one camera at ``poses`` ``(T, 7)``, and where in view."""
    from bcmocap.geometry import matrix_from_quat

    in_camera = np.einsum("tpi,tij->tpj", points[None] - poses[:, None, 4:], matrix_from_quat(poses[:, :4]))
    uv, ok = camera.project(in_camera)
    return np.asarray(uv), np.asarray(ok) & np.asarray(camera.in_image(uv))
