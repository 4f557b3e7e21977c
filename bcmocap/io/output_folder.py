"""The ``--out`` folder of a command."""

from __future__ import annotations

import os
import sys
from pathlib import Path


def output_folder(command: str, out: str | os.PathLike) -> Path | None:
    """``--out`` as a Path, or None after telling the user (on stderr) that it exists and is not a folder."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        print(f"bcmocap {command}: --out {out} exists and is not a folder", file=sys.stderr)
        return None
    return out
