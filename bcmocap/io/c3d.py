"""C3D motion-capture files (Vicon, Qualisys, PhaseSpace, …): 3D marker trajectories in metres.

Reading goes through `ezc3d <https://github.com/pyomeca/ezc3d>`_, a maintained C++ reader with Python
bindings (binary wheels on PyPI), so every C3D flavour it knows (Intel/DEC/SGI, integer or float storage,
scaled points) is handled there. This module only turns its output into what the marker pipeline
(:mod:`bcmocap.markers`) needs:

* positions ``(F, M, 3)`` in **metres** (``POINT:UNITS`` honoured: mm, cm, m, in, ft), **NaN** where a
  marker is not seen (a negative residual, or the old "all zero" convention);
* the frame rate from ``POINT:RATE`` (Hz) and the first frame number from the header;
* marker labels (``POINT:LABELS``, continued in ``LABELS2`` … when there are more than 255).

Points that are not markers are left out unless asked for: the outputs a modelling package writes into
the POINT group (``POINT:ANGLES``, ``FORCES``, ``MOMENTS``, ``POWERS``, ``SCALARS``, ``REACTIONS`` list
them) and, by name, Plug-in Gait's virtual bone points (``PELO``, ``LFEA`` … the four points
``O/A/L/P`` of each model segment), centres of mass and hip-centre estimates. They are reported in
:attr:`C3dData.excluded`.

No axis convention is imposed: C3D files are usually Z up already (as bcmocap's world), and the marker
pipeline does not depend on the up axis.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["C3dData", "read_c3d", "MODELLED_POINT_PATTERN"]

#: metres per unit for the ``POINT:UNITS`` values seen in the wild (case-insensitive).
_UNITS_M = {"mm": 1e-3, "millimeters": 1e-3, "millimetres": 1e-3, "cm": 1e-2, "m": 1.0, "meters": 1.0,
            "metres": 1.0, "in": 0.0254, "inch": 0.0254, "inches": 0.0254, "ft": 0.3048, "feet": 0.3048}

#: POINT parameters that list labels of computed quantities stored as points (not positions).
_NON_POSITION_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")

#: Labels (after any ``Subject:`` prefix) of points a model computes rather than a camera sees:
#: Plug-in Gait bone axes (segment code + O/A/L/P), centres of mass, hip-centre estimates, "#", Motion Analysis's
#: virtual points of the Helen Hayes set (V + SAC, MID, PEL or a side and HI, KN, AN, HA, TO, HE, SH, EL, WR: hip,
#: knee and ankle centres, mid-pelvis, virtual hand and toe) and OpenSim's joint centres ([LR][HKA]JC).
MODELLED_POINT_PATTERN = re.compile(
    r"^(?:(?:PEL|HED|TRX|[LR](?:FE|TI|FO|TO|CL|HU|RA|HN))[OALP]|CentreOfMass\w*|CenterOfMass\w*|\w*Hip_?Cent(?:er|re)\w*"
    r"|#|V(?:SAC|MID|PEL|[LR](?:HI|KN|AN|HA|TO|HE|SH|EL|WR))|[LR][HKA]JC)$",
    re.IGNORECASE,
)


@dataclasses.dataclass(frozen=True)
class C3dData:
    """Marker trajectories read from a C3D file.

    Attributes:
        positions: ``(F, M, 3)`` marker positions in metres, NaN where the marker is not seen.
        labels: ``M`` marker labels as in the file (a ``Subject:`` prefix is kept).
        frame_rate_hz: frames per second (``POINT:RATE``).
        first_frame: number of the first frame in the capture (C3D header, 1-based in most files).
        units: the file's length unit (``POINT:UNITS``) that was converted to metres.
        excluded: labels of points left out (computed outputs, modelled points, or not asked for).
        path: the file read.
    """

    positions: np.ndarray
    labels: tuple[str, ...]
    frame_rate_hz: float
    first_frame: int
    units: str
    excluded: tuple[str, ...]
    path: Path


def _param(group: dict, name: str):
    entry = group.get(name)
    return None if entry is None else entry.get("value")


def _labels(point: dict, count: int) -> list[str]:
    labels: list[str] = []
    for name in ["LABELS"] + [f"LABELS{k}" for k in range(2, 100)]:
        value = _param(point, name)
        if value is None:
            if name != "LABELS":
                break
            continue
        labels += [str(x).strip() for x in value]
    labels = labels[:count]
    # Unnamed or duplicated labels would make markers impossible to refer to: number them.
    labels += [""] * (count - len(labels))
    seen: dict[str, int] = {}
    out = []
    for k, label in enumerate(labels):
        label = label or f"point{k + 1}"
        if label in seen:
            seen[label] += 1
            label = f"{label}#{seen[label]}"
        else:
            seen[label] = 1
        out.append(label)
    return out


def _strip_subject(label: str) -> str:
    return label.split(":", 1)[1] if ":" in label else label


def _header_words(path: Path) -> tuple[int, ...] | None:
    """The raw C3D header's first five 16-bit words after byte 1 (words 2–6: points, analog values a frame, first
    and last frame, largest gap), in the file's byte order; None where the header is not C3D's."""
    import struct

    with open(path, "rb") as f:
        head = f.read(12)
        if len(head) < 12 or head[1] != 0x50:
            return None
        f.seek(512 * (head[0] - 1) + 3)
        processor = f.read(1)
    order = ">" if processor == bytes([86]) else "<"  # 84 Intel, 85 DEC: little-endian words; 86 MIPS: big
    return struct.unpack(order + "5H", head[2:12])


def _announced_frames(path: Path) -> int | None:
    """Frames the raw C3D header announces (words 4–5: first and last frame), or None where it cannot
    say: a header that is not C3D's, or a trial longer than its 16-bit fields (ezc3d adjusts the header it
    returns to the frames it could read, so truncation is only visible in the bytes)."""
    words = _header_words(path)
    if words is None:
        return None
    first, last = words[2:4]
    if last == 0xFFFF or last < first:
        return None
    return last - first + 1


def _header_analog_words(path: Path) -> int | None:
    """Analog values in each 3-D frame by the raw header (word 3: channels × samples a frame), or None where the
    header is not C3D's."""
    words = _header_words(path)
    return None if words is None else words[1]


def _check_sections(path: Path) -> None:
    """Refuse a file shorter than the sections its header announces, or whose parameter section does not
    hold together: ezc3d loops forever on some (a C3D cut inside its parameter section) and crashes the
    process on others (a run of bytes deleted from it). Words of the header: byte 0 the first parameter
    block, word 9 the first data block; byte 2 of the parameter section its number of 512-byte blocks."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(18)
        if len(head) < 18 or head[1] != 0x50 or head[0] < 1:
            return  # not C3D's header: ezc3d says so
        start = 512 * (head[0] - 1)
        f.seek(start)
        parameters = f.read(4)
        if len(parameters) < 4:
            raise ValueError(f"{path}: truncated: the header puts the parameter section at byte {start}, "
                             f"the file has {size} bytes")
        order = ">" if parameters[3] == 86 else "<"
        data_block = int.from_bytes(head[16:18], "big" if order == ">" else "little")
        end = max(start + 512 * parameters[2], 512 * (data_block - 1))
        if size < end:
            raise ValueError(f"{path}: truncated: the header and parameter section announce at least {end} bytes, "
                             f"the file has {size}")
        f.seek(start)
        section = f.read(512 * parameters[2])
    problem = _parameter_records_problem(section, order)
    if problem is not None:
        raise ValueError(f"{path}: not a readable C3D file (its parameter section is damaged: {problem})")


C3D_PARAMETER_TYPES = (-1, 1, 2, 4)  # char, byte, 16-bit integer, float: bytes per element (char: 1)


def _parameter_records_problem(section: bytes, order: str) -> str | None:
    """Walk the group and parameter records of a C3D parameter section (after its 4-byte header); say what
    does not fit, or None. A record: name length (int8; negative when locked; 0 ends the section), group id
    (int8; negative for a group), the name, the int16 offset from that word to the next record (0: the last);
    a parameter then has its type, dimension count, dimensions, data and a description, which must end
    before the next record."""
    import struct

    pos, count = 4, 0
    while pos + 2 <= len(section):
        name_length = abs(struct.unpack_from("b", section, pos)[0])
        if name_length == 0:
            return None
        group = struct.unpack_from("b", section, pos + 1)[0]
        offset_at = pos + 2 + name_length
        if offset_at + 2 > len(section):
            return f"record {count} at byte {pos} runs past the section"
        offset = struct.unpack_from(order + "h", section, offset_at)[0]
        following = offset_at + offset if offset else len(section)
        if offset and not offset_at + 2 <= following <= len(section):
            return f"record {count} at byte {pos} points to byte {following}, outside the section"
        body = offset_at + 2
        if group > 0:  # a parameter: type, dimensions, data, description
            if body + 2 > following:
                return f"parameter record {count} at byte {pos} is cut short"
            kind, dims = struct.unpack_from("bB", section, body)
            if kind not in C3D_PARAMETER_TYPES:
                return f"parameter record {count} at byte {pos} has data type {kind}"
            shape = section[body + 2:body + 2 + dims]
            elements = 1
            for d in shape:
                elements *= d
            data_end = body + 2 + dims + abs(kind) * elements
            if len(shape) < dims or data_end + 1 > following or data_end + 1 + section[data_end] > following:
                return f"parameter record {count} at byte {pos} holds more than the {following - pos} bytes before the next"
        elif group < 0:  # a group: its description
            if body + 1 > following or body + 1 + section[body] > following:
                return f"group record {count} at byte {pos} holds more than the {following - pos} bytes before the next"
        else:
            return f"record {count} at byte {pos} has group id 0"
        if not offset:
            return None
        pos, count = following, count + 1
    return None


def read_c3d(
    path: str | os.PathLike,
    *,
    markers: Sequence[str] | None = None,
    keep_modelled: bool = False,
) -> C3dData:
    """Read the 3D points of a C3D file as marker trajectories in metres.

    Args:
        path: the ``.c3d`` file.
        markers: labels to keep, in this order (with or without the ``Subject:`` prefix); None keeps
            every marker (points that are not markers are left out, see the module docstring).
        keep_modelled: keep points that look modelled (Plug-in Gait bone axes, centres of mass …).

    Returns:
        A :class:`C3dData` with positions ``(F, M, 3)`` in metres and NaN gaps.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a readable C3D file, no 3D points, an infinite coordinate, an unknown unit or frame
            rate, or a label in ``markers`` that the file does not have (the message names the file and the field).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"read_c3d: no such file: {path}")
    try:
        import ezc3d
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise ImportError("read_c3d needs the 'ezc3d' package (pip install 'ezc3d>=1.5,<2')") from exc
    _check_sections(path)
    try:
        c3d = ezc3d.c3d(str(path))
    except Exception as exc:  # ezc3d raises OSError/RuntimeError with its own words
        raise ValueError(f"{path}: not a readable C3D file ({exc})") from exc

    point = c3d["parameters"].get("POINT", {})
    data = np.asarray(c3d["data"]["points"], dtype=np.float64)  # (4, M, F)
    if data.ndim != 3 or data.shape[1] == 0 or data.shape[2] == 0:
        shape = tuple(data.shape) if data.ndim == 3 else data.shape
        raise ValueError(f"{path}: the C3D file has no 3D points (POINT:USED = {_param(point, 'USED')}, data {shape})")
    announced = _announced_frames(path)
    if announced is not None and data.shape[2] < announced:
        raise ValueError(f"{path}: truncated: the header announces {announced} frames, the file holds "
                         f"{data.shape[2]}")
    analogs = np.shape(c3d["data"].get("analogs", np.zeros((1, 0, 0))))
    words = _header_analog_words(path)
    if words and len(analogs) == 3 and analogs[1] and analogs[2] % data.shape[2] == 0 \
            and analogs[1] * (analogs[2] // data.shape[2]) != words:
        per_frame = analogs[2] // data.shape[2]
        raise ValueError(f"{path}: the header puts {words} analog values in each frame, the ANALOG parameters "
                         f"{analogs[1]} channels × {per_frame} samples (ANALOG:RATE / POINT:RATE): read that way, "
                         "every frame after the first would be taken from the wrong place in the file")
    count = data.shape[1]
    labels = _labels(point, count)

    rate = _param(point, "RATE")
    rate = float(np.ravel(rate)[0]) if rate is not None and np.size(rate) else float(c3d["header"]["points"]["frame_rate"])
    if not np.isfinite(rate) or rate <= 0:
        raise ValueError(f"{path}: POINT:RATE is {rate}; a positive frame rate is needed")

    units_value = _param(point, "UNITS")
    units = str(units_value[0]).strip() if units_value is not None and len(units_value) else "mm"
    if units.lower() not in _UNITS_M:
        raise ValueError(f"{path}: POINT:UNITS is {units!r}; known units are {sorted(set(_UNITS_M))}")
    scale = _UNITS_M[units.lower()]

    xyz = np.moveaxis(data[:3], 0, -1).transpose(1, 0, 2) * scale  # (F, M, 3)
    if np.isinf(xyz).any():  # NaN marks a gap (ezc3d's reading of an invalid point); inf is damage
        f, m, _ = np.argwhere(np.isinf(xyz))[0]
        raise ValueError(f"{path}: point '{labels[m]}' has an infinite coordinate at frame {f}")
    missing = ~np.all(np.isfinite(xyz), axis=-1)
    residuals = c3d["data"].get("meta_points", {}).get("residuals")
    if residuals is not None:
        residuals = np.asarray(residuals)[0].T  # (F, M)
        if residuals.shape == missing.shape:
            missing |= residuals < 0
    missing |= np.all(xyz == 0.0, axis=-1)  # the old convention for an invalid point
    xyz[missing] = np.nan

    non_position = {str(x).strip() for g in _NON_POSITION_GROUPS for x in (_param(point, g) or [])}
    keep = []
    excluded = []
    for k, label in enumerate(labels):
        if label in non_position or _strip_subject(label) in non_position:
            excluded.append(label)
        elif not keep_modelled and MODELLED_POINT_PATTERN.match(re.sub(r"#\d+$", "", _strip_subject(label))):  # VMID#2: a second VMID
            excluded.append(label)
        else:
            keep.append(k)

    if markers is not None:
        by_name: dict[str, int] = {}
        for k in keep:
            by_name.setdefault(labels[k], k)
            by_name.setdefault(_strip_subject(labels[k]), k)
        unknown = [m for m in markers if m not in by_name]
        if unknown:
            raise ValueError(f"{path}: no marker labelled {unknown}; the file has {[labels[k] for k in keep]}")
        chosen = [by_name[m] for m in markers]
        excluded += [labels[k] for k in keep if k not in chosen]
        keep = chosen
    if not keep:
        raise ValueError(f"{path}: the C3D file has no marker points (all {count} points are computed outputs: {excluded[:10]} …)")

    header = c3d["header"]["points"]
    return C3dData(
        positions=np.ascontiguousarray(xyz[:, keep]),
        labels=tuple(labels[k] for k in keep),
        frame_rate_hz=rate,
        first_frame=int(header.get("first_frame", 0)) + 1,
        units=units,
        excluded=tuple(excluded),
        path=path,
    )
