"""Camera files with their own audio, through PyAV (FFmpeg's libraries, shipped inside its wheels).

A body camera's file holds a video stream and, usually, an audio track (MP4/MOV with H.264 or H.265 and
AAC). :func:`probe_media` says what a file holds; :func:`read_audio_track` decodes its audio as one mono
track whose sample 0 is the time of the **first video frame** (the convention of the WAV files a capture
keeps beside its videos, :mod:`bcmocap.io.wav`), so claps found in it date video frames directly;
:class:`MediaWriter` writes frames and a soundtrack into one H.264 + AAC MP4 (what ``bcmocap simulate
--container mp4-aac`` writes, so a rendered capture looks like a real shoot).

Frames themselves are decoded by OpenCV (:mod:`bcmocap.frontend.capture`), whose FFmpeg numbers them
the same way: frame 0 is the first decoded frame. Errors are ``ValueError`` naming the file.
"""

from __future__ import annotations

import dataclasses
import os
from fractions import Fraction
from pathlib import Path

import numpy as np

__all__ = ["MediaInfo", "MediaWriter", "probe_media", "read_audio_track"]

_SCALE = {"s16": 32768.0, "s32": 2147483648.0, "u8": 128.0}


@dataclasses.dataclass(frozen=True)
class MediaInfo:
    """What a camera file's container says.

    Attributes:
        path: the file.
        video_codec: name of the first video stream's codec (``None`` without video).
        width, height: its frame size (px, 0 without video); fps its average frame rate (Hz, 0 if unknown).
        num_frames: frames the container's index lists (0 if it does not say).
        audio_codec: name of the first audio stream's codec (``None`` without an audio track).
        audio_rate: its sample rate (Hz, 0 without audio); audio_channels its channel count.
        duration_s: the container's duration (s, 0 if unknown).
    """

    path: Path
    video_codec: str | None
    width: int
    height: int
    fps: float
    num_frames: int
    audio_codec: str | None
    audio_rate: int
    audio_channels: int
    duration_s: float

    @property
    def has_audio(self) -> bool:
        return self.audio_codec is not None


def _open(path: Path, mode: str = "r"):
    import av

    if mode == "r" and not path.is_file():
        raise ValueError(f"{path}: missing (expected a video file)")
    try:
        return av.open(str(path), mode)
    except (av.FFmpegError, OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: FFmpeg (PyAV) cannot open it as a media file ({' '.join(str(err).split())})") from None


def probe_media(path: str | os.PathLike) -> MediaInfo:
    """The streams of a camera file (no frame is decoded).

    Raises:
        ValueError: the file is missing or FFmpeg cannot read its container.
    """
    path = Path(path)
    with _open(path) as container:
        video = container.streams.video[0] if container.streams.video else None
        audio = container.streams.audio[0] if container.streams.audio else None
        fps = float(video.average_rate) if video is not None and video.average_rate else 0.0
        duration = container.duration / 1_000_000 if container.duration else 0.0  # AV_TIME_BASE units
        return MediaInfo(
            path=path,
            video_codec=video.codec_context.name if video is not None else None,
            width=int(video.codec_context.width) if video is not None else 0,
            height=int(video.codec_context.height) if video is not None else 0,
            fps=fps,
            num_frames=int(video.frames or 0) if video is not None else 0,
            audio_codec=audio.codec_context.name if audio is not None else None,
            audio_rate=int(audio.codec_context.sample_rate or 0) if audio is not None else 0,
            audio_channels=int(audio.codec_context.channels or 0) if audio is not None else 0,
            duration_s=duration,
        )


def _mono(frame) -> np.ndarray:
    """One decoded audio frame as float64 mono samples in [-1, 1] (channels averaged)."""
    data = frame.to_ndarray()
    channels = max(len(frame.layout.channels), 1)
    if not frame.format.is_planar:  # packed: (1, samples * channels), interleaved
        data = data.reshape(-1, channels).T
    data = data.astype(np.float64)
    name = frame.format.name.rstrip("p")
    if name == "u8":
        data = (data - 128.0) / 128.0
    elif name in _SCALE:
        data = data / _SCALE[name]
    return data.mean(axis=0)


def _origin(container) -> Fraction:
    """Time (s) of the first video frame: sample 0 of the track :func:`read_audio_track` returns."""
    if container.streams.video:
        video = container.streams.video[0]
        if video.start_time is not None and video.time_base is not None:
            return video.start_time * video.time_base
    return Fraction(0)


def read_audio_track(path: str | os.PathLike, start_s: float = 0.0, stop_s: float | None = None) -> tuple[np.ndarray, int]:
    """The first audio track of a camera file, mono, from ``start_s`` to ``stop_s`` (s after the first video frame).

    Each decoded audio frame is placed by its presentation time, so an audio stream that starts before or
    after the video (encoder priming, a recorder that starts late) comes out aligned with the video; what
    the track does not cover is zeros. Channels are averaged.

    Args:
        path: an MP4, MOV, MKV… with an audio track.
        start_s, stop_s: the stretch to return; ``stop_s`` None reads to the end of the track.

    Returns:
        ``(samples (N,) float64 in [-1, 1], sample rate in Hz)``; with ``stop_s`` given,
        ``N = round(stop_s * rate) - round(start_s * rate)``.

    Raises:
        ValueError: naming the file when it is missing, unreadable, or has no audio track.
    """
    import av

    path = Path(path)
    if start_s < 0 or (stop_s is not None and stop_s < start_s):
        raise ValueError(f"{path}: audio stretch [{start_s}, {stop_s}] s must start at 0 or later and not end before it")
    with _open(path) as container:
        if not container.streams.audio:
            raise ValueError(f"{path}: no audio track (the claps are found in the camera's own audio)")
        stream = container.streams.audio[0]
        rate = int(stream.codec_context.sample_rate or 0)
        if rate <= 0:
            raise ValueError(f"{path}: the audio track has no sample rate")
        origin = _origin(container)
        first = int(round(start_s * rate))
        last = None if stop_s is None else int(round(stop_s * rate))
        if start_s > 2.0 and stream.time_base is not None:
            # Seek a little before the stretch (to a packet boundary at or before it), then decode forward.
            target = int((origin + Fraction(start_s - 1.0).limit_denominator(1_000_000)) / stream.time_base)
            container.seek(max(target, 0), stream=stream, backward=True, any_frame=False)
        pieces: list[tuple[int, np.ndarray]] = []
        position = None  # sample (from the origin) where the next frame starts, when it has no timestamp
        try:
            for frame in container.decode(stream):
                if frame.pts is not None and frame.time_base is not None:
                    position = int(round((frame.pts * frame.time_base - origin) * rate))
                elif position is None:
                    position = 0
                samples = _mono(frame)
                end = position + len(samples)
                if end > first and (last is None or position < last):
                    pieces.append((position, samples))
                position = end
                if last is not None and position >= last:
                    break
        except av.FFmpegError as err:
            raise ValueError(f"{path}: the audio track cannot be decoded ({' '.join(str(err).split())})") from None
    if last is None:
        last = max([p + len(s) for p, s in pieces], default=first)
    track = np.zeros(max(last - first, 0))
    for position, samples in pieces:
        lo, hi = max(position, first), min(position + len(samples), last)
        if hi > lo:
            track[lo - first: hi - first] = samples[lo - position: hi - position]
    return np.clip(track, -1.0, 1.0), rate


class MediaWriter:
    """One MP4 with an H.264 video stream and, if ``audio_rate`` is given, a mono AAC track.

    Frames are given as RGB ``uint8 (H, W, 3)`` and numbered from 0 at ``fps``; the soundtrack (samples in
    [-1, 1], sample 0 at the first frame) may be given in pieces, before, between or after the frames.
    The encoder runs on one thread with fixed settings, so the same input gives the same bytes.

    Args:
        path: the file to write (replaced).
        fps: frame rate (Hz).
        size: ``(width, height)`` in px, both even (4:2:0 chroma).
        audio_rate: soundtrack sample rate (Hz), or None for no audio track.
        crf: x264 constant rate factor (lower is better; 16 is visually lossless on rendered frames); used
            when ``bitrate`` is None.
        preset: x264 speed preset.
        audio_bitrate: AAC bit rate (bit/s).
        bitrate: video bit rate (bit/s) instead of a quality: x264's one-pass average bit rate with a VBV
            buffer of one second at twice the rate, as a camera's encoder holds a bit rate; None: ``crf``.
        keyframe_interval: frames between keyframes (None: x264's default of 250).
    """

    def __init__(self, path: str | os.PathLike, fps: float, size: tuple[int, int], audio_rate: int | None = None, *,
                 crf: int = 16, preset: str = "fast", audio_bitrate: int = 192_000, bitrate: int | None = None,
                 keyframe_interval: int | None = None):
        width, height = (int(s) for s in size)
        if width % 2 or height % 2 or width < 2 or height < 2:
            raise ValueError(f"{path}: H.264 (4:2:0) needs an even frame size, got {width} x {height}")
        if bitrate is not None and not bitrate > 0:
            raise ValueError(f"{path}: the video bit rate must be positive, got {bitrate}")
        self.path = Path(path)
        self._container = _open(self.path, "w")
        rate = Fraction(fps).limit_denominator(1001)
        self._video = self._container.add_stream("libx264", rate=rate)
        self._video.width, self._video.height, self._video.pix_fmt = width, height, "yuv420p"
        self._video.thread_count = 1  # x264's output depends on its thread count: one thread, the same bytes anywhere
        if bitrate is None:
            self._video.options = {"crf": str(crf), "preset": preset}
        else:
            self._video.bit_rate = int(bitrate)
            self._video.options = {"preset": preset, "maxrate": str(2 * int(bitrate)), "bufsize": str(2 * int(bitrate))}
        if keyframe_interval is not None:
            self._video.options = {**self._video.options, "g": str(int(keyframe_interval))}
        self._audio = None
        if audio_rate is not None:
            self._audio = self._container.add_stream("aac", rate=int(audio_rate))
            self._audio.layout = "mono"
            self._audio.bit_rate = int(audio_bitrate)
        self._frames = 0
        self._samples = 0
        self._size = (height, width)

    def write(self, frames_rgb) -> None:
        """Append frames (each RGB ``uint8 (H, W, 3)``)."""
        import av

        for image in frames_rgb:
            image = np.ascontiguousarray(image, dtype=np.uint8)
            if image.shape != (*self._size, 3):
                raise ValueError(f"{self.path}: frame {self._frames} has shape {image.shape}, expected {(*self._size, 3)}")
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts = self._frames
            self._frames += 1
            self._container.mux(self._video.encode(frame))

    def write_audio(self, samples: np.ndarray) -> None:
        """Append soundtrack samples (mono, in [-1, 1])."""
        import av

        if self._audio is None:
            raise ValueError(f"{self.path}: written without an audio track (audio_rate=None)")
        data = np.clip(np.asarray(samples, np.float64), -1.0, 1.0).astype(np.float32)[None]
        for lo in range(0, data.shape[1], 48_000):
            frame = av.AudioFrame.from_ndarray(np.ascontiguousarray(data[:, lo: lo + 48_000]), format="flt", layout="mono")
            frame.sample_rate = self._audio.rate
            frame.pts = self._samples
            self._samples += frame.samples
            self._container.mux(self._audio.encode(frame))

    def close(self) -> None:
        """Flush the encoders and finish the file."""
        if self._container is None:
            return
        try:
            self._container.mux(self._video.encode(None))
            if self._audio is not None:
                self._container.mux(self._audio.encode(None))
        finally:
            self._container.close()
            self._container = None
