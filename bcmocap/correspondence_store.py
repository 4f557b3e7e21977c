"""A trial's :class:`~bcmocap.correspondences.Correspondences` on disk, read a window of frames at a time.

A long capture's measurements do not fit in memory as dense ``(T, C, N)`` arrays (10 minutes at 30
frames/s and ~3500 slots per camera-frame are ~35 GB), but the solver only ever needs one window of
frames. A store is a folder::

    index.json        fps, frames, cameras, slot counts, the blocks and their frame ranges
    points.f64        (P, 3) float64 scene points (m), raw little-endian, read through numpy.memmap
    poses.npz         world_from_camera (T, C, 7), registered (T, C): small, read whole
    block_NNNNNN.npz  point_ids, pixels, weights and homography data of frames [start, stop),
                      each block padded only to its own widest camera-frame

:meth:`CorrespondenceStore.frames` returns a window as an ordinary ``Correspondences`` padded to the
store's widths (so every window has the same shapes and the solver compiles once) with only the
points that window uses. Memory is that of a block and a window, whatever the trial's length.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import zipfile
import zlib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from .atomic import DiskFull, tree_size, disk_full, is_disk_full
from .correspondences import Correspondences, pad_slots

FORMAT = "bcmocap.correspondence_store/1"
_UNREADABLE = (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)  # a damaged .npz
_MEASUREMENTS = ("point_ids", "pixels", "weights", "homography_pixels", "homography_pixels_prev", "homography_weights")


@dataclasses.dataclass(frozen=True)
class Block:
    """Frames ``[start, stop)`` of a store, in ``file``."""

    start: int
    stop: int
    file: str


class CorrespondenceStore:
    """Read side of a store folder (see the module docstring); open with :meth:`open`.

    Attributes:
        path: the folder.
        fps: frame rate (Hz); num_frames ``T``; num_cameras ``C``.
        slots: ``N``, the widest camera-frame's measurement count over the trial.
        homography_slots: ``M``, the same for homography pairs.
        homography_cameras: the most cameras with homography pairs in one frame (0: none at all).
        blocks: the blocks in frame order.
        num_points: ``P``; :attr:`points` maps them from the file when asked.
        world_from_camera: ``(T, C, 7)``; registered: ``(T, C)`` bool.
    """

    def __init__(self, path: Path, index: dict, world_from_camera: np.ndarray, registered: np.ndarray):
        self.path = path
        self.fps = float(index["fps"])
        self.num_frames = int(index["frames"])
        self.num_cameras = int(index["cameras"])
        self.slots = int(index["slots"])
        self.homography_slots = int(index["homography_slots"])
        self.homography_cameras = int(index["homography_cameras"])
        self.blocks = [Block(int(a), int(b), str(f)) for a, b, f in index["blocks"]]
        self.num_points = int(index["points"])
        self.world_from_camera = world_from_camera
        self.registered = registered

    @property
    def points(self) -> np.ndarray:
        """``(P, 3)`` scene points (m), memory-mapped read-only. A fresh map each time: pages a window
        touched are released with its map, so resident memory does not grow along the trial."""
        if not self.num_points:
            return np.zeros((0, 3))
        return np.memmap(self.path / "points.f64", dtype="<f8", mode="r", shape=(self.num_points, 3))

    # ---- reading ----------------------------------------------------------------------------------
    @classmethod
    def open(cls, path: str | Path) -> CorrespondenceStore:
        """Open a store; errors name the folder and the missing or inconsistent file or field."""
        path = Path(path)
        if not path.is_dir():
            raise ValueError(f"{path}: no correspondence store (not a folder)")
        try:
            index = json.loads((path / "index.json").read_text())
        except (OSError, ValueError) as err:
            raise ValueError(f"{path / 'index.json'}: not readable ({err})") from None
        if not isinstance(index, dict) or index.get("format") != FORMAT:
            found = index.get("format") if isinstance(index, dict) else type(index).__name__
            raise ValueError(f"{path / 'index.json'}: format {found!r}, expected {FORMAT!r}")
        for key in ("fps", "frames", "cameras", "points", "slots", "homography_slots", "homography_cameras", "blocks"):
            if key not in index:
                raise ValueError(f"{path / 'index.json'}: missing field {key!r}")
        _check_index(path / "index.json", index)
        num_points = int(index["points"])
        points_file = path / "points.f64"
        if not points_file.is_file() or points_file.stat().st_size != 24 * num_points:
            size = points_file.stat().st_size if points_file.is_file() else "missing"
            raise ValueError(f"{points_file}: expected {num_points} points ({24 * num_points} bytes), found {size}")
        try:
            with np.load(path / "poses.npz", allow_pickle=False) as poses:
                world_from_camera, registered = poses["world_from_camera"], poses["registered"].astype(bool)
        except _UNREADABLE as err:
            raise ValueError(f"{path / 'poses.npz'}: not readable ({err})") from None
        t, c = int(index["frames"]), int(index["cameras"])
        if world_from_camera.shape != (t, c, 7) or registered.shape != (t, c):
            raise ValueError(f"{path / 'poses.npz'}: world_from_camera {world_from_camera.shape} and registered "
                             f"{registered.shape}, expected ({t}, {c}, 7) and ({t}, {c})")
        if not np.issubdtype(world_from_camera.dtype, np.floating):
            raise ValueError(f"{path / 'poses.npz'}: world_from_camera has dtype {world_from_camera.dtype}")
        bad = registered & ~np.all(np.isfinite(world_from_camera), axis=-1)
        if bad.any():
            ti, ci = np.argwhere(bad)[0]
            raise ValueError(f"{path / 'poses.npz'}: world_from_camera has NaN or inf at registered frame {ti}, "
                             f"camera {ci}")
        store = cls(path, index, world_from_camera, registered)
        for k, piece in enumerate(store.iter_points()):
            bad = ~np.all(np.isfinite(piece), axis=1)
            if bad.any():
                raise ValueError(f"{points_file}: point {k * (1 << 20) + int(np.argmax(bad))} has NaN or inf")
        edges = [b.start for b in store.blocks] + [store.num_frames]
        if store.blocks and (edges[0] != 0 or any(b.stop != e for b, e in zip(store.blocks, edges[1:]))):
            raise ValueError(f"{path / 'index.json'}: blocks do not cover frames [0, {t}) in order")
        return store

    def block(self, k: int) -> dict[str, np.ndarray]:
        """Block ``k``'s measurement arrays (each padded only to the block's own widths)."""
        b = self.blocks[k]
        file = self.path / b.file
        try:
            with np.load(file, allow_pickle=False) as archive:
                data = {name: archive[name] for name in _MEASUREMENTS}
        except _UNREADABLE as err:
            raise ValueError(f"{file}: not a readable block of {self.path} ({err})") from None
        frames, cameras = b.stop - b.start, self.num_cameras
        for name, a in data.items():
            width = self.slots if name in _MEASUREMENTS[:3] else self.homography_slots
            tail = (2,) if name in ("pixels", "homography_pixels", "homography_pixels_prev") else ()
            if a.ndim != 3 + len(tail) or a.shape[:2] != (frames, cameras) or a.shape[2] > width or a.shape[3:] != tail:
                raise ValueError(f"{file}: {name} has shape {a.shape}, expected ({frames}, {cameras}, ≤{width}"
                                 f"{''.join(f', {n}' for n in tail)}) (block of {self.path})")
            if not np.issubdtype(a.dtype, np.integer if name == "point_ids" else np.floating):
                raise ValueError(f"{file}: {name} has dtype {a.dtype} (block of {self.path})")
        ids = data["point_ids"]
        if ids.size and (ids.min() < -1 or ids.max() >= self.num_points):
            raise ValueError(f"{file}: point_ids outside [-1, {self.num_points}) (block of {self.path})")
        for name, weights in (("weights", "weights"), ("homography_weights", "homography_weights"),
                              ("pixels", "weights"), ("homography_pixels", "homography_weights"),
                              ("homography_pixels_prev", "homography_weights")):
            a, w = data[name], data[weights]  # a weight must be finite; a measurement where it is used
            bad = ~np.isfinite(a) | (a < 0) if name == weights else (w > 0) & ~np.all(np.isfinite(a), axis=-1)
            if bad.any():
                ti, ci, k = np.argwhere(bad)[0]
                what = "NaN, inf or a negative value" if name == weights else "NaN or inf"
                raise ValueError(f"{file}: {name} has {what} at frame {b.start + ti}, camera {ci}, slot {k} "
                                 f"(block of {self.path})")
        return data

    def frames(self, start: int, stop: int) -> Correspondences:
        """Frames ``[start, stop)`` as ``Correspondences`` padded to the store's ``slots`` and
        ``homography_slots``, with only the points they measure (ids renumbered)."""
        if not 0 <= start < stop <= self.num_frames:
            raise ValueError(f"{self.path}: frames [{start}, {stop}) outside [0, {self.num_frames})")
        pieces = []
        for k, b in enumerate(self.blocks):
            if b.stop <= start or b.start >= stop:
                continue
            data, lo, hi = self.block(k), max(start, b.start) - b.start, min(stop, b.stop) - b.start
            pieces.append({name: pad_slots(a[lo:hi], self._width(name), -1 if name == "point_ids" else 0)
                           for name, a in data.items()})
        data = {name: np.concatenate([p[name] for p in pieces]) for name in _MEASUREMENTS}
        ids = data["point_ids"]
        used, local = np.unique(ids[ids >= 0], return_inverse=True)
        remapped = np.full(ids.shape, -1, np.int32)
        remapped[ids >= 0] = local
        data["point_ids"] = remapped
        return Correspondences(np.asarray(self.points[used]).reshape(-1, 3), **data,
                               world_from_camera=self.world_from_camera[start:stop],
                               registered=self.registered[start:stop], fps=self.fps)

    def load(self) -> Correspondences:
        """The whole trial in memory (small trials, tests); ids index :attr:`points` unchanged."""
        blocks = [self.block(k) for k in range(len(self.blocks))]
        data = {name: np.concatenate([pad_slots(b[name], self._width(name), -1 if name == "point_ids" else 0) for b in blocks])
                for name in _MEASUREMENTS}
        return Correspondences(np.array(self.points).reshape(-1, 3), **data, world_from_camera=self.world_from_camera,
                               registered=self.registered, fps=self.fps)

    def _width(self, name: str) -> int:
        return self.slots if name in _MEASUREMENTS[:3] else self.homography_slots

    def used_mask(self) -> np.ndarray:
        """``(P,)`` bool: the points some frame measures (with weight > 0); read block by block."""
        used = np.zeros(self.num_points, bool)
        for k in range(len(self.blocks)):
            data = self.block(k)
            used[data["point_ids"][(data["weights"] > 0) & (data["point_ids"] >= 0)]] = True
        return used

    def used_points(self) -> np.ndarray:
        """Ids of the points some frame measures, sorted."""
        return np.flatnonzero(self.used_mask())

    def iter_points(self, mask: np.ndarray | None = None, piece: int = 1 << 20) -> Iterator[np.ndarray]:
        """The points (``(n, 3)`` arrays, in id order) read from the file ``piece`` at a time, only those
        where ``mask`` ``(P,)`` is True if given; memory is that of one piece."""
        with open(self.path / "points.f64", "rb") as f:
            for a in range(0, self.num_points, piece):
                points = np.frombuffer(f.read(24 * min(piece, self.num_points - a)), "<f8").reshape(-1, 3)
                yield points if mask is None else points[mask[a:a + len(points)]]

    def num_observations(self) -> int:
        """Measurements with weight > 0 over the trial."""
        return int(sum((self.block(k)["weights"] > 0).sum() for k in range(len(self.blocks))))

    def transformed(self, path: str | Path, points: Callable[[np.ndarray], np.ndarray],
                    poses: Callable[[np.ndarray], np.ndarray], *, world_from_camera: np.ndarray | None = None,
                    registered: np.ndarray | None = None, dropped: np.ndarray | None = None) -> CorrespondenceStore:
        """A copy at ``path`` with points and camera poses mapped (e.g. by a similarity into the metric
        world); the measurement blocks are copied unchanged, the points mapped in pieces. ``world_from_camera``
        ``(T, C, 7)`` and ``registered`` ``(T, C)``: these poses instead of the store's (re-fitted ones);
        ``dropped`` ``(T, C)`` bool: camera-frames whose point measurements get weight 0 (their blocks rewritten)."""
        world_from_camera = self.world_from_camera if world_from_camera is None else np.asarray(world_from_camera)
        registered = self.registered if registered is None else np.asarray(registered, bool)
        dropped = np.zeros_like(self.registered) if dropped is None else np.asarray(dropped, bool)
        if (world_from_camera.shape != self.world_from_camera.shape or registered.shape != self.registered.shape
                or dropped.shape != self.registered.shape):
            raise ValueError(f"{self.path}: world_from_camera {world_from_camera.shape}, registered "
                             f"{registered.shape} and dropped {dropped.shape} for a store of poses "
                             f"{self.world_from_camera.shape}")
        with _Folder(Path(path)) as tmp:
            for k, b in enumerate(self.blocks):
                if not dropped[b.start:b.stop].any():
                    shutil.copyfile(self.path / b.file, tmp / b.file)
                    continue
                data = self.block(k)
                data["weights"] = np.where(dropped[b.start:b.stop, :, None], 0.0, data["weights"]).astype(data["weights"].dtype)
                np.savez_compressed(tmp / b.file, **data)
            with open(tmp / "points.f64", "wb") as dst:
                for piece in self.iter_points():
                    dst.write(np.ascontiguousarray(points(piece), "<f8").tobytes())
            np.savez(tmp / "poses.npz", world_from_camera=poses(world_from_camera), registered=registered)
            shutil.copyfile(self.path / "index.json", tmp / "index.json")
        return CorrespondenceStore.open(path)


def _check_index(where: Path, index: dict) -> None:
    """The index's counts are non-negative integers, fps a positive number, blocks ``[start, stop, file]``
    with a plain file name (never a path out of the folder)."""
    for key in ("frames", "cameras", "points", "slots", "homography_slots", "homography_cameras"):
        value = index[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{where}: field {key!r} must be a non-negative integer, got {value!r}")
    fps = index["fps"]
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not 0 < fps < float("inf"):
        raise ValueError(f"{where}: field 'fps' must be a positive number, got {fps!r}")
    blocks = index["blocks"]
    if not isinstance(blocks, list):
        raise ValueError(f"{where}: field 'blocks' must be a list, got {type(blocks).__name__}")
    for i, block in enumerate(blocks):
        if (not isinstance(block, list) or len(block) != 3 or not all(isinstance(x, int) and not isinstance(x, bool)
                                                                        for x in block[:2])
                or not isinstance(block[2], str) or Path(block[2]).name != block[2] or block[2] in ("", ".", "..")
                or "\\" in block[2] or "\x00" in block[2] or not block[0] < block[1]):
            raise ValueError(f"{where}: blocks[{i}] must be [start, stop, file name] with start < stop, got {block!r}")


def write_store(path: str | Path, parts: Iterable[Correspondences], *, block_frames: int = 50) -> CorrespondenceStore:
    """Write consecutive stretches of one trial (e.g. chunks registered one after the other) as a store.

    Each part carries its own points; they are appended with the part's ids offset. Parts are consumed one
    at a time (a generator keeps only one in memory). The folder is written beside ``path`` and renamed
    into place when complete, replacing an earlier store there.

    Args:
        path: the store folder.
        parts: ``Correspondences`` with equal cameras and fps, in frame order.
        block_frames: frames per block file (windows read the blocks they overlap).
    """
    if block_frames < 1:
        raise ValueError(f"write_store: block_frames must be ≥ 1, got {block_frames}")
    path = Path(path)
    blocks, poses, registered = [], [], []
    num_points = frames = slots = homography_slots = homography_cameras = 0
    cameras = fps = None
    with _Folder(path) as tmp, open(tmp / "points.f64", "wb") as points_file:
        for k, part in enumerate(parts):
            if cameras is None:
                cameras, fps = part.num_cameras, part.fps
            elif (part.num_cameras, part.fps) != (cameras, fps):
                raise ValueError(f"write_store: part {k} has {part.num_cameras} cameras at {part.fps:g} fps, "
                                 f"part 0 {cameras} at {fps:g}")
            points_file.write(np.ascontiguousarray(part.points, "<f8").tobytes())
            ids = np.where(part.point_ids >= 0, part.point_ids + num_points, -1).astype(np.int32)
            num_points += len(part.points)
            for a in range(0, part.num_frames, block_frames):
                b = min(a + block_frames, part.num_frames)
                data = {"point_ids": ids[a:b], **{name: getattr(part, name)[a:b] for name in _MEASUREMENTS[1:]}}
                data = _trimmed(data)
                slots = max(slots, data["point_ids"].shape[2])
                homography_slots = max(homography_slots, data["homography_weights"].shape[2])
                active = (data["homography_weights"] > 0).any(axis=2).sum(axis=1)
                homography_cameras = max(homography_cameras, int(active.max(initial=0)))
                file = f"block_{frames + a:06d}.npz"
                np.savez_compressed(tmp / file, **data)
                blocks.append((frames + a, frames + b, file))
            poses.append(part.world_from_camera)
            registered.append(part.registered)
            frames += part.num_frames
            part = ids = data = None  # released before the next part is made
        if cameras is None:
            raise ValueError("write_store: no parts")
        np.savez(tmp / "poses.npz", world_from_camera=np.concatenate(poses), registered=np.concatenate(registered))
        (tmp / "index.json").write_text(json.dumps({
            "format": FORMAT, "fps": fps, "frames": frames, "cameras": cameras, "points": num_points,
            "slots": slots, "homography_slots": homography_slots, "homography_cameras": homography_cameras,
            "blocks": blocks}, indent=1))
    return CorrespondenceStore.open(path)


def _trimmed(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Drop trailing slots that no camera-frame of the block uses."""
    n = int((data["point_ids"] >= 0).sum(axis=(0, 1)).nonzero()[0].max(initial=-1)) + 1
    m = int((data["homography_weights"] > 0).sum(axis=(0, 1)).nonzero()[0].max(initial=-1)) + 1
    return {name: a[:, :, : (n if name in _MEASUREMENTS[:3] else m)] for name, a in data.items()}


class _Folder:
    """Write a folder as ``<path>.tmp`` and rename it to ``path`` (replacing it) only on success."""

    def __init__(self, path: Path):
        self.path, self.tmp = path, path.with_name(path.name + ".tmp")

    def __enter__(self) -> Path:
        shutil.rmtree(self.tmp, ignore_errors=True)
        self.tmp.mkdir(parents=True)
        return self.tmp

    def __exit__(self, kind, value, traceback):
        if kind is not None:
            written = tree_size(self.tmp)
            shutil.rmtree(self.tmp, ignore_errors=True)
            if is_disk_full(value) and not isinstance(value, DiskFull):
                raise disk_full(self.path.parent, f"{self.path.name}/", written=written) from None
            return False
        old = self.path.with_name(self.path.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        if self.path.exists():
            self.path.rename(old)
        self.tmp.rename(self.path)
        shutil.rmtree(old, ignore_errors=True)
        return False
