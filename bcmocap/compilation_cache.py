"""JAX's persistent compilation cache, turned on by the commands, benchmarks and examples."""

from __future__ import annotations

import os
from pathlib import Path

#: Seconds a compilation must take to be written to the cache (reading is not affected). A host process that must
#: not serialize executables raises it: the test suite's long-lived workers, where XLA's serialization of an
#: executable threw a C++ exception whose unwinding faulted (``bcmocap.native_crashes``).
MIN_COMPILE_SECONDS = 0.5


def enable_compilation_cache() -> None:
    """Persist XLA compilations across runs (``BCMOCAP_CACHE_DIR``, default ``~/.cache/bcmocap/jax``)."""
    cache = os.environ.get("BCMOCAP_CACHE_DIR", str(Path.home() / ".cache" / "bcmocap" / "jax"))
    try:
        Path(cache).mkdir(parents=True, exist_ok=True)
    except OSError:
        return
    import jax

    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
