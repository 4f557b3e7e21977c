"""Expected errors as the one line a command prints."""

from __future__ import annotations


def one_line_error(exc: BaseException) -> str:
    """``exc`` as one line: its message (or its type when it has none), newlines folded."""
    if isinstance(exc, MemoryError):
        return f"out of memory ({exc})" if str(exc) else "out of memory"
    if isinstance(exc, OSError) and exc.strerror and exc.filename is not None:
        text = f"{exc.filename}: {exc.strerror}"
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())

