"""Marker trajectories and their preprocessing (Kirk et al. §3, first paragraphs).

An optical system's data for a marker is typically wrong just before it loses track of it and just after
it finds it again, and "ghost" markers appear for a few frames. So, as in the paper:

* a few frames are trimmed off both ends of every visible stretch of every marker;
* a marker whose longest visible stretch is shorter than half a second is ignored.

Added here (not in the paper): isolated jumps ("spikes", a marker displaced by centimetres for a frame or
two) are removed by comparing each sample with the median of its neighbours, and markers with no data at
all are dropped with a warning that names them.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence

import numpy as np

__all__ = ["MarkerTrajectories", "PreprocessReport", "preprocess", "visible_runs"]


@dataclasses.dataclass(frozen=True)
class MarkerTrajectories:
    """Positions of labelled markers over time.

    Attributes:
        positions: ``(F, M, 3)`` positions (m), NaN where a marker is not seen.
        labels: ``M`` unique marker labels.
        fps: frame rate (Hz).
    """

    positions: np.ndarray
    labels: tuple[str, ...]
    fps: float

    def __post_init__(self):
        p = np.asarray(self.positions, dtype=np.float64)
        if p.ndim != 3 or p.shape[-1] != 3:
            raise ValueError(f"marker positions must have shape (frames, markers, 3), got {p.shape}")
        if p.shape[0] < 2 or p.shape[1] < 1:
            raise ValueError(f"marker positions need at least 2 frames and 1 marker, got {p.shape}")
        if np.isinf(p).any():
            f, m, _ = np.argwhere(np.isinf(p))[0]
            raise ValueError(f"marker positions hold inf (marker {m}, frame {f}); use NaN for gaps")
        labels = tuple(str(x) for x in self.labels)
        if len(labels) != p.shape[1]:
            raise ValueError(f"{p.shape[1]} markers but {len(labels)} labels")
        if len(set(labels)) != len(labels):
            dup = sorted({x for x in labels if labels.count(x) > 1})
            raise ValueError(f"duplicate marker labels {dup}")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"the frame rate must be positive, got {self.fps}")
        # A point with some NaN coordinates is a gap as a whole.
        p = np.where(np.isnan(p).any(axis=-1, keepdims=True), np.nan, p)
        object.__setattr__(self, "positions", p)
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "fps", float(self.fps))

    @classmethod
    def from_array(cls, positions, fps: float, labels: Sequence[str] | None = None) -> MarkerTrajectories:
        """From a ``(frames, markers, 3)`` array (m, NaN gaps); labels default to ``m0, m1, …``."""
        positions = np.asarray(positions, dtype=np.float64)
        if labels is None:
            labels = [f"m{k}" for k in range(positions.shape[1] if positions.ndim == 3 else 0)]
        return cls(positions, tuple(labels), fps)

    @classmethod
    def from_c3d(cls, data) -> MarkerTrajectories:
        """From :class:`bcmocap.io.c3d.C3dData` (already in metres)."""
        return cls(data.positions, data.labels, data.frame_rate_hz)

    @property
    def num_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def num_markers(self) -> int:
        return self.positions.shape[1]

    @property
    def visible(self) -> np.ndarray:
        """``(F, M)`` True where the marker is seen."""
        return np.isfinite(self.positions[..., 0])

    def select(self, markers: Sequence[int]) -> MarkerTrajectories:
        """The markers at the given indices, in that order."""
        idx = list(markers)
        return MarkerTrajectories(self.positions[:, idx], tuple(self.labels[k] for k in idx), self.fps)


@dataclasses.dataclass(frozen=True)
class PreprocessReport:
    """What preprocessing removed.

    Attributes:
        dropped: ``(label, reason)`` of each marker left out.
        trimmed_samples: marker-frames removed at the ends of visible stretches.
        spikes_removed: marker-frames removed as jumps.
        kept: indices (into the input) of the markers kept, in order.
    """

    dropped: tuple[tuple[str, str], ...]
    trimmed_samples: int
    spikes_removed: int
    kept: tuple[int, ...]


def visible_runs(visible: np.ndarray) -> list[tuple[int, int]]:
    """Visible stretches ``[start, stop)`` of one marker (``visible`` is ``(F,)`` bool)."""
    padded = np.concatenate([[0], np.asarray(visible, np.int8), [0]])
    edges = np.flatnonzero(np.diff(padded))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def _remove_spikes(positions: np.ndarray, half_window: int, threshold_m: float) -> tuple[np.ndarray, int]:
    """NaN out samples farther than ``threshold_m`` from the median of their ``±half_window`` neighbours."""
    num_frames = positions.shape[0]
    pad = np.pad(positions, ((half_window, half_window), (0, 0), (0, 0)), constant_values=np.nan)
    windows = np.stack([pad[k : k + num_frames] for k in range(2 * half_window + 1)], axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows
        median = np.nanmedian(windows, axis=0)
        count = np.sum(np.isfinite(windows[..., 0]), axis=0)
    deviation = np.linalg.norm(positions - median, axis=-1)
    spikes = (deviation > threshold_m) & (count >= half_window + 2)
    out = positions.copy()
    out[spikes] = np.nan
    return out, int(spikes.sum())


def _off_the_body(positions: np.ndarray, markers: list[int], still_m: float, apart_m: float) -> list[int]:
    """The markers among ``markers`` that stay still and far from every other one (see :func:`preprocess`)."""
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        spreads = [np.sqrt(np.nanmean(np.sum((positions[:, m] - np.nanmedian(positions[:, m], axis=0)) ** 2, axis=-1)))
                   for m in markers]
        if not np.nanmedian(spreads) > 10.0 * still_m:
            return []  # the body barely moved: a still marker is no sign of anything
        for m, spread in zip(markers, spreads):
            track = positions[:, m]
            if not spread <= still_m:
                continue
            others = positions[:, [k for k in markers if k != m]]
            nearest = np.nanmin(np.linalg.norm(others - track[:, None], axis=-1), axis=1)
            if np.nanmedian(nearest) > apart_m:
                out.append(m)
    return out


def preprocess(
    trajectories: MarkerTrajectories,
    *,
    trim_frames: int = 2,
    min_run_seconds: float = 0.5,
    spike_threshold_m: float | None = 0.03,
    spike_half_window: int = 2,
    still_m: float = 0.002,
    apart_m: float = 0.4,
    warn: bool = True,
) -> tuple[MarkerTrajectories, PreprocessReport]:
    """Clean marker trajectories as in §3 of Kirk et al.

    Args:
        trajectories: the input.
        trim_frames: frames removed at each end of every visible stretch (ends of the capture excepted).
        min_run_seconds: a marker whose longest visible stretch (after trimming) is shorter is dropped.
        spike_threshold_m: remove samples farther than this from the median of their neighbours
            (None: keep them).
        spike_half_window: neighbours on each side for that median.
        still_m, apart_m: a marker that stays within ``still_m`` (RMS about its median position) and lies farther
            than ``apart_m`` from every other marker (median over frames) while most markers move (their median
            RMS over ten times ``still_m``) is not on the body (a marker on the floor or on the lab's equipment)
            and is dropped.
        warn: emit a :class:`UserWarning` naming the markers dropped for having no data.

    Returns:
        The cleaned trajectories (markers dropped) and a :class:`PreprocessReport`.

    Raises:
        ValueError: if no marker is left, naming why each was dropped.
    """
    if trim_frames < 0:
        raise ValueError(f"trim_frames must be >= 0, got {trim_frames}")
    positions = trajectories.positions.copy()
    num_frames = trajectories.num_frames
    spikes = 0
    if spike_threshold_m is not None:
        positions, spikes = _remove_spikes(positions, spike_half_window, spike_threshold_m)
    visible = np.isfinite(positions[..., 0])
    trimmed = 0
    min_run = max(1, int(round(min_run_seconds * trajectories.fps)))
    keep, dropped = [], []
    for m, label in enumerate(trajectories.labels):
        if not visible[:, m].any():
            dropped.append((label, "no data"))
            continue
        longest = 0
        for start, stop in visible_runs(visible[:, m]):
            a = start + (trim_frames if start > 0 else 0)
            b = stop - (trim_frames if stop < num_frames else 0)
            if b <= a:
                trimmed += stop - start
                visible[start:stop, m] = False
                continue
            trimmed += (a - start) + (stop - b)
            visible[start:a, m] = False
            visible[b:stop, m] = False
            longest = max(longest, b - a)
        if longest < min_run:
            dropped.append((label, f"longest visible stretch {longest / trajectories.fps:.2f} s < {min_run_seconds:g} s"))
            continue
        keep.append(m)
    positions[~visible] = np.nan
    for m in _off_the_body(positions, keep, still_m, apart_m):
        keep.remove(m)
        dropped.append((trajectories.labels[m], f"still (within {still_m * 1000:g} mm) and over {apart_m:g} m from "
                                                "every other marker: not on the body"))
    empty = [label for label, why in dropped if why == "no data"]
    if warn and empty:
        warnings.warn(f"markers with no data were ignored: {empty}", UserWarning, stacklevel=2)
    if not keep:
        reasons = "; ".join(f"{label}: {why}" for label, why in dropped[:10])
        raise ValueError(f"no marker left after preprocessing ({reasons}{' …' if len(dropped) > 10 else ''})")
    out = MarkerTrajectories(positions[:, keep], tuple(trajectories.labels[k] for k in keep), trajectories.fps)
    return out, PreprocessReport(tuple(dropped), trimmed, spikes, tuple(keep))
