"""Mount wobble: each body camera moves on its strap relative to the bone it is mounted on.

A camera strapped over clothing and soft tissue is not rigidly fixed to its bone (the soft-tissue
artefact of skin-marker motion capture). Here each camera's offset from its mount is, per trial frame,
a 6-vector ``(translation m, rotation rad)`` in the camera's own frame, the convention of the solver's
:data:`~bcmocap.residuals.variables.CAMERA_OFFSETS`::

    world_from_camera = world_from_mount · SE3.exp(offset),   world_from_mount = world_from_segment · segment_from_camera

It is the sum of two parts, different for every camera (seeded):

- **inertial wobble**: a damped spring (natural frequency 6–12 Hz, damping ratio 0.25–0.5 per camera) driven
  by the mount's acceleration in the camera frame: the translation lags the acceleration (``−a``) and the
  camera tips about the strap like a block standing on it (``e_z × −a``, e_z the optical axis pointing
  away from the body);
- **slow drift**: an Ornstein-Uhlenbeck process with a 3 s time constant on all six components (the strap
  slides and settles).

Amplitudes are given as the RMS over the capture trial of the translation (m) and rotation (rad) norms,
half of the mean square from the drift and half from the wobble, times a per-camera factor in [0.5, 1.5];
the spring's gain and the drift's σ found on the capture trial serve every trial of the capture (the same
strap on the same body), so another trial wobbles by what its own accelerations give (the studio's
range-of-motion trial swings the limbs harder than a walk: up to about twice the capture's amplitude on
the arms). A capture trial with hardly any acceleration wobbles less than asked (``_MIN_RESPONSE``). A strap
only gives so much: the translation and rotation norms beyond :data:`KNEE` times the camera's RMS saturate
smoothly (``tanh``) below twice that, so a violent trial cannot throw a camera off its mount.

Where the numbers come from: soft-tissue artefacts of skin-mounted marker clusters reach peaks of about
10 mm and 5–10° on the thigh and 17 mm / 7° on the shank in walking (Leardini et al. 2005, *Gait & Posture*
21:212; Peters et al. 2010, *Gait & Posture* 31:1, a systematic review; fluoroscopy-based cluster values
in PMC8631460), largest on the thigh; the RMS of a few mm and 1–3° used by the ``realistic`` preset
(:data:`bcmocap.sim.studio.REALISTIC`) gives peaks of that order. Soft-tissue vibrations of the leg after
heel strike have frequencies of roughly 10–20 Hz with damping ratios 0.2–0.5 (Wakeling & Nigg 2001,
*J. Appl. Physiol.* 90:412); a camera with its strap is heavier, hence the somewhat lower 6–12 Hz.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..geometry import matrix_from_quat

__all__ = ["MountWobble", "mount_wobble"]

NATURAL_HZ = (6.0, 12.0)  # spring natural frequency range (per camera)
DAMPING = (0.25, 0.5)  # damping ratio range (per camera)
DRIFT_TIME_S = 3.0  # correlation time of the slow drift
DRIFT_SHARE = 0.5  # share of the mean square amplitude from the drift
CAMERA_SCALE = (0.5, 1.5)  # per-camera amplitude factor
KNEE = 3.0  # the strap gives: offsets beyond KNEE x the camera's RMS saturate smoothly towards 2 x KNEE x RMS
# The spring's gain is fitted to the capture trial's response, but on a trial with hardly any acceleration (a
# subject standing still, a few frames) it would be huge: a response RMS below this (m/s^2; a walk gives 3-25, the
# least for the rotation of cameras that look along their acceleration, on the chest and back) counts as this,
# so such a trial wobbles less than asked.
_MIN_RESPONSE = 2.0


def _drive(world_from_mount: np.ndarray, fps: float) -> np.ndarray:
    """``(T, C, 6)`` spring inputs: ``-a`` and ``e_z × -a`` with ``a`` the mount's acceleration in the camera frame."""
    position = np.asarray(world_from_mount[..., 4:], np.float64)
    padded = np.concatenate([position[:1], position, position[-1:]], axis=0)
    accel = (padded[2:] - 2.0 * padded[1:-1] + padded[:-2]) * fps**2  # (T, C, 3) world
    rotation = np.asarray(matrix_from_quat(world_from_mount[..., :4]))  # world_from_camera
    local = -np.einsum("tcji,tcj->tci", rotation, accel)
    tip = np.cross(np.array([0.0, 0.0, 1.0]), local)
    return np.concatenate([local, tip], axis=-1)


def _spring(drive: np.ndarray, fps: float, natural_hz: np.ndarray, damping: np.ndarray) -> np.ndarray:
    """Response ``(T, C, 6)`` of ``x'' + 2ζω x' + ω² x = ω² u`` (unit static gain) to ``u`` = ``drive``, starting
    at rest; exact for an input held over each frame."""
    from scipy.linalg import expm

    dt = 1.0 / fps
    out = np.zeros_like(drive)
    for c in range(drive.shape[1]):
        w = 2 * np.pi * natural_hz[c]
        a = np.array([[0.0, 1.0], [-w * w, -2.0 * damping[c] * w]])
        b = np.array([0.0, w * w])
        ad = expm(a * dt)
        bd = np.linalg.solve(a, (ad - np.eye(2)) @ b)
        state = np.zeros((2, drive.shape[2]))
        for t in range(drive.shape[0]):
            state = ad @ state + np.outer(bd, drive[t, c])
            out[t, c] = state[0]
    return out


def _drift(num_frames: int, num_cameras: int, fps: float, rng: np.random.Generator) -> np.ndarray:
    """``(T, C, 6)`` stationary Ornstein-Uhlenbeck process with unit variance per component."""
    rho = np.exp(-1.0 / (fps * DRIFT_TIME_S))
    noise = rng.normal(size=(num_frames, num_cameras, 6))
    out = np.empty_like(noise)
    out[0] = noise[0]
    for t in range(1, num_frames):
        out[t] = rho * out[t - 1] + np.sqrt(1.0 - rho * rho) * noise[t]
    return out


def _saturate(offsets: np.ndarray, knee: np.ndarray) -> np.ndarray:
    """Offsets ``(T, C, 6)`` with each translation and rotation norm ``r`` above its camera's ``knee`` ``(C, 2)``
    replaced by ``knee + knee · tanh((r − knee) / knee)`` (unchanged below: continuous with slope 1 at the knee)."""
    out = np.array(offsets, np.float64)
    for k in range(2):
        part = out[..., 3 * k:3 * k + 3]
        r = np.linalg.norm(part, axis=-1)
        a = knee[None, :, k]
        over = (r > a) & (a > 0)
        limited = np.where(over, a + a * np.tanh((r - a) / np.where(a > 0, a, 1.0)), r)
        part *= np.where(over, limited / np.where(over, r, 1.0), 1.0)[..., None]
    return out


def _rms_norm(x: np.ndarray) -> np.ndarray:
    """RMS over frames of the norm of 3-vectors ``(T, C, 3)`` → ``(C,)``."""
    return np.sqrt(np.mean(np.sum(x * x, axis=-1), axis=0))


@dataclasses.dataclass(frozen=True)
class MountWobble:
    """The straps of a rig: per camera, spring parameters, the spring's gains and the drift's σ.

    Attributes:
        natural_hz, damping: ``(C,)`` the spring's natural frequency (Hz) and damping ratio.
        spring_gain: ``(C, 2)`` metres and radians of spring response per unit of drive (translation, rotation).
        drift_sigma: ``(C, 2)`` σ of each drift component (m, rad).
        knee: ``(C, 2)`` translation (m) and rotation (rad) norms beyond which the offsets saturate.
    """

    natural_hz: np.ndarray
    damping: np.ndarray
    spring_gain: np.ndarray
    drift_sigma: np.ndarray
    knee: np.ndarray

    def offsets(self, world_from_mount: np.ndarray, fps: float, rng: np.random.Generator) -> np.ndarray:
        """``(T, C, 6)`` offsets (translation m, rotation rad; camera frame) of one trial.

        Args:
            world_from_mount: ``(T, C, 7)`` the cameras' rigid mount poses over the trial (wxyz_xyz).
            fps: frame rate (Hz).
            rng: the trial's random stream (drift).
        """
        response = _spring(_drive(world_from_mount, fps), fps, self.natural_hz, self.damping)
        drift = _drift(response.shape[0], response.shape[1], fps, rng)
        gain = np.repeat(self.spring_gain, 3, axis=1)[None]
        sigma = np.repeat(self.drift_sigma, 3, axis=1)[None]
        return _saturate(response * gain + drift * sigma, self.knee)


def mount_wobble(world_from_mount: np.ndarray, fps: float, translation_rms_m: float, rotation_rms_rad: float,
                 rng: np.random.Generator) -> tuple[MountWobble, np.ndarray]:
    """Draw each camera's strap and fit its gains so that the trial it is given wobbles by the requested RMS.

    Args:
        world_from_mount: ``(T, C, 7)`` the rigid mount poses over the reference (capture) trial.
        fps: frame rate (Hz).
        translation_rms_m, rotation_rms_rad: RMS over the trial of the offsets' translation and rotation
            norms, before the per-camera factor (:data:`CAMERA_SCALE`).
        rng: draws the straps, then the trial's drift.

    Returns:
        ``(straps, offsets (T, C, 6))``: the straps (for the other trials) and this trial's offsets, whose
        RMS norms are the requested ones times each camera's factor (exactly before the rare peaks beyond
        :data:`KNEE` RMS saturate; less where the trial's accelerations are below ``_MIN_RESPONSE``).
    """
    num_cameras = world_from_mount.shape[1]
    natural = rng.uniform(*NATURAL_HZ, num_cameras)
    damping = rng.uniform(*DAMPING, num_cameras)
    scale = rng.uniform(*CAMERA_SCALE, num_cameras)
    target = np.stack([translation_rms_m * scale, rotation_rms_rad * scale], axis=1)  # (C, 2)
    response = _spring(_drive(world_from_mount, fps), fps, natural, damping)
    drift = _drift(response.shape[0], num_cameras, fps, rng)
    gain, sigma = np.zeros((num_cameras, 2)), np.zeros((num_cameras, 2))
    for k in range(2):
        part = slice(3 * k, 3 * k + 3)
        response_rms = _rms_norm(response[..., part])
        gain[:, k] = np.sqrt(1.0 - DRIFT_SHARE) * target[:, k] / np.maximum(response_rms, _MIN_RESPONSE)
        sigma[:, k] = np.sqrt(DRIFT_SHARE) * target[:, k] / np.maximum(_rms_norm(drift[..., part]), 1e-12)
        # The two parts are only nearly uncorrelated over a short trial: scale both so that their sum has the RMS
        # they would have if they were (the target, unless the response was below the floor).
        total = _rms_norm(response[..., part] * gain[None, :, k:k + 1] + drift[..., part] * sigma[None, :, k:k + 1])
        expected = np.sqrt((response_rms * gain[:, k]) ** 2 + (np.sqrt(DRIFT_SHARE) * target[:, k]) ** 2)
        fix = np.where(total > 0, expected / np.maximum(total, 1e-300), 0.0)
        gain[:, k] *= fix
        sigma[:, k] *= fix
    straps = MountWobble(natural, damping, gain, sigma, KNEE * target)
    offsets = response * np.repeat(gain, 3, axis=1)[None] + drift * np.repeat(sigma, 3, axis=1)[None]
    return straps, _saturate(offsets, straps.knee)
