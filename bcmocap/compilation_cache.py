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


def memory_mappings() -> tuple[int, int] | None:
    """``(mappings this process has, the kernel's limit vm.max_map_count)``, or None where /proc does not say."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            count = sum(1 for _ in maps)
        with open("/proc/sys/vm/max_map_count") as limit:
            return count, int(limit.read())
    except (OSError, ValueError):
        return None


def release_compiled_programs(share: float = 0.4) -> bool:
    """Free JAX's compiled programs when this process's memory mappings pass ``share`` of the kernel's limit.

    Every compiled XLA:CPU program holds its own memory mappings (about 18 for a small one) for as long as a jitted
    function's cache keeps it, and a process that compiles thousands of them (a batch of captures, a test worker)
    reaches ``vm.max_map_count`` (65530 by default): the next ``mmap`` fails inside XLA and the process aborts or
    crashes. Called between captures and between test files; the programs are compiled again when next used (or
    read from the persistent cache). Returns whether it freed them.
    """
    mappings = memory_mappings()
    if mappings is None or mappings[0] < share * mappings[1]:
        return False
    import gc

    import jax

    jax.clear_caches()
    gc.collect()
    return True
