"""The frontend's threads: how many, and the memory their work freed handed back to the system."""

import platform
import subprocess
import sys

import pytest

from bcmocap.frontend.threads import default_threads


def test_threads_from_the_environment_or_the_cpu_count(monkeypatch):
    monkeypatch.setenv("BCMOCAP_THREADS", "1")
    assert default_threads() == 1
    monkeypatch.setenv("BCMOCAP_THREADS", "none")
    assert default_threads() >= 1


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="malloc_trim is glibc's")
def test_freed_memory_held_between_live_blocks_goes_back_to_the_system():
    """In a fresh process (this one's heap depends on the tests before): 180 MB of 60 kB blocks (from the heap, below
    glibc's mmap threshold) freed between small live ones stay held by glibc (as a registration's FLANN indexes
    did) until handed back."""
    script = """
import numpy as np
from bcmocap.frontend.threads import give_back_freed_memory
def anonymous_mb():
    return next(int(line.split()[1]) / 1024 for line in open("/proc/self/status") if line.startswith("RssAnon"))
live, freed = [], []
for _ in range(3000):
    freed.append(np.ones(60_000 // 8))
    live.append(np.ones(4))
del freed
before = anonymous_mb()
give_back_freed_memory()
print(before, anonymous_mb(), len(live))
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout.split()
    before, after, live = float(out[0]), float(out[1]), int(out[2])
    assert after < before - 100 and live == 3000
