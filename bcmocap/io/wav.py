"""Soundtracks as mono 16-bit PCM WAV files, through Python's :mod:`wave` module (OpenCV cannot add an audio
stream to an MP4, so a capture keeps one WAV per camera and trial beside its videos)."""

from __future__ import annotations

import os
import wave
from pathlib import Path

import numpy as np

from ..atomic import atomic_path

__all__ = ["read_wav", "write_wav"]


def write_wav(path: str | os.PathLike, samples: np.ndarray, rate: int) -> Path:
    """Write mono samples in [-1, 1] as 16-bit PCM WAV (atomically: temporary file, then rename)."""
    path = Path(path)
    pcm = np.round(np.clip(np.asarray(samples, np.float64), -1.0, 1.0) * 32767.0).astype("<i2")
    with atomic_path(path) as tmp, wave.open(str(tmp), "wb") as out:
        out.setnchannels(1)
        out.setsampwidth(2)
        out.setframerate(int(rate))
        out.writeframes(pcm.tobytes())
    return path


def read_wav(path: str | os.PathLike) -> tuple[np.ndarray, int]:
    """``(samples in [-1, 1], rate)`` of a mono 16-bit PCM WAV file."""
    path = os.fspath(path)
    try:
        with wave.open(path, "rb") as f:
            if f.getnchannels() != 1 or f.getsampwidth() != 2:
                raise ValueError(
                    f"{path}: expected mono 16-bit PCM, got {f.getnchannels()} channels of {8 * f.getsampwidth()} bits"
                )
            rate = f.getframerate()
            data = np.frombuffer(f.readframes(f.getnframes()), "<i2")
    except (wave.Error, EOFError) as err:
        raise ValueError(f"{path}: not a readable WAV file ({err})") from None
    return data.astype(np.float64) / 32767.0, rate
