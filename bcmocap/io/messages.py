"""Expected errors as the one line a command prints."""

from __future__ import annotations

import os

from ..atomic import DiskFull, disk_full, is_disk_full


def one_line_error(exc: BaseException, folder: str | os.PathLike | None = None) -> str:
    """``exc`` as one line: its message (or its type when it has none), newlines folded. A full disk met by a
    writer that did not say so itself names the file's folder, or ``folder`` (the command's ``--out``) when the
    error names no file."""
    if isinstance(exc, MemoryError):
        return f"out of memory ({exc})" if str(exc) else "out of memory"
    if is_disk_full(exc) and not isinstance(exc, DiskFull):
        if exc.filename is not None:
            name = os.fspath(exc.filename)
            exc = disk_full(os.path.dirname(name) or ".", os.path.basename(name))
        elif folder is not None:
            exc = disk_full(folder, "its outputs")
    if isinstance(exc, OSError) and exc.strerror and exc.filename is not None:
        text = f"{exc.filename}: {exc.strerror}"
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())

