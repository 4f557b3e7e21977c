"""float64 in JAX. bcmocap's geometry and solvers need it; JAX defaults to float32, and importing bcmocap does
not change that (no import-time side effect): entry points call :func:`enable_float64` (the ``bcmocap``
command, the benchmarks and the examples do) and the solvers check with :func:`require_float64`."""

from __future__ import annotations

import os
import sys

__all__ = ["enable_float64", "require_float64"]


def enable_float64() -> None:
    """Switch JAX to float64 (``jax_enable_x64``); call it before any JAX array is made. Before JAX is imported
    this only sets ``JAX_ENABLE_X64=1``, which JAX reads when it is imported (so a command that may not need JAX,
    e.g. ``bcmocap view`` until its server is up, does not import it here)."""
    if "jax" not in sys.modules:
        os.environ["JAX_ENABLE_X64"] = "1"
        return
    import jax

    jax.config.update("jax_enable_x64", True)


def require_float64(what: str) -> None:
    """Raise ``RuntimeError`` naming ``what`` unless JAX runs in float64."""
    import jax

    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError(f"{what} needs float64 in JAX: call bcmocap.enable_float64() before building the problem "
                           "(or set the environment variable JAX_ENABLE_X64=1)")
