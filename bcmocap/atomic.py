"""Atomic file writes: write beside the target under a temporary name, then rename over it.

Needed from the core (:meth:`bcmocap.correspondences.Correspondences.save`) up, so it imports nothing of bcmocap.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tempfile
import zipfile
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

# mkstemp creates 0600 files; renamed into place they should get the permissions a plain open() gives.
_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder (created if needed); when the block ends normally it
    replaces ``path``, otherwise it is removed. ``suffix`` matters to writers that add their own (``.npz``)."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        yield Path(tmp)
        if os.path.exists(tmp):
            os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_json_atomic(path: str | os.PathLike, payload: dict) -> None:
    """Write JSON to ``path`` through a temporary file in the same folder."""
    with atomic_path(path, suffix=".json") as tmp:
        tmp.write_text(json.dumps(payload, indent=2) + "\n")


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
    with atomic_path(path, suffix=".npz") as tmp:
        tmp.write_bytes(buffer.getvalue())
