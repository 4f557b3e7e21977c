"""Audio synchronisation of the body cameras by the clapper board's two claps (§4.1, footnote 1).

Each camera starts recording at its own moment, so the claps at the start and the end of a trial land at
different samples of each camera's soundtrack, but always the same time apart. For each camera,
:func:`clap_candidates` finds onsets on the track's envelope (a short moving RMS): the loudest local
peaks well above the noise floor, each dated to the first sample of its rise. :func:`synchronize` then
tries every duration between two candidates of any camera, keeps the one most cameras agree on (within
``tolerance_s``; ties go to the louder claps), and takes in each camera the pair closest to it.

Convention: ``offsets[c]`` is the video frame of camera ``c`` in which the first clap happens, so video
frame ``i`` of camera ``c`` shows the common time ``i - offsets[c]`` frames after the first clap, and
``offsets[c] - offsets[d]`` is how many frames camera ``c`` started before camera ``d``.

Cameras start at arbitrary sub-frame times and count time with their own clocks, so the claps also give
what whole frames do not: ``frame_offsets[c]``, the first clap's time in camera ``c``'s video to the audio
sample (1/800 of a frame at 48 kHz and 60 fps), and ``clock_rates[c]``, how fast camera ``c``'s clock runs
against the cameras' median clock, from the samples between its two claps (a 10 s take dates the rate to a
few ppm). Video frame ``i`` of camera ``c`` then shows the common time ``(i - frame_offsets[c]) /
clock_rates[c]`` frames after the first clap. What audio cannot tell is a camera's own delay between its
picture and its sound (an audio latency): it is in ``frame_offsets``.

A camera that recorded several trials in one file has two claps per trial in its track;
:func:`common_claps` finds them all (the candidates of every camera aligned by one shift per camera,
so a bang only some cameras heard is outvoted), which is how ``bcmocap init`` cuts such files into trials.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np

from .capture import Capture

__all__ = ["SyncResult", "clap_candidates", "common_claps", "given_offsets", "synchronize", "synchronize_tracks"]


@dataclasses.dataclass(frozen=True)
class SyncResult:
    """Per-camera frame offsets of one trial.

    Attributes:
        cameras: camera names.
        offsets: ``(C,)`` int, video frame of the first clap in each camera (see the module docstring).
        clap_samples: ``(C, 2)`` int, first sample of each clap in each track (-1 when offsets were given).
        duration_s: time between the two claps (s), NaN when offsets were given.
        agreeing: number of cameras whose claps agree with ``duration_s``.
        frame_offsets: ``(C,)`` float, video frame of the first clap to the audio sample (``offsets`` when given).
        clock_rates: ``(C,)`` each camera's clock rate against the cameras' median clock (1 when offsets were
            given).
    """

    cameras: tuple[str, ...]
    offsets: np.ndarray
    clap_samples: np.ndarray
    duration_s: float
    agreeing: int
    frame_offsets: np.ndarray = None
    clock_rates: np.ndarray = None

    def __post_init__(self):
        if self.frame_offsets is None:
            object.__setattr__(self, "frame_offsets", np.asarray(self.offsets, np.float64))
        if self.clock_rates is None:
            object.__setattr__(self, "clock_rates", np.ones(len(self.cameras)))

    def offset(self, camera: str) -> int:
        return int(self.offsets[self.cameras.index(camera)])


def _envelope(samples: np.ndarray, window: int) -> np.ndarray:
    x2 = np.asarray(samples, np.float64) ** 2
    csum = np.concatenate([[0.0], np.cumsum(x2)])
    n = len(x2)
    hi = np.minimum(np.arange(n) + window, n)
    return np.sqrt((csum[hi] - csum[np.arange(n)]) / window)  # forward-looking: rises at the onset


def clap_candidates(samples: np.ndarray, rate: int, *, max_count: int = 8, min_gap_s: float = 0.15,
                    window_s: float = 0.002, snr: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """Onsets of loud transients in a track: ``(first samples (K,), peak envelope (K,))``, sorted in time.

    The envelope is a forward moving RMS over ``window_s``; a candidate is its maximum over a
    ``min_gap_s`` neighbourhood that exceeds ``snr`` times the median envelope (the noise floor). Its
    onset is the first sample, within two windows of the peak, whose magnitude reaches half the peak
    sample magnitude there. At most the ``max_count`` loudest are kept.
    """
    x = np.asarray(samples, np.float64)
    if x.ndim != 1 or len(x) == 0:
        raise ValueError(f"clap_candidates: expected a non-empty mono track, got shape {x.shape}")
    window = max(int(round(window_s * rate)), 1)
    env = _envelope(x, window)
    floor = max(float(np.median(env)), 1e-9)
    gap = max(int(round(min_gap_s * rate)), 1)
    # Greedy non-maximum suppression from the loudest sample down.
    order = np.argsort(env)[::-1]
    peaks: list[int] = []
    for i in order:
        if env[i] < snr * floor or len(peaks) >= max_count:
            break
        if all(abs(int(i) - p) >= gap for p in peaks):
            peaks.append(int(i))
    onsets, levels = [], []
    mag = np.abs(x)
    for p in peaks:
        lo = max(p - 2 * window, 0)
        seg = mag[lo: p + 2 * window]
        first = lo + int(np.flatnonzero(seg >= 0.5 * seg.max())[0])
        onsets.append(first)
        levels.append(float(env[p]))
    order = np.argsort(onsets)
    return np.asarray(onsets, np.int64)[order], np.asarray(levels)[order]


def synchronize_tracks(tracks: Sequence[np.ndarray], rate: int, fps: float, *, cameras: Sequence[str] | None = None,
                       tolerance_s: float | None = None, min_duration_s: float = 0.2) -> SyncResult:
    """Frame offsets from the claps in each camera's track (module docstring for the method).

    Args:
        tracks: one mono track per camera, all starting with their camera's first video frame.
        rate: audio sample rate (Hz); fps: video frame rate (Hz).
        cameras: names (default ``"0", "1", …``).
        tolerance_s: how far two cameras' clap durations may differ and still agree (default: a quarter
            of a frame, or 100 ppm of the duration if that is more: clocks that drift apart).
        min_duration_s: shortest plausible time between the two claps.

    Raises:
        ValueError: if a camera has no pair of claps agreeing with the chosen duration (names them).
    """
    names = tuple(cameras) if cameras is not None else tuple(str(i) for i in range(len(tracks)))
    if len(names) != len(tracks) or not tracks:
        raise ValueError(f"synchronize_tracks: {len(tracks)} tracks for {len(names)} camera names")
    tol = (0.25 / fps if tolerance_s is None else tolerance_s) * rate
    drift = 1e-4 if tolerance_s is None else 0.0  # clocks apart by up to 100 ppm
    cands = [clap_candidates(t, rate) for t in tracks]
    # Every pair (i < j) of candidates of every camera: its duration and loudness.
    pairs = []
    for onsets, levels in cands:
        i, j = np.triu_indices(len(onsets), 1)
        d = (onsets[j] - onsets[i]).astype(np.float64)
        keep = d >= min_duration_s * rate
        pairs.append((i[keep], j[keep], d[keep], np.minimum(levels[i], levels[j])[keep]))
    durations = np.concatenate([p[2] for p in pairs]) if pairs else np.zeros(0)
    if len(durations) == 0:
        raise ValueError(f"synchronize_tracks: no two claps at least {min_duration_s} s apart in any track")
    best, best_key = None, None
    for d in np.unique(durations):
        agree, loud = 0, 0.0
        for _, _, dc, lc in pairs:
            ok = np.abs(dc - d) <= max(tol, drift * d)
            if ok.any():
                agree += 1
                loud += float(lc[ok].max())
        key = (agree, loud)
        if best_key is None or key > best_key:
            best, best_key = d, key
    samples = np.full((len(tracks), 2), -1, np.int64)
    missing = []
    for c, ((onsets, _), (i, j, dc, lc)) in enumerate(zip(cands, pairs)):
        ok = np.flatnonzero(np.abs(dc - best) <= max(tol, drift * best))
        if len(ok) == 0:
            missing.append(names[c])
            continue
        k = ok[np.argmax(lc[ok])]
        samples[c] = onsets[i[k]], onsets[j[k]]
    if missing:
        raise ValueError(f"synchronize_tracks: no pair of claps {best / rate:.4f} s apart (the duration "
                         f"{best_key[0]} of {len(tracks)} cameras agree on) in cameras {missing}; give offsets instead")
    frame_offsets = samples[:, 0] * fps / rate
    offsets = np.round(frame_offsets).astype(np.int64)
    spans = (samples[:, 1] - samples[:, 0]).astype(np.float64)
    duration = float(np.mean(spans) / rate)
    return SyncResult(names, offsets, samples, duration, int(best_key[0]), frame_offsets, spans / np.median(spans))


def common_claps(candidates: Sequence[tuple[np.ndarray, np.ndarray]], rate: int, count: int, *,
                 cameras: Sequence[str] | None = None, tolerance_s: float = 0.05) -> np.ndarray:
    """The ``count`` claps most cameras heard, in each camera's track: ``(C, count)`` first samples, sorted in time.

    Each camera's candidates (``clap_candidates(track, rate, max_count=count + 8)``, one track at a time so
    that long recordings need not be in memory together) are aligned with a
    reference camera's by the one shift (its start time) that matches most of them within ``tolerance_s``
    (loose enough for the clocks of two cameras to drift apart over a long recording). A reference
    candidate matched in more than half of the cameras is a clap; with every camera as the reference in
    turn, the one whose claps most cameras agree on wins, and the ``count`` best supported (then loudest)
    claps are kept. A camera that missed a clap gets it at the reference's time plus its shift.

    Args:
        candidates: ``(onsets, levels)`` per camera (:func:`clap_candidates` of its track, which starts at
            its first video frame).
        rate: sample rate (Hz); count: the number of claps to find (two per trial).
        cameras: names for the error message (default ``"0", "1", …``).

    Raises:
        ValueError: fewer than ``count`` claps are heard by more than half of the cameras.
    """
    cands = [(np.asarray(o, np.int64), np.asarray(v, np.float64)) for o, v in candidates]
    names = tuple(cameras) if cameras is not None else tuple(str(i) for i in range(len(cands)))
    if not cands or len(names) != len(cands) or count < 1:
        raise ValueError(f"common_claps: {len(cands)} cameras' candidates for {len(names)} names, count {count}")
    tol = tolerance_s * rate
    best = None
    for r, (ref, ref_levels) in enumerate(cands):
        if not len(ref):
            continue
        matched = np.full((len(cands), len(ref)), -1, np.int64)  # each camera's candidate for each reference one
        shifts = np.zeros(len(cands), np.int64)
        for c, (onsets, _) in enumerate(cands):
            if not len(onsets):
                continue
            pair_shifts = (onsets[:, None] - ref[None, :]).ravel()  # (S,): every pairing's start-time shift
            error = np.abs(onsets[None, :, None] - pair_shifts[:, None, None] - ref[None, None, :]).min(axis=1)  # (S, J)
            hits = (error <= tol).sum(axis=1) - 1e-9 * np.where(error <= tol, error, 0).sum(axis=1)
            shifts[c] = pair_shifts[int(np.argmax(hits))]
            close = np.abs(onsets[:, None] - shifts[c] - ref[None, :])
            nearest = np.argmin(close, axis=0)
            ok = close[nearest, np.arange(len(ref))] <= tol
            matched[c, ok] = onsets[nearest[ok]]
        support = (matched >= 0).sum(axis=0)
        claps = np.flatnonzero(2 * support > len(cands))
        order = np.lexsort((-ref_levels[claps], -support[claps]))[:count]
        keep = np.sort(claps[order])
        key = (len(keep) >= count, int(support[keep].sum()), float(ref_levels[keep].sum()))
        if best is None or key > best[0]:
            samples = np.where(matched[:, keep] >= 0, matched[:, keep], ref[keep][None, :] + shifts[:, None])
            deaf = [names[c] for c in range(len(cands)) if not (matched[c, keep] >= 0).any()]
            best = (key, samples, len(keep), deaf)
    if best is None or not best[0][0]:
        found = 0 if best is None else best[2]
        raise ValueError(f"found {found} claps heard by more than half of the cameras {list(names)}, expected {count} "
                         "(two per trial); give the trials' times instead")
    if best[3]:  # their start times cannot be told from the others'
        raise ValueError(f"cameras {best[3]} heard none of the {count} claps the other cameras agree on; give the "
                         "trials' times instead")
    return best[1]


def synchronize(capture: Capture, trial: str, **options) -> SyncResult:
    """Frame offsets of one trial of a capture from its soundtracks (:meth:`~.capture.Capture.soundtrack`: the
    WAV beside each video, ``trials/<trial>/<camera>.wav``, else the video's own audio track)."""
    tracks, rate = [], None
    for name in capture.camera_names:
        samples, r = capture.soundtrack(trial, name)
        path = capture.audio_path(trial, name)
        if not path.is_file():
            path = capture.video_path(trial, name)
        if not len(samples):
            raise ValueError(f"{path}: the soundtrack holds no samples")
        if rate is not None and r != rate:
            raise ValueError(f"{path}: sample rate {r} Hz differs from the other cameras' {rate} Hz")
        tracks.append(samples)
        rate = r
    try:
        return synchronize_tracks(tracks, rate, capture.fps, cameras=capture.camera_names, **options)
    except ValueError as err:
        raise ValueError(f"{capture.path / 'trials' / trial}: the soundtracks cannot be synchronised ({err}); "
                         "give the offsets instead (bcmocap frontend --offsets)") from None


def given_offsets(capture: Capture, offsets: Mapping[str, int] | Sequence[int]) -> SyncResult:
    """A :class:`SyncResult` from known offsets (by camera name, or one per camera in order)."""
    names = capture.camera_names
    if isinstance(offsets, Mapping):
        missing = [n for n in names if n not in offsets]
        unknown = sorted(set(offsets) - set(names))
        if missing or unknown:
            raise ValueError(f"given_offsets: missing cameras {missing}, unknown cameras {unknown}")
        values = [offsets[n] for n in names]
    else:
        values = list(offsets)
        if len(values) != len(names):
            raise ValueError(f"given_offsets: {len(values)} offsets for {len(names)} cameras")
    return SyncResult(names, np.asarray(values, np.int64), np.full((len(names), 2), -1, np.int64), float("nan"),
                      len(names))
