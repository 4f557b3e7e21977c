"""Robust losses ρ(s) of a residual block's squared norm s = ‖r‖², as in Ceres.

The solver minimises ½ Σ ρ(‖r‖²). With optimistix (which has no robust loss) each block is replaced
by ``r · sqrt(ρ(s) / s)``, whose squared norm is ρ(s); autodiff through that scaling gives the exact
Gauss–Newton Jacobian of the robustified problem.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp


class RobustLoss(eqx.Module):
    """Base class: identity loss ρ(s) = s."""

    def rho(self, s: jax.Array) -> jax.Array:
        return s

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
