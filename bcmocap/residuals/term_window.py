"""What a term factory is given: the frames of one solver window, the model and the capture's files.

A user's terms reach ``bcmocap run`` through a *term factory*, ``factory(window: TermWindow, **settings)``, named by
import path in the run's config (``[[solver.user_terms]]``); it returns one term or a list of them, with data over
the window's frames. Every window of a sequence must get terms of the same kinds and data shapes (one compilation
serves them all).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..correspondences import Correspondences
from ..kinematics.rig import Rig
from ..kinematics.skeleton import Skeleton

__all__ = ["TermWindow"]


@dataclasses.dataclass(frozen=True)
class TermWindow:
    """What a term factory is given: frames ``[start, stop)`` of a trial.

    Attributes:
        start, stop: the window's frames in the trial (solver frames, ``fps`` per second).
        fps: solver frames per second.
        skeleton, rig: the model the terms will be evaluated on.
        correspondences: the window's measurements (frames ``[start, stop)``), or None.
        trial_folder: the capture's folder of this trial (``CAPTURE/trials/<trial>``) where a user's own
            measurement files live, or None when the problem does not come from a capture folder.
    """

    start: int
    stop: int
    fps: float
    skeleton: Skeleton
    rig: Rig | None
    correspondences: Correspondences | None = None
    trial_folder: Path | None = None

    @property
    def num_frames(self) -> int:
        return self.stop - self.start

    @property
    def times(self) -> np.ndarray:
        """``(W,)`` seconds of the window's frames since the trial's first clap (the synchronised clock)."""
        return (self.start + np.arange(self.num_frames)) / self.fps

    @property
    def first_frame_has_previous(self) -> bool:
        return self.start > 0

    def trial_file(self, name: str) -> Path:
        """The path of a file of the trial's folder (e.g. ``"imu.npz"``) for a factory to read.

        Raises:
            ValueError: one line, when the problem has no trial folder, the name leads outside it, or the file
                is missing.
        """
        if self.trial_folder is None:
            raise ValueError(f"a term factory asks for {name!r}, but this problem has no capture trial folder")
        if not name or Path(name).is_absolute() or ".." in Path(name).parts:
            raise ValueError(f"a term factory asks for {name!r}: expected a file name inside the trial folder")
        path = Path(self.trial_folder) / name
        if not path.is_file():
            raise ValueError(f"{path}: missing (a term factory reads it)")
        return path
