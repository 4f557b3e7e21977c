"""The frontend's threads: how many, and the memory their work freed handed back to the system."""

import platform

import numpy as np
import pytest

from bcmocap.frontend.threads import default_threads, give_back_freed_memory


def _anonymous_mb() -> float:
    for line in open("/proc/self/status"):
        if line.startswith("RssAnon"):
            return int(line.split()[1]) / 1024
    pytest.skip("no RssAnon in /proc/self/status")


def test_threads_from_the_environment_or_the_cpu_count(monkeypatch):
    monkeypatch.setenv("BCMOCAP_THREADS", "1")
    assert default_threads() == 1
    monkeypatch.setenv("BCMOCAP_THREADS", "none")
    assert default_threads() >= 1


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="malloc_trim is glibc's")
def test_freed_memory_held_between_live_blocks_goes_back_to_the_system():
    """180 MB of 60 kB blocks (from the heap, below glibc's mmap threshold) freed between small live ones: glibc
    keeps them (as it keeps a registration's FLANN indexes) until handed back."""
    live, freed = [], []
    for _ in range(3000):
        freed.append(np.ones(60_000 // 8))
        live.append(np.ones(4))
    del freed
    before = _anonymous_mb()
    give_back_freed_memory()
    assert _anonymous_mb() < before - 100
    assert len(live) == 3000
