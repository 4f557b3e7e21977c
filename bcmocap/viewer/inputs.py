"""What the viewer shows: plain arrays and callbacks, filled by whoever reads a folder
(:mod:`bcmocap.pipeline.view_input` for ``bcmocap run`` folders: :class:`ViewerInput`;
:mod:`bcmocap.pipeline.view_tracks` for ``bcmocap markers`` and ``bcmocap kcs`` folders: :class:`TrackInput`;
tests for synthetic ones).

All positions are in the run's metric world (m, Z up); poses are wxyz_xyz ``world_from_camera``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np


@dataclasses.dataclass
class CameraFrame:
    """One camera's video frame at one time, with what the solver measured in it.

    Attributes:
        image: ``(H, W, 3)`` uint8 RGB, at the camera's calibrated size.
        pixels: ``(N, 2)`` measured pixel positions (OpenCV convention).
        points: ``(N, 3)`` the scene points they measure (m).
        video_frame: the frame's index in its video.
    """

    image: np.ndarray
    pixels: np.ndarray
    points: np.ndarray
    video_frame: int


@dataclasses.dataclass
class GroundTruth:
    """The true skeleton over the viewed frames, mapped into the run's world.

    Attributes:
        joints: ``(T, K, 3)`` true joint centres (m), NaN where the truth has no frame.
        parents: ``(K,)`` the true skeleton's parents; names its segment names.
        to_truth_scale: the scale of the §5.1 similarity (run world → true world), so that errors
            are reported in true metres like ``metrics.json``.
    """

    joints: np.ndarray
    parents: tuple[int, ...]
    names: tuple[str, ...]
    to_truth_scale: float = 1.0


@dataclasses.dataclass
class ViewerInput:
    """Everything one viewer session shows and may edit.

    Attributes:
        title: shown at the top of the panel.
        skeleton, rig: the model (``rig`` None when there are no cameras, e.g. a marker skeleton).
        motions: name → :class:`~bcmocap.kinematics.skeleton.Motion` over the same ``T`` frames; the
            first is shown first.
        fps: frames per second of the motions (Hz).
        scene_points: ``(P, 3)`` scene points (m), already subsampled for the browser, or None.
        registered: ``(T, C, 7)`` the frontend's registered camera poses (NaN where not registered), or None.
        truth: the ground truth, or None.
        pictures: PNG files to show in the panel (inside the run folder).
        metrics: numbers to show in the panel (``metrics.json``), or None.
        camera_frame: ``(camera index, frame) → CameraFrame | None``, or None without videos.
        save_model: ``(skeleton, rig) → message``: stores an edited model (raises ValueError with a
            message when it cannot), or None when the folder cannot be edited.
        notes: lines shown under the title (what was read, what is missing).
        later: reads what the first frame does without (e.g. ``scene_points``, ``truth``, ``camera_frame``)
            and returns those fields by name, with ``notes`` to add; :meth:`complete` calls it, which the
            viewer does in the background after drawing the first frame. None when everything is read.
    """

    title: str
    skeleton: object
    rig: object | None
    motions: dict
    fps: float
    scene_points: np.ndarray | None = None
    registered: np.ndarray | None = None
    truth: GroundTruth | None = None
    pictures: list[Path] = dataclasses.field(default_factory=list)
    metrics: dict | None = None
    camera_frame: Callable[[int, int], CameraFrame | None] | None = None
    save_model: Callable[[object, object], str] | None = None
    notes: list[str] = dataclasses.field(default_factory=list)
    later: Callable[[], dict] | None = None

    @property
    def num_frames(self) -> int:
        return int(next(iter(self.motions.values())).num_frames)

    def complete(self) -> None:
        """Read what :attr:`later` defers into this input (at once; nothing when all is read). Raises what
        ``later`` raises (ValueError, OSError), after which nothing is deferred any more."""
        if self.later is None:
            return
        try:
            fields = dict(self.later())
        finally:
            self.later = None
        notes = fields.pop("notes", [])
        unknown = set(fields) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise ValueError(f"ViewerInput.later returned unknown fields {sorted(unknown)}")
        for name, value in fields.items():
            setattr(self, name, value)
        self.notes = [*self.notes, *notes]


@dataclasses.dataclass
class PointTracks:
    """Points over time, drawn as one point cloud per frame.

    Attributes:
        label: what the panel calls them ("markers", "joints").
        positions: ``(T, N, 3)`` m, NaN where a point is not seen (it is left out of that frame).
        colours: ``(N, 3)`` uint8 RGB.
        names: ``(N,)`` a name per point.
        size_m: the points' diameter (m).
    """

    label: str
    positions: np.ndarray
    colours: np.ndarray
    names: tuple[str, ...]
    size_m: float = 0.02

    def at(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """``(n, 3)`` float32 positions and ``(n, 3)`` colours of the points seen at ``frame``."""
        p = self.positions[frame]
        seen = np.isfinite(p).all(axis=-1)
        return p[seen].astype(np.float32), self.colours[seen]


@dataclasses.dataclass
class LineTracks:
    """Line segments over time (bones, links), drawn as one set of lines per frame.

    Attributes:
        label: what the panel calls them.
        ends: ``(T, L, 2, 3)`` m, NaN where an end is not known (the line is left out of that frame).
        colours: ``(L, 3)`` uint8 RGB.
        thickness_m: line thickness (m).
    """

    label: str
    ends: np.ndarray
    colours: np.ndarray
    thickness_m: float = 0.01

    def at(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """``(l, 2, 3)`` float32 segments and ``(l, 2, 3)`` colours of the lines known at ``frame``."""
        e = self.ends[frame]
        known = np.isfinite(e).all(axis=(-1, -2))
        colours = np.repeat(self.colours[known][:, None], 2, axis=1)
        return e[known].astype(np.float32), colours


@dataclasses.dataclass
class TrackInput:
    """Points and lines over time without a model to edit: what ``bcmocap markers`` (markers coloured by
    segment, joints, the skeleton and its segments) and ``bcmocap kcs`` (the reconstructed chain) write.

    Attributes:
        title: shown at the top of the panel.
        kind: the command that wrote the folder ("markers", "kcs").
        fps: frames per second (Hz).
        layers: scene node name → :class:`PointTracks` or :class:`LineTracks`, all over the same ``T`` frames;
            drawn in this order, each with a checkbox.
        legend: ``(text, RGB)`` rows explaining the colours (e.g. one per segment).
        report: markdown for the panel's report folder (the command's own report), or "".
        notes: lines shown under the title.
    """

    title: str
    kind: str
    fps: float
    layers: dict[str, PointTracks | LineTracks]
    legend: list[tuple[str, tuple[int, int, int]]] = dataclasses.field(default_factory=list)
    report: str = ""
    notes: list[str] = dataclasses.field(default_factory=list)

    @property
    def num_frames(self) -> int:
        layer = next(iter(self.layers.values()))
        return int(len(layer.positions) if isinstance(layer, PointTracks) else len(layer.ends))

    def counts(self) -> str:
        """``"9 markers, 2 joints"``: the points of each :class:`PointTracks` layer."""
        return ", ".join(f"{layer.positions.shape[1]} {layer.label}" for layer in self.layers.values()
                         if isinstance(layer, PointTracks))
