"""Mount compliance: cameras strapped to the body move on their mounts (beyond the paper).

A camera on a strap or on clothing is not rigid on its bone: it swings and slides a few millimetres and
degrees as the limb accelerates (soft-tissue artefact). :class:`MountCompliance` lets each camera deviate
from its mount at every frame by a small offset (the per-frame block
:data:`~.variables.CAMERA_OFFSETS`, seen by every camera term through the camera poses) with a Gaussian
prior, and :class:`MountSmoothness` keeps the offsets from jumping between frames, so the wobble is
absorbed by the offsets instead of bending the skeleton.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .base import FrameTerm, PairTerm
from .variables import CAMERA_OFFSETS, Euclidean, PerCamera


def camera_offsets(num_cameras: int) -> PerCamera:
    """The :data:`~.variables.CAMERA_OFFSETS` block of a rig of ``num_cameras`` cameras."""
    return PerCamera(Euclidean(6), num_cameras)


class MountCompliance(FrameTerm):
    """Prior on each camera's offset from its mount: ``(offset / sigma)²`` per camera and frame.

    ``data`` ``(T,)``: 1 where the prior applies (every frame, normally).

    Attributes:
        num_cameras: the rig's camera count.
        sigma: ``(6,)`` standard deviations of the offset's SE(3) tangent (translation m, rotation rad).
    """

    num_cameras: int = eqx.field(static=True, kw_only=True)
    sigma: jax.Array = eqx.field(kw_only=True, converter=jnp.asarray)

    def frame_variables(self):
        return {CAMERA_OFFSETS: camera_offsets(self.num_cameras)}

    def residual(self, x, data, variables):
        return x.variables[CAMERA_OFFSETS] / self.sigma, jnp.full(self.num_cameras, data > 0)


class MountSmoothness(PairTerm):
    """Each camera's offset changes little between consecutive frames: ``(Δoffset / sigma)²``.

    ``data`` ``(T,)``: the pair mask (0 for the first frame of a sequence).
    """

    num_cameras: int = eqx.field(static=True, kw_only=True)
    sigma: jax.Array = eqx.field(kw_only=True, converter=jnp.asarray)

    def frame_variables(self):
        return {CAMERA_OFFSETS: camera_offsets(self.num_cameras)}

    def residual(self, x, data, variables):
        step = x.variables[CAMERA_OFFSETS][1] - x.variables[CAMERA_OFFSETS][0]
        return step / self.sigma, jnp.full(self.num_cameras, data > 0)
