"""On-disk SIFT features of one camera of one trial, written frame by frame and read back memory-mapped.

A long capture's features do not fit in memory (10 s of the standard rig at 30 Hz with 4000 features per
image hold 2.8 GB of descriptors), so :func:`~bcmocap.frontend.relative.extract_trial_features` streams
each camera's features to a folder and registration reads them through ``numpy.memmap``: only the frames
being matched are paged in, and the operating system drops them again under memory pressure.

Layout of ``<folder>/`` (one camera):

- ``features.json``: ``{"format": 1, "settings": {...}, "counts": [N_0, N_1, ...]}``: the settings the
  features were made with (start frame, stride, frame count, SIFT feature cap) and features per frame;
- ``keypoints.f64``: ``(ΣN, 2)`` float64 pixel positions (x, y), little-endian, no header;
- ``descriptors.u8``: ``(ΣN, 128)`` uint8 SIFT descriptors, no header.

A folder is written under a temporary name and renamed when complete, so an interrupted extraction
leaves no half-written cache behind.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ..atomic import full_disk_named
from .reference import uint8_descriptors

FORMAT = 1
# What a features folder may hold when it is replaced (the tracking cache adds its track.npz beside them).
_FILES = ("features.json", "keypoints.f64", "descriptors.u8", "track.npz", ".track.npz")
__all__ = ["write_camera_features", "read_camera_features"]


def write_camera_features(folder: str | os.PathLike, settings: dict,
                          frames: Iterable[tuple[np.ndarray, np.ndarray]]) -> None:
    """Stream ``(keypoints (N, 2), descriptors (N, 128) uint8)`` per frame into ``folder`` (replaced if it
    exists); only one frame is in memory at a time."""
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f".{folder.name}."))
    try:
        with full_disk_named(folder.parent, f"{folder.name}/", tmp):
            counts = []
            with open(tmp / "keypoints.f64", "wb") as kp_file, open(tmp / "descriptors.u8", "wb") as desc_file:
                for kp, desc in frames:
                    kp = np.ascontiguousarray(kp, "<f8").reshape(-1, 2)
                    desc = np.ascontiguousarray(uint8_descriptors(desc))
                    if len(kp) != len(desc):
                        raise ValueError(f"{folder}: frame {len(counts)} has {len(kp)} keypoints and "
                                         f"{len(desc)} descriptors")
                    kp_file.write(kp.tobytes())
                    desc_file.write(desc.tobytes())
                    counts.append(len(kp))
            (tmp / "features.json").write_text(json.dumps({"format": FORMAT, "settings": settings, "counts": counts}))
            if folder.is_symlink() or folder.exists():
                _remove_features_folder(folder)
            os.replace(tmp, folder)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def _remove_features_folder(folder: Path) -> None:
    """Remove an earlier features folder, refusing (``ValueError``) anything else found at that path: a
    symlink, a file, or a folder holding files this module does not write."""
    if folder.is_symlink() or not folder.is_dir():
        raise ValueError(f"{folder}: exists and is not a features folder; refusing to replace it")
    foreign = sorted(p.name for p in folder.iterdir() if p.name not in _FILES)
    if foreign:
        raise ValueError(f"{folder}: holds files that are not features ({', '.join(foreign[:3])}); "
                         "refusing to replace it")
    shutil.rmtree(folder)


def read_camera_features(folder: str | os.PathLike, settings: dict | None = None) -> list | None:
    """The features in ``folder`` as ``[(keypoints (N, 2) float64, descriptors (N, 128) uint8)]`` per frame,
    memory-mapped read-only; ``None`` when the folder is missing, incomplete, or was made with other
    ``settings`` (then the caller recomputes)."""
    folder = Path(folder)
    try:
        meta = json.loads((folder / "features.json").read_text())
        if meta.get("format") != FORMAT or (settings is not None and meta.get("settings") != settings):
            return None
        counts = np.asarray(meta["counts"], np.int64)
        total = int(counts.sum())
        if (folder / "keypoints.f64").stat().st_size != 16 * total \
                or (folder / "descriptors.u8").stat().st_size != 128 * total:
            return None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if not len(counts):
        return []
    if total == 0:
        kp, desc = np.zeros((0, 2)), np.zeros((0, 128), np.uint8)
    else:
        kp = np.memmap(folder / "keypoints.f64", dtype="<f8", mode="r", shape=(total, 2))
        desc = np.memmap(folder / "descriptors.u8", dtype=np.uint8, mode="r", shape=(total, 128))
    cut = np.cumsum(counts)[:-1]
    return list(zip(np.split(kp, cut), np.split(desc, cut)))
