"""Self-calibration of each camera's focal length and principal point from the capture (beyond the paper).

A lens calibrated on a board drifts from the one that filmed the capture (a refocus, heat, a different
mode of the camera): the intrinsics the user gives are off by a few tenths of a percent in focal length and
a few pixels in the centre. :class:`SelfCalibratingReprojection` reprojects with each camera's intrinsics
corrected by the static block :data:`INTRINSICS_CORRECTION` (``PerCamera(Euclidean(3), C)``: log focal scale,
principal point shift in px), and :class:`StaticPrior` holds such a block near zero.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..cameras import CameraModel
from ..geometry import transform_points
from .base import FrameTerm
from .reprojection import Reprojection, window_data
from .variables import PerCamera, Euclidean

#: Static block of per-camera intrinsics corrections: ``(log focal scale, Δcx px, Δcy px)`` per camera.
INTRINSICS_CORRECTION = "intrinsics_correction"


def intrinsics_correction(num_cameras: int) -> PerCamera:
    """The :data:`INTRINSICS_CORRECTION` block of a rig of ``num_cameras`` cameras."""
    return PerCamera(Euclidean(3), num_cameras)


def corrected_camera(camera: CameraModel, correction: jax.Array) -> CameraModel:
    """``camera`` with focal lengths scaled by ``exp(correction[0])`` and the principal point moved by
    ``correction[1:]`` px (the distortion parameters unchanged)."""
    return eqx.tree_at(lambda c: (c.focal, c.principal_point), camera,
                       (camera.focal * jnp.exp(correction[0]), camera.principal_point + correction[1:]))


def corrected_cameras(cameras: CameraModel, corrections) -> CameraModel:
    """A rig's stacked ``cameras`` (``C``) each corrected by its row of ``corrections`` ``(C, 3)`` (as
    :func:`corrected_camera`)."""
    return jax.vmap(corrected_camera)(cameras, jnp.asarray(corrections))


class SelfCalibratingReprojection(Reprojection):
    """:class:`Reprojection` through each camera's corrected intrinsics (:data:`INTRINSICS_CORRECTION`).

    Attributes:
        num_cameras: the rig's camera count (the block's size).
    """

    num_cameras: int = eqx.field(static=True, kw_only=True)

    def static_variables(self):
        return {INTRINSICS_CORRECTION: intrinsics_correction(self.num_cameras)}

    def window(self, start: int, stop: int) -> SelfCalibratingReprojection:
        return SelfCalibratingReprojection(window_data(self.data, self.points, start, stop), points=jnp.zeros((0, 3)),
                                           weight=self.weight, loss=self.loss, name=self.name, num_cameras=self.num_cameras)

    def residual(self, x, data, variables):
        camera = corrected_camera(x.camera, variables[INTRINSICS_CORRECTION])
        return self.residual_in_camera(transform_points(x.cam_from_world, data["points"]), camera, data)


class StaticPrior(FrameTerm):
    """A Gaussian prior ``((value − mean) / sigma)²`` on a Euclidean (or :class:`PerCamera` Euclidean) static block.

    A frame term counts once per frame, so ``data`` ``(T,)`` holds each frame's share of the prior: with windows
    of ``W`` frames, ``1 / W`` per frame gives the prior once per window.

    Attributes:
        block: the static block's name; variable: its declaration; sigma: standard deviations broadcasting to
            its value's shape; mean: the prior's centre, broadcasting likewise (default 0: a correction expected
            to be small; a measured value, e.g. the cameras' time offsets from their gyros).
    """

    block: str = eqx.field(static=True, kw_only=True)
    variable: PerCamera | Euclidean = eqx.field(kw_only=True)
    sigma: jax.Array = eqx.field(kw_only=True, converter=jnp.asarray)
    mean: jax.Array = eqx.field(default=0.0, kw_only=True, converter=jnp.asarray)

    def static_variables(self):
        return {self.block: self.variable}

    def residual(self, x, data, variables):
        value = jnp.reshape((variables[self.block] - self.mean) / self.sigma, (1, -1))
        return value * jnp.sqrt(data), jnp.ones(1, bool)
