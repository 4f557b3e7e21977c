"""Random access to the frames of a video, cheap when playing forward (OpenCV)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: A frame up to this many frames ahead is reached by decoding forward; further, by seeking.
_FORWARD = 90


class VideoFrames:
    """One video, opened on first use and kept open; ``frame(i)`` is frame ``i`` as RGB uint8 ``(H, W, 3)``.

    Consecutive or slightly later frames are decoded forward (what playback asks for); earlier or far
    frames are reached by seeking. ``frame`` returns None past the end; ValueError if the file cannot
    be opened.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._video = None
        self._next = 0  # index of the frame the next read returns

    def _open(self):
        import cv2

        if self._video is None:
            if not self.path.is_file():
                raise ValueError(f"{self.path}: video missing")
            video = cv2.VideoCapture(str(self.path))
            if not video.isOpened():
                raise ValueError(f"{self.path}: OpenCV cannot open this video")
            self._video, self._next = video, 0
        return self._video

    def frame(self, index: int) -> np.ndarray | None:
        import cv2

        if index < 0:
            return None
        video = self._open()
        if not self._next <= index <= self._next + _FORWARD:
            video.set(cv2.CAP_PROP_POS_FRAMES, index)
            self._next = index
        while self._next < index:
            if not video.grab():
                return None
            self._next += 1
        ok, image = video.read()
        if not ok:
            return None
        self._next += 1
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        if self._video is not None:
            self._video.release()
            self._video = None
