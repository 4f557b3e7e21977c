"""The ``--out`` folder of a command: checked, and locked while a command writes to it."""

from __future__ import annotations

import contextlib
import fcntl
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path


def output_folder(command: str, out: str | os.PathLike) -> Path | None:
    """``--out`` as a Path, or None after telling the user (on stderr) that it exists and is not a folder."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        print(f"bcmocap {command}: --out {out} exists and is not a folder", file=sys.stderr)
        return None
    return out


def check_outside(out: Path, capture: Path) -> None:
    """``ValueError`` if ``out`` is the capture folder or inside it: a capture is only ever read."""
    out, capture = Path(out).resolve(), Path(capture).resolve()
    if out == capture or capture in out.parents:
        raise ValueError(f"--out {out} is inside the capture folder {capture}: the capture is never written")


@contextlib.contextmanager
def locked_output(out: Path, wait_s: float = 0.0) -> Iterator[None]:
    """Hold ``out/run.lock`` (an advisory ``flock``, released by the kernel even on kill -9) while the block
    runs. When another process or thread holds it, wait up to ``wait_s`` seconds for it, then raise
    ``ValueError`` naming the holder's pid: two commands never write into one output folder at once, and two
    short writers (model saves from two viewer clients) take turns."""
    path = Path(out) / "run.lock"
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    try:
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() < deadline:
                    time.sleep(0.05)
                    continue
                holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
                waited = f" (waited {wait_s:g} s)" if wait_s else ""
                raise ValueError(f"{out}: another bcmocap command (pid {holder}) is writing to this folder{waited}; "
                                 "wait for it or choose another --out") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)
