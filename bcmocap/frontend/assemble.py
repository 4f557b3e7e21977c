"""``bcmocap init``: a capture folder assembled from a shoot's camera files, a rig file and the calibrations.

A shoot comes back with one video per camera (or one per camera and trial) whose audio is inside it, a
calibration per camera or per lens model (what ``bcmocap calibrate`` writes), reference photos, and the
rig file (:mod:`.rig_file`). :func:`assemble_capture` checks all of it before writing anything, then
writes the folder :func:`~.capture.read_capture` reads (the layout of :mod:`bcmocap.io.capture_folder`)::

    capture.json        manifest: fps, audio rate, cameras, trials, the subject (from the rig file), where
                        the videos came from, the claps found in each trial
    rig.json            camera -> segment, mount note, lens files, and per trial the video and the stretch of
                        it the trial is ({"file", "first_frame", "num_frames"})
    intrinsics/<camera>.json|.yml      the camera's calibration files (copied: small)
    reference/<photo>, camera.json|.yml the reference photos and their camera
    trials/<trial>/<camera>.<ext>      a video holding one trial (and <camera>.wav if the video had none)
    trials/<trial>/imu.npz             the cameras' own gyroscopes and accelerometers (GoPro files' GPMF
                                       telemetry, :mod:`.telemetry`), where some camera has any

    videos/<camera>.<ext>              a video holding several trials, cut by the stretches in rig.json

Videos and photos are **symbolic links** to the user's files (absolute targets), or copies with
``copy=True``; nothing the user gave is written to. A file holding several trials is cut by its claps
(two per trial, :func:`~.sync.common_claps` over every camera's own audio, each trial kept from
``margin_s`` before its first clap to ``margin_s`` after its second, and never past the middle between two
trials) or by given times (seconds of each video's own clock). Each trial is then synchronised as the
frontend will (:func:`~.sync.synchronize_tracks`), so a trial whose claps some camera missed fails here, not
later. The folder is written under a temporary name beside ``capture_dir`` and renamed when complete.

A take a camera split over chapter files (a GoPro's ``GX01nnnn.MP4``, ``GX02nnnn.MP4``…: :mod:`bcmocap.io.chapters`)
is joined into one file, its packets copied unchanged, which the capture folder holds (not a link); naming any of its
chapters names the take. The chapters are joined first, in the temporary folder (the checks read the joined take),
and an error about a joined take names its chapters.

Every path written is built from checked names (:mod:`bcmocap.io.names`) inside the new folder; every
expected failure is a ``ValueError`` naming the file and the field.
"""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..io.capture_folder import (
    intrinsics_path,
    manifest_path,
    new_manifest,
    reference_camera_path,
    reference_photo_path,
    relative_name,
    rig_path,
    shared_video_path,
    subject_record,
    trial_audio_path,
    trial_dir,
    trial_video_path,
    write_json,
    write_manifest,
)
from ..io.chapters import join_chapters, take_chapters
from ..io.gopro import read_gopro_imu
from ..io.media import probe_media, read_audio_track
from ..io.names import checked_name
from ..io.opencv_calibration import read_opencv_fisheye_calibration
from ..io.sensors import IMU_FILE, ImuRecording, write_imu
from ..io.wav import read_wav
from .capture import read_camera_json, read_capture
from .rig_file import RigFile
from .sync import clap_candidates, common_claps, synchronize_tracks
from .telemetry import CameraTelemetry, trial_imu

__all__ = ["VIDEO_SUFFIXES", "CameraFile", "TrialStretch", "assemble_capture"]

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv", ".avi")
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
CALIBRATION_SUFFIXES = (".json", ".yml", ".yaml", ".xml")
_EXTRA_CANDIDATES = 8  # clap candidates kept per camera beyond the claps expected


@dataclasses.dataclass(frozen=True)
class CameraFile:
    """One video file of a camera, as probed.

    Attributes:
        path: the file; trials: the trials it holds (recording order).
        num_frames, fps, width, height: its video (OpenCV's count, frame rate in Hz, size in px).
        audio_rate: its audio track's sample rate (Hz), or the WAV's beside it; wav: that WAV, if the video has
            no audio track of its own.
        duration_s: the video's length (s).
    """

    path: Path
    trials: tuple[str, ...]
    num_frames: int
    fps: float
    width: int
    height: int
    audio_rate: int
    wav: Path | None

    @property
    def duration_s(self) -> float:
        return self.num_frames / self.fps

    def audio(self, start_s: float = 0.0, stop_s: float | None = None) -> np.ndarray:
        """Its soundtrack from ``start_s`` to ``stop_s`` (s after its first frame), mono in [-1, 1]."""
        if self.wav is None:
            return read_audio_track(self.path, start_s, stop_s)[0]
        samples, rate = read_wav(self.wav)
        lo = int(round(start_s * rate))
        hi = None if stop_s is None else int(round(stop_s * rate))
        track = samples[lo:hi]
        if hi is not None and len(track) < hi - lo:
            track = np.concatenate([track, np.zeros(hi - lo - len(track))])
        return track


@dataclasses.dataclass(frozen=True)
class TrialStretch:
    """The frames ``[first_frame, first_frame + num_frames)`` of ``source`` that one trial of one camera is."""

    source: CameraFile
    first_frame: int
    num_frames: int


def _probe(path: Path, trials: tuple[str, ...]) -> CameraFile:
    """Open a camera file with PyAV (audio) and OpenCV (video, as the frontend decodes it)."""
    import cv2

    info = probe_media(path)
    if info.video_codec is None:
        raise ValueError(f"{path}: no video stream")
    video = cv2.VideoCapture(str(path))
    try:
        if not video.isOpened() or not video.read()[0]:
            raise ValueError(f"{path}: OpenCV cannot decode its {info.video_codec} video (the frontend decodes with "
                             "OpenCV); convert it, e.g. ffmpeg -i IN -c:v libx264 -crf 16 -c:a copy OUT.mp4")
        count, fps = int(video.get(cv2.CAP_PROP_FRAME_COUNT)), float(video.get(cv2.CAP_PROP_FPS))
        width, height = int(video.get(cv2.CAP_PROP_FRAME_WIDTH)), int(video.get(cv2.CAP_PROP_FRAME_HEIGHT))
    finally:
        video.release()
    if count < 1 or not 0 < fps < 10_000:
        raise ValueError(f"{path}: its container gives {count} frames at {fps} frames/s (damaged or still being written?)")
    wav = None
    rate = info.audio_rate
    if not info.has_audio:
        beside = path.with_suffix(".wav")
        if not beside.is_file():
            raise ValueError(f"{path}: no audio track, and no {beside.name} beside it: the claps that cut and "
                             "synchronise the trials cannot be heard")
        wav, rate = beside, read_wav(beside)[1]
    return CameraFile(path, trials, count, fps, width, height, rate, wav)


def _find_videos(rig: RigFile, videos: Path) -> dict[str, dict[str, Path]]:
    """``{camera: {trial: file}}``: the rig file's ``video`` fields, else files named after the camera."""
    found: dict[str, dict[str, Path]] = {}
    listing = {p.name: p for p in videos.iterdir()} if videos.is_dir() else {}

    def named(folder_listing: dict[str, Path], camera: str) -> list[Path]:
        return sorted(p for name, p in folder_listing.items()
                      if Path(name).stem == camera and Path(name).suffix.lower() in VIDEO_SUFFIXES and p.is_file())

    for cam in rig.cameras:
        where = f"{rig.path}: cameras.{cam.name}.video"
        if isinstance(cam.video, dict):
            missing = [t for t in rig.trials if t not in cam.video]
            if missing:
                raise ValueError(f"{where} gives no file for trials {missing}")
            files = {t: videos / cam.video[t] for t in rig.trials}
        elif cam.video is not None:
            files = {t: videos / cam.video for t in rig.trials}
        else:
            whole = named(listing, cam.name)
            per_trial = {t: named({p.name: p for p in (videos / t).iterdir()} if (videos / t).is_dir() else {}, cam.name)
                         for t in rig.trials}
            if len(whole) > 1 or any(len(v) > 1 for v in per_trial.values()):
                many = whole if len(whole) > 1 else next(v for v in per_trial.values() if len(v) > 1)
                raise ValueError(f"{videos}: several videos of camera {cam.name!r} ({', '.join(p.name for p in many)}); "
                                 f"name one in {rig.path} (cameras.{cam.name}.video)")
            have = [t for t, v in per_trial.items() if v]
            if whole and have:
                raise ValueError(f"{videos}: camera {cam.name!r} has both {whole[0].name} and per-trial videos "
                                 f"({', '.join(have)}/); name its files in {rig.path} (cameras.{cam.name}.video)")
            if whole:
                files = {t: whole[0] for t in rig.trials}
            elif have and len(have) == len(rig.trials):
                files = {t: per_trial[t][0] for t in rig.trials}
            else:
                lacking = [t for t in rig.trials if t not in have]
                raise ValueError(f"{videos}: no video of camera {cam.name!r} (looked for {cam.name}.mp4|.mov|… and "
                                 f"{'/'.join(lacking)}/{cam.name}.mp4|…); or name it in {rig.path} "
                                 f"(cameras.{cam.name}.video)")
        for trial, file in files.items():
            if not file.is_file():
                raise ValueError(f"{where if cam.video is not None else videos}: video {file} missing "
                                 f"(camera {cam.name!r}, trial {trial!r})")
        found[cam.name] = files
    return found


def _stretch_from_times(source: CameraFile, span: tuple[float, float], what: str) -> tuple[int, int]:
    """``(first_frame, num_frames)``: the frames nearest to ``[start, end]`` s, within the file."""
    first = max(int(round(span[0] * source.fps)), 0)
    last = min(int(round(span[1] * source.fps)), source.num_frames - 1)
    if last - first + 1 < 2:
        raise ValueError(f"{what}: [{span[0]}, {span[1]}] s leaves fewer than 2 frames of {source.path} "
                         f"({source.duration_s:.2f} s long)")
    return first, last - first + 1


def _cut_by_claps(files: dict[tuple[str, Path], CameraFile], margin_s: float,
                  log: Callable[[str], None]) -> dict[tuple[str, str], tuple[int, int]]:
    """``{(trial, camera): (first_frame, num_frames)}`` for the files (``{(camera, path): file}``) that hold
    several trials, cut by their claps; the files holding the same trials are cut together."""
    groups: dict[tuple[str, ...], list[tuple[str, CameraFile]]] = {}
    for (camera, _), source in files.items():
        groups.setdefault(source.trials, []).append((camera, source))
    cuts = {}
    for trials, members in groups.items():
        count = 2 * len(trials)
        cameras = [camera for camera, _ in members]
        candidates = [clap_candidates(source.audio(), source.audio_rate, max_count=count + _EXTRA_CANDIDATES)
                      for _, source in members]  # one track in memory at a time
        try:
            claps = common_claps(candidates, members[0][1].audio_rate, count, cameras=cameras)
        except ValueError as err:
            raise ValueError(f"{members[0][1].path.parent}: cutting trials {list(trials)} by their claps: {err} "
                             "(split = \"times\" with [trials.times] in the rig file, or --times)") from None
        for c, (camera, source) in enumerate(members):
            seconds = claps[c] / source.audio_rate
            for k, trial in enumerate(trials):
                a, b = seconds[2 * k], seconds[2 * k + 1]
                start = max(a - margin_s, 0.0 if k == 0 else 0.5 * (seconds[2 * k - 1] + a))
                end = min(b + margin_s, source.duration_s if k == len(trials) - 1 else 0.5 * (b + seconds[2 * k + 2]))
                cuts[(trial, camera)] = _stretch_from_times(source, (start, end), f"trial {trial!r} of camera {camera!r}")
        log(f"cut {len(cameras)} cameras' files into trials {', '.join(trials)} by {count} claps (in {cameras[0]}'s: "
            f"{', '.join(f'{t:.2f}' for t in claps[0] / members[0][1].audio_rate)} s)")
    return cuts


def _probe_all(rig: RigFile, paths: dict[str, dict[str, Path]]) -> dict[tuple[str, str], CameraFile]:
    """``{(trial, camera): CameraFile}``, every file probed once; one frame rate and one audio rate for all."""
    probed: dict[Path, CameraFile] = {}
    for cam in rig.cameras:
        for trial in rig.trials:
            path = paths[cam.name][trial]
            if path not in probed:
                probed[path] = _probe(path, tuple(t for t in rig.trials if paths[cam.name][t] == path))
    sources = {(t, c.name): probed[paths[c.name][t]] for c in rig.cameras for t in rig.trials}
    for cam in rig.cameras:
        files = {sources[(t, cam.name)] for t in rig.trials}
        if len({(f.width, f.height) for f in files}) > 1:
            raise ValueError(f"{', '.join(str(f.path) for f in files)}: camera {cam.name!r} recorded its trials at "
                             "different sizes (another resolution mode is another lens)")
    fps = {round(s.fps, 3) for s in sources.values()}
    if len(fps) > 1:
        slow = min(sources.values(), key=lambda s: s.fps)
        fast = max(sources.values(), key=lambda s: s.fps)
        raise ValueError(f"{fast.path}: {fast.fps:g} frames/s, but {slow.path} has {slow.fps:g}: every camera must "
                         "record at the same frame rate")
    rates = {s.audio_rate for s in sources.values()}
    if len(rates) > 1:
        low = min(sources.values(), key=lambda s: s.audio_rate)
        high = max(sources.values(), key=lambda s: s.audio_rate)
        raise ValueError(f"{high.path}: audio at {high.audio_rate} Hz, but {low.path} at {low.audio_rate} Hz: the "
                         "frontend compares the cameras' claps sample by sample, so they must share one rate")
    return sources


def _stretches(rig: RigFile, sources: dict[tuple[str, str], CameraFile], log) -> dict[tuple[str, str], TrialStretch]:
    """Each trial's stretch of each camera's file: given times, the claps, or the whole file."""
    several = {(c, s.path): s for (_, c), s in sources.items() if len(s.trials) > 1}  # files to cut by their claps
    cuts = _cut_by_claps(several, rig.margin_s, log) if rig.split == "claps" else {}
    stretches = {}
    for cam in rig.cameras:
        for trial in rig.trials:
            source = sources[(trial, cam.name)]
            span = cam.times.get(trial) or (rig.times.get(trial) if rig.split == "times" else None)
            if span is not None:
                field = f"cameras.{cam.name}.times.{trial}" if trial in cam.times else f"trials.times.{trial}"
                first, count = _stretch_from_times(source, span, f"{rig.path}: {field}")
            elif (trial, cam.name) in cuts:
                first, count = cuts[(trial, cam.name)]
            elif rig.split == "times":
                raise ValueError(f"{rig.path}: trials.times.{trial} missing (split = \"times\"; camera {cam.name!r})")
            else:
                first, count = 0, source.num_frames  # the file holds this trial alone
            stretches[(trial, cam.name)] = TrialStretch(source, first, count)
    return stretches


def _check_sync(rig: RigFile, stretches: dict[tuple[str, str], TrialStretch]) -> dict[str, dict]:
    """Synchronise each trial as the frontend will; ``{trial: {"first_clap_frames", "seconds_between_claps"}}``."""
    found = {}
    for trial in rig.trials:
        tracks = []
        for cam in rig.cameras:
            s = stretches[(trial, cam.name)]
            tracks.append(s.source.audio(s.first_frame / s.source.fps, (s.first_frame + s.num_frames) / s.source.fps))
        first = stretches[(trial, rig.cameras[0].name)].source
        try:
            result = synchronize_tracks(tracks, first.audio_rate, first.fps, cameras=[c.name for c in rig.cameras])
        except ValueError as err:
            raise ValueError(f"trial {trial!r}: the cameras' audio cannot be synchronised by two claps ({err}); check "
                             f"the trial's times or margin in {rig.path}") from None
        found[trial] = {"first_clap_frames": result.offsets.tolist(), "seconds_between_claps": round(result.duration_s, 4)}
    return found


def _takes(rig: RigFile, paths: dict[str, dict[str, Path]]) -> dict[Path, list[Path]]:
    """``{file named: the chapters of its take}`` (:func:`~bcmocap.io.chapters.take_chapters`). ValueError naming the
    rig field when a named file is a later chapter of a take (it is joined to the take's first chapter, so the rig
    must name that one)."""
    takes = {}
    for camera, files in paths.items():
        for trial, path in files.items():
            if path not in takes:  # a file named for several trials: its folder listed once
                takes[path] = take_chapters(path)
            chapters = takes[path]
            if chapters[0] != path:
                raise ValueError(f"{rig.path}: cameras.{camera}.video names {path.name} for trial {trial!r}, but by "
                                 f"GoPro's naming it is chapter {chapters.index(path) + 1} of the take that starts with "
                                 f"{chapters[0].name} (its chapters are joined); name each take by its first chapter")
    return takes


def _join_takes(takes: dict[Path, list[Path]], work: Path, log) -> dict[Path, tuple[Path, list[float]]]:
    """The takes of several chapters joined into ``work/.chapters/`` (:func:`~bcmocap.io.chapters.join_chapters`):
    ``{file named: (the joined file, each chapter's start in it, s)}``."""
    joined = {}
    for number, (path, chapters) in enumerate(sorted(takes.items())):
        if len(chapters) < 2:
            continue
        folder = work / ".chapters"
        folder.mkdir(exist_ok=True)
        out = folder / f"{number}-{checked_name(chapters[0].stem, 'a video name', str(chapters[0]))}.mp4"
        starts = join_chapters(chapters, out)
        joined[path] = (out, starts)
        log(f"joined {len(chapters)} chapters of one take: {', '.join(c.name for c in chapters)}")
    return joined


def _gopro_imu(path: Path):
    """A file's GoPro telemetry, or None (a container GoPro does not write, or no GPMF track)."""
    return read_gopro_imu(path) if path.suffix.lower() in (".mp4", ".mov", ".lrv") else None


def _telemetry(path: Path, chapters: tuple[list[Path], list[float]] | None):
    """A camera file's GoPro telemetry (None without), a joined take's from its chapters on the joined clock."""
    from ..io.gopro import GoProImu, SensorSamples

    if chapters is None:
        return _gopro_imu(path)
    parts = [_gopro_imu(c) for c in chapters[0]]
    if all(p is None for p in parts):
        return None
    if any(p is None for p in parts):
        missing = next(c for c, p in zip(chapters[0], parts) if p is None)
        raise ValueError(f"{missing}: a chapter without the telemetry the take's other chapters carry")

    ends = [*chapters[1][1:], np.inf]  # a chapter's samples past its video's end (its last payload's fit) are dropped

    def joined(kind: str):
        samples = [getattr(p, kind) for p in parts]
        if any(x is None for x in samples):
            return None
        keep = [x.time_s + start < end for x, start, end in zip(samples, chapters[1], ends)]
        return SensorSamples(np.concatenate([x.time_s[k] + start for x, k, start in zip(samples, keep, chapters[1])]),
                             np.concatenate([x.values[k] for x, k in zip(samples, keep)]),
                             float(np.median([x.rate_hz for x in samples])))

    gyro = joined("gyro")
    if np.any(np.diff(gyro.time_s) <= 0):
        raise ValueError(f"{chapters[0][0]}: the chapters' gyro samples overlap in time once joined")
    return GoProImu(path, parts[0].device, gyro, joined("accel"), parts[0].channels)


def _trial_imus(rig: RigFile, stretches: dict[tuple[str, str], TrialStretch], claps: dict[str, dict],
                chapters: dict[Path, tuple[list[Path], list[float]]], log) -> dict[str, ImuRecording]:
    """Each trial's ``imu.npz`` content from the cameras' own telemetry (:mod:`.telemetry`; GoPro files), for the
    trials where some camera has any; a line saying which cameras have none (their gyro terms are then off)."""
    found = {}
    for path in {s.source.path for s in stretches.values()}:
        found[path] = _telemetry(path, chapters.get(path))
    with_imu = [c.name for c in rig.cameras if any(found[stretches[(t, c.name)].source.path] for t in rig.trials)]
    if not with_imu:
        return {}
    without = [c.name for c in rig.cameras if c.name not in with_imu]
    devices = sorted({imu.device or "?" for imu in found.values() if imu is not None})
    log(f"telemetry (GPMF: {', '.join(devices)}) in {len(with_imu)} of {len(rig.cameras)} cameras"
        + (f"; none in {', '.join(without)}: their gyro terms are off" if without else ""))
    imus = {}
    for trial in rig.trials:
        cameras = []
        for c, cam in enumerate(rig.cameras):
            s = stretches[(trial, cam.name)]
            cameras.append(CameraTelemetry(cam.name, found[s.source.path], s.first_frame, s.num_frames,
                                           int(claps[trial]["first_clap_frames"][c]), s.source.fps))
        recording = trial_imu(cameras, where=f"trial {trial!r}")
        if recording is not None:
            imus[trial] = recording
    return imus


def _calibration_files(rig: RigFile, calibration: Path, size: dict[str, tuple[int, int]]) -> dict[str, list[Path]]:
    """``{camera: [lens .json and/or cv2.fisheye .yml]}``, each read and checked against the video's size."""
    out = {}
    for cam in rig.cameras:
        stem = cam.lens or cam.name
        files = [calibration / f"{stem}{suffix}" for suffix in CALIBRATION_SUFFIXES
                 if (calibration / f"{stem}{suffix}").is_file()]
        if not files:
            field = f"cameras.{cam.name}.lens" if cam.lens else f"cameras.{cam.name} (no lens given)"
            raise ValueError(f"{calibration}: no calibration {stem}.json or {stem}.yml for camera {cam.name!r} "
                             f"({rig.path}: {field}); `bcmocap calibrate` writes them")
        lens = [f for f in files if f.suffix == ".json"][:1]
        fisheye = [f for f in files if f.suffix != ".json"][:1]
        for file in lens + fisheye:
            camera = read_camera_json(file) if file.suffix == ".json" else read_opencv_fisheye_calibration(file)
            if (camera.width, camera.height) != size[cam.name]:
                raise ValueError(f"{file}: calibrated for {camera.width} x {camera.height} images, but camera "
                                 f"{cam.name!r} records {size[cam.name][0]} x {size[cam.name][1]} (another resolution "
                                 "or field-of-view mode is another lens)")
        out[cam.name] = lens + fisheye
    return out


def _reference_files(folder: Path | None) -> tuple[list[Path], list[Path]]:
    """The photos (plain names, checked) and the camera files ``camera.json`` / ``camera.yml`` of a folder."""
    if folder is None:
        return [], []
    if not folder.is_dir():
        raise ValueError(f"{folder}: reference photo folder does not exist")
    photos = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES and p.is_file())
    for p in photos:
        checked_name(p.name, "photo name", folder)
    if not photos:
        raise ValueError(f"{folder}: no reference photos (.jpg, .jpeg or .png)")
    cameras = [folder / n for n in ("camera.json", "camera.yml") if (folder / n).is_file()]
    if cameras and cameras[0].name == "camera.json":
        read_camera_json(cameras[0])
    return photos, cameras


def _suffix(path: Path) -> str:
    """The file's extension, lower-cased, if it is a plain one (``.mp4``, ``.mts``…), else none: the name of the
    link is the camera's; the extension only helps a person, FFmpeg reads the container from the content."""
    suffix = path.suffix.lower()
    return suffix if re.fullmatch(r"\.[a-z0-9]{1,8}", suffix) else ""


def _place(source: Path, target: Path, copy: bool) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    if copy:
        shutil.copyfile(source, target)
    else:
        os.symlink(source.resolve(), target)


def _check_target(capture_dir: Path) -> None:
    if capture_dir.exists() and (not capture_dir.is_dir() or any(capture_dir.iterdir())):
        raise ValueError(f"{capture_dir}: exists and is not an empty folder; bcmocap init writes a new capture folder "
                         "and overwrites nothing")


def assemble_capture(capture_dir: str | os.PathLike, videos: str | os.PathLike, rig: RigFile, *,
                     calibration: str | os.PathLike, reference_photos: str | os.PathLike | None = None,
                     copy: bool = False, log: Callable[[str], None] = print) -> Path:
    """Write a capture folder from a shoot's files (module docstring).

    Args:
        capture_dir: the new folder (must not exist, or be empty).
        videos: the folder of camera files (``CAMERA.<ext>``, ``TRIAL/CAMERA.<ext>``, or as the rig file names them).
        rig: the rig file (:func:`~.rig_file.read_rig_file`).
        calibration: the folder of calibration files (per camera or per lens model).
        reference_photos: the folder of reference photos (and their ``camera.json``), if any.
        copy: copy the videos and photos instead of linking to them.
        log: where progress lines go.

    Returns:
        The folder.

    Raises:
        ValueError: one line naming the file and field at fault; nothing has been written then.
    """
    capture_dir, videos, calibration = Path(capture_dir).absolute(), Path(videos), Path(calibration)
    _check_target(capture_dir)
    if not videos.is_dir():
        raise ValueError(f"{videos}: videos folder does not exist")
    if not calibration.is_dir():
        raise ValueError(f"{calibration}: calibration folder does not exist")
    paths = _find_videos(rig, videos)
    takes = _takes(rig, paths)
    capture_dir.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{capture_dir.name}.init-", dir=capture_dir.parent))
    try:
        joined = _join_takes(takes, work, log)  # file named in paths -> (its take joined, each chapter's start)
        paths = {camera: {t: joined[p][0] if p in joined else p for t, p in files.items()} for camera, files in paths.items()}
        try:
            sources = _probe_all(rig, paths)
            first = sources[(rig.trials[0], rig.cameras[0].name)]
            lenses = _calibration_files(rig, calibration, {c: (s.width, s.height) for (_, c), s in sources.items()})
            photos, photo_cameras = _reference_files(None if reference_photos is None else Path(reference_photos))
            stretches = _stretches(rig, sources, log)  # the audio work last: the cheap checks fail first
            claps = _check_sync(rig, stretches)
            chapters = {file: (takes[source], starts) for source, (file, starts) in joined.items()}
            imus = _trial_imus(rig, stretches, claps, chapters, log)
        except ValueError as err:  # name the user's chapters, not the joined take in the temporary folder
            message = str(err)
            for source, (file, _) in joined.items():
                message = message.replace(str(file), f"the take joined from {', '.join(str(c) for c in takes[source])}")
            raise ValueError(message) from None

        placed: dict[Path, tuple[Path, Path]] = {}  # source file -> its path in the capture, and its WAV's
        entries = []
        for cam in rig.cameras:
            entry = {"name": cam.name, "segment": cam.segment}
            if cam.mount:
                entry["mount"] = cam.mount
            if cam.lens:
                entry["lens_model"] = cam.lens
            for file in lenses[cam.name]:
                target = intrinsics_path(work, cam.name, file.suffix)
                _place(file, target, copy=True)
                entry["lens" if file.suffix == ".json" else "intrinsics"] = relative_name(work, target)
            entry["video"], audio = {}, {}
            for trial in rig.trials:
                s = stretches[(trial, cam.name)]
                if s.source.path not in placed:
                    suffix = _suffix(s.source.path)
                    if len(s.source.trials) > 1:  # videos/<camera>.<ext>, cut by the stretches in rig.json
                        target = shared_video_path(work, cam.name, suffix)
                        wav = shared_video_path(work, cam.name, ".wav")
                    else:
                        target = trial_video_path(work, trial, cam.name, suffix)
                        wav = trial_audio_path(work, trial, cam.name)
                    if s.source.path in chapters:  # a take joined from its chapters: made here, moved in
                        target.parent.mkdir(parents=True, exist_ok=True)
                        os.replace(s.source.path, target)
                    else:
                        _place(s.source.path, target, copy)
                    if s.source.wav is not None:
                        _place(s.source.wav, wav, copy)
                    placed[s.source.path] = (target, wav)
                target, wav = placed[s.source.path]
                entry["video"][trial] = {"file": relative_name(work, target), "first_frame": s.first_frame,
                                         "num_frames": s.num_frames}
                if s.source.wav is not None:
                    audio[trial] = relative_name(work, wav)
            if audio:
                entry["audio"] = audio
            entries.append(entry)
        for photo in photos:
            _place(photo, reference_photo_path(work, photo.name), copy)
        for file in photo_cameras:
            _place(file, reference_camera_path(work, file.suffix), copy=True)
        for trial, recording in imus.items():
            trial_dir(work, trial).mkdir(parents=True, exist_ok=True)
            write_imu(trial_dir(work, trial) / IMU_FILE, recording)
        shutil.rmtree(work / ".chapters", ignore_errors=True)  # the joined takes are in place
        write_json(rig_path(work), {"cameras": entries, "segments": list(rig.segment_names)})
        manifest = new_manifest(
            fps=first.fps,
            audio_rate=first.audio_rate,
            cameras=[c.name for c in rig.cameras],
            trials=list(rig.trials),
            subject=subject_record(rig.segments, rig.measurements, rig.rest),
            made_by={"command": "bcmocap init", "videos": str(videos.resolve()),
                     "rig": str(rig.path.resolve()) if rig.path else None, "copied": copy, "split": rig.split,
                     "margin_s": rig.margin_s},
            claps=claps,
            complete=True,
        )
        write_manifest(work, manifest)
        read_capture(work)  # what the frontend will read: any inconsistency fails here, before the rename
        if capture_dir.exists():  # an empty folder the user made: filled, the manifest last
            for child in sorted(work.iterdir(), key=lambda p: p == manifest_path(work)):
                os.rename(child, capture_dir / child.name)
            work.rmdir()
        else:
            os.rename(work, capture_dir)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    log(f"wrote {capture_dir}: {len(rig.cameras)} cameras, trials "
        + ", ".join(f"{t} ({min(stretches[(t, c.name)].num_frames for c in rig.cameras)}-"
                    f"{max(stretches[(t, c.name)].num_frames for c in rig.cameras)} frames, claps "
                    f"{claps[t]['seconds_between_claps']:.2f} s apart)" for t in rig.trials)
        + f" at {first.fps:g} frames/s; videos {'copied' if copy else 'linked'}, {len(photos)} reference photos")
    return capture_dir
