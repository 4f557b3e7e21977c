"""A folder on a small filesystem of fixed size (a tmpfs), for the tests and benchmarks of a full disk.

Mounting needs root (CI's machines and the developers' run as root); elsewhere the tests that need a real full
disk are skipped, and those that inject ``ENOSPC`` at the write calls still run.
"""

from __future__ import annotations

import contextlib
import subprocess
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def small_disk(folder: Path, size_bytes: int) -> Iterator[Path]:
    """Mount a tmpfs of ``size_bytes`` (rounded up to pages) on ``folder`` for the block; ``None`` is never
    yielded: raises ``PermissionError`` where this process may not mount."""
    folder.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={max(4096, size_bytes)}", "tmpfs", str(folder)],
                          capture_output=True, text=True)
    if done.returncode:
        raise PermissionError(f"cannot mount a tmpfs on {folder}: {done.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def resize(folder: Path, size_bytes: int) -> None:
    """Give the tmpfs mounted on ``folder`` a new size (space freed, or taken away)."""
    subprocess.run(["mount", "-o", f"remount,size={max(4096, size_bytes)}", str(folder)], check=True,
                   capture_output=True)


def fill(folder: Path) -> None:
    """Take the free space of ``folder``'s filesystem (a file ``filler`` as large as it goes)."""
    with open(folder / "filler", "wb", buffering=0) as out:
        try:
            while out.write(b"\0" * 4096):
                pass
        except OSError:
            pass
