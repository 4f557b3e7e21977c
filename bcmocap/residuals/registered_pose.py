"""A prior holding a camera at its registered pose where it has too few measurements (beyond the paper).

The solver sees a camera-frame through its measurements of scene points. Registration may place a camera well
where few of those points survive into the solver — a foot camera mid-swing tracked by its own new points while
the solver keeps only the reference model's (``frontend.points = "reference"``), or a frame registered by a
homography-free relative round — and then nothing but smoothness holds the joints that camera alone sees: the
solve drags them toward neighbours that are themselves unregistered and interpolated. :class:`RegisteredPose`
ties such a camera-frame to its registered pose with a Gaussian prior on the rotation and the camera centre.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import SE3
from .base import CameraTerm

IDENTITY_POSE = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])


class RegisteredPose(CameraTerm):
    """``((c − c_reg) / σ_pos, 2·vec(q_regᵀ ⊗ q) / σ_rot)`` per camera-frame: one block of 6.

    The rotation part is twice the vector part of the relative quaternion (the rotation vector for small
    angles, smooth everywhere); ``c`` is the camera centre in the world.

    Sequence-level data ``(T, C, ...)``: ``world_from_camera`` ``(T, C, 7)`` the registered poses (any finite
    value where unused); ``weights`` ``(T, C)`` 1 where the prior applies, else 0.

    Attributes:
        sigma: ``(2,)`` standard deviations of the camera centre (m) and of the rotation (rad).
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
    use = np.asarray(registered, bool) & (count < below)
    poses = np.where(use[..., None], np.asarray(world_from_camera, dtype=np.float64), IDENTITY_POSE)
    return {"world_from_camera": poses, "weights": use.astype(np.float64)}
