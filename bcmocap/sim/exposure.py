"""Auto exposure and auto white balance of a body camera: per-frame RGB gains that follow what it sees.

A consumer camera meters each frame and moves its exposure and white balance towards what the metered
frame asks for, smoothly and a little late. :class:`ExposureControl` does the same for one camera over one
trial, frame by frame in recording order: the gains of the next frames come from the frames already
rendered (the renderer applies them before the sensor noise, :class:`~bcmocap.sim.render.RenderOptions`).

- **Auto exposure**: the metered level is the mean of the last rendered frame's valid pixels divided by
  the gains it was taken with (the scene's own brightness); the exposure gain moves in log space towards
  ``TARGET_LEVEL / metered`` with a time constant of :data:`EXPOSURE_TIME_S`, within ``GAIN_RANGE``.
- **Auto white balance**: grey world: the red and blue gains move towards ``mean(G) / mean(R)`` and
  ``mean(G) / mean(B)`` of the metered frame with a time constant of :data:`WHITE_BALANCE_TIME_S`
  (within ``WB_RANGE``), starting from a white balance off by up to ±:data:`WB_START_ERROR` per channel.

Where the numbers come from: these are plausible settings, not measurements of one camera. Video exposure
loops change exposure smoothly over a fraction of a second rather than per frame (a frame-by-frame loop would
flicker), hence 0.3 s; white balance is kept slower (about a second) so that colours do not pump. The target
level is the mean level of the studio's clean renders, so that gains stay near 1 and change with the view.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ExposureControl"]

TARGET_LEVEL = 76.0  # mean 8-bit level the exposure loop aims at: the clean renders' mean (standard 2 s walk, all cameras)
EXPOSURE_TIME_S = 0.3
WHITE_BALANCE_TIME_S = 1.0
GAIN_RANGE = (0.25, 4.0)
WB_RANGE = (0.5, 2.0)
WB_START_ERROR = 0.05


class ExposureControl:
    """The exposure and white-balance loops of one camera over one trial (frames in recording order).

    Args:
        fps: frame rate (Hz).
        auto_exposure, white_balance: which loops run (a loop that does not run keeps its gain at 1).
        rng: draws the starting white-balance error.
        valid: ``(H, W)`` bool, the pixels inside the lens's image (metered).
    """

    def __init__(self, fps: float, auto_exposure: bool, white_balance: bool, rng: np.random.Generator,
                 valid: np.ndarray):
        self.auto_exposure, self.white_balance = auto_exposure, white_balance
        self.alpha_exposure = 1.0 - np.exp(-1.0 / (fps * EXPOSURE_TIME_S))
        self.alpha_wb = 1.0 - np.exp(-1.0 / (fps * WHITE_BALANCE_TIME_S))
        self.valid = np.asarray(valid, bool)
        self.log_exposure = 0.0
        start = rng.uniform(-WB_START_ERROR, WB_START_ERROR, 3) if white_balance else np.zeros(3)
        self.log_wb = np.log1p(start) - np.log1p(start[1])  # green is the reference channel
        self.metered: tuple[float, np.ndarray] | None = None  # (scene level, scene channel means) of the last frame

    def _step(self) -> None:
        if self.metered is None:
            return
        level, means = self.metered
        if self.auto_exposure and level > 0:
            goal = np.clip(np.log(TARGET_LEVEL / level), *np.log(GAIN_RANGE))
            self.log_exposure += self.alpha_exposure * (goal - self.log_exposure)
        if self.white_balance and np.all(means > 0):
            goal = np.clip(np.log(means[1] / means), *np.log(WB_RANGE))
            self.log_wb = self.log_wb + self.alpha_wb * (goal - self.log_wb)

    def gains(self, count: int) -> np.ndarray:
        """``(count, 3)`` RGB gains of the next ``count`` frames (each frame moves the loops one step towards the
        last metering: a batch of frames rendered together shares one metering, as a camera meters late)."""
        out = np.empty((count, 3))
        for k in range(count):
            self._step()
            out[k] = np.exp(self.log_exposure + self.log_wb)
        return out

    def meter(self, image: np.ndarray, gains: np.ndarray) -> None:
        """Meter a rendered frame ``(H, W, 3)`` uint8 taken with ``gains`` ``(3,)``."""
        pixels = np.asarray(image, np.float64)[self.valid]
        if not len(pixels):
            return
        means = pixels.mean(axis=0) / np.asarray(gains, np.float64)
        self.metered = (float(means.mean()), means)
