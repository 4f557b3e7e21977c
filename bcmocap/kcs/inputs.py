"""Input files of ``bcmocap kcs``: 2-D joints per frame plus the chain's topology, as NPZ or CSV.

**NPZ** (one file, ``*.npz``):

* ``joints_2d`` — ``(F, J, 2)`` float image positions (pixels); NaN in both coordinates marks a missing joint;
* ``names`` — ``(J,)`` joint names;
* ``parents`` — ``(J,)`` parent per joint: an index (``-1`` for the root) or a name (``""`` for the root);
* ``rest`` — ``(J, 3)`` an initial configuration ``X0`` of the chain in metres (a mean or typical pose,
  Z up; it fixes the scale of the result and the rest pose of the BVH);
* optional ``mask`` — ``(F, J)`` bool, False for missing joints; ``links`` — ``(L, 2)`` extra rigid links
  (indices or names); ``fps`` — frame rate (a positive scalar).

**CSV** (a folder):

* ``topology.csv`` — header ``joint,parent,x,y,z``; one row per joint; ``parent`` empty for the root;
  ``x,y,z`` the joint in the initial configuration (metres);
* ``joints_2d.csv`` — header ``frame,joint,x,y``; one row per observed joint and frame (frames numbered
  from 0, below ``MAX_CSV_FRAMES``); a missing row, or empty ``x``/``y``, marks the joint missing in that frame;
* optional ``links.csv`` — header ``joint_a,joint_b``; one extra rigid link per row.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np

from .chain_space import KinematicChainSpace

__all__ = ["MAX_CSV_FRAMES", "KCSInput", "read_input"]

#: frames a joints_2d.csv may number (a 55-minute video at 30 frames/s): one row with a bigger frame
#: number would make the whole (frames, joints, 2) array.
MAX_CSV_FRAMES = 100_000


@dataclasses.dataclass(frozen=True, eq=False)
class KCSInput:
    """What ``bcmocap kcs`` reconstructs.

    Attributes:
        chain: topology and extra links.
        joints_2d: ``(F, J, 2)`` pixels, NaN where missing.
        rest: ``(J, 3)`` initial configuration (metres).
        fps: frame rate, or None if the input does not say.
    """

    chain: KinematicChainSpace
    joints_2d: np.ndarray
    rest: np.ndarray
    fps: float | None


def read_input(path: str | Path) -> KCSInput:
    """Read an NPZ file or a CSV folder (layouts in the module docstring); ValueError naming the file and field."""
    path = Path(path)
    if path.is_dir():
        return _read_csv_folder(path)
    if path.suffix.lower() == ".npz" and path.is_file():
        return _read_npz(path)
    if not path.exists():
        raise ValueError(f"{path}: no such file or folder")
    raise ValueError(f"{path}: expected a .npz file or a folder with topology.csv and joints_2d.csv")


def _check_arrays(where: str, chain: KinematicChainSpace, joints_2d: np.ndarray, rest: np.ndarray) -> None:
    j = chain.num_joints
    if joints_2d.ndim != 3 or joints_2d.shape[1:] != (j, 2):
        raise ValueError(f"{where}: joints_2d must have shape (F, {j}, 2) for the {j} joints, got {joints_2d.shape}")
    if joints_2d.shape[0] < 1:
        raise ValueError(f"{where}: joints_2d has no frames")
    if rest.shape != (j, 3):
        raise ValueError(f"{where}: rest must have shape ({j}, 3), got {rest.shape}")
    if not np.all(np.isfinite(rest)):
        k = int(np.argwhere(~np.isfinite(rest))[0, 0])
        raise ValueError(f"{where}: rest[{k}] (joint '{chain.names[k]}') holds NaN or inf")
    nan = np.isnan(joints_2d)
    for bad, what in ((np.isinf(joints_2d).any(-1), "is inf; mark missing joints with NaN"),
                      (nan.any(-1) & ~nan.all(-1), "has one NaN coordinate; a missing joint is NaN in both")):
        if bad.any():
            f, k = (int(i) for i in np.argwhere(bad)[0])
            raise ValueError(f"{where}: joints_2d[{f}, {k}] (frame {f}, joint '{chain.names[k]}') {what}")


def _fps(where: str, raw: np.ndarray) -> float:
    if raw.ndim != 0 or raw.dtype.kind not in "iuf":
        raise ValueError(f"{where}: 'fps' must be one number, got {raw.dtype} of shape {raw.shape}")
    fps = float(raw)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"{where}: 'fps' must be a positive finite frame rate, got {fps}")
    return fps


def _read_npz(path: Path) -> KCSInput:
    where = str(path)
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - numpy raises several kinds for a bad archive
        raise ValueError(f"{where}: not a readable .npz archive ({exc})") from None
    with data:
        for key in ("joints_2d", "names", "parents", "rest"):
            if key not in data:
                raise ValueError(f"{where}: missing array '{key}' (has {sorted(data.files)})")
        names = [str(n) for n in data["names"].reshape(-1)]
        parents_raw = data["parents"].reshape(-1)
        if parents_raw.dtype.kind in "iu":
            parents = [int(p) for p in parents_raw]
        elif parents_raw.dtype.kind in "US":
            parents = [str(p) or None for p in parents_raw]
        else:
            raise ValueError(f"{where}: 'parents' must hold integers or joint names, got dtype {parents_raw.dtype}")
        links = []
        if "links" in data:
            raw = data["links"]
            if raw.size and (raw.ndim != 2 or raw.shape[1] != 2):
                raise ValueError(f"{where}: 'links' must have shape (L, 2), got {raw.shape}")
            links = [(_item(a), _item(b)) for a, b in raw.reshape(-1, 2)]
        try:
            chain = KinematicChainSpace.from_parents(names, parents, links)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        joints_2d = np.array(data["joints_2d"], dtype=np.float64)
        rest = np.array(data["rest"], dtype=np.float64)
        if "mask" in data:
            mask = np.asarray(data["mask"]).astype(bool)
            if mask.shape != joints_2d.shape[:2]:
                raise ValueError(f"{where}: 'mask' must have shape {joints_2d.shape[:2]} (F, J), got {mask.shape}")
            joints_2d[~mask] = np.nan
        _check_arrays(where, chain, joints_2d, rest)
        fps = _fps(where, data["fps"]) if "fps" in data else None
    return KCSInput(chain, joints_2d, rest, fps)


def _item(x):
    return int(x) if isinstance(x, (int, np.integer)) else str(x)


def _rows(path: Path, header: tuple[str, ...]):
    """(line number, row dict) of a CSV file whose header must be ``header``."""
    if not path.is_file():
        raise ValueError(f"{path}: file not found (expected a CSV with header {','.join(header)})")
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        first = next(reader, None)
        if first is None or tuple(c.strip().lower() for c in first) != header:
            raise ValueError(f"{path}:1: expected the header '{','.join(header)}', found '{','.join(first or [])}'")
        for n, row in enumerate(reader, 2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise ValueError(f"{path}:{n}: expected {len(header)} fields ({','.join(header)}), found {len(row)}")
            yield n, dict(zip(header, (c.strip() for c in row)))


def _number(path: Path, line: int, field: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{path}:{line}: expected a number for '{field}', found '{text}'") from None
    if not math.isfinite(value):
        raise ValueError(f"{path}:{line}: '{field}' is not finite ('{text}')")
    return value


def _read_csv_folder(folder: Path) -> KCSInput:
    topo = folder / "topology.csv"
    names, parents, rest = [], [], []
    for n, row in _rows(topo, ("joint", "parent", "x", "y", "z")):
        if not row["joint"]:
            raise ValueError(f"{topo}:{n}: empty joint name")
        names.append(row["joint"])
        parents.append(row["parent"] or None)
        rest.append([_number(topo, n, k, row[k]) for k in ("x", "y", "z")])
    if not names:
        raise ValueError(f"{topo}: no joints")
    links = []
    link_file = folder / "links.csv"
    if link_file.exists():
        links = [(row["joint_a"], row["joint_b"]) for _, row in _rows(link_file, ("joint_a", "joint_b"))]
    try:
        chain = KinematicChainSpace.from_parents(names, parents, links)
    except ValueError as exc:
        raise ValueError(f"{topo}: {exc}") from None
    index = {name: k for k, name in enumerate(names)}
    obs = folder / "joints_2d.csv"
    entries = {}
    for n, row in _rows(obs, ("frame", "joint", "x", "y")):
        try:
            frame = int(row["frame"])
        except ValueError:
            frame = -1
        if not 0 <= frame < MAX_CSV_FRAMES:
            raise ValueError(f"{obs}:{n}: expected a frame number from 0 to {MAX_CSV_FRAMES - 1}, found '{row['frame']}'")
        if row["joint"] not in index:
            raise ValueError(f"{obs}:{n}: unknown joint '{row['joint']}'; topology.csv has {names}")
        key = (frame, index[row["joint"]])
        if key in entries:
            raise ValueError(f"{obs}:{n}: joint '{row['joint']}' appears twice in frame {frame} (first on line {entries[key][0]})")
        if not row["x"] and not row["y"]:
            entries[key] = (n, None)
            continue
        entries[key] = (n, (_number(obs, n, "x", row["x"]), _number(obs, n, "y", row["y"])))
    if not entries:
        raise ValueError(f"{obs}: no observations")
    num_frames = max(f for f, _ in entries) + 1
    joints_2d = np.full((num_frames, len(names), 2), np.nan)
    for (f, j), (_, uv) in entries.items():
        if uv is not None:
            joints_2d[f, j] = uv
    rest = np.asarray(rest)
    _check_arrays(str(folder), chain, joints_2d, rest)
    return KCSInput(chain, joints_2d, rest, None)
