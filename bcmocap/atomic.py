"""Atomic file writes: write beside the target under a temporary name, then rename over it.

A write that finds the disk full (``ENOSPC``, or ``EDQUOT`` past a quota) raises :class:`DiskFull`, one line that
names the folder, the bytes the write needed and the bytes free; the temporary is removed and the target is left
as it was, so a rerun after space is freed resumes. Needed from the core
(:meth:`bcmocap.correspondences.Correspondences.save`) up, so it imports nothing of bcmocap.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import shutil
import tempfile
import zipfile
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

# mkstemp creates 0600 files; renamed into place they should get the permissions a plain open() gives.
_UMASK = os.umask(0)
os.umask(_UMASK)


#: The errors of a full disk: no space, or a user's quota reached.
DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})


class DiskFull(OSError):
    """A write found its disk full; the message names the folder, the bytes needed and the bytes free."""

    def __str__(self) -> str:
        return str(self.strerror)


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` is the error of a full disk (or a quota reached)."""
    return isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS


def _free_bytes(folder: Path) -> int | None:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def disk_full(folder: str | os.PathLike, what: str, needed: int | None = None, written: int | None = None) -> DiskFull:
    """The :class:`DiskFull` of a write of ``what`` into ``folder``: ``needed`` bytes when the writer knew its size,
    else more than the ``written`` bytes it had written when the disk filled."""
    folder = Path(folder)
    if needed is not None:
        size = f"needed {needed:,} bytes"
    elif written:
        size = f"needed more than the {written:,} bytes written"
    else:
        size = "needed more space"
    free = _free_bytes(folder)
    text = (f"no space left on the disk of {folder}: writing {what} {size}"
            f"{f', {free:,} bytes free' if free is not None else ''}; free some space and rerun the same command "
            "(what was complete is kept)")
    return DiskFull(errno.ENOSPC, text)


def _size(path: str | os.PathLike) -> int | None:
    try:
        return os.path.getsize(path)
    except OSError:
        return None


def tree_size(path: str | os.PathLike) -> int:
    """Bytes of the files under ``path`` (a file's own size)."""
    path = Path(path)
    try:
        if path.is_file():
            return path.stat().st_size
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    except OSError:
        return 0


@contextlib.contextmanager
def full_disk_named(folder: str | os.PathLike, what: str, partial: str | os.PathLike | None = None) -> Iterator[None]:
    """Turn a full disk met in the block into :class:`DiskFull` naming ``folder`` and ``what`` (for writers that do
    not go through :func:`atomic_path`: folders written as a whole, video encoders); ``partial``: the temporary file
    or folder being written, whose size so far goes into the message."""
    try:
        yield
    except OSError as exc:
        if is_disk_full(exc) and not isinstance(exc, DiskFull):
            raise disk_full(folder, what, written=tree_size(partial) if partial else None) from None
        raise


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp", size: int | None = None) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder (created if needed); when the block ends normally it
    replaces ``path``, otherwise it is removed. ``suffix`` matters to writers that add their own (``.npz``).
    A full disk raises :class:`DiskFull` naming ``path``'s folder and ``size`` (the bytes the write needs, when
    the writer knows them)."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    tmp = None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=suffix)
        os.close(fd)
        yield Path(tmp)
        if os.path.exists(tmp):
            os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except OSError as exc:
        if is_disk_full(exc) and not isinstance(exc, DiskFull):
            raise disk_full(folder, path.name, size, _size(tmp) if tmp else None) from None
        raise
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def write_json_atomic(path: str | os.PathLike, payload: dict) -> None:
    """Write JSON to ``path`` through a temporary file in the same folder."""
    data = (json.dumps(payload, indent=2) + "\n").encode()
    with atomic_path(path, suffix=".json", size=len(data)) as tmp:
        tmp.write_bytes(data)


def write_npz_atomic(path: str | os.PathLike, arrays: Mapping[str, np.ndarray], compress: bool = True) -> None:
    """A deterministic ``.npz`` (fixed zip timestamps: the same arrays give the same bytes), written atomically.
    ``compress=False`` stores the arrays as they are (for files written often and removed soon: deflating
    megabytes takes about a second)."""
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=method) as z:
        for name, value in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = method
            body = io.BytesIO()
            np.lib.format.write_array(body, np.asarray(value), allow_pickle=False)
            z.writestr(info, body.getvalue())
    data = buffer.getvalue()
    with atomic_path(path, suffix=".npz", size=len(data)) as tmp:
        tmp.write_bytes(data)
