"""What the viewer shows: plain arrays and callbacks, filled by whoever reads a run folder
(:mod:`bcmocap.pipeline.view_input` for ``bcmocap run`` folders, tests for synthetic ones).

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

    @property
    def num_frames(self) -> int:
        return int(next(iter(self.motions.values())).num_frames)
