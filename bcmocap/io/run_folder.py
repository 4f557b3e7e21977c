"""The run folder of ``bcmocap run``: its layout, its log and the readers of what its stages saved.

One module owns this format; the pipeline writes through it, and the viewer adapter, the model editor and
the outputs read through it. Layout (``DIR``, relative paths)::

    run.json                       the run log (:class:`RunLog`): format "bcmocap-run", the capture's absolute
                                   path, and per finished stage its settings fingerprint, time and seconds
    config.json, log.txt           the settings the run was made with; one line per event
    frontend/                      the layout of ``bcmocap frontend``: frontend/<trial>/registration.json and
                                   frontend/<trial>/correspondences/ (a correspondence store) per trial,
                                   frontend/intrinsics.npz with the frontend's self-calibration
    world/similarity.json          reference-model frame → metric Z-up world (scale, rotation (3, 3), translation m)
    world/registered/              registered camera poses re-fitted under the solver's camera model (when set)
    model/skeleton.json, rig.json  the estimated model (bcmocap.io.model_json); model/versions.json and
                                   model/versions/NNN/ after edits in ``bcmocap view``
    solve/correspondences/         the capture's measurements in the metric world (a correspondence store)
    solve/initial.npz              the initial motion (root_position (T, 3) m, rotations (T, J, 4) wxyz)
    solve/checkpoint.npz, .json    the motion so far and the windows' reports, while the solve runs
    solve/motion.npz               the solved motion, with the user terms' variables ("static:NAME", "frame:NAME")
    solve/skeleton.json, rig.json  the model refined in the solve (only with solver.refine_rounds)
    solve/reports.json             per window and refinement round, the solver's report
    motion.bvh, motion.npz, joint_angles.csv, joint_positions.csv, scene.ply, camera_paths.ply, metrics.json,
    pictures/                      the outputs stage's files

:data:`STAGE_OUTPUTS` lists what each stage must leave behind for the run to count it finished.
"""

from __future__ import annotations

import datetime
import json
from pathlib import Path

import numpy as np

from ..atomic import atomic_path, write_json_atomic

RUN_FORMAT = "bcmocap-run"
#: The stages of ``bcmocap run``, in order.
STAGES = ("frontend", "world", "skeleton", "initial", "solve", "outputs")
#: What each stage writes (relative to DIR): a finished stage whose outputs were deleted is done again.
STAGE_OUTPUTS = {
    "frontend": ("frontend/rom/registration.json", "frontend/rom/correspondences/index.json",
                 "frontend/capture/registration.json", "frontend/capture/correspondences/index.json"),
    "world": ("world/similarity.json",),
    "skeleton": ("model/skeleton.json", "model/rig.json"),
    "initial": ("solve/initial.npz", "solve/correspondences/index.json"),
    "solve": ("solve/motion.npz",),
    "outputs": ("motion.bvh", "motion.npz", "joint_angles.csv", "joint_positions.csv", "scene.ply", "camera_paths.ply"),
}
RUN_LOG = "run.json"
SIMILARITY = "world/similarity.json"
#: The model's files, in ``model/`` (estimated or edited) and in ``solve/`` (refined in the solve).
MODEL_FILES = ("skeleton.json", "rig.json")


def read_json(path: Path) -> dict:
    """A JSON file's content; ValueError of one line naming the file when it cannot be read or parsed."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:  # ValueError: not UTF-8 or not JSON
        raise ValueError(f"{path}: cannot read ({exc})") from None


def write_npz(path: Path, **arrays) -> None:
    """``np.savez`` written atomically (a reader never sees half a file)."""
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, **arrays)


def read_run_log(run_dir: str | Path) -> dict:
    """The content of ``DIR/run.json``; ValueError (one line) when ``run_dir`` is no run folder."""
    run_dir = Path(run_dir)
    run_json = run_dir / RUN_LOG
    if not run_json.is_file():
        raise ValueError(f"{run_dir}: not a bcmocap run folder (no run.json; `bcmocap run CAPTURE --out DIR` "
                         "makes one)")
    data = read_json(run_json)
    if not isinstance(data, dict) or data.get("format") != RUN_FORMAT or not isinstance(data.get("capture"), str):
        raise ValueError(f"{run_json}: not a bcmocap run log")
    return data


class RunLog:
    """``DIR/run.json``: the capture, and per finished stage its settings fingerprint, time and seconds.

    It is written only into the folder it was opened in: when ``DIR`` is deleted or replaced while a run goes on
    (another inode at that path), the next write raises ``ValueError`` instead of starting a new run log there.
    """

    def __init__(self, out: Path, capture_path: Path):
        self.out = Path(out)
        self.identity = _identity(self.out)
        self.path = out / RUN_LOG
        self.data = {"format": RUN_FORMAT, "capture": str(capture_path.resolve()), "stages": {}}
        if self.path.exists():
            data = read_json(self.path)
            if data.get("format") != RUN_FORMAT:
                raise ValueError(f"{self.path}: not a bcmocap run log")
            if data.get("capture") != self.data["capture"]:
                raise ValueError(
                    f"{out} holds a run of another capture ({data.get('capture')}); choose another --out")
            self.data = data

    def finished(self, stage: str, fingerprint: str) -> bool:
        rec = self.data["stages"].get(stage)
        return bool(rec) and rec.get("fingerprint") == fingerprint

    def check_folder(self) -> None:
        """``ValueError`` (one line) when ``DIR`` is gone or is another folder than the one the run opened."""
        if self.identity is not None and _identity(self.out) != self.identity:
            raise ValueError(f"{self.out} was deleted or replaced while the run was going; nothing more is written "
                             "there (rerun the same command to start again)")

    def save(self) -> None:
        self.check_folder()
        write_json_atomic(self.path, self.data)

    def record(self, stage: str, fingerprint: str, seconds: float, **extra) -> None:
        self.data["stages"][stage] = {"fingerprint": fingerprint, "seconds": round(seconds, 3),
                                      "finished": datetime.datetime.now().isoformat(timespec="seconds"), **extra}
        self.save()

    def forget_from(self, stage: str) -> None:
        for s in STAGES[STAGES.index(stage):]:
            self.data["stages"].pop(s, None)
        self.save()


def _identity(folder: Path) -> tuple[int, int] | None:
    """``(device, inode)`` of a folder, or None when there is none at that path."""
    try:
        stat = folder.stat()
    except OSError:
        return None
    return stat.st_dev, stat.st_ino


def load_model(out: Path | str, stage: str = "model"):
    """The skeleton and rig a run estimated (``DIR/model/``), or refined in its solve (``stage="solve"``:
    ``DIR/solve/`` holds them after ``solver.refine_rounds``; else the estimate): ``(Skeleton, Rig)``."""
    from .model_json import rig_from_dict, skeleton_from_dict

    out = Path(out)
    folder = out / stage
    if stage == "solve" and not (folder / "skeleton.json").is_file():
        folder = out / "model"
    sk_path, rig_path = folder / "skeleton.json", folder / "rig.json"
    skeleton = skeleton_from_dict(read_json(sk_path), str(sk_path))
    return skeleton, rig_from_dict(read_json(rig_path), skeleton, str(rig_path))


def save_motion(path: Path, motion, **extra) -> None:
    """A :class:`~bcmocap.kinematics.Motion` (and ``extra`` arrays) as ``path`` (npz, atomically)."""
    write_npz(path, root_position=np.asarray(motion.root_position), rotations=np.asarray(motion.rotations), **extra)


def load_motion(path: Path | str):
    """A motion saved by a run (``DIR/solve/motion.npz``, ``DIR/initial/motion.npz``, ``DIR/motion.npz``)."""
    from ..kinematics.skeleton import Motion

    try:
        with np.load(path) as data:
            arrays = {name: data[name] for name in ("root_position", "rotations")}
    except (OSError, KeyError, ValueError) as exc:
        raise ValueError(f"{path}: not a saved motion ({exc})") from None
    for name, a in arrays.items():  # a damaged checkpoint must not carry NaN into the solve or motion.bvh
        if a.dtype.kind != "f" or not np.all(np.isfinite(a)):
            where = f" at frame {np.argwhere(~np.isfinite(a))[0][0]}" if a.dtype.kind == "f" else f" (dtype {a.dtype})"
            raise ValueError(f"{path}: {name} holds NaN or inf{where}" if a.dtype.kind == "f" else f"{path}: {name}{where}")
    return Motion(arrays["root_position"], arrays["rotations"])


def solved_variables(solution) -> dict:
    """The user terms' static and per-frame variables of a :class:`~bcmocap.solver.Solution`, as npz entries
    (``"static:NAME"``, ``"frame:NAME"``) to save beside its motion."""
    return {**{f"static:{k}": v for k, v in solution.statics.items()},
            **{f"frame:{k}": v for k, v in solution.frame_variables.items()}}


def load_solved_variables(path: Path) -> tuple[dict, dict]:
    """``(statics, frame_variables)`` saved beside a motion by :func:`solved_variables`."""
    try:
        with np.load(path) as data:
            pick = lambda prefix: {k[len(prefix):]: data[k] for k in data.files if k.startswith(prefix)}  # noqa: E731
            return pick("static:"), pick("frame:")
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a saved motion ({exc})") from None
