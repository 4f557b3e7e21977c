"""``bcmocap frontend CAPTURE_DIR --out DIR``: from a capture folder to the solver's Correspondences.

Stages, each saved under ``DIR`` and reused when rerun (delete a stage's output to redo it):

1. ``reference/``: the reference model of the reference photos (:func:`~.reference.build_reference`,
   saved by :func:`~.reference.save_reference`);
2. per trial, audio synchronisation (:func:`~.sync.synchronize`; ``--offsets`` gives them instead), then
   SIFT of every ``--stride``-th frame of every camera from the first clap to the second
   (``features/<trial>/<camera>/``, :mod:`~.features`: streamed to disk and read back memory-mapped);
3. per trial, registration (:func:`~.relative.register_capture`; with ``--chunk-frames N`` in chunks of N
   frames saved to ``<trial>/chunks/`` as they are done; its progress within a chunk is saved to
   ``<trial>/progress/`` as it goes, so a killed run continues there), homographies for the frames left
   (:func:`~.homography.fill_with_homographies`) and ``<trial>/correspondences/`` (the solver's
   measurements as a :class:`~bcmocap.correspondence_store.CorrespondenceStore`, in blocks of frames, in
   the reference model's frame and scale) with
   ``<trial>/registration.json``.

Heavy modules are imported inside :func:`run_frontend`, so ``bcmocap --help`` stays fast.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path

from ..atomic import write_json_atomic
from ..io.output_folder import check_outside, locked_output, output_folder
from ..native_crashes import load_pycolmap

MAX_MEASUREMENTS = 300
"""Measurements per camera-frame for the solver (the paper used about 300 inliers per image). On the 10 s walk
(``benchmarks/measurement_budget.py``) 200, 300, 400, 600 and all gave the same accuracy within 0.006 cm and
0.002°, and the warm solve ran at 93, 79, 67, 53 and 31 frames/s."""

SETTINGS_VERSION = 3
"""Bumped when registration changes for the same settings (2: the tracking frontend's rounds work on every
third frame left, :func:`~.tracking.round_seeds`; 3: a pose whose correspondences support a second one is refused,
:func:`~.poses.second_pose`), so an earlier ``registration.json`` is not reused."""
#: Version of :mod:`~.gyro_timing`'s estimate, in the saved settings of registrations that used it.
GYRO_TIMING_VERSION = 1

CHUNK_FRAMES = 400
"""Default chunk: registration holds about 1 GB per 1000 images of a chunk (measured: 1080 images of the
rendered walk), so 400 frames of 18 cameras stay within a few GB; shorter trials are one chunk."""


def add_frontend_command(sub: argparse._SubParsersAction) -> None:
    """Register ``bcmocap frontend`` on the CLI's subparsers."""
    cmd = sub.add_parser(
        "frontend",
        help="capture folder → reference model, sync, registration, correspondences",
        description=__doc__.split("\n\n", 1)[1].rsplit("\n\nHeavy", 1)[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    cmd.add_argument("capture", help="capture folder (the layout `bcmocap simulate` writes)")
    cmd.add_argument("--out", required=True, help="output folder (created if needed; stages found there are reused)")
    cmd.add_argument("--trial", action="append", help="trial to process (repeatable; default: every trial)")
    cmd.add_argument("--stride", type=int, default=1, help="use every n-th frame (default 1)")
    cmd.add_argument("--frames", type=int, default=None, help="at most this many frames per camera from the first clap")
    cmd.add_argument("--offsets", help="comma-separated video frame of the first clap per camera (skips audio sync)")
    cmd.add_argument("--max-features", type=int, default=8000, help="SIFT features per image (default 8000)")
    cmd.add_argument("--registration", choices=("tracking", "global"), default="tracking",
                     help="tracking (default): KLT tracking per camera with SIFT and global matching at keyframes; "
                          "global: SIFT of every frame matched against the whole reference (about 8 times slower, "
                          "as accurate)")
    cmd.add_argument("--max-measurements", type=int, default=MAX_MEASUREMENTS,
                     help=f"at most this many measurements per camera-frame, spread over the image (default "
                          f"{MAX_MEASUREMENTS}; 0 keeps all)")
    cmd.add_argument("--points", choices=["all", "reference"], default="reference",
                     help="which 3D points the solver measures: only the reference model's (the default: points "
                          "triangulated from a body camera carry that camera's pose error), or all")
    cmd.add_argument("--chunk-frames", type=int, default=CHUNK_FRAMES,
                     help="register each trial in equal chunks of at most this many processed frames, each saved as "
                          f"it is done, so memory does not grow with the trial (default {CHUNK_FRAMES}; 0: the whole "
                          "trial at once)")
    cmd.add_argument("--rolling-shutter-readout", type=float, default=0.0, metavar="SECONDS",
                     help="correct every frame for a rolling shutter with this readout (s from the first row to the "
                          "last) by the cameras' gyros (trials/<trial>/imu.npz); default 0: global shutter")
    cmd.add_argument("--gyro-timing", choices=["clock", "frames"], default="clock",
                     help="with a readout, when each frame was exposed on its gyro's clock: clock (the clap sync's frame "
                          "time, default) or frames (each camera's shift found in its own frames; "
                          "bcmocap.frontend.gyro_timing)")
    cmd.add_argument("--estimate-readout", action="store_true",
                     help="with --gyro-timing frames, find the readout in the frames too (--rolling-shutter-readout "
                          "only starts the search)")

    def run(args: argparse.Namespace) -> int:
        if args.stride < 1:
            cmd.error("--stride must be at least 1")
        if args.frames is not None and args.frames < 1:
            cmd.error("--frames must be at least 1")
        if args.chunk_frames < 0:
            cmd.error("--chunk-frames must be 0 (no chunks) or positive")
        if args.max_measurements < 0:
            cmd.error("--max-measurements must be 0 (keep all) or positive")
        return run_frontend(args)

    cmd.set_defaults(run=run)


def _progress(label: str):
    state = {"last": 0.0}

    def report(done: int, total: int) -> None:
        now = time.perf_counter()
        if done == total or now - state["last"] > 2.0:
            state["last"] = now
            print(f"  {label}: {done}/{total}", flush=True)

    return report


def prepare_reference(capture, ref_dir, log=print):
    """The reference model of ``capture``'s photos: read from ``ref_dir`` if saved there, else built and saved.

    Raises:
        ValueError: the capture has no reference photos.
    """
    pycolmap = load_pycolmap()

    from .reference import build_reference, load_reference, save_reference

    pycolmap.logging.minloglevel = 2
    if (ref_dir / "reference.json").is_file():
        model = load_reference(ref_dir)
        log(f"reference: read {ref_dir} ({model.num_registered}/{len(model.image_names)} photos)")
    else:
        if not capture.reference_photos:
            raise ValueError(f"{capture.path / 'reference'}: no reference photos")
        log(f"reference: {len(capture.reference_photos)} photos ...")
        model = build_reference(capture.path / "reference", [p.name for p in capture.reference_photos],
                                camera=capture.reference_camera, workdir=ref_dir / "work")
        save_reference(model, ref_dir)
    log(f"reference: {model.num_registered}/{len(model.image_names)} photos registered, "
        f"{model.num_points3D} points, mean reprojection error {model.mean_reprojection_error_px:.3f} px; "
        f"{len(model.pair_inliers)} photo pairs used; rotation check: {model.rotation_check} "
        f"({model.inconsistent_pairs} of {model.distinctive_pairs} distinctive pairs inconsistent in rotation)")
    return model


@dataclasses.dataclass(frozen=True)
class TrialOptions:
    """How :func:`process_trial` registers a trial: the settings its result depends on (saved in
    ``registration.json`` by :meth:`saved_settings`; a saved registration is reused only with the same).

    Attributes:
        stride: use every ``stride``-th video frame (1: all).
        frames: at most this many frames per camera from the first clap (None: up to the second clap).
        max_features: SIFT features per image.
        homographies: fill the frames registration leaves with homographies (:mod:`~.homography`).
        chunk_frames: register in equal chunks of at most this many processed frames (0: the whole trial at once;
            see :func:`process_trial`).
        registration: "tracking" or "global" (see :func:`process_trial`; the commands default to "tracking").
        max_measurements: at most this many measurements per camera-frame (:mod:`~.selection`; None keeps all).
        points: which 3D points the solver measures: "all", or "reference" (the reference model's only).
        rolling_shutter_readout: s from the first row to the last; > 0 corrects every frame for the rolling
            shutter by the cameras' gyros first (0: global shutter).
        gyro_timing: with a readout, when each frame was exposed on its gyro's clock: "clock" (the frame time the
            clap sync gives, on the clock of ``imu.npz``), or "frames" (each camera's shift found in its own frames,
            :mod:`~.gyro_timing`).
        estimate_readout: with ``gyro_timing`` "frames", also find the readout there (``rolling_shutter_readout``
            is then only the starting value of the search, e.g. a data sheet's).
    """

    stride: int = 1
    frames: int | None = None
    max_features: int = 8000
    homographies: bool = True
    chunk_frames: int = 0
    registration: str = "global"
    max_measurements: int | None = None
    points: str = "all"
    rolling_shutter_readout: float = 0.0
    gyro_timing: str = "clock"
    estimate_readout: bool = False

    def __post_init__(self):
        if self.gyro_timing not in ("clock", "frames"):
            raise ValueError(f"gyro_timing must be 'clock' or 'frames', got {self.gyro_timing!r}")
        if self.estimate_readout and self.gyro_timing != "frames":
            raise ValueError("estimate_readout needs gyro_timing = 'frames' (the readout is found with the gyro's timing)")

    def saved_settings(self, gyro: str | None = None) -> dict:
        """:func:`trial_settings` of these options (``gyro``: the gyros' fingerprint, with a rolling-shutter
        readout)."""
        return trial_settings(**dataclasses.asdict(self), gyro=gyro)


def trial_frames(capture, trial: str, sync, frames: int | None = None) -> int:
    """Frames per camera :func:`process_trial` uses from each camera's first clap (``sync``): up to the second clap (or
    the end of the shortest video when the offsets were given), at most ``frames``."""
    import numpy as np

    available = min(capture.video_info(trial, n).num_frames - int(s) for n, s in zip(capture.camera_names, sync.offsets))
    if np.isfinite(sync.duration_s):  # the take ends at the second clap
        available = min(available, int(round(sync.duration_s * capture.fps)) + 1)
    return available if frames is None else min(available, frames)


def process_trial(capture, index, trial: str, out, options: TrialOptions = TrialOptions(), *, offsets=None,
                  extra_settings: dict | None = None, log=print, map_tasks=None, gyro_timing=None) -> dict:
    """One trial, from its first clap to its second (or to the end of the shortest video when ``offsets``
    are given), through sync, features, registration and homographies, written under ``out``, as ``options``
    say (:class:`TrialOptions`).

    ``options.registration`` "tracking" tracks each camera's video (:mod:`~.tracking`: KLT and PnP, SIFT
    and global matching only at keyframes; cached in ``out/tracks/<trial>/``) and hands every third frame it
    leaves to the rounds of relative registration, with SIFT extracted only for them and their neighbours,
    then tracks the others from the frames the rounds registered (a second pass of the rounds takes the rest);
    "global" (:class:`TrialOptions`' default; the commands default to "tracking") extracts SIFT of every frame and
    matches each against the reference (about 8 times slower than tracking on the 10 s walk, as accurate).
    ``options.max_measurements`` caps the measurements per camera-frame (:mod:`~.selection`; None keeps all);
    ``options.points`` "reference" keeps only the measurements of reference-model points
    (:meth:`~.relative.CaptureRegistration.correspondences`). With ``options.rolling_shutter_readout`` > 0 (s,
    first row to last), every frame is first corrected for the rolling shutter
    by the cameras' gyros (``trials/<trial>/imu.npz``; :mod:`~.rolling_shutter`), so the poses and measurements are
    those of a global shutter at the frame times (the camera's translation across the readout aside). With
    ``options.gyro_timing`` "frames" the gyro is read at the times :mod:`~.gyro_timing` finds in the frames, with the
    readout found there too under ``options.estimate_readout`` (``gyro_timing``: a
    :class:`~.gyro_timing.GyroTiming` found beforehand, e.g. for several trials together; None: found for this
    trial alone); its report is saved as ``"gyro_timing"``.
    ``extra_settings`` join the settings saved with the result (e.g. the lens correction a caller applied to
    ``capture``), so a saved registration is reused only with them.

    With ``options.chunk_frames`` > 0 the trial is registered in equal chunks of at most that many processed
    frames (:func:`chunk_bounds`), one after the other: a chunk's points, tracks and matches are dropped
    once its correspondences are written to ``out/<trial>/chunks/NNNN.npz`` (with ``NNNN.json``), so
    memory no longer grows with the trial's length during registration, and a rerun reuses the chunks
    already done. Frames in different chunks are not
    matched with each other (each chunk starts again from the reference model). 0: the whole trial at once.

    Writes ``out/<trial>/correspondences/`` (a :class:`~bcmocap.correspondence_store.CorrespondenceStore`,
    written one chunk at a time) and ``out/<trial>/registration.json`` (features are cached in
    ``out/features/<trial>/``) and returns the registration report (the JSON's content).
    """
    import numpy as np

    from ..correspondence_store import write_store
    from .sync import given_offsets, synchronize

    o = options
    sync = given_offsets(capture, offsets) if offsets is not None else synchronize(capture, trial)
    starts = np.asarray(sync.offsets, np.int64)
    frames = trial_frames(capture, trial, sync, o.frames)
    log(f"{trial}: first clap at video frames {starts.tolist()}; {frames} frames per camera up to the second clap")
    timing = None
    if o.rolling_shutter_readout > 0:
        from .rolling_shutter import gyro_unwarp

        readout, shifts = o.rolling_shutter_readout, None
        if o.gyro_timing == "frames":
            from .gyro_timing import timing_of_trials

            timing = gyro_timing or timing_of_trials(capture, {trial: starts}, o.rolling_shutter_readout,
                                                     spans={trial: frames}, estimate_readout=o.estimate_readout,
                                                     log=log)[trial]
            readout, shifts = timing.readout_s, timing.time_shift_s
            log(f"{trial}: gyro timing from the frames: shifts {np.round(1e3 * shifts, 2).tolist()} ms, readout "
                f"{1e3 * readout:.2f} ms ({'estimated' if o.estimate_readout else 'given'})")
        if readout > 0:
            capture = capture.corrected(trial, gyro_unwarp(capture, trial, starts, readout, time_shifts=shifts))
            log(f"{trial}: frames corrected for a {1e3 * readout:.3g} ms rolling-shutter readout by the gyros")
        else:
            log(f"{trial}: the frames show no rolling shutter (readout 0): not corrected")
    if o.registration not in ("tracking", "global"):
        raise ValueError(f"registration must be 'tracking' or 'global', got {o.registration!r}")
    clock = time.perf_counter()
    settings = {"first_clap_frames": starts.tolist(), "stride": o.stride, "max_features": o.max_features,
                "homographies": o.homographies, "registration": o.registration,
                "max_measurements": o.max_measurements, **({} if o.points == "all" else {"points": o.points}),
                **capture.correction_settings(trial), **(extra_settings or {})}
    job = TrialRegistrationJob(capture, index, trial, Path(out), starts, frames, o, settings)
    state = job.per_camera(log, map_tasks)
    count = state.count
    if not count:
        raise ValueError(f"trial {trial!r}: no frames to register after the first clap (stride {o.stride})")
    bounds = chunk_bounds(count, o.chunk_frames)
    if map_tasks is not None and len(bounds) > 1:  # chunks are independent: register them as tasks, saved
        todo = [k for k, (a, b) in enumerate(bounds) if _saved_summary(job.chunk_path(k), settings, [a, b]) is None]
        if todo:
            log(f"{trial}: {len(todo)} of {len(bounds)} chunks as tasks")

            def done(i, result):
                for line in result:
                    log(line)

            map_tasks(functools.partial(_chunk_task, job, bounds), todo, label=f"register {trial}", on_done=done)
    chunks = []

    def parts():
        """Each chunk's correspondences, registered or reused, one at a time (the store writes each
        before the next is made)."""
        for k, (a, b) in enumerate(bounds):
            label = trial if len(bounds) == 1 else f"{trial} chunk {k + 1}/{len(bounds)}"
            saved = job.chunk_path(k)
            part, summary = _saved_chunk(saved, settings, [a, b]) if len(bounds) > 1 else (None, None)
            if part is not None:
                log(f"{label}: reused {saved.with_suffix('.npz')}")
            else:
                part, summary = job.register_chunk(state, k, a, b, label, log, save=len(bounds) > 1)
            chunks.append(summary)
            yield part
            del part  # before the next chunk is registered

    store = write_store(out / trial / "correspondences", parts())
    shutil.rmtree(out / trial / "progress", ignore_errors=True)  # the trial is saved: its progress is not needed
    reg = store.registered
    report = {"trial": trial, "first_clap_frames": starts.tolist(), "stride": o.stride,
              "frames": int(reg.shape[0]), "cameras": list(capture.camera_names),
              "registered_fraction": float(reg.mean()) if reg.size else 0.0,
              "registered_per_camera": reg.mean(axis=0).tolist(),
              "chunk_frames": o.chunk_frames}
    report["registration"] = o.registration
    report["max_measurements"] = o.max_measurements
    report["points"] = o.points
    from .rolling_shutter import gyro_fingerprint

    gyro = gyro_fingerprint(capture, trial) if o.rolling_shutter_readout > 0 else None
    report["settings"] = o.saved_settings(gyro) | (extra_settings or {})
    if timing is not None:
        report["gyro_timing"] = timing.as_dict()
    for key in ("registered_absolute", "registered_tracked", "registered_relocalised", "registered_relative",
                "tracked_after_rounds", "points", "new_points", "filled_by_homographies", "homography_pairs"):
        report[key] = int(sum(c.get(key, 0) for c in chunks))
    report["rounds"] = chunks[0]["rounds"] if len(chunks) == 1 else [c["rounds"] for c in chunks]
    report["seconds"] = time.perf_counter() - clock
    report["note"] = "poses and points are in the reference model's frame and scale"
    write_json_atomic(out / trial / "registration.json", report)
    log(f"{trial}: {reg.sum()}/{reg.size} frames registered ({100 * report['registered_fraction']:.1f} %: "
        f"{report['registered_absolute']} absolute, {report['registered_tracked']} tracked, "
        f"{report['registered_relocalised']} relocalised, "
        f"{report['registered_relative']} relative); "
        f"wrote {store.path}")
    return report


def trial_settings(*, stride: int, frames: int | None, max_features: int, homographies: bool, chunk_frames: int,
                   registration: str, max_measurements: int | None, points: str = "all",
                   rolling_shutter_readout: float = 0.0, gyro_timing: str = "clock", estimate_readout: bool = False,
                   gyro: str | None = None) -> dict:
    """The settings of :func:`process_trial` that its result depends on (:class:`TrialOptions`' fields), as saved in
    ``registration.json`` (``"settings"``): a saved registration is reused only when they are all the same."""
    from .tracking import ROUND_PARTNERS

    return {"stride": int(stride), "frames": None if frames is None else int(frames), "max_features": int(max_features),
            "homographies": bool(homographies), "chunk_frames": int(chunk_frames), "registration": str(registration),
            "max_measurements": None if max_measurements is None else int(max_measurements), "version": SETTINGS_VERSION,
            **({} if points == "all" else {"points": str(points)}),  # registrations saved before the setting: "all"
            **({"round_partners": ROUND_PARTNERS} if registration == "tracking" else {}),
            **({"rolling_shutter_readout": float(rolling_shutter_readout), "gyro": gyro}
               if rolling_shutter_readout > 0 else {}),
            **({"gyro_timing": "frames", "estimate_readout": bool(estimate_readout), "gyro_timing_version": GYRO_TIMING_VERSION}
               if rolling_shutter_readout > 0 and gyro_timing == "frames" else {})}


@dataclasses.dataclass(frozen=True)
class _PerCamera:
    """What :meth:`TrialRegistrationJob.per_camera` found: SIFT of every frame (global registration) or the
    camera tracks and their keyframe SIFT (tracking), and the frames every camera has."""

    count: int
    features: list | None = None
    tracks: list | None = None
    keyframe_features: list | None = None
    options: object = None


@dataclasses.dataclass(frozen=True)
class _ChunkInputs:
    """What the registration of one chunk of processed frames starts from (:meth:`TrialRegistrationJob._chunk_inputs`,
    for :func:`_register_frames`).

    Attributes:
        features: ``features[t][c] = (keypoints (N, 2), descriptors (M ≤ N, 128))`` of the chunk's frames.
        initial: ``initial[t][c] = (world_from_camera (7,), point_ids (N,), how)``: their registration by tracking
            (:func:`~.tracking.tracking_states`), or None (global registration: absolute registration first).
        initial_points: ``{id: (3,) position}`` of the points ``initial`` observes besides the reference's, or None.
        leave: ``(T, C)`` bool, the frames the rounds skip, or None.
        after_rounds: ``after_rounds(result, progress) → (result, count)`` registers frames after the rounds
            (before the homographies), or None.
    """

    features: list
    initial: list | None = None
    initial_points: dict | None = None
    leave: object = None
    after_rounds: Callable | None = None


@dataclasses.dataclass(frozen=True)
class TrialRegistrationJob:
    """The registration of one trial after sync, split into what a cluster can run as tasks: each camera's
    SIFT or tracking (:meth:`per_camera`), then each chunk of frames (:meth:`register_chunk`). Holds paths
    and small values only (it is pickled into every task); what a task makes is written under ``out``.

    Attributes:
        capture, index: the capture (:class:`~.capture.Capture`) and its reference index
            (:func:`~.register.reference_index`); trial: its name; out: the output folder.
        starts: ``(C,)`` int64, each camera's first clap frame.
        num_frames: frames per camera from the first clap (the video frames, before ``options.stride``).
        options: how it is registered; settings: what the chunks are saved with (reused only with the same).
    """

    capture: object
    index: object
    trial: str
    out: Path
    starts: object
    num_frames: int
    options: TrialOptions
    settings: dict

    def chunk_path(self, k: int) -> Path:
        """Chunk ``k``'s saved correspondences and summary, without suffix (``.npz``, ``.json``)."""
        return self.out / self.trial / "chunks" / f"{k:04d}"

    def per_camera(self, log=print, map_tasks=None, progress: bool = True) -> _PerCamera:
        """Each camera's SIFT (global) or track (tracking), computed or read from the caches under ``out``;
        with ``map_tasks``, each camera not cached yet is one task."""
        import numpy as np

        from .register import RegistrationOptions
        from .relative import extract_trial_features
        from .tracking import TrackingOptions, track_trial

        trial, o = self.trial, self.options
        if o.registration == "global":
            features = extract_trial_features(self.capture, trial, stride=o.stride, starts=self.starts,
                                              num_frames=self.num_frames, max_features=o.max_features,
                                              cache_dir=self.out / "features" / trial,
                                              progress=_progress(f"{trial} features") if progress else None,
                                              map_tasks=map_tasks)
            return _PerCamera(len(features), features=features)
        options = TrackingOptions(registration=RegistrationOptions(max_features=o.max_features))
        tracks, keyframe_features = track_trial(self.capture, trial, self.index, starts=self.starts,
                                                num_frames=self.num_frames, stride=o.stride, options=options,
                                                cache_dir=self.out / "tracks" / trial,
                                                progress=_progress(f"{trial} tracking") if progress else None,
                                                map_tasks=map_tasks)
        count = min(len(t.how) for t in tracks)
        tracked = np.stack([t.registered[:count] for t in tracks], 1)
        if progress:
            log(f"{trial}: tracking registered {100 * tracked.mean():.1f} % of {tracked.size} camera-frames "
                f"({sum(int(t.keyframe[:count].sum()) for t in tracks)} keyframes)")
        return _PerCamera(count, tracks=tracks, keyframe_features=keyframe_features, options=options)

    def _chunk_inputs(self, state: _PerCamera, a: int, b: int, progress_dir: Path, log) -> _ChunkInputs:
        """What the registration of the processed frames ``a … b − 1`` starts from."""
        from .tracking import (
            rounds_for_the_rest,
            sift_for_homographies,
            states_for_rounds,
            track_after_rounds,
        )

        if state.tracks is None:
            return _ChunkInputs(state.features[a:b])
        capture, trial, starts, options = self.capture, self.trial, self.starts, state.options
        stride, max_features = self.options.stride, self.options.max_features
        features, initial, points, leave, partners = states_for_rounds(
            capture, trial, state.tracks, state.keyframe_features, self.index, starts=starts, stride=stride, first=a,
            stop=b, options=options, log=log)

        def after_rounds(result, progress):
            """The frames the rounds left: tracked from theirs, a second pass for the rest, SIFT for the
            homographies of what is still left. Returns ``(registration, frames tracked)``."""
            filled = track_after_rounds(capture, trial, result, starts=starts, stride=stride, first=a, options=options)
            rest = int((leave & ~result.registered).sum())
            result = rounds_for_the_rest(capture, trial, result, leave, partners, self.index, starts=starts,
                                         stride=stride, first=a, max_features=max_features, progress=progress,
                                         checkpoint=_checkpoint(progress_dir, "rest", self.settings, [a, b]))
            extracted = sift_for_homographies(capture, trial, result, leave, starts=starts, stride=stride, first=a,
                                              max_features=max_features) if self.options.homographies else 0
            log(f"{trial}: frames {a}-{b - 1}: of the {int(leave.sum())} frames the rounds left, {filled} tracked "
                f"from the frames they registered, {rest - int((leave & ~result.registered).sum())} of the {rest} "
                f"others in a second pass; SIFT of {extracted} frames for the homographies")
            return result, filled

        return _ChunkInputs(features, initial, points, leave, after_rounds)

    def register_chunk(self, state: _PerCamera, k: int, a: int, b: int, label: str, log=print, save: bool = True,
                       progress: bool = True):
        """Register chunk ``k`` (processed frames ``a … b − 1``): ``(Correspondences, summary)``; with ``save``
        written to :meth:`chunk_path` (its progress, saved as it goes under ``out/<trial>/progress/``, is
        then removed)."""
        progress_dir = self.out / self.trial / "progress" / f"{k:04d}"
        part, summary = _register_frames(self, self._chunk_inputs(state, a, b, progress_dir, log), a, label,
                                         checkpoint=_checkpoint(progress_dir, "rounds", self.settings, [a, b]),
                                         progress=progress)
        summary = {"frames": [a, b], "settings": self.settings, **summary}
        if save:
            saved = self.chunk_path(k)
            part.save(saved.with_suffix(".npz"))
            write_json_atomic(saved.with_suffix(".json"), summary)
            shutil.rmtree(progress_dir, ignore_errors=True)  # the chunk is saved
        return part, summary


def _chunk_task(job: TrialRegistrationJob, bounds: list, k: int) -> list[str]:
    """A task on a cluster: register and save chunk ``k`` of ``job`` (the per-camera work is read from its
    caches); returns the log lines it wrote."""
    lines: list[str] = []
    state = job.per_camera(lines.append, progress=False)
    a, b = bounds[k]
    job.register_chunk(state, k, a, b, f"{job.trial} chunk {k + 1}/{len(bounds)}", lines.append, progress=False)
    return lines


def chunk_bounds(num_frames: int, chunk_frames: int) -> list[tuple[int, int]]:
    """``[(start, stop), …]``: the fewest chunks of at most ``chunk_frames`` frames, of equal length within
    one frame (no short tail chunk); ``chunk_frames`` 0 gives one chunk."""
    count = -(-num_frames // chunk_frames) if chunk_frames > 0 else 1
    edges = [round(k * num_frames / count) for k in range(count + 1)]
    return list(zip(edges[:-1], edges[1:]))


def _saved_chunk(saved, settings: dict, frames: list[int]):
    """``(Correspondences, summary)`` of a chunk written by an earlier run with the same settings and
    frames (``saved`` without suffix), or ``(None, None)``."""
    from ..correspondences import Correspondences

    summary = _saved_summary(saved, settings, frames)
    if summary is None:
        return None, None
    try:
        return Correspondences.load(saved.with_suffix(".npz")), summary
    except ValueError:
        return None, None


def _saved_summary(saved, settings: dict, frames: list[int]) -> dict | None:
    """The summary (``saved`` + ``.json``) of a chunk saved with these settings and frames, or None (its
    correspondences are read by :func:`_saved_chunk`)."""
    try:
        summary = json.loads(saved.with_suffix(".json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(summary, dict) or summary.get("settings") != settings or summary.get("frames") != frames:
        return None
    return summary


def _checkpoint(folder, stage: str, settings: dict, frames: list[int]):
    """The :class:`~.relative.RegistrationCheckpoint` of one :func:`~.relative.register_capture` call of a chunk
    (``stage`` "rounds", or "rest" for the tracking frontend's second pass)."""
    from .relative import RegistrationCheckpoint

    return RegistrationCheckpoint(folder / stage, {"settings": settings, "frames": frames, "stage": stage,
                                                   "version": SETTINGS_VERSION})


def _register_frames(job: TrialRegistrationJob, inputs: _ChunkInputs, first: int, label: str, checkpoint=None,
                     progress: bool = True):
    """Registration (from ``inputs.initial`` when given, :func:`~.relative.register_capture`) and homographies of
    the processed frames ``first … first + len(inputs.features) − 1`` of ``job``'s trial: ``(Correspondences,
    summary)``; the registration's points and tracks are released on return. The rounds skip the frames in
    ``inputs.leave``; ``inputs.after_rounds``, when given, registers frames after them (before the homographies).
    ``checkpoint`` (a :class:`~.relative.RegistrationCheckpoint`) saves the registration's progress, and a rerun
    continues from it; ``label`` names the chunk in the progress lines, shown with ``progress``."""
    import numpy as np

    from .homography import fill_with_homographies
    from .relative import RelativeOptions, register_capture
    from .tracking import round_options

    stages: dict[str, object] = {}

    show = progress

    def progress(stage, done, total):
        if show:
            stages.setdefault(stage, _progress(f"{label} {stage}"))(done, total)

    capture, o, features = job.capture, job.options, inputs.features
    cameras = [c.intrinsics for c in capture.cameras]
    # After tracking, many frames may be left: only the pairs their new points come from are matched, and each
    # frame with fewer other cameras.
    options = RelativeOptions() if inputs.initial is None else round_options()
    result = register_capture(features, cameras, job.index, options,
                              frames=(first + np.arange(len(features))) * o.stride, initial=inputs.initial,
                              initial_points=inputs.initial_points, leave=inputs.leave, checkpoint=checkpoint,
                              progress=progress)
    tracked_after = 0
    if inputs.after_rounds is not None:
        result, tracked_after = inputs.after_rounds(result, progress)
    fill = fill_with_homographies(result, cameras) if o.homographies else None
    corr = result.correspondences(fps=capture.fps / o.stride, homographies=fill, max_per_frame=o.max_measurements,
                                  points=o.points)
    states = [s for row in result.states for s in row]
    summary = {"registered_absolute": sum(s.how == "absolute" for s in states),
               "registered_tracked": sum(s.how == "tracked" for s in states),
               "registered_relocalised": sum(s.how == "relocalised" for s in states),
               "registered_relative": sum(s.how == "relative" for s in states),
               "tracked_after_rounds": tracked_after,
               "rounds": result.rounds, "points": len(result.points), "new_points": len(result.new_point_ids),
               "filled_by_homographies": int(fill.filled.sum()) if fill is not None else 0,
               "homography_pairs": len(fill.pixels) if fill is not None else 0}
    return corr, summary


def run_frontend(args: argparse.Namespace) -> int:
    from .capture import read_capture
    from .register import reference_index

    out = output_folder("frontend", args.out)
    if out is None:
        return 2
    try:
        capture = read_capture(args.capture)
        check_outside(out, capture.path)
        trials = args.trial or list(capture.trials)
        unknown = [t for t in trials if t not in capture.trials]
        if unknown:
            raise ValueError(f"{args.capture}: no trial {unknown[0]!r} (trials: {', '.join(capture.trials)})")
        if args.rolling_shutter_readout != 0:
            from .rolling_shutter import check_readout

            check_readout(args.rolling_shutter_readout, capture.fps)
        if (args.gyro_timing == "frames" or args.estimate_readout) and args.rolling_shutter_readout <= 0:
            raise ValueError("--gyro-timing frames and --estimate-readout need a --rolling-shutter-readout to start from")
        if args.estimate_readout and args.gyro_timing != "frames":
            raise ValueError("--estimate-readout needs --gyro-timing frames")
        offsets = None
        if args.offsets:
            offsets = [int(v) for v in args.offsets.split(",")]
            if len(offsets) != len(capture.camera_names):
                raise ValueError(f"--offsets gives {len(offsets)} values for {len(capture.camera_names)} cameras")
        out.mkdir(parents=True, exist_ok=True)
    except ValueError as exc:
        print(f"bcmocap frontend: {exc}", file=sys.stderr)
        return 2
    with locked_output(out):  # a second command on this --out is refused (bcmocap's main prints it)
        index = reference_index(prepare_reference(capture, out / "reference", log=lambda m: print(m, flush=True)))
        for trial in trials:
            options = TrialOptions(stride=args.stride, frames=args.frames, max_features=args.max_features,
                                   chunk_frames=args.chunk_frames, registration=args.registration,
                                   max_measurements=args.max_measurements or None, points=args.points,
                                   rolling_shutter_readout=args.rolling_shutter_readout, gyro_timing=args.gyro_timing,
                                   estimate_readout=args.estimate_readout)
            process_trial(capture, index, trial, out, options, offsets=offsets, log=lambda m: print(m, flush=True))
    return 0
