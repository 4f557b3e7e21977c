"""Camera soundtracks with clapper-board claps, as the paper synchronises its cameras (§3, footnote 1).

Each body camera records its own audio from the moment it starts, so the claps at the start and end of a
trial land at a different sample in every camera's track. A soundtrack here is low room noise plus the
two claps: an impulse (the boards meeting) followed by a burst of decaying noise, scaled by a per-camera
gain (distance and direction of the microphone). Sound travel between cameras on one body (< 6 ms) is
neglected, so a clap's first sample is exactly the written position.

Tracks are written as WAV files by :mod:`bcmocap.io.wav` (see :mod:`bcmocap.sim.studio`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["CLAP_SECONDS", "clap_onsets", "soundtrack"]

#: Length of a clap's decaying burst (s).
CLAP_SECONDS = 0.12


def _clap(rate: int, rng: np.random.Generator) -> np.ndarray:
    n = int(round(CLAP_SECONDS * rate))
    t = np.arange(n) / rate
    burst = rng.normal(size=n) * np.exp(-t / 0.012)
    burst /= max(np.abs(burst).max(), 1e-9)
    burst[0] = 1.0  # the boards meeting: a sharp positive pressure peak on the first sample
    return 0.9 * burst


def soundtrack(num_samples: int, clap_samples: Sequence[int], rate: int, rng: np.random.Generator, *,
               gain: float = 1.0, noise_level: float = 0.01) -> np.ndarray:
    """A camera's audio: room noise and a clap starting at each of ``clap_samples``.

    Args:
        num_samples: length of the track (samples).
        clap_samples: first sample of each clap (claps may run past the end; they are cut).
        rate: sample rate (Hz).
        rng: random generator (the noise and the claps' bursts).
        gain: loudness of the claps in this camera (1 = near full scale).
        noise_level: standard deviation of the room noise (full scale = 1).

    Returns:
        ``(num_samples,)`` float64 samples in [-1, 1].
    """
    white = rng.normal(size=num_samples)
    # Slightly low-passed room noise (a one-pole filter written as a recursion-free convolution).
    kernel = 0.6 ** np.arange(16)
    noise = np.convolve(white, kernel / np.linalg.norm(kernel), mode="same") * noise_level
    track = noise
    for start in clap_samples:
        clap = gain * _clap(rate, rng)
        lo, hi = max(int(start), 0), min(int(start) + len(clap), num_samples)
        if hi > lo:
            track[lo:hi] += clap[lo - int(start): hi - int(start)]
    return np.clip(track, -1.0, 1.0)


def clap_onsets(samples: np.ndarray, rate: int, count: int = 2, threshold: float = 0.5,
                min_gap_s: float = 0.25) -> np.ndarray:
    """First samples of the ``count`` loudest claps: where the track first exceeds ``threshold`` times
    its peak, then again at least ``min_gap_s`` later (a simple reference detector, sorted in time)."""
    x = np.abs(np.asarray(samples, np.float64))
    loud = np.flatnonzero(x >= threshold * x.max())
    onsets: list[int] = []
    for i in loud:
        if not onsets or i - onsets[-1] >= min_gap_s * rate:
            onsets.append(int(i))
    if len(onsets) > count:
        peaks = [x[i: i + int(CLAP_SECONDS * rate)].max() for i in onsets]
        keep = np.sort(np.argsort(peaks)[::-1][:count])
        onsets = [onsets[i] for i in keep]
    return np.asarray(onsets, dtype=np.int64)
