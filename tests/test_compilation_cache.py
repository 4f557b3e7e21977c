"""bcmocap.compilation_cache.release_compiled_programs: compiled programs hold memory mappings; past a share of the
kernel's limit they are freed (and compiled again when used)."""

import jax
import jax.numpy as jnp

from bcmocap.compilation_cache import memory_mappings, release_compiled_programs


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
