"""Robust losses ρ(s) of a residual block's squared norm s = ‖r‖², as in Ceres.

The solver minimises ½ Σ ρ(‖r‖²). optimistix has no robust loss, so the residual it sees is each block
scaled by ``sqrt(ρ(s) / s)`` (squared norm ρ(s): the true cost). The structured normal equations use
the IRLS model instead, as Ceres does where ρ'' ≤ 0: ``H = Σ ρ'(s) JᵀJ`` and ``g = Σ ρ'(s) Jᵀr`` on the
raw residuals. The gradient is exact and H stays positive semi-definite; the Gauss–Newton matrix of the
scaled residual is not, and in Cauchy's non-convex zone it proposed steps that raised the cost.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp


class RobustLoss(eqx.Module):
    """Base class: identity loss ρ(s) = s."""

    def rho(self, s: jax.Array) -> jax.Array:
        return s

    def derivative(self, s: jax.Array) -> jax.Array:
        """ρ'(s), elementwise (autodiff of :meth:`rho`): the IRLS weight of a block."""
        return jnp.vectorize(jax.grad(self.rho))(s)

    def scale_residual(self, r: jax.Array) -> jax.Array:
        """Scale residual blocks ``(..., k)`` so that their squared norms become ρ(s)."""
        s = jnp.sum(r * r, axis=-1, keepdims=True)
        positive = s > 0.0
        s_safe = jnp.where(positive, s, 1.0)
        factor = jnp.where(positive, jnp.sqrt(self.rho(s_safe) / s_safe), 1.0)
        return r * factor


class TrivialLoss(RobustLoss):
    """Plain least squares: ρ(s) = s."""

    def scale_residual(self, r: jax.Array) -> jax.Array:
        return r

    def derivative(self, s: jax.Array) -> jax.Array:
        return jnp.ones_like(s)


class HuberLoss(RobustLoss):
    """ρ(s) = s for s ≤ c², 2c√s − c² beyond; ``scale`` c in the residual's (whitened) units."""

    scale: jax.Array = eqx.field(default=1.0, converter=jnp.asarray)

    def rho(self, s):
        c = self.scale
        root = jnp.sqrt(jnp.where(s > c * c, s, c * c))
        return jnp.where(s <= c * c, s, 2.0 * c * root - c * c)


class CauchyLoss(RobustLoss):
    """ρ(s) = c² log(1 + s/c²); ``scale`` c in the residual's (whitened) units."""

    scale: jax.Array = eqx.field(default=1.0, converter=jnp.asarray)

    def rho(self, s):
        c2 = self.scale * self.scale
        return c2 * jnp.log1p(s / c2)


def loss_from_name(name: str, scale: float = 1.0) -> RobustLoss:
    """``"none" | "huber" | "cauchy"`` → a loss object (ValueError naming the choices otherwise)."""
    table = {"none": TrivialLoss, "trivial": TrivialLoss, "huber": HuberLoss, "cauchy": CauchyLoss}
    key = name.lower()
    if key not in table:
        raise ValueError(f"unknown robust loss '{name}'; choose one of none, huber, cauchy")
    return table[key]() if table[key] is TrivialLoss else table[key](scale)
