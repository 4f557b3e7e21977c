"""A ``bcmocap run`` folder as what ``bcmocap view`` shows (:class:`~bcmocap.viewer.inputs.ViewerInput`).

Read from the run folder ``DIR`` (fixed names only; pictures must resolve inside ``DIR``): the model
(``model/``), the solved and initial motions (``solve/motion.npz``, else the solver's checkpoint;
``solve/initial.npz``), the metric correspondence store (``solve/correspondences/``: frame rate,
registered camera poses, the scene points the solver used, the measurements), ``pictures/*.png`` and
``metrics.json``. Read, never written, from the capture folder the run names in ``run.json`` (or the one
given): the ground truth when it has one (mapped into the run's world by the §5.1 similarity, as in
``metrics.json``) and the capture trial's videos (each camera's frame ``first clap + stride × frame``,
from ``frontend/capture/registration.json``). Saving an edited model goes through
:func:`~bcmocap.pipeline.model_edit.save_model_version`.

``bcmocap view`` reads only what the first frame needs before it draws (the model, the motions, the
store's index and poses: a few tenths of a second) and defers the rest (``defer=True``): the scene points
(every block of the store), the ground truth (its motion, resampled with JAX) and the videos, about two
seconds for the 10 s walk, are read by the viewer in the background.
"""

from __future__ import annotations

import functools
import threading
from pathlib import Path

import numpy as np

from ..io.run_folder import MODEL_FILES, load_model, load_motion, read_json, read_run_log

#: At most this many scene points are sent to the browser (every n-th of those the solver used).
MAX_SCENE_POINTS = 60_000


def _inside(root: Path, path: Path) -> bool:
    real_root, real = root.resolve(), path.resolve()
    return real == real_root or real_root in real.parents


def load_view_input(run_dir: str | Path, capture: str | Path | None = None, *,
                    max_points: int = MAX_SCENE_POINTS, editable: bool = True, defer: bool = False):
    """Read a run folder for the viewer.

    Args:
        run_dir: the output folder of ``bcmocap run``.
        capture: the capture folder (default: the one in ``run.json``); its ground truth and videos are
            shown when it has them.
        max_points: scene points sent to the browser at most.
        editable: whether "save" may write the edited model into ``run_dir``.
        defer: leave what the first frame does without (the scene points, which take reading every block
            of the store; the ground truth; the capture's videos) to ``ViewerInput.later``, which the
            viewer reads in the background; False reads everything now.

    Raises:
        ValueError: one line naming the missing or unreadable file (the deferred part raises it from
            ``ViewerInput.complete``).
    """
    from ..correspondence_store import CorrespondenceStore
    from ..viewer.inputs import ViewerInput

    run_dir = Path(run_dir)
    log = check_run_folder(run_dir)
    skeleton, rig = load_model(run_dir, "solve")  # the model the motion was solved with
    notes = []
    if (run_dir / "solve" / "skeleton.json").is_file():
        notes.append("Showing the model refined in the solve (solver.refine_rounds); a saved edit becomes a new "
                     "version of model/.")
    motions = {}
    for label, name in (("solved", "motion.npz"), ("solver checkpoint", "checkpoint.npz"), ("initial", "initial.npz")):
        path = run_dir / "solve" / name
        if path.is_file() and not (label == "solver checkpoint" and "solved" in motions):
            motion = load_motion(path)
            try:
                motion.check(skeleton, str(path))
            except ValueError as exc:
                raise ValueError(f"{path}: does not fit model/skeleton.json ({exc})") from None
            motions[label] = motion
    if not motions:
        raise ValueError(f"{run_dir / 'solve'}: no motion yet (the run has not finished its initial stage)")
    if len({m.num_frames for m in motions.values()}) > 1:
        motions = {k: v for k, v in motions.items() if v.num_frames == next(iter(motions.values())).num_frames}
    if "solved" not in motions:
        notes.append("No solved motion yet: showing " + " and ".join(motions) + ".")
    store_path = run_dir / "solve" / "correspondences"
    store = CorrespondenceStore.open(store_path) if (store_path / "index.json").is_file() else None
    num_frames = next(iter(motions.values())).num_frames
    if store is not None and (store.num_frames != num_frames or store.num_cameras != rig.num_cameras):
        raise ValueError(f"{store_path}: {store.num_frames} frames of {store.num_cameras} cameras, the motion has "
                         f"{num_frames} frames and the rig {rig.num_cameras} cameras")
    fps = store.fps if store is not None else _fps_of(run_dir)
    registered = None
    if store is not None:
        registered = np.where(store.registered[..., None], store.world_from_camera, np.nan)
    capture_dir = Path(capture) if capture is not None else Path(log.get("capture", ""))
    has_capture = capture is not None or bool(log.get("capture"))
    metrics = None
    if (run_dir / "metrics.json").is_file():
        metrics = read_json(run_dir / "metrics.json")
    pictures = []
    if (run_dir / "pictures").is_dir():
        pictures = [p for p in sorted((run_dir / "pictures").glob("*.png")) if p.is_file() and _inside(run_dir, p)]
    save = None
    if editable:
        from .model_edit import save_model_version

        save = functools.partial(save_model_version, run_dir)
    later = None
    if store is not None:
        later = functools.partial(_store_extras, run_dir, store, rig, capture_dir, has_capture, max_points)
    data = ViewerInput(title=run_dir.resolve().name, skeleton=skeleton, rig=rig, motions=motions, fps=fps,
                       registered=registered, pictures=pictures, metrics=metrics if isinstance(metrics, dict) else None,
                       save_model=save, notes=notes, later=later)
    if not defer:
        data.complete()
    return data


def _store_extras(run_dir: Path, store, rig, capture_dir: Path, with_truth: bool, max_points: int) -> dict:
    """What the first frame does without: the scene points the solver used (every n-th, at most
    ``max_points``), the capture's ground truth (when ``with_truth``: a capture folder is known) and videos."""
    notes: list[str] = []
    used = store.used_points()
    step = max(1, -(-len(used) // max_points))
    if step > 1:
        notes.append(f"Scene: every {step}th of the {len(used)} points the solver used.")
    return {"scene_points": np.asarray(store.points[used[::step]]) if len(used) else None,
            "truth": _truth(capture_dir, store, notes) if with_truth else None,
            "camera_frame": _camera_frames(run_dir, capture_dir, store, rig, notes), "notes": notes}


def check_run_folder(run_dir: str | Path) -> dict:
    """The run log of ``run_dir`` if it is a run folder with a model; ValueError (one line) otherwise."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ValueError(f"{run_dir}: no such folder")
    log = read_run_log(run_dir)
    for name in MODEL_FILES:
        if not (run_dir / "model" / name).is_file():
            raise ValueError(f"{run_dir / 'model' / name}: missing (the run has not finished its skeleton stage)")
    return log


def _fps_of(run_dir: Path) -> float:
    try:
        with np.load(run_dir / "motion.npz") as data:
            return float(data["fps"])
    except (OSError, KeyError, ValueError):
        raise ValueError(f"{run_dir}: no frame rate (neither solve/correspondences/ nor motion.npz)") from None


def _truth(capture_dir: Path, store, notes: list[str]):
    """The ground truth in the run's world, or None (with a note) without one."""
    from ..viewer.inputs import GroundTruth
    from .outputs import align_to_truth, capture_truth

    if not (capture_dir / "ground_truth").is_dir():
        return None
    try:
        truth = capture_truth(capture_dir, store)
        sim, _ = align_to_truth(store, truth)
    except (ValueError, OSError, np.linalg.LinAlgError) as exc:
        notes.append(f"Ground truth not shown: {' '.join(str(exc).split())}")
        return None
    sk = truth["skeleton"]
    joints = np.array(truth["joint_positions"], np.float64)
    joints[~truth["valid"]] = np.nan
    back = sim.inverse()
    return GroundTruth(joints=back.points(joints), parents=tuple(sk.parents), names=tuple(sk.names),
                       to_truth_scale=float(sim.scale))


def _camera_frames(run_dir: Path, capture_dir: Path, store, rig, notes: list[str]):
    """``(camera, frame) → CameraFrame`` over the capture trial's videos and the store's measurements, or
    None (with a note) when the capture or its registration report cannot be read."""
    from ..frontend.capture import read_capture
    from ..viewer.inputs import CameraFrame
    from ..viewer.video import VideoFrames

    report_path = run_dir / "frontend" / "capture" / "registration.json"
    try:
        report = read_json(report_path)
        cameras, starts, stride = report["cameras"], report["first_clap_frames"], int(report["stride"])
        if list(cameras) != list(rig.names) or len(starts) != len(cameras):
            raise ValueError("its cameras are not the rig's")
        capture = read_capture(capture_dir, check_files=False)
        if "capture" not in capture.trials:
            raise ValueError(f"{capture_dir}: no 'capture' trial")
        paths = [capture.video_path("capture", name) for name in cameras]
        # A trial that is a stretch of a longer take (bcmocap init) starts at that frame of the file.
        firsts = [capture.trial_video("capture", name).first_frame for name in cameras]
    except (ValueError, KeyError, TypeError, OSError) as exc:
        notes.append(f"Camera videos not shown: {' '.join(str(exc).split())}")
        return None
    videos = [VideoFrames(p) for p in paths]
    lock = threading.Lock()
    cache: dict[int, dict] = {}

    def block_of(frame: int):
        k = next(i for i, b in enumerate(store.blocks) if b.start <= frame < b.stop)
        if k not in cache:
            cache.clear()
            cache[k] = store.block(k)
        return store.blocks[k], cache[k]

    def camera_frame(c: int, frame: int):
        with lock:
            image = videos[c].frame(firsts[c] + int(starts[c]) + stride * frame)
            if image is None:
                return None
            block, data = block_of(frame)
            ids = data["point_ids"][frame - block.start, c]
            keep = (ids >= 0) & (data["weights"][frame - block.start, c] > 0)
            pixels = data["pixels"][frame - block.start, c][keep]
            points = np.asarray(store.points[ids[keep]]) if keep.any() else np.zeros((0, 3))
            return CameraFrame(image=image, pixels=pixels, points=points, video_frame=int(starts[c]) + stride * frame)

    return camera_frame
