"""Names and relative paths read from untrusted files (a capture folder's ``capture.json`` and ``rig.json``).

A camera or trial name becomes one component of paths that commands read (``trials/<trial>/<camera>.mp4``)
and write (``OUT/features/<trial>/<camera>/``), so it must never be able to leave those folders: it must
not be absolute, hold a separator, be ``.`` or ``..``, or hold a NUL or control character. A relative path
in such a file (a lens file in ``rig.json``) must stay inside the folder it is relative to. Both checks are
lexical: a symlink the user placed inside the folder is theirs to follow.
"""

from __future__ import annotations

import re
from pathlib import Path, PurePosixPath

__all__ = ["checked_name", "checked_relative_path"]

# Letters, digits and ``_ . + -`` (no separator, no whitespace), not starting with a dot; 1 to 128 characters.
_NAME = re.compile(r"[A-Za-z0-9_+\-][A-Za-z0-9_.+\-]{0,127}")


def checked_name(value: object, what: str, source: str | Path) -> str:
    """``value`` if it is a safe single path component, else ``ValueError`` naming ``source`` and ``what``.

    Args:
        value: the name as read (any JSON value).
        what: where in the file it was, e.g. ``"cameras[3].name"``.
        source: the file it came from.
    """
    if not isinstance(value, str):
        raise ValueError(f"{source}: {what} must be a string, got {type(value).__name__} {value!r}")
    if not _NAME.fullmatch(value):
        raise ValueError(f"{source}: {what} {value!r} is not a plain name (1-128 letters, digits, '_', '.', '+', "
                         "'-', not starting with '.'; no path separators)")
    return value


def checked_relative_path(value: object, what: str, source: str | Path) -> PurePosixPath:
    """``value`` as a relative POSIX path that stays inside the folder it is relative to (no absolute path,
    no ``..`` component, no NUL or backslash), else ``ValueError`` naming ``source`` and ``what``."""
    if not isinstance(value, str):
        raise ValueError(f"{source}: {what} must be a string, got {type(value).__name__} {value!r}")
    path = PurePosixPath(value)
    if (not value or path.is_absolute() or ".." in path.parts or "\\" in value
            or any(ord(c) < 32 for c in value) or not path.parts):
        raise ValueError(f"{source}: {what} {value!r} must be a relative path inside the folder "
                         "(no absolute path, no '..', no backslash or control character)")
    return path
