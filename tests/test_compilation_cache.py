"""bcmocap.compilation_cache.release_compiled_programs: compiled programs hold memory mappings; past a share of the
kernel's limit they are freed (and compiled again when used)."""

import jax
import pytest
import jax.numpy as jnp

from bcmocap.compilation_cache import memory_mappings, release_compiled_programs


@pytest.mark.slow  # ~10 s: the heavy tier
def test_compiled_programs_are_freed_past_the_share_of_the_mapping_limit():
    kept = [jax.jit(lambda x, k=k: jnp.cumsum(x) * k) for k in range(40)]
    for k, f in enumerate(kept):
        f(jnp.arange(k + 2.0)).block_until_ready()
    count, limit = memory_mappings()
    assert 0 < count < limit
    assert not release_compiled_programs(share=1.0)  # far from the limit: nothing freed
    assert memory_mappings()[0] >= count - 50
    assert release_compiled_programs(share=0.0)
    assert memory_mappings()[0] < count - 40 * 10  # each program held about 18 mappings
    assert float(kept[3](jnp.arange(5.0))[-1]) == 30.0  # compiled again when used


def _entry(folder, name, seconds_old=3600.0):
    """A JAX cache entry as JAX writes one (zstd of the compilation time then the executable), aged so it is checked."""
    import os
    import time

    import zstandard

    path = folder / f"jit_{name}-{'0' * 64}-cache"
    path.write_bytes(zstandard.ZstdCompressor().compress((1234).to_bytes(4, "big") + bytes(range(256)) * 40))
    old = time.time() - seconds_old
    os.utime(path, (old, old))
    return path


def _age(path, seconds_old=3600.0):
    import os
    import time

    old = time.time() - seconds_old
    os.utime(path, (old, old))


DAMAGE = {
    "empty": lambda b: b"",
    "truncated": lambda b: b[: len(b) // 2],
    "garbage": lambda b: bytes(len(b)),
    "header overwritten": lambda b: b"\xff" * 8 + b[8:],
    "one byte flipped after it was checked": lambda b: b[:-20] + bytes([b[-20] ^ 0x01]) + b[-19:],
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_a_damaged_compilation_cache_entry_is_dropped_with_a_note(tmp_path, damage):
    from bcmocap.compilation_cache import check_compilation_cache

    good, other = _entry(tmp_path, "good"), _entry(tmp_path, "other")
    first = check_compilation_cache(tmp_path)
    assert (first.checked, first.dropped, first.note()) == (2, [], None)
    assert check_compilation_cache(tmp_path).trusted == 2  # recorded: not read again
    good.write_bytes(DAMAGE[damage](good.read_bytes()))
    _age(good)
    result = check_compilation_cache(tmp_path)
    assert result.dropped == [good.name] and not good.exists() and other.exists()
    assert str(tmp_path) in result.note() and good.name in result.note()
    assert check_compilation_cache(tmp_path).dropped == []


def test_an_entry_being_written_is_left_alone_and_an_unchanged_one_touched_is_kept(tmp_path):
    from bcmocap.compilation_cache import check_compilation_cache

    young = _entry(tmp_path, "young", seconds_old=1.0)
    young.write_bytes(young.read_bytes()[:10])  # another process is still writing it
    kept = _entry(tmp_path, "kept")
    check_compilation_cache(tmp_path)
    _age(kept, 100.0)  # the same bytes, a new time (copied, touched): still the entry JAX wrote
    result = check_compilation_cache(tmp_path)
    assert result.dropped == [] and young.exists() and kept.exists()


def test_jax_reads_the_rebuilt_entry_after_the_damaged_one_is_dropped(tmp_path):
    """End to end in a fresh process: JAX writes an entry, it is truncated (a crash while writing), the next process
    drops it with a note, compiles again with the same result and writes a whole entry."""
    import subprocess
    import sys

    script = (
        "import jax, jax.numpy as jnp, bcmocap.compilation_cache as c\n"
        "c.MIN_COMPILE_SECONDS = 0.0\n"
        "jax.config.update('jax_persistent_cache_min_entry_size_bytes', 0)\n"
        "c.enable_compilation_cache()\n"
        "print(float(jax.jit(lambda x: jnp.sin(x) @ jnp.cos(x).T)(jnp.ones((40, 40))).sum()))\n")
    env = {**__import__("os").environ, "BCMOCAP_CACHE_DIR": str(tmp_path), "JAX_PLATFORMS": "cpu"}
    run = lambda: subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)  # noqa: E731
    first = run()
    (entry,) = [p for p in tmp_path.glob("jit_*-cache") if "lambda" in p.name]
    whole = entry.read_bytes()
    entry.write_bytes(whole[: len(whole) // 3])
    _age(entry)
    second = run()
    assert "note: dropped 1 damaged entry" in second.stderr and entry.name in second.stderr
    assert second.stdout == first.stdout
    from bcmocap.compilation_cache import entry_decodes

    assert entry_decodes(entry.read_bytes()) and len(entry.read_bytes()) > len(whole) // 3  # written again, whole
    assert "Error reading persistent compilation cache" not in second.stderr
