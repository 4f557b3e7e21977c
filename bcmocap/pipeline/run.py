"""``bcmocap run``: a capture folder to a motion, in stages that are saved as they finish.

Stages (each writes under ``DIR``; a finished stage is recorded in ``DIR/run.json`` and skipped when
the command is run again with the same settings for it; changed settings redo that stage and the
ones after it):

1. ``frontend`` — reference model, sync, SIFT, registration and homographies of the range-of-motion
   and capture trials (``DIR/frontend/``, the layout of ``bcmocap frontend``; features are cached, a
   finished trial is not redone);
2. ``world`` — with a rolling shutter or self-calibration in the solver's settings, both trials' registered
   camera poses re-fitted under that camera model (:func:`_refine_registered_poses`;
   ``DIR/world/registered/``); then the similarity from the reference model's frame to a metric, Z-up world
   (:mod:`.world`; ``DIR/world/similarity.json``);
3. ``skeleton`` — skeleton and camera mounts from the range-of-motion trial in that world
   (``DIR/model/skeleton.json``, ``rig.json``, ``rom_summary.txt``);
4. ``initial`` — the capture's correspondences in that world and the initial motion from its
   registered camera poses (``DIR/solve/correspondences/``, ``initial.npz``);
5. ``solve`` — Eq. (1) in overlapping windows; after every window the motion so far is saved
   (``DIR/solve/checkpoint.npz``), so an interrupted solve resumes at the next window;
6. ``outputs`` — :mod:`.outputs`: BVH, PLY, the reference model in COLMAP's format, NPZ/CSV,
   pictures, and ``metrics.json`` when the capture has ground truth.

Nothing in the capture folder is written; every output file is written atomically. With a cluster
(``--cluster``, :mod:`.cluster`) the frontend's cameras and chunks and (``solver.windows = "independent"``)
the solver's windows are Dask tasks; the results are those of the same settings without one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import hashlib
import json
import math
import os
import shutil
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..atomic import atomic_path, write_json_atomic
from ..io.output_folder import check_outside, locked_output
from ..io.run_folder import (SIMILARITY, STAGE_OUTPUTS, STAGES, RunLog, load_model, load_motion, load_solved_variables,
                             read_json, save_motion, solved_variables, write_npz)
from ..io.capture_folder import MANIFEST_FILE, RIG_FILE, changed_files, file_stamps
from .cluster import Executor, open_executor
from .config import RunConfig
from .peak_memory import out_of_memory, peak_mb, reset_peak, stage_out_of_memory
from .slips import SlipRepair, repair_slips

if TYPE_CHECKING:
    from .world import Similarity

#: Seconds a run waits for the output folder's lock (a model saved in ``bcmocap view`` holds it for milliseconds)
#: before refusing to start beside another command.
LOCK_WAIT_S = 10.0
#: Config sections each stage depends on (a change redoes the stage and every later one).
_STAGE_SECTIONS = {"frontend": ("frontend",), "world": ("skeleton",), "skeleton": ("skeleton",),
                   "initial": (), "solve": ("solver",), "outputs": ("outputs",)}



def _expected_outputs(stage: str, config: RunConfig) -> tuple[str, ...]:
    """:data:`STAGE_OUTPUTS` of a stage, with what its settings add (the frontend's lens correction)."""
    if stage == "frontend" and config.frontend.self_calibration:
        return (*STAGE_OUTPUTS[stage], "frontend/intrinsics.npz")
    return STAGE_OUTPUTS[stage]


@dataclasses.dataclass
class RunContext:
    """What every stage sees: the capture, the settings, the output folder and a log."""

    capture: object  # bcmocap.frontend.Capture
    config: RunConfig
    out: Path
    log: Callable[[str], None]
    executor: Executor = dataclasses.field(default_factory=Executor)  # this process, or a cluster

    def path(self, *parts: str) -> Path:
        return self.out.joinpath(*parts)


#: Settings added after runs were made, left out of the fingerprints at these (default) values, so that those
#: runs stay reusable.
_LATER_DEFAULTS = {"solver": {"windows": "sequential", "registered_pose": [0.0, 0.0], "registered_pose_below": 20,
                              "unmeasured_orientation": 0.0,
                              "gyro_turn": 0.0},
                   "skeleton": {"centre_trials": ["rom"], "unregistered_ends": "mirror", "unregistered_rest": "mirror"},
                   "frontend": {"rolling_shutter_readout": 0.0, "self_calibration": False, "gyro_timing": "clock",
                                "estimate_readout": False}}


#: ``solver`` settings the ``world`` stage also reads (the camera model it re-fits the registered poses under), with
#: their defaults: counted in its fingerprint only when set, so a run without them keeps its fingerprints.
_CAMERA_MODEL = {"rolling_shutter_readout": 0.0, "self_calibration": False}


def fingerprints(config: RunConfig) -> dict[str, str]:
    """Per stage, a hash of the settings it and the stages before it depend on."""
    data, out, acc = config.to_dict(), {}, []
    camera_model = {k: data["solver"][k] for k, default in _CAMERA_MODEL.items() if data["solver"][k] != default}
    for section, defaults in _LATER_DEFAULTS.items():
        for key, value in defaults.items():
            if data[section][key] == value:
                del data[section][key]
    for stage in STAGES:
        acc += [data[s] for s in _STAGE_SECTIONS[stage]]
        if stage == "world" and camera_model:
            acc.append({"camera_model": camera_model})
        out[stage] = hashlib.sha256(json.dumps(acc, sort_keys=True).encode()).hexdigest()[:16]
    return out


def run_pipeline(capture_dir: str | Path, out: str | Path, config: RunConfig = RunConfig(), *,
                 log: Callable[[str], None] = print, stop_after: str | None = None,
                 executor: Executor | None = None) -> dict:
    """Run (or resume) every stage; return the run log's content.

    Args:
        capture_dir: the capture folder (read only), or a :class:`~bcmocap.frontend.Capture` read from it.
        out: the output folder (created; stages found finished there are reused).
        config: the settings (saved as ``DIR/config.json``).
        log: receives one line per event (also appended to ``DIR/log.txt``).
        stop_after: stop after this stage (for inspection, or to split a long run).
        executor: where independent work runs (:mod:`~bcmocap.pipeline.cluster`; ``bcmocap batch`` shares
            one between captures); default: the cluster of ``config.cluster.address``, opened for this run.

    Raises:
        ValueError: an unreadable capture, a missing subject description, bad settings; naming the
            file or field.
        RuntimeError: JAX is not in float64 (call :func:`bcmocap.enable_float64` first): the capture's
            camera models and every stage compute in it.
    """
    from ..frontend.capture import Capture, read_capture
    from ..precision import require_float64

    require_float64("bcmocap.pipeline.run_pipeline")

    from ..solver.objective import import_term_factory

    if stop_after is not None and stop_after not in STAGES:
        raise ValueError(f"stop_after must be one of {STAGES}, got {stop_after!r}")
    for user in config.solver.user_terms:  # a user term that cannot be imported fails now, not after the frontend
        import_term_factory(user.factory)
    capture = capture_dir if isinstance(capture_dir, Capture) else read_capture(capture_dir)
    out = Path(out)
    check_outside(out, capture.path)
    out.mkdir(parents=True, exist_ok=True)
    with locked_output(out, wait_s=LOCK_WAIT_S), contextlib.ExitStack() as stack:
        if executor is None:
            executor = stack.enter_context(open_executor(config.cluster.address, log=log))
        return _run_stages(capture, out, config, log, stop_after, executor)


def _append_line(path: Path, line: str) -> None:
    """Append one line to ``path``, refusing to follow a symlink placed there."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    except OSError as err:
        if path.is_symlink():
            raise ValueError(f"{path}: is a symlink; the run log is only written to a plain file") from None
        raise
    with os.fdopen(fd, "a") as fh:
        fh.write(line + "\n")


def _run_stages(capture, out: Path, config: RunConfig, log: Callable[[str], None], stop_after: str | None,
                executor: Executor) -> dict:
    """:func:`run_pipeline` once the output folder is locked."""
    run_log = RunLog(out, capture.path)
    log_file = out / "log.txt"

    def say(line: str) -> None:
        log(line)
        _append_line(log_file, f"{datetime.datetime.now().isoformat(timespec='seconds')} {line}")

    ctx = RunContext(capture, config, out, say, executor)
    if not run_log.finished("skeleton", fingerprints(config)["skeleton"]):
        _topology(ctx)  # a capture without its subject description fails now, not after the frontend
        _rest_seconds(ctx)
    write_json_atomic(out / "config.json", config.to_dict())
    prints = fingerprints(config)
    stamps = file_stamps(capture.path)
    redo_from, drop_caches, why = stage_to_redo(changed_files(run_log.data.get("capture_files", stamps), stamps),
                                                frontend_reads_gyros=config.frontend.rolling_shutter_readout > 0)
    if why:
        say(why)
    if drop_caches:  # the frontend's caches were computed from other pictures or lenses
        for cache in _MEDIA_CACHES:
            shutil.rmtree(out / cache, ignore_errors=True)
    run_log.data["capture_files"] = stamps
    redo = False
    for i, stage in enumerate(STAGES, start=1):
        redo = redo or stage == redo_from
        missing = [name for name in _expected_outputs(stage, config) if not (out / name).exists()]
        if not redo and run_log.finished(stage, prints[stage]) and not missing:
            say(f"[{i}/{len(STAGES)}] {stage}: done before, reused")
        else:
            if not redo and run_log.finished(stage, prints[stage]):
                say(f"[{i}/{len(STAGES)}] {stage}: {out / missing[0]} is missing, redoing it and the stages after it")
            elif not redo and stage in run_log.data["stages"]:
                say(f"[{i}/{len(STAGES)}] {stage}: settings changed, redoing it and the stages after it")
            redo = True
            run_log.forget_from(stage)
            if STAGES.index(stage) < STAGES.index("solve"):  # the solve's checkpoint stood on what this stage redoes
                for name in ("checkpoint.json", "checkpoint.npz"):
                    (out / "solve" / name).unlink(missing_ok=True)
            say(f"[{i}/{len(STAGES)}] {stage} ...")
            clock = time.perf_counter()
            measured = reset_peak()
            try:
                extra = _STAGE_FUNCTIONS[stage](ctx) or {}
            except Exception as exc:
                run_log.check_folder()  # an output folder deleted under the run explains whatever failed after
                if out_of_memory(exc):  # an allocation that failed: say which setting lowers this stage's memory
                    raise stage_out_of_memory(stage, exc) from None
                raise
            seconds = time.perf_counter() - clock
            _check_capture(ctx, stamps)
            memory = {"peak_mb": peak_mb()} if measured else {"peak_mb_since_start": peak_mb()}
            run_log.record(stage, prints[stage], seconds, **extra, **memory)
            say(f"[{i}/{len(STAGES)}] {stage}: {seconds:.1f} s")
        if stage == stop_after:
            break
    return run_log.data


#: Notes kept beside a capture: their changes redo nothing.
_NOTE_SUFFIXES = (".md",)
#: Data files under ``trials/`` or ``ground_truth/`` (an IMU recording, a user term's measurements, the truth), read
#: after the frontend: a change redoes the stages after it (or, where the frontend reads the gyros, every stage with
#: its caches kept).
_DATA_SUFFIXES = (".npz", ".csv", ".txt")
_DATA_FOLDERS = ("trials/", "ground_truth/")
#: The capture's descriptions (rig, manifest): a change redoes every stage, the frontend reusing what it computed
#: from the recordings where its settings are the same. Any other file (videos, photos, sound, lens files, a file of
#: an unknown kind) drops the frontend's caches.
_DESCRIPTION_FILES = (RIG_FILE, MANIFEST_FILE)
#: What the frontend computed from the recordings (its features and tracks too), under ``DIR``.
_MEDIA_CACHES = ("frontend",)


def stage_to_redo(changes: list[str], frontend_reads_gyros: bool = False) -> tuple[str | None, bool, str]:
    """After these :func:`changed_files` of its capture, the first stage a rerun redoes, whether the frontend's caches
    go, and the line that says why; ``(None, False, "")`` when nothing is redone.

    A recording (video, photo, sound), a lens file or a file of an unknown kind: every stage, the caches dropped. The
    rig or the manifest: every stage, the caches kept (the frontend reuses a trial registered with the same
    settings). A data file under ``trials/`` or ``ground_truth/`` (``.npz``, ``.csv``, ``.txt``): the stages after the
    frontend, or every stage with the caches kept where the frontend reads the gyros (``frontend_reads_gyros``: a
    rolling-shutter readout; a trial whose gyros changed is registered again). Notes (``.md``): nothing."""
    changed = [c for c in changes if Path(_name(c)).suffix.lower() not in _NOTE_SUFFIXES]
    data = [c for c in changed if _name(c).startswith(_DATA_FOLDERS) and Path(_name(c)).suffix.lower() in _DATA_SUFFIXES]
    described = [c for c in changed if _name(c) in _DESCRIPTION_FILES]
    others = [c for c in changed if c not in data and c not in described]
    if others:
        return STAGES[0], True, (f"the capture's recordings or lens files changed since the last run ({_some(others)}): "
                                 "redoing every stage, the frontend's caches included")
    if described:
        return STAGES[0], False, (f"the capture's rig or manifest changed since the last run ({_some(described)}): "
                                  "redoing every stage (the frontend reuses what it registered with the same settings)")
    if data and frontend_reads_gyros:
        return STAGES[0], False, (f"the capture's data files changed since the last run ({_some(data)}): redoing every "
                                  "stage (the frontend registers again a trial whose gyros changed)")
    if data:
        return STAGES[1], False, (f"the capture's data files changed since the last run ({_some(data)}): redoing the "
                                  "stages after the frontend")
    return None, False, ""


def _name(change: str) -> str:
    """The file of one :func:`changed_files` phrase (``"NAME (modified, …)"``), relative to the capture."""
    return change.rsplit(" (", 1)[0]


def _some(changes: list[str]) -> str:
    return f"{', '.join(changes[:3])}{', ...' if len(changes) > 3 else ''}"


def _check_capture(ctx: RunContext, stamps: dict) -> None:
    """``ValueError`` (one line) when a file of the capture changed since the run began."""
    changed = changed_files(stamps, file_stamps(ctx.capture.path))
    if changed:
        raise ValueError(f"{ctx.capture.path}: {changed[0]}{f' and {len(changed) - 1} more' if len(changed) > 1 else ''}"
                         " changed while the run was reading the capture; the stages finished before are kept: rerun "
                         "the same command once the capture is complete (what was computed from changed recordings "
                         "is redone)")


# ---- stages -------------------------------------------------------------------------------------
def _stage_frontend(ctx: RunContext) -> dict:
    """Both trials registered (reused when saved with the same settings); on a cluster side by side, each
    handing its cameras and chunks to the cluster as tasks. With ``frontend.self_calibration`` a first
    registration (``DIR/frontend/calibration_pass/``) gives each camera's lens correction
    (``DIR/frontend/intrinsics.npz``), and the trials are registered again through the corrected lenses."""
    f = ctx.config.frontend
    missing = [t for t in ("rom", "capture") if t not in ctx.capture.trials]
    if missing:
        raise ValueError(f"{ctx.capture.path}: no trial {missing[0]!r} (bcmocap run needs 'rom' and 'capture')")
    if f.rolling_shutter_readout > 0:  # before anything runs
        from ..frontend.rolling_shutter import check_readout

        check_readout(f.rolling_shutter_readout, ctx.capture.fps)
    correction_path = ctx.path("frontend", "intrinsics.npz")
    if not f.self_calibration:
        correction_path.unlink(missing_ok=True)
        reports = _register_trials(ctx, ctx.capture, ctx.path("frontend"))
    else:
        given = {"given_lenses": ctx.capture.lens_fingerprint()}  # edited intrinsics files redo both passes
        _register_trials(ctx, ctx.capture, ctx.path("frontend", "calibration_pass"), given)
        correction = _lens_correction(ctx, ctx.path("frontend", "calibration_pass"))
        write_npz(correction_path, correction=correction, cameras=np.array(ctx.capture.camera_names))
        # the correction rounded: a redone fit may differ in the last bits, which should not redo the registration
        reports = _register_trials(ctx, _frontend_capture(ctx), ctx.path("frontend"),
                                   {**given, "lens_correction": np.round(correction, 6).tolist()})
    return {trial: {"registered_fraction": reports[trial]["registered_fraction"], "frames": reports[trial]["frames"]}
            for trial in ("rom", "capture")}


def _register_trials(ctx: RunContext, capture, folder: Path, extra: dict | None = None) -> dict:
    """Both trials of ``capture`` registered into ``folder`` (each reused when saved there with the same settings,
    ``extra`` included): the trials' registration reports."""
    from concurrent.futures import ThreadPoolExecutor

    from ..frontend.command import TrialOptions, prepare_reference, process_trial
    from ..frontend.register import reference_index
    from ..frontend.rolling_shutter import gyro_fingerprint

    f = ctx.config.frontend
    reports, todo = {}, []
    if f.rolling_shutter_readout > 0 and f.gyro_timing == "frames":  # both trials' gyros set each one's timing
        extra = (extra or {}) | {"gyros_timed_together": {t: gyro_fingerprint(capture, t) for t in ("rom", "capture")}}
    for trial, stride, homographies in (("rom", f.rom_stride, False), ("capture", f.stride, True)):
        done = folder / trial / "registration.json"
        options = TrialOptions(stride=stride, frames=f.frames or None, max_features=f.max_features,
                               homographies=homographies, chunk_frames=f.chunk_frames, registration=f.registration,
                               max_measurements=f.max_measurements or None, points=f.points,
                               rolling_shutter_readout=f.rolling_shutter_readout, gyro_timing=f.gyro_timing,
                               estimate_readout=f.estimate_readout)
        gyro = gyro_fingerprint(capture, trial) if f.rolling_shutter_readout > 0 else None
        settings = options.saved_settings(gyro) | (extra or {})
        if done.is_file() and (folder / trial / "correspondences" / "index.json").is_file():
            report = read_json(done)
            if report.get("settings") == settings:
                ctx.log(f"{trial}: registration found in {done}, reused")
                reports[trial] = report
                continue
        todo.append((trial, options))
    if todo:
        index = reference_index(prepare_reference(capture, folder / "reference", log=ctx.log))
        map_tasks = ctx.executor.map if ctx.executor.distributed else None
        timings = _gyro_timings(ctx, capture) if f.rolling_shutter_readout > 0 and f.gyro_timing == "frames" else {}

        def register(trial: str, options: TrialOptions) -> dict:
            return process_trial(capture, index, trial, folder, options=options, extra_settings=extra, log=ctx.log,
                                 map_tasks=map_tasks, gyro_timing=timings.get(trial))

        with ThreadPoolExecutor(max_workers=len(todo) if map_tasks is not None else 1) as pool:
            for (trial, *_), report in zip(todo, pool.map(lambda job: register(*job), todo)):
                reports[trial] = report
    return reports


def _gyro_timings(ctx: RunContext, capture) -> dict:
    """Both trials' gyro timing found in their frames together (:func:`~bcmocap.frontend.gyro_timing.timing_of_trials`:
    one readout for the capture's cameras, a shift per camera and trial), whichever trial is registered now, so a
    trial's timing does not depend on which was saved before."""
    from ..frontend.command import trial_frames
    from ..frontend.gyro_timing import timing_of_trials
    from ..frontend.sync import synchronize

    f = ctx.config.frontend
    syncs = {trial: synchronize(capture, trial) for trial in ("rom", "capture")}
    ctx.log(f"gyro timing: finding each camera's gyro time shift{' and the readout' * f.estimate_readout} in both trials' frames")
    return timing_of_trials(capture, {t: sync.offsets for t, sync in syncs.items()}, f.rolling_shutter_readout,
                            spans={t: trial_frames(capture, t, sync, f.frames or None) for t, sync in syncs.items()},
                            estimate_readout=f.estimate_readout, log=ctx.log)


def readouts_in_frames(readout_s: float, stores) -> list[float]:
    """``solver.rolling_shutter_readout`` (s) in each trial's frame periods (the processed frames: fps / stride).

    Raises:
        ValueError: naming the setting, when it spans more than 2 of a trial's frame periods (the camera's velocity
            is taken from the neighbouring frames, which then no longer bracket the rows' times).
    """
    out = [readout_s * store.fps for store in stores]
    for store, frames in zip(stores, out):
        if frames > 2.0:
            raise ValueError(f"solver.rolling_shutter_readout = {readout_s:g} s spans {frames:.3g} frame periods of "
                             f"the {store.fps:g} fps processed frames (frontend stride); at most 2 are modelled")
    return out


def _lens_correction(ctx: RunContext, folder: Path) -> np.ndarray:
    """``(C, 3)`` each camera's lens correction (log focal scale, Δcx, Δcy px) from both trials registered in
    ``folder``: their registered poses and the lenses re-fitted together, the reference points held
    (:func:`~bcmocap.solver.registered_poses.refine_trials`; the solver's readout, if any, modelled)."""
    from ..correspondence_store import CorrespondenceStore
    from ..solver.registered_poses import PoseRefinementOptions, refine_trials

    stores = [CorrespondenceStore.open(folder / trial / "correspondences") for trial in ("rom", "capture")]
    readout = ctx.config.solver.rolling_shutter_readout
    results = refine_trials(stores, _given_intrinsics(ctx, corrected=False), PoseRefinementOptions(calibrate=True),
                            readouts=readouts_in_frames(readout, stores))
    correction = np.asarray(results[0].intrinsics_correction, np.float64)
    ctx.log("frontend: lens correction from the first registration: focal scale "
            f"{100 * (np.exp(correction[:, 0].min()) - 1):+.2f} to {100 * (np.exp(correction[:, 0].max()) - 1):+.2f} %, "
            f"centre moved up to {np.abs(correction[:, 1:]).max():.2f} px; registering again through the corrected lenses")
    return correction


def _frontend_capture(ctx: RunContext):
    """The capture as the frontend registered it: with the lenses it corrected (``frontend.self_calibration``),
    else as given."""
    from ..cameras import camera_at
    from ..residuals.self_calibration import corrected_cameras

    path = ctx.path("frontend", "intrinsics.npz")
    if not ctx.config.frontend.self_calibration:
        return ctx.capture
    if not path.is_file():
        raise ValueError(f"{path}: missing: the lens correction of frontend.self_calibration (delete DIR/run.json's "
                         "frontend stage, or the whole run, to redo it)")
    with np.load(path) as data:
        correction, names = data["correction"], [str(n) for n in data["cameras"]]
    if names != list(ctx.capture.camera_names):
        raise ValueError(f"{path}: lens corrections of cameras {names}, the capture has {list(ctx.capture.camera_names)}")
    lenses = corrected_cameras(_given_intrinsics(ctx, corrected=False), correction)
    return ctx.capture.with_lenses([camera_at(lenses, i) for i in range(len(names))])


def _subject(ctx: RunContext) -> dict:
    subject = ctx.capture.manifest.get("subject")
    where = ctx.capture.path / "capture.json"
    if not isinstance(subject, dict):
        raise ValueError(f"{where}: no 'subject' entry (topology, measurements, rest) to estimate the skeleton")
    for key in ("topology", "measurements"):
        if key not in subject:
            raise ValueError(f"{where}: subject.{key} is missing")
    return subject


def _topology(ctx: RunContext):
    from ..kinematics.rom import Topology

    where = ctx.capture.path / "capture.json"
    try:
        return Topology.from_segments([(n, p, t) for n, p, t in _subject(ctx)["topology"]])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: subject.topology: {exc}") from None


def _rest_seconds(ctx: RunContext) -> tuple[float, float]:
    """The rest pose's ``[from, to)`` (s after the ROM trial's first clap): the config's, else the capture's."""
    if ctx.config.skeleton.rest_seconds:
        return tuple(ctx.config.skeleton.rest_seconds)
    rest = _subject(ctx).get("rest", {})
    try:
        start, stop = (float(x) for x in rest["after_first_clap_s"])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{ctx.capture.path / 'capture.json'}: subject.rest.after_first_clap_s missing or not "
                         "[from, to]; give skeleton.rest_seconds in a config file") from None
    return start, stop


def _rom_inputs(ctx: RunContext):
    """ROM trial camera poses (reference frame), registered mask, rest-frame mask."""
    from ..correspondence_store import CorrespondenceStore

    corr = CorrespondenceStore.open(ctx.path("frontend", "rom", "correspondences"))
    rest_s = _rest_seconds(ctx)
    frames = np.arange(corr.num_frames) / corr.fps
    rest = (frames >= rest_s[0]) & (frames < rest_s[1])
    if rest.sum() < 2:
        raise ValueError(f"rest pose {list(rest_s)} s after the first clap covers {int(rest.sum())} ROM frames "
                         f"at {corr.fps:g} fps; need at least 2")
    return *_registered_poses(ctx, "rom", corr), rest


def _registered_poses(ctx: RunContext, trial: str, corr) -> tuple[np.ndarray, np.ndarray]:
    """A trial's registered camera poses ``(T, C, 7)`` (reference model frame) and mask ``(T, C)``: as the
    ``world`` stage re-fitted them (``DIR/world/registered/<trial>.npz``), else as the frontend registered them
    (its store ``corr``)."""
    path = ctx.path("world", "registered", f"{trial}.npz")
    if not path.is_file():
        return corr.world_from_camera, corr.registered
    with np.load(path) as data:
        return data["world_from_camera"], data["registered"].astype(bool)


def _refine_registered_poses(ctx: RunContext) -> None:
    """Both trials' registered camera poses re-fitted under the solver's camera model
    (:func:`~bcmocap.solver.registered_poses.refine_trials`: ``solver.rolling_shutter_readout``, and with
    ``solver.self_calibration`` each camera's intrinsics, estimated with both trials and kept for the rig) into
    ``DIR/world/registered/`` (``<trial>.npz``, ``intrinsics.npz``, ``summary.json``); with neither, the folder is
    removed and the frontend's poses are used as they are."""
    import shutil

    from ..correspondence_store import CorrespondenceStore
    from ..solver.registered_poses import PoseRefinementOptions, refine_trials

    s = ctx.config.solver
    folder = ctx.path("world", "registered")
    shutil.rmtree(folder, ignore_errors=True)
    if not (s.rolling_shutter_readout > 0 or s.self_calibration):
        return
    trials = ("rom", "capture")
    stores = [CorrespondenceStore.open(ctx.path("frontend", trial, "correspondences")) for trial in trials]
    options = PoseRefinementOptions(calibrate=s.self_calibration)
    results = refine_trials(stores, _given_intrinsics(ctx), options,  # the readout in each trial's frame periods
                            readouts=readouts_in_frames(s.rolling_shutter_readout, stores))
    if s.self_calibration:
        write_npz(folder / "intrinsics.npz", correction=results[0].intrinsics_correction)
    summary = {}
    for trial, store, result in zip(trials, stores, results):
        write_npz(folder / f"{trial}.npz", world_from_camera=result.world_from_camera, registered=store.registered)
        rms = np.nanmedian(result.rms_px, axis=0) if np.isfinite(result.rms_px).any() else np.full(2, np.nan)
        summary[trial] = {"refined_frames": int(result.refined.sum()), "registered_frames": int(store.registered.sum()),
                          "iterations": result.iterations,
                          "median_camera_rms_px": {"before": _finite_or_none(rms[0]), "after": _finite_or_none(rms[1])}}
        ctx.log(f"world: {trial}: {int(result.refined.sum())} of {int(store.registered.sum())} registered camera-frames "
                f"re-fitted under the solver's camera model in {result.iterations} steps (median camera rms {rms[0]:.2f} → "
                f"{rms[1]:.2f} px); the others have fewer than {options.min_measurements} measurements and keep theirs")
    summary["intrinsics_correction"] = results[0].intrinsics_correction.tolist() if s.self_calibration else None
    write_json_atomic(folder / "summary.json", summary)


def _more_trials(ctx: RunContext, to_world: Similarity) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera poses and registered masks of the trials besides the ROM trial in ``skeleton.centre_trials``
    (through ``to_world``, as the ROM trial's), their slips onto a repeated pattern's copy repaired as the initial
    stage repairs them (:func:`~bcmocap.pipeline.slips.repair_slips`, with ``to_world``'s scale)."""
    from ..correspondence_store import CorrespondenceStore

    out = []
    for trial in ctx.config.skeleton.centre_trials[1:]:
        store = CorrespondenceStore.open(ctx.path("frontend", trial, "correspondences"))
        repair = repair_slips(*_registered_poses(ctx, trial, store), store.fps, to_world.scale)
        out.append((to_world.poses(repair.world_from_camera), repair.registered))
    return out


def _estimate_skeleton(ctx: RunContext, to_world: Similarity, poses, registered, rest, log=None, up=None):
    """Skeleton and mounts from the ROM trial (camera poses through ``to_world``), its joint centres fitted to the
    motion of ``skeleton.centre_trials``; ``up``: ``(3,)`` the up of ``to_world``'s frame where it has one (the metric
    Z-up world: a joint or rest orientation mirrored from its other side is then mirrored through a vertical midplane),
    None for the world stage's provisional frame (the reference model's axes). Pixel-registered poses are noisier than the 2 cm default certainty of
    :class:`~bcmocap.kinematics.rom.RomOptions` allows for a small joint like the ankle (3.0 cm for the left ankle
    of a rendered 3 s trial), hence ``skeleton.max_centre_std_cm`` (5 cm)."""
    from ..kinematics.rom import RomOptions, skeleton_from_range_of_motion

    cams = [(c.name, c.segment) for c in ctx.capture.cameras]
    settings = ctx.config.skeleton
    options = RomOptions(max_centre_std_m=settings.max_centre_std_cm / 100, degenerate=settings.degenerate,
                         unregistered_ends=settings.unregistered_ends, unregistered_rest=settings.unregistered_rest)
    log = ctx.log if log is None else log
    carried = _gyro_rest_orientations(ctx, poses, registered, rest, log)
    if carried is not None:  # the similarity turns orientations as it turns poses
        carried = to_world.poses(np.concatenate([carried, np.zeros((len(carried), 3))], axis=1)[None])[0, :, :4]
    more_trials = _more_trials(ctx, to_world)
    siblings = _sibling_rotations_from_gyros(ctx, [("rom", poses, registered)] + [
        (trial, p, r) for trial, (p, r) in zip(settings.centre_trials[1:], more_trials)], options.min_frames, log)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            estimate = skeleton_from_range_of_motion(
                _topology(ctx), cams, to_world.poses(poses), registered, rest_frames=rest, options=options,
                intrinsics=_stacked_intrinsics(ctx), root_origin=list(settings.root_origin),
                more_trials=more_trials, rest_orientations=carried, sibling_rotations=siblings, up=up)
    except ValueError as exc:
        raise ValueError(f"{exc} (run settings: [skeleton] max_centre_std_cm = {settings.max_centre_std_cm:g}, "
                         f"degenerate = {settings.degenerate!r}, centre_trials = {list(settings.centre_trials)}, "
                         f"unregistered_ends = {settings.unregistered_ends!r}, "
                         f"unregistered_rest = {settings.unregistered_rest!r})") from None
    for warning in caught:  # in the run's log, where a user reads what the skeleton stage assumed
        log(f"skeleton: {warning.message}")
    return estimate


def _sibling_rotations_from_gyros(ctx: RunContext, trials, min_frames: int, log) -> dict:
    """For each camera registered in no frame of the ``trials`` (``[(name, world_from_camera, registered)]``) whose
    segment has a camera registered in ``min_frames``, its rotation from that camera, from its gyro in the trials'
    ``imu.npz`` on the clock the frontend's gyro timing found
    (:func:`~bcmocap.pipeline.gyro_turns.rotations_from_siblings_by_gyro`; each one ``log``-ged): the
    ``sibling_rotations`` of :func:`~bcmocap.kinematics.rom.skeleton_from_range_of_motion`. Empty without gyros."""
    from ..correspondence_store import CorrespondenceStore
    from ..io.sensors import read_imu
    from .gyro_turns import rotations_from_siblings_by_gyro

    names = [c.name for c in ctx.capture.cameras]
    segments = [c.segment for c in ctx.capture.cameras]
    counts = sum(np.asarray(r, bool).sum(axis=0) for _, _, r in trials)
    nowhere = np.array([counts[i] == 0 and any(counts[k] >= min_frames for k in range(len(names))
                                               if segments[k] == segments[i]) for i in range(len(names))])
    recorded = [(trial, p, r) for trial, p, r in trials if (ctx.capture.path / "trials" / trial / "imu.npz").is_file()]
    if not nowhere.any() or not recorded:
        return {}
    inputs = []
    for trial, p, r in recorded:
        timing = _gyro_shifts(ctx, trial)
        fps = CorrespondenceStore.open(ctx.path("frontend", trial, "correspondences")).fps
        inputs.append((p, r, fps, read_imu(ctx.capture.path / "trials" / trial / "imu.npz"),
                       np.zeros(len(names)) if timing is None else timing[0]))
    placed, report = rotations_from_siblings_by_gyro(inputs, names, segments, nowhere)
    for name, r in report.items():
        how = "sits" if r["placed"] else "does not sit (its turns' axes too alike, or too few)"
        log(f"skeleton: camera '{name}' is registered in no frame; by its gyro it {how} relative to '{r['sibling']}': "
            f"{r['pairs']} turns, median residual {r['residual_deg']:.2f}°, axes' spread {r['spread']:.2f}")
    return placed


def _gyro_rest_orientations(ctx: RunContext, poses, registered, rest, log) -> np.ndarray | None:
    """``(C, 4)`` the rest orientations (reference model frame) of the cameras of the ROM trial's segments that no rest
    frame registered, carried there by their gyros (:func:`~bcmocap.pipeline.gyro_turns.rest_orientations_from_gyros`,
    on the gyro's clock as the frontend's gyro timing found it; each one ``log``-ged), NaN for the others; None when
    every segment registered at rest or the trial has no ``imu.npz``."""
    from ..correspondence_store import CorrespondenceStore
    from ..io.sensors import read_imu
    from .gyro_turns import rest_orientations_from_gyros

    path = ctx.capture.path / "trials" / "rom" / "imu.npz"
    segments = np.array([c.segment for c in ctx.capture.cameras])
    at_rest = registered[rest].any(axis=0)
    unplaced = np.array([not at_rest[segments == s].any() for s in segments])  # per camera: its segment, nowhere at rest
    if not unplaced.any() or not path.is_file():
        return None
    timing = _gyro_shifts(ctx, "rom")
    names = [c.name for c in ctx.capture.cameras]
    fps = CorrespondenceStore.open(ctx.path("frontend", "rom", "correspondences")).fps
    carried, report = rest_orientations_from_gyros(poses, registered, rest, fps, read_imu(path), names,
                                                   None if timing is None else timing[0], cameras=unplaced)
    for name, r in report.items():
        log(f"skeleton: camera '{name}' is registered in no rest frame of the range-of-motion trial; its gyro carries "
            f"its rest orientation from {r['frames']} registered frames (the nearest {r['nearest_s']:.2f} s away; "
            f"their median spread {r['spread_deg']:.2f}°)")
    return carried


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _given_intrinsics(ctx: RunContext, corrected: bool = True):
    """The cameras' stacked intrinsics the frontend registered through (the capture's, corrected by the frontend
    with ``frontend.self_calibration``; the capture's own with ``corrected=False``)."""
    from ..cameras import stack_cameras

    capture = _frontend_capture(ctx) if corrected else ctx.capture
    return stack_cameras([c.intrinsics for c in capture.cameras])


def _stacked_intrinsics(ctx: RunContext):
    """The rig's intrinsics: the capture's, corrected as the ``world`` stage estimated (self-calibration)."""
    from ..residuals.self_calibration import corrected_cameras

    cameras = _given_intrinsics(ctx)
    path = ctx.path("world", "registered", "intrinsics.npz")
    if not path.is_file():
        return cameras
    with np.load(path) as data:
        return corrected_cameras(cameras, data["correction"])


def _stage_world(ctx: RunContext) -> dict:
    from ..kinematics.ik import motion_from_camera_poses
    from .world import Similarity, scale_from_measurements, upright_frame

    _refine_registered_poses(ctx)
    poses, registered, rest = _rom_inputs(ctx)
    if not registered.any():
        raise ValueError(f"world: the frontend registered no camera-frame of the range-of-motion trial (see "
                         f"{ctx.path('frontend', 'rom', 'registration.json')}): the scene did not match the reference "
                         f"model")
    # A provisional scale (a body ~1.7 m across its cameras) only brings the estimator's thresholds, in
    # metres, to the right order; the measurements then fix the scale.
    centres = poses[rest][..., 4:]
    spans = [np.nanmax(np.linalg.norm(c[:, None] - c[None], axis=-1)) for c in centres
             if np.isfinite(c).all(axis=-1).sum() >= 2]
    if not spans or float(np.median(spans)) <= 0:
        raise ValueError("world: no rest frame with two registered cameras in the range-of-motion trial")
    provisional = Similarity(1.7 / float(np.median(spans)), np.eye(3), np.zeros(3))
    root = _topology(ctx).names[0]
    root_cameras = [i for i, c in enumerate(ctx.capture.cameras) if c.segment == root]
    if not registered[rest][:, root_cameras].any():
        raise ValueError(f"world: no camera of the root segment '{root}' ({', '.join(ctx.capture.cameras[i].name for i in root_cameras)}) "
                         f"is registered in the rest frames of the range-of-motion trial ({list(_rest_seconds(ctx))} s "
                         "after the first clap), which set the world's up direction and floor")
    est = _estimate_skeleton(ctx, provisional, poses, registered, rest, log=lambda text: None)  # logged by the skeleton stage
    measurements = _subject(ctx)["measurements"]
    factor = scale_from_measurements(est.skeleton, measurements, f"{ctx.capture.path / 'capture.json'}: subject.measurements")
    rest_motion = motion_from_camera_poses(est.skeleton, est.rig, provisional.poses(poses)[rest], registered[rest], robust=True)
    k = ctx.config.skeleton
    upright = upright_frame(est.skeleton, rest_motion, k.up_from, k.up_to, factor)
    sim = provisional.then(upright)
    write_json_atomic(ctx.out / SIMILARITY, {
        **sim.to_dict(), "maps": "reference model frame → metric world (m, Z up, origin on the floor under the rest pose)",
        "provisional_scale": provisional.scale, "measurement_factor": factor})
    ctx.log(f"world: {sim.scale:.4g} m per reference-model unit (measurements × {factor:.3f} on the provisional scale)")
    return {"metres_per_unit": sim.scale}


def _stage_skeleton(ctx: RunContext) -> dict:
    from ..io.model_json import rig_to_dict, skeleton_to_dict
    from .world import load_similarity

    poses, registered, rest = _rom_inputs(ctx)
    est = _estimate_skeleton(ctx, load_similarity(ctx.out), poses, registered, rest, up=np.array([0.0, 0.0, 1.0]))
    write_json_atomic(ctx.path("model", "skeleton.json"), skeleton_to_dict(est.skeleton))
    write_json_atomic(ctx.path("model", "rig.json"), rig_to_dict(est.rig, est.skeleton))
    with atomic_path(ctx.path("model", "rom_summary.txt"), suffix=".txt") as tmp:
        tmp.write_text(est.summary() + "\n")
    ctx.log("skeleton:\n" + est.summary())
    return {"segments": len(est.skeleton.names), "cameras": len(est.rig.names)}


def _stage_initial(ctx: RunContext) -> dict:
    from ..correspondence_store import CorrespondenceStore
    from ..kinematics.ik import motion_from_camera_poses
    from .world import load_similarity

    sim = load_similarity(ctx.out)
    corr = CorrespondenceStore.open(ctx.path("frontend", "capture", "correspondences"))
    poses, registered = _registered_poses(ctx, "capture", corr)
    repair = _repaired_slips(ctx, poses, registered, corr.fps, sim.scale)
    metric = corr.transformed(ctx.path("solve", "correspondences"), sim.points, sim.poses,
                              world_from_camera=repair.world_from_camera, registered=repair.registered,
                              dropped=repair.changed)
    skeleton, rig = load_model(ctx.out)
    poses, oriented = _gyro_filled_poses(ctx, rig, metric.world_from_camera, metric.registered, corr.fps)
    initial = motion_from_camera_poses(skeleton, rig, poses, metric.registered | oriented, robust=True)
    save_motion(ctx.path("solve", "initial.npz"), initial)
    return {"frames": metric.num_frames, "registered_fraction": float(metric.registered.mean()),
            "gyro_filled_fraction": float(oriented.mean()), "slips": len(repair.slips),
            "slipped_camera_frames_moved": int(repair.moved.sum()),
            "slipped_camera_frames_left_out": int(repair.left_out.sum())}


def _repaired_slips(ctx: RunContext, poses: np.ndarray, registered: np.ndarray, fps: float,
                    metres_per_unit: float) -> SlipRepair:
    """The capture's registrations with the body's and each camera's slips onto a repeated pattern's copy undone
    (:func:`~bcmocap.pipeline.slips.repair_slips`), each ``log``-ged; the solve reads no measurement of a camera-frame
    moved or left out (it was made on the copy)."""
    repair = repair_slips(poses, registered, fps, metres_per_unit)
    for slip in repair.slips:
        ctx.log(f"initial: capture: between frames {slip.frame - 1} and {slip.frame} {slip.cameras} cameras "
                f"registered in both jumped {100 * metres_per_unit * np.linalg.norm(slip.jump):.0f} cm together, "
                "further than a body moves (a repeated pattern's copy): the side with fewer registrations is moved back")
    if repair.changed.any():
        ctx.log(f"initial: capture: {int(repair.moved.sum())} registered camera-frames moved back from a slip onto a "
                f"repeated pattern's copy and {int(repair.left_out.sum())} left out as unregistered; the solve reads "
                "none of their measurements")
    return repair


def _gyro_filled_poses(ctx: RunContext, rig, poses, registered, fps) -> tuple[np.ndarray, np.ndarray]:
    """The capture trial's camera poses for the initial motion, with the orientations of the camera-frames no
    registration gave carried by the cameras' gyros (:func:`~bcmocap.pipeline.gyro_turns.fill_orientations_from_gyros`,
    on the gyro's clock as the frontend's gyro timing found it; their positions interpolated, which only the root's
    cameras' are read for, and those are not filled) where the frontend timed the gyros, and which camera-frames were
    filled ``(T, C)``. Without the timing or ``imu.npz``, the poses as given and none filled."""
    from ..io.sensors import read_imu
    from ..kinematics.ik import fill_gaps
    from .gyro_turns import fill_orientations_from_gyros

    none = np.zeros_like(registered)
    path = ctx.capture.path / "trials" / "capture" / "imu.npz"
    timing = _gyro_shifts(ctx)
    if timing is None or not path.is_file():
        return poses, none
    names = [c.name for c in ctx.capture.cameras]
    off_root = np.asarray(rig.segments) != 0
    filled_poses, filled = fill_orientations_from_gyros(poses, registered, fps, read_imu(path), names, timing[0],
                                                        cameras=off_root)
    for c in np.flatnonzero(filled.any(axis=0)):
        filled_poses[:, c, 4:] = fill_gaps(np.where(registered[:, c, None], poses[:, c, 4:], 0.0), registered[:, c],
                                           rotations=False)
    if filled.any():
        ctx.log(f"initial: {int(filled.sum())} unregistered camera-frames of {int(filled.any(axis=0).sum())} cameras "
                "oriented by their gyros from the registered frames around them")
    return filled_poses, filled


def objective_weights(s):
    """The :class:`~bcmocap.solver.objective.ObjectiveWeights` of a run's ``solver`` settings."""
    from ..solver.objective import ObjectiveWeights

    smooth = "smoothness" in s.terms
    return ObjectiveWeights(root_smoothness=s.root_smoothness if smooth else 0.0,
                            joint_smoothness=s.joint_smoothness if smooth else 0.0,
                            homography=s.homography, loss=s.loss, loss_scale=s.loss_scale,
                            registered_pose=(s.registered_pose[0], math.radians(s.registered_pose[1])),
                            registered_pose_below=s.registered_pose_below)


def camera_effects(s):
    """The :class:`~bcmocap.solver.objective.CameraEffects` of a run's ``solver`` settings."""
    from ..solver.objective import CameraEffects

    return CameraEffects(readout_seconds=s.rolling_shutter_readout, estimate_readout=s.estimate_readout,
                         estimate_time_offsets=s.estimate_time_offsets, self_calibration=s.self_calibration,
                         mount_sigma=(s.mount_compliance[0], math.radians(s.mount_compliance[1])))


def _user_terms(ctx: RunContext) -> list:
    """The ``[[solver.user_terms]]`` of the settings as :class:`~bcmocap.solver.objective.UserTerms`."""
    from ..solver.objective import UserTerms, import_term_factory

    return [UserTerms(import_term_factory(u.factory), u.settings, u.factory) for u in ctx.config.solver.user_terms]


def _unmeasured_orientation_terms(ctx: RunContext, skeleton, rig) -> list:
    """``[solver] unmeasured_orientation``: each camera-frame with neither a registration nor a measurement, on a
    segment no camera of which is measured there, held at the initial motion's orientation (``DIR/solve/initial.npz``:
    carried across the gap by the camera's gyro where it could be, else interpolated;
    :func:`~bcmocap.residuals.registered_pose.unmeasured_orientation_terms`)."""
    from ..kinematics.rig import camera_poses
    from ..residuals.registered_pose import unmeasured_orientation_terms
    from ..solver.objective import UserTerms

    s = ctx.config.solver
    if not s.unmeasured_orientation:
        return []
    poses = np.asarray(camera_poses(skeleton, rig, load_motion(ctx.path("solve", "initial.npz"))).wxyz_xyz)
    return [UserTerms(unmeasured_orientation_terms, {"world_from_camera": poses, "sigma_deg": s.unmeasured_orientation,
                                                     "loss": s.loss, "loss_scale": s.loss_scale}, "unmeasured orientation")]


def _gyro_terms(ctx: RunContext, trial_folder: Path) -> list:
    """``[solver] gyro_turn``: the cameras' gyro turns (:func:`~bcmocap.pipeline.gyro_turns.gyro_turns`), the solver's
    frame times read on the gyro's clock by the frontend's gyro timing: each camera at its own shift, or, where the
    solver estimates each camera's time offset (its exposure after the frame times), every camera at the shifts'
    mean, which the offsets are centred on (:func:`gyro_time_offsets`): the solver's poses are the body's at the frame
    times. Without the gyro timing, at the trial's times."""
    from ..solver.objective import UserTerms
    from .gyro_turns import gyro_turns

    sigma = ctx.config.solver.gyro_turn
    if not sigma:
        return []
    if not (trial_folder / "imu.npz").is_file():
        raise ValueError(f"{trial_folder / 'imu.npz'}: missing; [solver] gyro_turn needs the cameras' gyros")
    timing = _gyro_shifts(ctx)
    shifts = None
    if timing is not None:
        shifts, measured = timing
        if ctx.config.solver.estimate_time_offsets:  # the solver's frame times are the cameras' mean exposure
            shifts = np.full(len(shifts), shifts[measured].mean() if measured.any() else shifts.mean())
        shifts = shifts.tolist()
    return [UserTerms(gyro_turns, {"sigma_deg": sigma, "time_shifts_s": shifts}, "gyro turns")]


#: A homography match further than this many times ``[solver] gyro_turn`` (the gyro's σ) from where the camera's gyro
#: turn carries it is dropped (:func:`~bcmocap.pipeline.gyro_turns.homography_weights_gyros_agree_with`).
HOMOGRAPHY_GYRO_GATE = 2.0


def _gyro_homography_check(ctx: RunContext):
    """With ``[solver] gyro_turn`` and the homography term, the solve's homography filter: the matches a camera's
    gyro contradicts by more than :data:`HOMOGRAPHY_GYRO_GATE` σ dropped, each camera read at its own shift on the
    gyro's clock as the frontend timed it; else None."""
    import functools

    from .gyro_turns import homography_weights_gyros_agree_with

    s = ctx.config.solver
    if not s.gyro_turn or "homography" not in s.terms:
        return None
    timing = _gyro_shifts(ctx)
    shifts = None if timing is None else timing[0].tolist()
    return functools.partial(homography_weights_gyros_agree_with, tolerance_deg=HOMOGRAPHY_GYRO_GATE * s.gyro_turn,
                             time_shifts_s=shifts)


def _gyro_shifts(ctx: RunContext, trial: str = "capture") -> tuple[np.ndarray, np.ndarray] | None:
    """``(shifts (C,) s, determined (C,) bool)``: where the frontend's gyro timing put each camera's frames of
    ``trial`` on the gyro's clock after the trial's times, and which it determined; None when it did not time the
    gyros. ValueError (naming the file) when it holds a shift count other than the capture's cameras."""
    path = ctx.path("frontend", trial, "registration.json")
    timing = read_json(path).get("gyro_timing") if path.is_file() else None
    if timing is None:
        return None
    shifts = np.asarray(timing["time_shift_ms"], np.float64) / 1e3
    if shifts.shape != (len(ctx.capture.cameras),):
        raise ValueError(f"{path}: gyro_timing.time_shift_ms has {shifts.size} values for {len(ctx.capture.cameras)} "
                         "cameras")
    return shifts, np.asarray(timing.get("determined", [True] * len(shifts)), bool)


#: σ of the prior on a camera's time offset measured by its gyro (s): the gyro timing's error on the studio's walk
#: (benchmarks/results/gyro_timing.json) with margin.
GYRO_TIME_OFFSET_SIGMA_S = 0.001


def gyro_time_offsets(ctx: RunContext) -> tuple[np.ndarray, np.ndarray] | None:
    """``(offsets (C,) s, measured (C,) bool)``: each camera's exposure after the capture trial's frame times as its
    gyro timed it (the frontend's ``gyro_timing`` shifts, relative to the mean of those it determined: the IMU
    clock's offset is common, a common offset is a shift of the whole motion; a camera whose gyro it could not time
    is not measured, offset 0), or None when the frontend did not time the gyros from the frames."""
    timing = _gyro_shifts(ctx)
    if timing is None or not timing[1].any():
        return None
    shifts, measured = timing
    return np.where(measured, shifts - shifts[measured].mean(), 0.0), measured


def solve_problem(ctx: RunContext):
    """The solve stage's problem (:class:`~bcmocap.solver.objective.StoredProblem` on the run's metric store,
    ``DIR/solve/correspondences``, and the estimated model) and its :class:`~bcmocap.solver.SolverOptions`."""
    from ..correspondence_store import CorrespondenceStore
    from ..solver import SolverOptions
    from ..solver.objective import StoredProblem

    s = ctx.config.solver
    corr = CorrespondenceStore.open(ctx.path("solve", "correspondences"))
    skeleton, rig = load_model(ctx.out)
    effects = camera_effects(s)
    gyro = gyro_time_offsets(ctx) if s.estimate_time_offsets else None
    if gyro is not None:  # the prior is the gyro's where it measured, the default elsewhere
        offsets, measured = gyro
        sigma = np.where(measured, GYRO_TIME_OFFSET_SIGMA_S, effects.time_offset_sigma_seconds)
        effects = dataclasses.replace(effects, time_offsets_measured=tuple(offsets.tolist()),
                                      time_offset_sigma_seconds=tuple(sigma.tolist()))
    trial_folder = ctx.capture.path / "trials" / "capture"
    problem = StoredProblem(corr, skeleton, rig, objective_weights(s), include_homography="homography" in s.terms and None,
                            extra_terms=[*_gyro_terms(ctx, trial_folder), *_unmeasured_orientation_terms(ctx, skeleton, rig),
                                         *_user_terms(ctx)], trial_folder=trial_folder,
                            effects=effects, homography_filter=_gyro_homography_check(ctx))
    return problem, SolverOptions(window=s.window, overlap=s.overlap)


def _stage_solve(ctx: RunContext) -> dict:
    """The sliding-window solve; each window's measurements are read from the metric store on disk
    (:class:`~bcmocap.solver.objective.StoredProblem`), so memory does not grow with the trial."""
    from ..io.model_json import rig_to_dict, skeleton_to_dict
    from ..solver import refine_model, solve, solve_windows_independently
    from ..solver.solve import window_starts

    s = ctx.config.solver
    problem, options = solve_problem(ctx)
    corr, skeleton, rig = problem.store, problem.skeleton, problem.rig
    initial = load_motion(ctx.path("solve", "initial.npz"))
    checkpoint_path, reports_path = ctx.path("solve", "checkpoint.npz"), ctx.path("solve", "checkpoint.json")
    skip, reports, statics, frame_variables = 0, [], {}, {}
    if checkpoint_path.exists() and reports_path.exists():
        saved = read_json(reports_path)
        if saved.get("fingerprint") == fingerprints(ctx.config)["solve"]:
            initial = load_motion(checkpoint_path)
            statics, frame_variables = load_solved_variables(checkpoint_path)
            reports = saved["reports"]
            skip = len(reports)
            ctx.log(f"solve: resuming after window {skip} of {len(window_starts(corr.num_frames, min(s.window, corr.num_frames), s.overlap))}")

    first_statics = {}  # where a solve of the whole sequence starts its static variables
    if problem.effects.time_offsets_measured is not None:  # the time offsets where the gyros put them
        from ..residuals.rolling_shutter import TIME_OFFSET

        first_statics = {TIME_OFFSET: np.asarray(problem.effects.time_offsets_measured)[:, None] * corr.fps}
        if not statics:
            ctx.log(f"solve: time offsets start from the gyros' (prior σ {1e3 * GYRO_TIME_OFFSET_SIGMA_S:g} ms where "
                    f"timed): {np.round(np.asarray(problem.effects.time_offsets_measured) * 1e3, 2).tolist()} ms")
    statics = statics or first_statics

    def save(index, report, so_far):
        reports.append(dataclasses.asdict(report))
        save_motion(checkpoint_path, so_far.motion, **solved_variables(so_far))
        write_json_atomic(reports_path, {"fingerprint": fingerprints(ctx.config)["solve"], "reports": reports})

    def solve_all(problem, motion, **resume):
        """The whole sequence: sequential windows (``resume``: where a checkpoint left them), or independent ones
        (tasks on a cluster; they start from ``motion``, so a checkpoint does not apply)."""
        if s.windows == "independent":
            return solve_windows_independently(problem, motion, options, map=_window_map(ctx.executor),
                                               initial_statics=first_statics)
        return solve(problem, motion, options, progress=True, **resume)

    if s.windows == "independent":  # every window from the initial motion (no checkpoint)
        ctx.log(f"solve: {len(window_starts(corr.num_frames, min(s.window, corr.num_frames), s.overlap))} windows "
                f"solved independently{' on the cluster' if ctx.executor.distributed else ''}, then their seams")
    solution = solve_all(problem, initial, skip_windows=skip, checkpoint=save, initial_statics=statics,
                         initial_frame_variables=frame_variables)
    if s.windows == "independent":
        reports = [dataclasses.asdict(r) for r in solution.reports]
    refinements = []
    for k in range(1, s.refine_rounds + 1):  # the model refined on the same problem, then solved again
        ctx.log(f"solve: refinement round {k} of {s.refine_rounds} (bone offsets, mounts, hinge axes, with the motion)")
        refinement = refine_model(problem, solution.motion, prior=(skeleton, rig))
        refinements.append(dataclasses.asdict(refinement.report))
        ctx.log(f"solve: refinement moved offsets ≤ {1e3 * refinement.report.offset_change_m:.2f} mm, mounts ≤ "
                f"{1e3 * refinement.report.mount_translation_change_m:.2f} mm / {refinement.report.mount_rotation_change_deg:.3f}°")
        problem = dataclasses.replace(problem, skeleton=refinement.skeleton, rig=refinement.rig)
        solution = solve_all(problem, refinement.motion, initial_statics=first_statics)
    for name in ("skeleton.json", "rig.json"):  # a refined model lives in solve/ (a rerun without refinement drops it)
        ctx.path("solve", name).unlink(missing_ok=True)
    if refinements:
        write_json_atomic(ctx.path("solve", "skeleton.json"), skeleton_to_dict(problem.skeleton))
        write_json_atomic(ctx.path("solve", "rig.json"), rig_to_dict(problem.rig, problem.skeleton))
    save_motion(ctx.path("solve", "motion.npz"), solution.motion, **solved_variables(solution))
    write_json_atomic(ctx.path("solve", "reports.json"), {"windows": reports, "refinements": refinements})
    return {"windows": len(reports), "converged": all(r["converged"] for r in reports), "refinement_rounds": len(refinements)}


def _window_map(executor: Executor):
    """``map(fn, starts)`` for :func:`~bcmocap.solver.solve_windows_independently` on ``executor``: its first
    call solves the windows, its second the seams (labelled so in the executor's timings)."""
    labels = iter(("window", "seam"))

    def map_windows(fn, starts):
        return executor.map(fn, list(starts), label=next(labels, "window"))

    return map_windows


def _stage_outputs(ctx: RunContext) -> dict:
    from .outputs import write_outputs

    return write_outputs(ctx)


_STAGE_FUNCTIONS = {"frontend": _stage_frontend, "world": _stage_world, "skeleton": _stage_skeleton,
                    "initial": _stage_initial, "solve": _stage_solve, "outputs": _stage_outputs}
