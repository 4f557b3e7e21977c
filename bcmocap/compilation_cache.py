"""JAX's persistent compilation cache, turned on by the commands, benchmarks and examples."""

from __future__ import annotations

import os
from pathlib import Path


def enable_compilation_cache() -> None:
    """Persist XLA compilations across runs (``BCMOCAP_CACHE_DIR``, default ``~/.cache/bcmocap/jax``)."""
    cache = os.environ.get("BCMOCAP_CACHE_DIR", str(Path.home() / ".cache" / "bcmocap" / "jax"))
    try:
        Path(cache).mkdir(parents=True, exist_ok=True)
    except OSError:
        return
    import jax

    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
