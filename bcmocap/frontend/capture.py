"""Reading a capture folder: manifest, rig, intrinsics, trials, videos (decoded lazily) and soundtracks.

The layout is specified in :mod:`bcmocap.io.capture_folder` (what :mod:`bcmocap.sim.studio` writes, and a real
shoot is arranged into by ``bcmocap init``)::

    capture.json, rig.json, intrinsics/<camera>.yml|.json, reference/photo_*.jpg, reference/camera.json|.yml,
    trials/<trial>/<camera>.mp4, trials/<trial>/<camera>.wav

A camera's entry in ``rig.json`` may say where its videos are instead (a stretch of a longer file; see
:mod:`bcmocap.io.capture_folder`). A trial's soundtrack is the WAV when it exists (cut to the stretch), else the audio
track inside the video itself (read with PyAV, :func:`bcmocap.io.media.read_audio_track`); sample 0 is
the time of the trial's first video frame either way.

:func:`read_capture` checks that every file the frontend needs exists and parses the small ones; the
videos are only opened when :meth:`Capture.frames` is iterated, one camera at a time, so a long capture
never has to fit in memory. Errors are ``ValueError`` naming the file and what was expected.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..cameras import CameraModel
from ..io.capture_folder import (
    intrinsics_path,
    lens_path,
    read_json,
    read_manifest,
    reference_camera_path,
    reference_dir,
    relative_name,
    rig_path,
    trial_audio_path,
    trial_video_path,
)
from ..io.colmap import from_pycolmap
from ..io.names import checked_name, checked_relative_path
from ..io.opencv_calibration import read_opencv_fisheye_calibration
from ..native_crashes import load_pycolmap

__all__ = ["Capture", "CaptureCamera", "TrialVideo", "VideoInfo", "read_capture", "read_camera_json"]

MAX_IMAGE_SIDE = 100_000  # px


def lens_fingerprint(lenses) -> str:
    """A hash of camera models (class, image size, parameters to 1e-9) for cache keys."""
    import hashlib

    import jax

    text = repr([(type(lens).__name__, int(lens.width), int(lens.height),
                  [np.round(np.asarray(x, np.float64), 9).tolist() for x in jax.tree.leaves(lens)]) for lens in lenses])
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def read_camera_json(path: str | os.PathLike) -> CameraModel:
    """A lens file ``{"model": "FOV" | "OPENCV_FISHEYE" | "THIN_PRISM_FISHEYE" | "PINHOLE", "width", "height",
    "params"}`` (COLMAP's parameter order, OpenCV pixel convention) as a camera model."""
    pycolmap = load_pycolmap()

    path = Path(path)
    data = read_json(path)
    try:
        params = [float(x) for x in data["params"]]
        width, height, model = int(data["width"]), int(data["height"]), str(data["model"])
    except KeyError as err:
        raise ValueError(f"{path}: missing field {err} (need model, width, height, params)") from None
    except (TypeError, ValueError, OverflowError) as err:
        raise ValueError(f"{path}: malformed camera field ({err})") from None
    if not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE) or not all(map(math.isfinite, params)):
        raise ValueError(f"{path}: width and height must be in [1, {MAX_IMAGE_SIDE}] px and params finite, got "
                         f"{width} x {height}, {params}")
    expected = {"FOV": 5, "OPENCV_FISHEYE": 8, "THIN_PRISM_FISHEYE": 12, "PINHOLE": 4}
    if expected.get(model) != len(params):
        raise ValueError(f"{path}: model {model!r} with {len(params)} params; expected one of "
                         f"{', '.join(f'{m} ({n} params)' for m, n in expected.items())}")
    colmap_params = list(params)
    colmap_params[2] += 0.5  # OpenCV -> COLMAP pixel convention (from_pycolmap shifts back)
    colmap_params[3] += 0.5
    return from_pycolmap(pycolmap.Camera(model=model, width=width, height=height, params=colmap_params))


@dataclasses.dataclass(frozen=True)
class VideoInfo:
    """What the container says about one video: frame count, size (px) and rate (Hz)."""

    num_frames: int
    width: int
    height: int
    fps: float


@dataclasses.dataclass(frozen=True)
class TrialVideo:
    """Where one camera's video of one trial is: ``file``, from its frame ``first_frame`` on, for
    ``num_frames`` frames (None: to the end of the file), and its WAV soundtrack ``audio`` if it has one
    beside it (None: the default ``trials/<trial>/<camera>.wav``, else the video's own audio track)."""

    file: Path
    first_frame: int = 0
    num_frames: int | None = None
    audio: Path | None = None


@dataclasses.dataclass(frozen=True)
class CaptureCamera:
    """One body camera: its name, the body segment it is strapped to, and its intrinsics."""

    name: str
    segment: str
    intrinsics: CameraModel
    intrinsics_file: Path


@dataclasses.dataclass(frozen=True)
class Capture:
    """A capture folder, read by :func:`read_capture`.

    Attributes:
        path: the folder.
        manifest: ``capture.json``.
        fps: video frame rate (Hz); audio_rate: soundtrack sample rate (Hz), if the manifest gives it.
        cameras: the body cameras, in manifest order.
        segments: body segment names from ``rig.json``.
        trials: trial names (e.g. ``("rom", "capture")``).
        reference_photos: paths of the reference photos (sorted); reference_camera their intrinsics
            (``None`` without ``reference/camera.json``; the pinhole ``.yml`` beside it is not read).
        videos: ``{(trial, camera): TrialVideo}`` where ``rig.json`` places a video elsewhere than
            ``trials/<trial>/<camera>.mp4`` or gives only a stretch of it.
        corrections: ``{trial: correction}``: every frame of the trial that :meth:`frames` decodes is passed through
            ``correction(camera index, frame index, image)`` (e.g. :class:`~.rolling_shutter.GyroUnwarp`; its
            ``settings`` join the frame caches' keys, :meth:`correction_settings`). Set by :meth:`corrected`.
    """

    path: Path
    manifest: dict
    fps: float
    audio_rate: int | None
    cameras: tuple[CaptureCamera, ...]
    segments: tuple[str, ...]
    trials: tuple[str, ...]
    reference_photos: tuple[Path, ...]
    reference_camera: CameraModel | None
    videos: dict = dataclasses.field(default_factory=dict)
    corrections: dict = dataclasses.field(default_factory=dict)

    def corrected(self, trial: str, correction) -> Capture:
        """This capture with every decoded frame of ``trial`` passed through ``correction`` (see ``corrections``)."""
        return dataclasses.replace(self, corrections={**self.corrections, self._trial(trial): correction})

    def correction_settings(self, trial: str) -> dict:
        """What the trial's frames depend on besides the videos: ``{}`` without a correction, else the
        correction's ``settings``; caches of anything computed from frames include it in their keys."""
        correction = self.corrections.get(trial)
        return {} if correction is None else dict(correction.settings)

    def lens_fingerprint(self) -> str:
        """:func:`lens_fingerprint` of the cameras' intrinsics: the tracking cache's key includes it, and the
        pipeline's frontend self-calibration records the given lenses' in its saved registrations."""
        return lens_fingerprint(c.intrinsics for c in self.cameras)

    def with_lenses(self, lenses) -> Capture:
        """This capture with each camera's intrinsics replaced by ``lenses`` (one per camera, in order; e.g. the
        self-calibrated ones)."""
        lenses = list(lenses)
        if len(lenses) != len(self.cameras):
            raise ValueError(f"with_lenses: {len(lenses)} lenses for {len(self.cameras)} cameras")
        return dataclasses.replace(self, cameras=tuple(dataclasses.replace(c, intrinsics=lens)
                                                       for c, lens in zip(self.cameras, lenses)))

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cameras)

    def camera_index(self, camera: str | int) -> int:
        if isinstance(camera, (int, np.integer)):
            if not 0 <= int(camera) < len(self.cameras):
                raise ValueError(f"camera index {camera} out of range [0, {len(self.cameras)})")
            return int(camera)
        try:
            return self.camera_names.index(camera)
        except ValueError:
            raise ValueError(f"{self.path}: no camera {camera!r}; cameras are {list(self.camera_names)}") from None

    def _trial(self, trial: str) -> str:
        if trial not in self.trials:
            raise ValueError(f"{self.path}: no trial {trial!r}; trials are {list(self.trials)}")
        return trial

    def trial_video(self, trial: str, camera: str | int) -> TrialVideo:
        """Where the camera's video of the trial is (the file, the stretch of it, the WAV beside it)."""
        name = self.cameras[self.camera_index(camera)].name
        default = trial_video_path(self.path, self._trial(trial), name)
        return self.videos.get((trial, name), TrialVideo(default))

    def video_path(self, trial: str, camera: str | int) -> Path:
        return self.trial_video(trial, camera).file

    def audio_path(self, trial: str, camera: str | int) -> Path:
        """The trial's WAV soundtrack, which need not exist (the video's own audio track is used then)."""
        source = self.trial_video(trial, camera)
        if source.audio is not None:
            return source.audio
        return trial_audio_path(self.path, trial, self.cameras[self.camera_index(camera)].name)

    def soundtrack(self, trial: str, camera: str | int) -> tuple[np.ndarray, int]:
        """The camera's audio of the trial: ``(samples (N,) float64 in [-1, 1], rate)``, sample 0 at the trial's
        first video frame. The WAV beside the video when there is one, else the video's own audio track.

        Raises:
            ValueError: naming the files when there is neither, or the one there is cannot be read.
        """
        from ..io.media import read_audio_track
        from ..io.wav import read_wav

        source = self.trial_video(trial, camera)
        wav = self.audio_path(trial, camera)
        if wav.is_file():
            samples, rate = read_wav(wav)
            lo = int(round(source.first_frame * rate / self.fps))
            hi = None if source.num_frames is None else int(round((source.first_frame + source.num_frames) * rate / self.fps))
            return samples[lo:hi], rate
        if not source.file.is_file():
            raise ValueError(f"{wav}: soundtrack missing, and so is the video {source.file}")
        start = source.first_frame / self.fps
        stop = None if source.num_frames is None else (source.first_frame + source.num_frames) / self.fps
        try:
            return read_audio_track(source.file, start, stop)
        except ValueError as err:
            raise ValueError(f"{wav}: soundtrack missing, and the video's own audio cannot be used ({err})") from None

    def _open(self, trial: str, camera: str | int):
        import cv2

        path = self.video_path(trial, camera)
        if not path.is_file():
            raise ValueError(f"{path}: video missing")
        video = cv2.VideoCapture(str(path))
        if not video.isOpened():
            raise ValueError(f"{path}: OpenCV cannot open this video (unreadable or unsupported codec)")
        return path, video

    def video_info(self, trial: str, camera: str | int) -> VideoInfo:
        """The trial's video: its frame count (of the stretch ``rig.json`` gives, if it gives one), size and rate."""
        import cv2

        source = self.trial_video(trial, camera)
        _, video = self._open(trial, camera)
        try:
            count = int(video.get(cv2.CAP_PROP_FRAME_COUNT))
            count = max(count - source.first_frame, 0) if source.num_frames is None else source.num_frames
            return VideoInfo(count, int(video.get(cv2.CAP_PROP_FRAME_WIDTH)),
                             int(video.get(cv2.CAP_PROP_FRAME_HEIGHT)), float(video.get(cv2.CAP_PROP_FPS)))
        finally:
            video.release()

    def frames(self, trial: str, camera: str | int, *, stride: int = 1, start: int = 0, stop: int | None = None,
               gray: bool = False) -> Iterator[tuple[int, np.ndarray]]:
        """Decode one camera's video lazily: ``(frame index, image)`` for ``start, start + stride, …``
        before ``stop`` (BGR ``uint8 (H, W, 3)``, or ``(H, W)`` with ``gray``), through the trial's correction if it
        has one (``corrections``).

        Frames in between are grabbed without being decoded to images. The video is opened when
        iteration begins and closed when it ends. Indices count from the trial's first frame (frame
        ``first_frame`` of the file when the trial is a stretch of a longer video, reached by grabbing).

        Raises:
            ValueError: naming the video if it is missing or unreadable, or if it ends before its first
                requested frame could be read.
        """
        import cv2

        if stride < 1 or start < 0:
            raise ValueError(f"frames: stride must be >= 1 and start >= 0, got stride={stride}, start={start}")
        source = self.trial_video(trial, camera)
        if source.num_frames is not None:
            stop = source.num_frames if stop is None else min(stop, source.num_frames)
        correction, camera_index = self.corrections.get(trial), self.camera_index(camera)
        path, video = self._open(trial, camera)
        try:
            for skipped in range(source.first_frame):  # exact: OpenCV's seeking may land near, not on, a frame
                if not video.grab():
                    raise ValueError(f"{path}: ends after {skipped} frames, before the trial's first frame "
                                     f"{source.first_frame} (rig.json)")
            index = 0
            while stop is None or index < stop:
                wanted = index >= start and (index - start) % stride == 0
                if not video.grab():
                    if index == 0:
                        raise ValueError(f"{path}: no frame could be decoded")
                    return
                if wanted:
                    ok, image = video.retrieve()
                    if not ok:
                        raise ValueError(f"{path}: frame {index} could not be decoded")
                    if gray:
                        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
                    yield index, (image if correction is None else correction(camera_index, index, image))
                index += 1
        finally:
            video.release()


def read_capture(path: str | os.PathLike, *, check_files: bool = True) -> Capture:
    """Read a capture folder's manifest, rig and intrinsics, and list its trials, videos and photos.

    Each camera's intrinsics come from ``intrinsics/<camera>.json`` (the exact lens) when present,
    else from the ``cv2.fisheye`` calibration ``intrinsics/<camera>.yml``.

    Args:
        path: the capture folder.
        check_files: check that every trial has a video and a soundtrack per camera.

    Raises:
        ValueError: naming the missing or malformed file (and field).
    """
    folder = Path(path)
    checked = read_manifest(folder, require_complete=True, require_fps=True)
    manifest, manifest_path, trials = checked.data, checked.path, list(checked.trials)

    rig_file = rig_path(folder)
    rig = read_json(rig_file)
    entries = rig.get("cameras")
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{rig_file}: field 'cameras' must be a non-empty list")
    cameras = []
    videos: dict[tuple[str, str], TrialVideo] = {}
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict) or "name" not in entry or "segment" not in entry:
            raise ValueError(f"{rig_file}: cameras[{i}] needs fields 'name' and 'segment'")
        name = checked_name(entry["name"], f"cameras[{i}].name", rig_file)
        videos.update(_trial_videos(folder, entry, i, name, trials, rig_file))
        segment = entry["segment"]
        if not isinstance(segment, str) or not segment:
            raise ValueError(f"{rig_file}: cameras[{i}].segment must be a segment name, got {segment!r}")
        lens = (folder / checked_relative_path(entry["lens"], f"cameras[{i}].lens", rig_file) if "lens" in entry
                else lens_path(folder, name))
        calib = (folder / checked_relative_path(entry["intrinsics"], f"cameras[{i}].intrinsics", rig_file)
                 if "intrinsics" in entry else intrinsics_path(folder, name))
        if lens.is_file():
            cameras.append(CaptureCamera(name, segment, read_camera_json(lens), lens))
        elif calib.is_file():
            cameras.append(CaptureCamera(name, segment, read_opencv_fisheye_calibration(calib), calib))
        else:
            raise ValueError(f"{calib}: intrinsics of camera {name!r} missing (nor {lens.name} beside it)")
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise ValueError(f"{rig_file}: field 'cameras' names a camera twice: {names}")
    if "cameras" in manifest:
        listed = manifest["cameras"]
        if not isinstance(listed, list) or listed != names:
            raise ValueError(f"{rig_file}: cameras {names} differ from those in {manifest_path}: {listed!r}")

    if check_files:
        from ..io.media import probe_media

        for trial in trials:
            for name in names:
                source = videos.get((trial, name), TrialVideo(trial_video_path(folder, trial, name)))
                if not source.file.is_file():
                    raise ValueError(f"{source.file}: missing (video of camera {name!r} in trial {trial!r})")
                wav = source.audio or trial_audio_path(folder, trial, name)
                if not wav.is_file() and not probe_media(source.file).has_audio:
                    raise ValueError(f"{wav}: missing (soundtrack of camera {name!r} in trial {trial!r}), and the "
                                     f"video {source.file.name} has no audio track of its own")

    ref = reference_dir(folder)
    photos = tuple(sorted(p for p in ref.glob("*") if p.suffix.lower() in (".jpg", ".jpeg", ".png"))) if ref.is_dir() else ()
    if reference_camera_path(folder).is_file():
        ref_camera = read_camera_json(reference_camera_path(folder))
    else:
        ref_camera = None
    segments = rig.get("segments", [])
    if not isinstance(segments, list) or not all(isinstance(s, str) for s in segments):
        raise ValueError(f"{rig_file}: field 'segments' must be a list of names, got {segments!r}")
    return Capture(folder, manifest, checked.fps, checked.audio_rate, tuple(cameras), tuple(segments), tuple(trials),
                   photos, ref_camera, videos)


def _trial_videos(folder: Path, entry: dict, i: int, name: str, trials: list[str],
                  rig_file: Path) -> dict[tuple[str, str], TrialVideo]:
    """The ``video`` and ``audio`` fields of camera ``i``'s entry in ``rig.json`` (:mod:`bcmocap.io.capture_folder`)."""
    where = f"cameras[{i}]"
    found = {}
    video, audio = entry.get("video", {}), entry.get("audio", {})
    for field, value in (("video", video), ("audio", audio)):
        if not isinstance(value, dict):
            raise ValueError(f"{rig_file}: {where}.{field} must map trial names to files, got {value!r}")
        unknown = sorted(set(value) - set(trials))
        if unknown:
            raise ValueError(f"{rig_file}: {where}.{field} names trials {unknown} that capture.json does not list")
    for trial in trials:
        spec = video.get(trial, relative_name(folder, trial_video_path(folder, trial, name)))
        first, count = 0, None
        if isinstance(spec, dict):
            first, count = spec.get("first_frame", 0), spec.get("num_frames")
            for key, value, least in (("first_frame", first, 0), ("num_frames", count, 1)):
                if value is None and key == "num_frames":
                    continue
                if isinstance(value, bool) or not isinstance(value, int) or value < least:
                    raise ValueError(f"{rig_file}: {where}.video.{trial}.{key} must be a whole number >= {least}, "
                                     f"got {value!r}")
            spec = spec.get("file")
        file = folder / checked_relative_path(spec, f"{where}.video.{trial}", rig_file)
        wav = (folder / checked_relative_path(audio[trial], f"{where}.audio.{trial}", rig_file)
               if trial in audio else None)
        if trial in video or wav is not None:
            found[(trial, name)] = TrialVideo(file, first, count, wav)
    return found
