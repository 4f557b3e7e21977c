"""Extra variable blocks a term can declare, each with its manifold.

A term reads the motion (root pose and joint angles) and, besides it, may declare blocks of its own
variables, solved with the motion:

- **static** blocks (:meth:`~bcmocap.residuals.Term.static_variables`): one value per window, shared by
  all its frames — an IMU bias, a readout time, a lens correction, a sensor-to-camera rotation;
- **per-frame** blocks (:meth:`~bcmocap.residuals.Term.frame_variables`): one value per frame — a camera's
  wobble on its strap, a contact force.

A block is a :class:`Variable`: its value's shape, the size of its tangent space (what the solver steps
in) and the retraction that moves a value by a tangent vector. ``Euclidean(n)`` is a plain vector;
:class:`Rotation` a unit quaternion stepped by ``q ⊗ exp(δ)``; :class:`PerCamera` gives every camera of
the rig its own copy of a block, so a camera term sees only its own camera's (and the solver
differentiates only that one).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..geometry import SO3


class Variable(eqx.Module):
    """A variable block: ``size`` tangent entries, values of :attr:`value_shape`, a start and a retraction."""

    @property
    def size(self) -> int:
        """Tangent-space dimension: the number of the solver's variables for this block."""
        raise NotImplementedError

    @property
    def value_shape(self) -> tuple[int, ...]:
        raise NotImplementedError

    def start(self) -> jax.Array:
        """The value a block starts from when nothing else is given (zero, identity)."""
        raise NotImplementedError

    def retract(self, value: jax.Array, delta: jax.Array) -> jax.Array:
        """``value`` moved by tangent ``delta`` ``(size,)``; ``retract(v, 0) = v``."""
        raise NotImplementedError


class Euclidean(Variable):
    """A vector of ``n`` reals, stepped by addition (a bias, a time offset, a length correction)."""

    n: int = eqx.field(static=True)

    @property
    def size(self) -> int:
        return self.n

    @property
    def value_shape(self) -> tuple[int, ...]:
        return (self.n,)

    def start(self) -> jax.Array:
        return jnp.zeros(self.n)

    def retract(self, value: jax.Array, delta: jax.Array) -> jax.Array:
        return value + delta


class Rotation(Variable):
    """A rotation as a unit quaternion ``(w, x, y, z)``, stepped on the right: ``q ⊗ exp(δ)``, δ in rad."""

    @property
    def size(self) -> int:
        return 3

    @property
    def value_shape(self) -> tuple[int, ...]:
        return (4,)

    def start(self) -> jax.Array:
        return jnp.array([1.0, 0.0, 0.0, 0.0])

    def retract(self, value: jax.Array, delta: jax.Array) -> jax.Array:
        return (SO3(value) @ SO3.exp(delta)).wxyz


class PerCamera(Variable):
    """One copy of ``block`` per camera of the rig: values ``(C, *block.value_shape)``, tangent ``C·block.size``
    (camera-major). A camera term reads its own camera's copy only."""

    block: Variable
    num_cameras: int = eqx.field(static=True)

    @property
    def size(self) -> int:
        return self.num_cameras * self.block.size

    @property
    def value_shape(self) -> tuple[int, ...]:
        return (self.num_cameras, *self.block.value_shape)

    def start(self) -> jax.Array:
        return jnp.broadcast_to(self.block.start(), self.value_shape)

    def retract(self, value: jax.Array, delta: jax.Array) -> jax.Array:
        return jax.vmap(self.block.retract)(value, delta.reshape(self.num_cameras, self.block.size))


def as_variable(declared: int | Variable, what: str) -> Variable:
    """A term's declaration (a size means ``Euclidean(size)``) as a :class:`Variable`.

    Raises:
        ValueError: neither a positive int nor a Variable (``what`` names the term and block).
    """
    if isinstance(declared, Variable):
        return declared
    if isinstance(declared, int) and not isinstance(declared, bool) and declared > 0:
        return Euclidean(declared)
    raise ValueError(f"{what}: a variable block is a positive size or a bcmocap.residuals.Variable, got {declared!r}")


#: The per-frame block that moves cameras on their mounts: ``PerCamera(Euclidean(6), C)``, each camera's
#: (translation m, rotation rad) offset in its own frame, so ``world_from_camera · exp(offset)`` is where the
#: camera is at that frame (strap wobble, soft tissue). A term that declares it must also give it a prior.
CAMERA_OFFSETS = "camera_offsets"


def retract_blocks(layout, values: dict, delta: jax.Array | None) -> dict:
    """``{name: value}`` of the blocks of ``layout`` (``((name, Variable), …)``) moved by the stacked tangent
    ``delta`` ``(..., Σ size)`` (None: unmoved). Values may carry leading batch axes matching ``delta``'s."""
    if delta is None:
        return {name: values[name] for name, _ in layout}
    out, at = {}, 0
    for name, variable in layout:
        step = delta[..., at : at + variable.size]
        retract = variable.retract
        for _ in range(step.ndim - 1):
            retract = jax.vmap(retract)
        out[name] = retract(values[name], step)
        at += variable.size
    return out
