"""PLY (Stanford polygon file) output for the sparse scene and camera paths, and a small reader.

What is written is standard PLY 1.0 that MeshLab, CloudCompare, Open3D and ``plyfile`` read:

* :func:`write_ply`: a ``vertex`` element with ``x y z`` (``double`` or ``float``) and optionally
  ``red green blue`` (``uchar``).
* :func:`write_camera_paths_ply`: camera centres as coloured vertices (plus ``int`` properties ``camera``
  and ``frame``, which CloudCompare shows as scalar fields) and an ``edge`` element (``int vertex1``,
  ``int vertex2``) joining consecutive frames of each camera, so viewers draw each path as a polyline.

Coordinates are written as given (bcmocap's Z-up world in metres). Files are written atomically
(temporary file + rename). :func:`read_ply` / :func:`read_ply_elements` read ``ascii`` and
``binary_little_endian`` files whose elements have scalar properties only (``list`` properties, as in
meshes' ``face`` elements, are only accepted after the ``vertex`` element, where they are not read).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from ..atomic import atomic_path

__all__ = ["read_ply", "read_ply_elements", "write_camera_paths_ply", "write_ply", "write_ply_pieces"]

# PLY scalar type names (both the 1.0 spellings and the sized aliases) → little-endian numpy dtypes.
_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2",
    "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4",
    "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4",
    "double": "<f8", "float64": "<f8",
}  # fmt: skip

# Distinct colours for camera paths (matplotlib's tab10), cycled when there are more cameras.
_PALETTE = np.array(
    [
        [31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
        [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207],
    ],
    dtype=np.uint8,
)  # fmt: skip


# ---- writing ----------------------------------------------------------------------------------------


def _check_points(points, what: str) -> np.ndarray:
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{what}: points must have shape (N, 3), got {p.shape}")
    if not np.issubdtype(p.dtype, np.number) or np.issubdtype(p.dtype, np.complexfloating):
        raise ValueError(f"{what}: points must be real numbers, got dtype {p.dtype}")
    p = p.astype(np.float64)
    bad = ~np.all(np.isfinite(p), axis=1)
    if np.any(bad):
        raise ValueError(
            f"{what}: points hold NaN or inf in {int(bad.sum())} of {len(p)} rows (first: row {int(np.argmax(bad))}); "
            "drop them before writing"
        )
    return p


def _check_colors(colors, n: int, what: str, name: str = "colors") -> np.ndarray:
    c = np.asarray(colors)
    if c.shape != (n, 3):
        raise ValueError(f"{what}: {name} must have shape ({n}, 3), got {c.shape}")
    if not (np.issubdtype(c.dtype, np.integer) or c.dtype == np.bool_):
        raise ValueError(f"{what}: {name} must be integers 0..255 (e.g. uint8), got dtype {c.dtype}")
    if c.size and (c.min() < 0 or c.max() > 255):
        raise ValueError(f"{what}: {name} must lie in 0..255, got values in [{c.min()}, {c.max()}]")
    return c.astype(np.uint8)


def _write(
    path: str | os.PathLike,
    vertex: list[tuple[str, str, np.ndarray]],
    edges: np.ndarray | None,
    binary: bool,
    comments: Sequence[str],
) -> Path:
    """Write a ``vertex`` element (list of ``(name, ply type, (N,) column)``) and optional ``edge`` pairs."""
    path = Path(path)
    n = len(vertex[0][2])
    header = ["ply", "format " + ("binary_little_endian" if binary else "ascii") + " 1.0"]
    header += [f"comment {c}" for c in comments]
    header.append(f"element vertex {n}")
    header += [f"property {ptype} {name}" for name, ptype, _ in vertex]
    if edges is not None:
        header += [f"element edge {len(edges)}", "property int vertex1", "property int vertex2"]
    header.append("end_header")
    head = ("\n".join(header) + "\n").encode("ascii")

    vdtype = np.dtype([(name, _PLY_TYPES[ptype]) for name, ptype, _ in vertex])
    vrows = np.empty(n, dtype=vdtype)
    for name, _, column in vertex:
        vrows[name] = column
    erows = None
    if edges is not None:
        erows = np.empty(len(edges), dtype=[("vertex1", "<i4"), ("vertex2", "<i4")])
        erows["vertex1"], erows["vertex2"] = edges[:, 0], edges[:, 1]

    with atomic_path(path, suffix=".ply") as tmp, open(tmp, "wb") as f:
        f.write(head)
        for rows in (vrows, erows):
            if rows is None:
                continue
            f.write(rows.tobytes() if binary else _ascii_rows(rows).encode("ascii"))
    return path


def _ascii_rows(rows: np.ndarray) -> str:
    """One line per structured row; floats with ``repr`` precision (round-trips exactly)."""
    if len(rows) == 0:
        return ""
    columns = []
    for name in rows.dtype.names:
        col = rows[name]
        if np.issubdtype(col.dtype, np.floating):
            columns.append([repr(float(v)) for v in col])
        else:
            columns.append([str(int(v)) for v in col])
    return "".join(" ".join(vals) + "\n" for vals in zip(*columns))


def write_ply(
    path: str | os.PathLike,
    points,
    colors=None,
    *,
    binary: bool = True,
    double: bool = True,
) -> Path:
    """Write a point cloud as PLY (atomically).

    Args:
        path: the output ``.ply`` file.
        points: ``(N, 3)`` positions (m, bcmocap world); must be finite.
        colors: optional ``(N, 3)`` RGB integers 0..255 (written as ``uchar red green blue``).
        binary: ``binary_little_endian`` (default) or ``ascii``.
        double: coordinates as ``double`` (default) or ``float`` (float32, half the size).

    Returns:
        The path written.

    Raises:
        ValueError: on wrong shapes or dtypes, non-finite points or colours outside 0..255.
    """
    p = _check_points(points, "write_ply")
    ptype = "double" if double else "float"
    vertex = [("x", ptype, p[:, 0]), ("y", ptype, p[:, 1]), ("z", ptype, p[:, 2])]
    if colors is not None:
        c = _check_colors(colors, len(p), "write_ply")
        vertex += [("red", "uchar", c[:, 0]), ("green", "uchar", c[:, 1]), ("blue", "uchar", c[:, 2])]
    return _write(path, vertex, None, binary, ["bcmocap point cloud (Z up, metres)"])


def write_ply_pieces(path: str | os.PathLike, num_points: int, pieces: Iterable) -> Path:
    """Write a point cloud that arrives in pieces as binary PLY (``double`` x y z), atomically, holding one
    piece at a time (a long capture's scene need not fit in memory).

    Args:
        path: the output ``.ply`` file.
        num_points: how many points the pieces hold in all (the header comes first).
        pieces: ``(n, 3)`` arrays of finite positions (m).

    Raises:
        ValueError: a piece of the wrong shape or with NaN/inf, or pieces that do not add up to
            ``num_points`` (the file is then not written).
    """
    path = Path(path)
    head = ("\n".join(["ply", "format binary_little_endian 1.0", "comment bcmocap point cloud (Z up, metres)",
                       f"element vertex {int(num_points)}", "property double x", "property double y",
                       "property double z", "end_header"]) + "\n").encode("ascii")
    written = 0
    with atomic_path(path, suffix=".ply") as tmp, open(tmp, "wb") as f:
        f.write(head)
        for piece in pieces:
            p = _check_points(piece, "write_ply_pieces")
            written += len(p)
            if written > num_points:
                break
            f.write(np.ascontiguousarray(p, "<f8").tobytes())
        if written != num_points:
            held = f"more than {num_points}" if written > num_points else str(written)
            raise ValueError(f"write_ply_pieces: {path}: the pieces hold {held} points, the header says {num_points}")
    return path


def write_camera_paths_ply(
    path: str | os.PathLike,
    centres,
    *,
    colors_per_camera=None,
    binary: bool = True,
    bridge_gaps: bool = False,
) -> Path:
    """Write camera centre trajectories as PLY vertices joined by edges (atomically).

    Vertices are the valid (finite) centres, camera by camera and frame by frame within a camera. Each
    vertex has ``x y z`` (double), ``red green blue`` (its camera's colour) and ``int camera``, ``int frame``.
    Edges join frames ``t`` and ``t + 1`` of a camera when both are valid, so a missing frame leaves a gap
    in the drawn path; with ``bridge_gaps=True`` successive valid frames are joined across gaps instead.

    Args:
        path: the output ``.ply`` file.
        centres: ``(T, C, 3)`` camera centres (m), NaN (any coordinate) where a camera has no pose.
        colors_per_camera: optional ``(C, 3)`` RGB integers 0..255; default a 10-colour palette, cycled.
        binary: ``binary_little_endian`` (default) or ``ascii``.
        bridge_gaps: join successive valid frames even when frames in between are missing.

    Returns:
        The path written.

    Raises:
        ValueError: on wrong shapes, infinite coordinates, or colours outside 0..255.
    """
    x = np.asarray(centres)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"write_camera_paths_ply: centres must have shape (T, C, 3), got {x.shape}")
    x = x.astype(np.float64)
    if np.any(np.isinf(x)):
        raise ValueError("write_camera_paths_ply: centres hold inf (use NaN for missing frames)")
    num_frames, num_cameras, _ = x.shape
    if colors_per_camera is None:
        palette = _PALETTE[np.arange(num_cameras) % len(_PALETTE)]
    else:
        palette = _check_colors(colors_per_camera, num_cameras, "write_camera_paths_ply", "colors_per_camera")

    valid = np.all(np.isfinite(x), axis=2)  # (T, C)
    cams, frames = np.nonzero(valid.T)  # camera-major order
    index = np.full((num_cameras, num_frames), -1, dtype=np.int64)
    index[cams, frames] = np.arange(len(cams))
    pts = x[frames, cams]
    rgb = palette[cams] if len(cams) else np.zeros((0, 3), np.uint8)

    # Consecutive vertices of the same camera are successive valid frames (camera-major order).
    same_camera = cams[1:] == cams[:-1]
    adjacent = frames[1:] == frames[:-1] + 1
    keep = same_camera if bridge_gaps else same_camera & adjacent
    starts = np.nonzero(keep)[0]
    edges = np.stack([starts, starts + 1], axis=1)

    vertex = [
        ("x", "double", pts[:, 0]), ("y", "double", pts[:, 1]), ("z", "double", pts[:, 2]),
        ("red", "uchar", rgb[:, 0]), ("green", "uchar", rgb[:, 1]), ("blue", "uchar", rgb[:, 2]),
        ("camera", "int", cams), ("frame", "int", frames),
    ]  # fmt: skip
    comments = [f"bcmocap camera paths: {num_cameras} cameras, {num_frames} frames (Z up, metres)"]
    return _write(path, vertex, edges, binary, comments)


# ---- reading ----------------------------------------------------------------------------------------


def _parse_header(where: str, data: bytes):
    """Return (format, [(element name, count, [(property name, dtype | None for list)])], data offset)."""
    if not data.startswith(b"ply") or data[3:4] not in (b"\n", b"\r"):
        raise ValueError(f"{where}: not a PLY file (it does not start with a 'ply' line)")
    end = -1
    for marker in (b"\nend_header\n", b"\nend_header\r\n", b"\r\nend_header\r\n"):
        at = data.find(marker)
        if at >= 0 and (end < 0 or at < end):
            end, size = at, len(marker)
    if end < 0:
        raise ValueError(f"{where}: no 'end_header' line")
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, np.dtype | None]]]] = []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            if len(words) != 3 or words[2] != "1.0":
                raise ValueError(f"{where}:{number}: expected 'format <kind> 1.0', found '{line.strip()}'")
            if words[1] not in ("ascii", "binary_little_endian"):
                raise ValueError(
                    f"{where}:{number}: format '{words[1]}' is not supported (ascii or binary_little_endian only)"
                )
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise ValueError(f"{where}:{number}: expected 'element <name> <count>', found '{line.strip()}'")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise ValueError(f"{where}:{number}: 'property' before any 'element'")
            if len(words) == 5 and words[1] == "list":
                elements[-1][2].append((words[4], None))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], np.dtype(_PLY_TYPES[words[1]])))
            else:
                raise ValueError(
                    f"{where}:{number}: expected 'property <type> <name>' with a PLY type "
                    f"({', '.join(sorted(_PLY_TYPES))}), found '{line.strip()}'"
                )
        else:
            raise ValueError(f"{where}:{number}: unexpected header line '{line.strip()}'")
    if fmt is None:
        raise ValueError(f"{where}: the header has no 'format' line")
    return fmt, elements, end + size


def _check_finite(where: str, element: str, names: list[str], values: np.ndarray) -> None:
    """Refuse NaN or inf in ``values (rows, len(names))``, naming the element, row and property."""
    bad = ~np.isfinite(values)
    if bad.any():
        row, k = np.argwhere(bad)[0]
        raise ValueError(f"{where}: element '{element}' row {row} property '{names[k]}' is {values[row, k]} "
                         "(NaN and inf are not read)")


def read_ply_elements(path: str | os.PathLike, *, stop_after: str | None = None) -> dict[str, dict[str, np.ndarray]]:
    """Read the elements of a PLY file into ``{element: {property: (count,) array}}``.

    Elements are read in file order; reading stops after the element named ``stop_after`` (later
    elements, which may then have ``list`` properties, are not read). ``list`` properties are not
    supported in elements that are read.

    Raises:
        ValueError: naming the file when it is not PLY, is big-endian, has a list property in an element
            it must read, or ends early / holds values that do not parse or are NaN or inf.
    """
    path = Path(path)
    where = str(path)
    data = path.read_bytes()
    fmt, elements, offset = _parse_header(where, data)
    out: dict[str, dict[str, np.ndarray]] = {}
    tokens: list[bytes] | None = data[offset:].split() if fmt == "ascii" else None
    pos = 0 if fmt == "ascii" else offset
    for name, count, props in elements:
        lists = [p for p, t in props if t is None]
        if lists:
            raise ValueError(f"{where}: element '{name}' has list properties {lists}, which read_ply does not read")
        dtype = np.dtype([(p, t) for p, t in props])
        if fmt == "ascii":
            need = count * len(props)
            if pos + need > len(tokens):
                raise ValueError(f"{where}: the file ends inside element '{name}' ({count} rows of {len(props)} values)")
            try:
                values = np.array(tokens[pos : pos + need], dtype=np.float64).reshape(count, len(props))
            except ValueError:
                raise ValueError(f"{where}: element '{name}' holds a value that is not a number") from None
            pos += need
            _check_finite(where, name, [p for p, _ in props], values)
            rows = {p: values[:, k].astype(t) for k, (p, t) in enumerate(props)}
        else:
            need = count * dtype.itemsize
            if pos + need > len(data):
                raise ValueError(
                    f"{where}: the file ends inside element '{name}' (needs {need} bytes, {len(data) - pos} left)"
                )
            arr = np.frombuffer(data, dtype=dtype, count=count, offset=pos)
            pos += need
            rows = {p: arr[p].astype(arr[p].dtype.newbyteorder("=")) for p, _ in props}
            floats = [p for p, _ in props if rows[p].dtype.kind == "f"]
            if floats:
                _check_finite(where, name, floats, np.stack([rows[p] for p in floats], axis=1))
        out[name] = rows
        if name == stop_after:
            break
    return out


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the vertices of a PLY point cloud (as written by :func:`write_ply` or :func:`write_camera_paths_ply`).

    Args:
        path: an ``ascii`` or ``binary_little_endian`` PLY file with a ``vertex`` element having ``x y z``.

    Returns:
        ``points (N, 3)`` float64 and ``colors (N, 3)`` uint8, or ``None`` when the vertices have no
        ``red green blue``. Other vertex properties and other elements are ignored.

    Raises:
        ValueError: naming the file, when it is not a PLY file this reader handles or lacks vertex x y z.
    """
    where = str(path)
    elements = read_ply_elements(path, stop_after="vertex")
    if "vertex" not in elements:
        raise ValueError(f"{where}: no 'vertex' element")
    vertex = elements["vertex"]
    missing = [p for p in ("x", "y", "z") if p not in vertex]
    if missing:
        raise ValueError(f"{where}: the vertex element has no {'/'.join(missing)} property")
    points = np.stack([vertex[p].astype(np.float64) for p in ("x", "y", "z")], axis=1)
    colors = None
    if all(p in vertex for p in ("red", "green", "blue")):
        colors = np.stack([vertex[p] for p in ("red", "green", "blue")], axis=1)
        if np.issubdtype(colors.dtype, np.floating):
            raise ValueError(f"{where}: vertex colours are floating point; expected uchar red green blue")
        colors = colors.astype(np.uint8)
    return points, colors
