"""A prior holding a camera at its registered pose where it has too few measurements (beyond the paper).

The solver sees a camera-frame through its measurements of scene points. Registration may place a camera well
where few of those points survive into the solver — a foot camera mid-swing tracked by its own new points while
the solver keeps only the reference model's (``frontend.points = "reference"``), or a frame registered by a
homography-free relative round — and then nothing but smoothness holds the joints that camera alone sees: the
solve drags them toward neighbours that are themselves unregistered and interpolated. :class:`RegisteredPose`
ties such a camera-frame to its registered pose with a Gaussian prior on the rotation and the camera centre.

A camera-frame with neither a registration nor a measurement is held by nothing but its neighbours and, with
gyros, its turns: across a stretch where a foot camera sees only a blank floor, the solve lets the segment's
orientation drift as a whole (the studio's sparse walk: the unregistered right ankle's angle error 12.9° initially,
17.0° solved). :func:`unmeasured_orientation_data` ties such camera-frames, where no other camera of the segment is
measured, to the initial motion's orientation (carried across the gap by the camera's gyro where it could be, else
interpolated by the inverse kinematics) with the same term, its centre left free (σ = ∞).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import SE3
from .base import CameraTerm
from .losses import loss_from_name

IDENTITY_POSE = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])


class RegisteredPose(CameraTerm):
    """``((c − c_reg) / σ_pos, 2·vec(q_regᵀ ⊗ q) / σ_rot)`` per camera-frame: one block of 6.

    The rotation part is twice the vector part of the relative quaternion (the rotation vector for small
    angles, smooth everywhere); ``c`` is the camera centre in the world.

    Sequence-level data ``(T, C, ...)``: ``world_from_camera`` ``(T, C, 7)`` the registered poses (any finite
    value where unused); ``weights`` ``(T, C)`` 1 where the prior applies, else 0.

    Attributes:
        sigma: ``(2,)`` standard deviations of the camera centre (m) and of the rotation (rad); an infinite σ of
            the centre leaves it free (the rotation alone is held).
    """

    sigma: jax.Array = eqx.field(kw_only=True, converter=jnp.asarray)

    def residual(self, x, data, variables):
        registered, world_from_camera = SE3(data["world_from_camera"]), x.cam_from_world.inverse()
        q = (registered.rotation().inverse() @ world_from_camera.rotation()).wxyz
        rotation = 2.0 * jnp.where(q[0] < 0, -1.0, 1.0) * q[1:]
        centre = world_from_camera.translation() - registered.translation()
        r = jnp.concatenate([centre / self.sigma[0], rotation / self.sigma[1]])
        return r[None], (data["weights"] > 0)[None]


def registered_pose_data(world_from_camera: np.ndarray, registered: np.ndarray, weights: np.ndarray,
                         below: int) -> dict:
    """The data of :class:`RegisteredPose` for registered camera-frames with fewer than ``below`` measurements.

    Args:
        world_from_camera: ``(T, C, 7)`` registered poses (NaN or anything where not registered).
        registered: ``(T, C)`` bool.
        weights: ``(T, C, N)`` the reprojection term's measurement weights (> 0: a measurement).
        below: the prior applies where a registered camera-frame has fewer measurements than this.
    """
    count = (np.asarray(weights) > 0).sum(axis=-1)
    return _held_at(world_from_camera, np.asarray(registered, bool) & (count < below))


def _held_at(world_from_camera: np.ndarray, use: np.ndarray) -> dict:
    """:class:`RegisteredPose` data holding the camera-frames ``use`` ``(T, C)`` at ``world_from_camera`` ``(T, C, 7)``
    (the identity elsewhere, so that the unused rows stay finite)."""
    poses = np.where(use[..., None], np.asarray(world_from_camera, dtype=np.float64), IDENTITY_POSE)
    return {"world_from_camera": poses, "weights": use.astype(np.float64)}


def unmeasured_orientation_data(world_from_camera: np.ndarray, registered: np.ndarray, weights: np.ndarray,
                                segments: np.ndarray) -> dict:
    """The data of :class:`RegisteredPose` holding each camera-frame with neither a registration nor a measurement,
    on a segment no camera of which is measured in that frame, at the orientation of ``world_from_camera`` (the
    initial motion's camera poses); use with ``sigma = (inf, σ_rot)``.

    Args:
        world_from_camera: ``(T, C, 7)`` the initial motion's camera poses (finite).
        registered: ``(T, C)`` bool. weights: ``(T, C, N)`` the reprojection term's measurement weights.
        segments: ``(C,)`` each camera's segment index.
    """
    segments = np.asarray(segments)
    measured = (np.asarray(weights) > 0).any(axis=-1)  # (T, C)
    segment_measured = measured.astype(int) @ (segments[:, None] == segments[None, :]) > 0  # (T, C): any camera on it
    return _held_at(world_from_camera, ~np.asarray(registered, bool) & ~segment_measured)


def unmeasured_orientation_terms(window, world_from_camera: np.ndarray, sigma_deg: float, loss: str = "cauchy",
                                 loss_scale: float = 8.0) -> list:
    """A term factory (``[solver] unmeasured_orientation``): over ``window`` (a
    :class:`~bcmocap.residuals.term_window.TermWindow` with its rig and correspondences), the :class:`RegisteredPose`
    holding its camera-frames with neither a registration nor a measurement, on a segment measured by no other camera
    in that frame, at the orientations of ``world_from_camera`` ``(T, C, 7)`` (the trial's initial camera poses), σ
    ``sigma_deg`` > 0. Every window gets the term (weights 0 where it holds nothing), so every window has one shape."""
    if not sigma_deg > 0:
        raise ValueError(f"unmeasured orientation: sigma_deg must be > 0, got {sigma_deg}")
    c = window.correspondences
    data = unmeasured_orientation_data(np.asarray(world_from_camera)[window.start:window.stop], c.registered, c.weights,
                                       np.asarray(window.rig.segments))
    return [RegisteredPose(data, sigma=np.array([np.inf, np.radians(sigma_deg)]), loss=loss_from_name(loss, loss_scale),
                           name="unmeasured orientation")]
