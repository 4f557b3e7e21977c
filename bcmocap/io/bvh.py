"""Biovision hierarchy (BVH) motion files: read into, and write from, a :class:`Skeleton` and a :class:`Motion`.

A BVH file declares a tree of joints (``ROOT``, ``JOINT``, ``End Site``) with rest offsets and per-joint
channels, then one line of channel values per frame. Segment frames are world-aligned at rest in BVH as in
bcmocap, so a joint's rotation channels give ``parent_from_child`` directly: for channels
``Zrotation Xrotation Yrotation`` the local rotation is ``Rz(z) @ Rx(x) @ Ry(y)`` (matrices multiplied in
channel order, angles in degrees).

Conventions chosen here:

* Frames: BVH files are Y up; bcmocap's world is Z up. With ``up_axis="y"`` every vector is mapped by
  ``A`` = rotation of +90° about X, ``(x, y, z) → (x, -z, y)``, and every rotation by ``R ↦ A R Aᵀ`` (so rest
  frames stay world-aligned). ``up_axis="z"`` means the file is already Z up: no change of basis.
* Units: offsets and root positions are multiplied by ``length_unit_m`` (CMU's BVH files use 1/0.45 inch,
  ``length_unit_m=0.056444``).
* Root position = ``OFFSET`` of the ROOT + its position channels (the usual reading; CMU's root offsets are
  zero). The skeleton's row 0 offset is left at zero.
* Joint types: the root is FREE; a joint with 1 rotation channel is a HINGE about that axis; with 2 or 3 it
  is a BALL (a 2-channel joint's motion still fits a ball joint); with none it is FIXED. ``End Site`` blocks
  become FIXED leaf segments named ``<joint>_end`` (``end_sites=True``).
* Position channels on joints other than the root are rejected (bcmocap joints only rotate).

Segments are numbered in file order (depth first), which keeps parents before children.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..geometry import euler_to_matrix, matrix_from_quat, quat_from_matrix
from ..kinematics.skeleton import JointType, Motion, Skeleton

__all__ = ["BvhData", "read_bvh", "write_bvh"]

# Y-up file frame → bcmocap Z-up world: +90° about X, (x, y, z) → (x, -z, y).
_Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

_TAIT_BRYAN_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")


def world_from_file(up_axis: str) -> np.ndarray:
    """``(3, 3)`` change of basis from a file's frame to bcmocap's Z-up world.

    Args:
        up_axis: the file's up axis, "y" (mapped by +90° about X) or "z" (identity).
    """
    if not isinstance(up_axis, str) or up_axis.lower() not in ("y", "z"):
        raise ValueError(f"up_axis must be 'y' or 'z', got {up_axis!r}")
    return _Y_UP_TO_Z_UP.copy() if up_axis.lower() == "y" else np.eye(3)


def matrix_to_euler(matrix: np.ndarray, order: str) -> np.ndarray:
    """Angles (rad) of Tait–Bryan rotations such that ``euler_to_matrix(angles, order) == matrix``.

    ``order`` names the axes in the order the matrices multiply (``"ZXY"``: ``Rz(a0) Rx(a1) Ry(a2)``), as in
    :func:`bcmocap.geometry.euler_to_matrix`. The middle angle is in ``[-π/2, π/2]``; at gimbal lock
    (middle angle ±π/2) the last angle is set to 0.

    Args:
        matrix: ``(..., 3, 3)`` rotation matrices.
        order: three distinct axes, e.g. "ZXY".

    Returns:
        ``(..., 3)`` angles in radians.
    """
    order = order.upper()
    if order not in _TAIT_BRYAN_ORDERS:
        raise ValueError(f"matrix_to_euler: order must be one of {_TAIT_BRYAN_ORDERS}, got {order!r}")
    r = np.asarray(matrix, dtype=np.float64)
    i, j, k = ("XYZ".index(a) for a in order)
    # +1 for cyclic orders (XYZ, YZX, ZXY), -1 for the others.
    e = 1.0 if (j - i) % 3 == 1 else -1.0
    cos_b = np.hypot(r[..., i, i], r[..., i, j])
    b = np.arctan2(e * r[..., i, k], cos_b)
    a = np.arctan2(-e * r[..., j, k], r[..., k, k])
    c = np.arctan2(-e * r[..., i, j], r[..., i, i])
    # Gimbal lock: only a ± c is defined; put it all in a.
    locked = cos_b < 1e-12
    a_locked = np.arctan2(e * r[..., k, j], r[..., j, j])
    a = np.where(locked, a_locked, a)
    c = np.where(locked, 0.0, c)
    return np.stack([a, b, c], axis=-1)


@dataclasses.dataclass(frozen=True)
class BvhData:
    """Contents of a BVH file.

    Attributes:
        skeleton: the joint tree (offsets in metres, Z-up world unless ``up_axis="z"`` was given a Z-up file).
        motion: all frames, batch shape ``(F,)``: root position ``(F, 3)`` (m) and rotations ``(F, J, 4)``.
        frame_time_s: seconds between frames (``Frame Time``).
        channels: per segment, the channel names as written in the file (``()`` for end sites).
        euler_orders: per segment, the axes of its rotation channels in file order, e.g. "ZYX"
            (``""`` when it has none).
    """

    skeleton: Skeleton
    motion: Motion
    frame_time_s: float
    channels: tuple[tuple[str, ...], ...]
    euler_orders: tuple[str, ...]

    @property
    def num_frames(self) -> int:
        return self.motion.num_frames


# ---- reading ----------------------------------------------------------------------------------------


@dataclasses.dataclass
class _Node:
    name: str
    parent: int
    line: int
    offset: np.ndarray
    channels: tuple[str, ...] = ()
    is_end: bool = False


class _Tokens:
    """Whitespace-separated tokens of the hierarchy with their line numbers."""

    def __init__(self, where: str, lines: Sequence[str], start: int, stop: int):
        self.where = where
        self.items: list[tuple[int, int, str]] = []  # (line number, index in line, token)
        self.lines = lines
        for n in range(start, stop):
            for k, tok in enumerate(lines[n].split()):
                self.items.append((n + 1, k, tok))
        self.pos = 0
        self.last_line = stop if stop > start else start + 1

    def error(self, line: int, message: str) -> ValueError:
        return ValueError(f"{self.where}:{line}: {message}")

    def peek(self) -> str | None:
        return self.items[self.pos][2] if self.pos < len(self.items) else None

    def line(self) -> int:
        return self.items[self.pos][0] if self.pos < len(self.items) else self.last_line

    def next(self, expected: str) -> tuple[int, str]:
        if self.pos >= len(self.items):
            raise self.error(self.last_line, f"expected {expected}, found the end of the hierarchy")
        line, _, tok = self.items[self.pos]
        self.pos += 1
        return line, tok

    def expect(self, word: str) -> int:
        line, tok = self.next(f"'{word}'")
        if tok.upper() != word.upper():
            raise self.error(line, f"expected '{word}', found '{tok}'")
        return line

    def rest_of_line(self, what: str, keyword_line: int) -> str:
        """Tokens left on the current token's line (a joint name may contain spaces); drops a trailing '{'."""
        parts = []
        while self.pos < len(self.items) and self.items[self.pos][0] == keyword_line:
            parts.append(self.items[self.pos][2])
            self.pos += 1
        if parts and parts[-1] == "{":
            self.pos -= 1  # leave the brace for the caller
            parts.pop()
        if not parts:
            raise self.error(keyword_line, f"expected {what} on the same line")
        return " ".join(parts)

    def numbers(self, count: int, what: str) -> np.ndarray:
        out = []
        for _ in range(count):
            line, tok = self.next(f"{count} numbers for {what}")
            try:
                out.append(float(tok))
            except ValueError:
                raise self.error(line, f"expected {count} numbers for {what}, found '{tok}'") from None
            if not np.isfinite(out[-1]):
                raise self.error(line, f"{what} holds '{tok}'; NaN and inf are not read")
        return np.array(out)


_CHANNEL_NAMES = {
    f"{axis}{kind}".upper(): (kind, axis) for axis in "XYZ" for kind in ("position", "rotation")
}


def _parse_hierarchy(tok: _Tokens) -> list[_Node]:
    nodes: list[_Node] = []
    line = tok.expect("HIERARCHY")
    line, word = tok.next("'ROOT'")
    if word.upper() != "ROOT":
        raise tok.error(line, f"expected 'ROOT', found '{word}'")
    _parse_joint(tok, nodes, parent=-1, keyword_line=line)
    nxt = tok.peek()
    if nxt is not None:
        raise tok.error(tok.line(), f"expected 'MOTION' after the ROOT's closing '}}', found '{nxt}' (one root only)")
    return nodes


def _parse_joint(tok: _Tokens, nodes: list[_Node], parent: int, keyword_line: int) -> None:
    # Iterative over the tree: a stack of open joints, so deep hierarchies do not hit the recursion limit.
    name = tok.rest_of_line("a joint name", keyword_line)
    stack = [_open_joint(tok, nodes, name, parent, keyword_line, is_end=False)]
    while stack:
        current = stack[-1]
        line, word = tok.next("'JOINT', 'End Site' or '}'")
        upper = word.upper()
        if upper == "}":
            if not nodes[current].is_end and not any(n.parent == current for n in nodes):
                raise tok.error(line, f"joint '{nodes[current].name}' has no child (expected 'JOINT' or 'End Site')")
            stack.pop()
        elif nodes[current].is_end:
            raise tok.error(
                line,
                f"expected '}}' to close the End Site of '{nodes[nodes[current].parent].name}', found "
                f"'{word}'"
            )
        elif upper == "JOINT":
            child = tok.rest_of_line("a joint name", line)
            stack.append(_open_joint(tok, nodes, child, current, line, is_end=False))
        elif upper == "END":
            site_line, site = tok.next("'Site'")
            if site.upper() != "SITE":
                raise tok.error(site_line, f"expected 'Site' after 'End', found '{site}'")
            stack.append(_open_joint(tok, nodes, "", current, line, is_end=True))
        else:
            raise tok.error(line, f"expected 'JOINT', 'End Site' or '}}', found '{word}'")


def _open_joint(tok: _Tokens, nodes: list[_Node], name: str, parent: int, line: int, is_end: bool) -> int:
    tok.expect("{")
    tok.expect("OFFSET")
    offset = tok.numbers(3, "OFFSET")
    channels: tuple[str, ...] = ()
    if not is_end:
        ch_line, word = tok.next("'CHANNELS'")
        if word.upper() != "CHANNELS":
            raise tok.error(ch_line, f"expected 'CHANNELS' after the OFFSET of '{name}', found '{word}'")
        cnt_line, cnt = tok.next("the number of channels")
        try:
            count = int(cnt)
        except ValueError:
            raise tok.error(cnt_line, f"expected the number of channels of '{name}', found '{cnt}'") from None
        if count < 0:
            raise tok.error(cnt_line, f"negative channel count {count} for '{name}'")
        names = []
        for _ in range(count):
            c_line, c = tok.next(f"{count} channel names for '{name}'")
            if c.upper() not in _CHANNEL_NAMES:
                raise tok.error(
                    c_line,
                    f"expected {count} channel names for '{name}' (Xposition … Zrotation), found '{c}'",
                )
            names.append(c)
        kinds = [_CHANNEL_NAMES[c.upper()] for c in names]
        positions = [axis for kind, axis in kinds if kind == "position"]
        if len(set(positions)) != len(positions):
            raise tok.error(ch_line, f"'{name}' repeats a position channel: {names}")
        if positions and parent >= 0:
            raise tok.error(
                ch_line,
                f"joint '{name}' has position channels {[c for c in names if 'POSITION' in c.upper()]}; "
                "only the ROOT may translate (bcmocap joints are rotations)",
            )
        channels = tuple(names)
    nodes.append(_Node(name=name, parent=parent, line=line, offset=offset, channels=channels, is_end=is_end))
    return len(nodes) - 1


def read_bvh(
    path: str | os.PathLike,
    *,
    length_unit_m: float = 1.0,
    up_axis: str = "y",
    end_sites: bool = True,
) -> BvhData:
    """Read a BVH file.

    Any rotation channel order per joint is accepted (the rotation is the product of the axis rotations
    in channel order); the root's position and rotation channels may come in any order. CRLF or LF line
    endings and tabs are fine.

    Args:
        path: the ``.bvh`` file.
        length_unit_m: metres per file length unit (CMU: 0.056444, i.e. 1/0.45 inch).
        up_axis: the file's up axis: "y" (BVH's usual, converted to bcmocap's Z up) or "z" (no conversion).
        end_sites: turn each ``End Site`` into a FIXED leaf segment ``<joint>_end`` (so forward kinematics
            gives the positions of the hands', feet's and head's ends).

    Returns:
        A :class:`BvhData`; ``motion`` has ``F`` frames: ``root_position (F, 3)`` m,
        ``rotations (F, J, 4)`` wxyz.

    Raises:
        ValueError: naming the file, the line and what was expected, when the file is malformed, or when a
            non-root joint has position channels.
    """
    path = Path(path)
    where = str(path)
    if not length_unit_m > 0:
        raise ValueError(f"read_bvh: length_unit_m must be positive, got {length_unit_m}")
    basis = world_from_file(up_axis)
    with open(path, encoding="utf-8", errors="replace", newline=None) as f:
        lines = f.read().split("\n")

    motion_at = next((n for n, text in enumerate(lines) if text.strip().upper() == "MOTION"), None)
    if motion_at is None:
        raise ValueError(f"{where}:{len(lines)}: expected a 'MOTION' line after the hierarchy, found none")
    nodes = _parse_hierarchy(_Tokens(where, lines, 0, motion_at))
    num_frames, frames_line, frame_time, time_line = _read_motion_header(where, lines, motion_at)
    joints = [k for k, node in enumerate(nodes) if not node.is_end]
    num_channels = sum(len(nodes[k].channels) for k in joints)
    values = _read_frames(where, lines, num_frames, num_channels, frames_line, time_line)

    keep = [k for k, node in enumerate(nodes) if end_sites or not node.is_end]
    names = _segment_names(where, nodes, keep)
    seg_of_node = {k: s for s, k in enumerate(keep)}
    parents = [seg_of_node[nodes[k].parent] if nodes[k].parent >= 0 else -1 for k in keep]
    offsets, types, axes, channels, orders, rot_file, root_position = _segments_and_motion(nodes, keep, joints, values)

    rotations = basis @ rot_file @ basis.T
    skeleton = Skeleton(
        names,
        parents,
        offsets @ basis.T * length_unit_m,
        joint_types=types,
        hinge_axes=axes @ basis.T,
    )
    motion = Motion(root_position @ basis.T * length_unit_m, quat_from_matrix(rotations))
    return BvhData(
        skeleton=skeleton,
        motion=motion,
        frame_time_s=float(frame_time),
        channels=tuple(channels),
        euler_orders=tuple(orders),
    )


def _read_motion_header(where: str, lines: Sequence[str], motion_at: int) -> tuple[int, int, float, int]:
    """``Frames:`` and ``Frame Time:`` after the ``MOTION`` line (0-based ``motion_at``): the frame count, its
    1-based line, the frame time (s) and its 1-based line."""
    n = motion_at + 1
    num_frames, frames_line = _header_value(where, lines, n, ("FRAMES",), int, "'Frames: <count>'")
    frame_time, time_line = _header_value(
        where, lines, frames_line, ("FRAME", "TIME"), float, "'Frame Time: <seconds>'"
    )
    if num_frames < 0:
        raise ValueError(f"{where}:{frames_line}: expected a non-negative frame count, found {num_frames}")
    if num_frames > len(lines):  # one line per frame: refused before allocating a huge array
        raise ValueError(f"{where}:{frames_line}: 'Frames: {num_frames}' but the file has only {len(lines)} lines")
    if not (np.isfinite(frame_time) and frame_time > 0):
        raise ValueError(f"{where}:{time_line}: expected a positive, finite frame time, found {frame_time}")
    return num_frames, frames_line, frame_time, time_line


def _read_frames(where: str, lines: Sequence[str], num_frames: int, num_channels: int, frames_line: int,
                 time_line: int) -> np.ndarray:
    """``(num_frames, num_channels)`` channel values of the frame lines after the ``Frame Time:`` line
    (1-based ``time_line``), exactly ``num_frames`` non-blank lines of finite numbers."""
    values = np.zeros((num_frames, num_channels))
    frame = 0
    last_line = time_line
    frame_lines = []
    for m in range(time_line, len(lines)):
        text = lines[m].strip()
        if not text:
            continue
        if frame >= num_frames:
            raise ValueError(
                f"{where}:{m + 1}: expected {num_frames} frames ('Frames:' on line {frames_line}), found more"
            )
        parts = text.split()
        if len(parts) != num_channels:
            raise ValueError(f"{where}:{m + 1}: expected {num_channels} numbers per frame, found {len(parts)}")
        try:
            values[frame] = np.array(parts, dtype=np.float64)
        except ValueError:
            bad = next(p for p in parts if not _is_float(p))
            raise ValueError(f"{where}:{m + 1}: expected {num_channels} numbers per frame, found '{bad}'") from None
        frame += 1
        last_line = m + 1
        frame_lines.append(last_line)
    if frame < num_frames:
        raise ValueError(
            f"{where}:{last_line}: expected {num_frames} frames ('Frames:' on line {frames_line}), "
            f"the file ends after {frame}"
        )
    if not np.all(np.isfinite(values)):
        f_bad, c_bad = np.argwhere(~np.isfinite(values))[0]
        raise ValueError(
            f"{where}:{frame_lines[int(f_bad)]}: value {int(c_bad) + 1} of the frame is not a finite "
            "number"
        )
    return values


def _segment_names(where: str, nodes: list[_Node], keep: list[int]) -> list[str]:
    """Segment names of the ``keep`` nodes: a joint's own (unique), ``<parent>_end`` for an End Site (numbered
    where that name is taken)."""
    names: list[str] = []
    for k in keep:
        node = nodes[k]
        if node.is_end:
            base = f"{nodes[node.parent].name}_end"
            name, suffix = base, 2
            while name in names or any(nd.name == name for nd in nodes if not nd.is_end):
                name, suffix = f"{base}{suffix}", suffix + 1
        else:
            name = node.name
            if name in names:
                raise ValueError(f"{where}:{node.line}: duplicate joint name '{name}'")
        names.append(name)
    return names


def _segments_and_motion(nodes: list[_Node], keep: list[int], joints: list[int], values: np.ndarray):
    """Per segment (the ``keep`` nodes), in the file's frame and units: offsets ``(J, 3)``, joint types, hinge
    axes ``(J, 3)``, channel names and rotation orders; and from the channel ``values`` ``(F, channels)`` of
    the ``joints`` nodes, the local rotations ``(F, J, 3, 3)`` and root positions ``(F, 3)``."""
    num_frames = len(values)
    offsets = np.zeros((len(keep), 3))
    types: list[JointType] = []
    axes = np.zeros((len(keep), 3))
    channels: list[tuple[str, ...]] = []
    orders: list[str] = []
    rot_file = np.broadcast_to(np.eye(3), (num_frames, len(keep), 3, 3)).copy()
    root_position = np.broadcast_to(nodes[0].offset, (num_frames, 3)).copy()

    column = 0
    col_of_node = {}
    for k in joints:
        col_of_node[k] = column
        column += len(nodes[k].channels)

    for s, k in enumerate(keep):
        node = nodes[k]
        if s > 0:
            offsets[s] = node.offset
        channels.append(node.channels)
        kinds = [_CHANNEL_NAMES[c.upper()] for c in node.channels]
        order = "".join(axis for kind, axis in kinds if kind == "rotation")
        orders.append(order)
        if node.is_end:
            types.append(JointType.FIXED)
            continue
        cols = col_of_node[k] + np.arange(len(node.channels))
        rot_cols = [c for c, (kind, _) in zip(cols, kinds) if kind == "rotation"]
        if s == 0:
            types.append(JointType.FREE)
            for c, (kind, axis) in zip(cols, kinds):
                if kind == "position":
                    root_position[:, "XYZ".index(axis)] += values[:, c]
        elif len(order) == 0:
            types.append(JointType.FIXED)
        elif len(order) == 1:
            types.append(JointType.HINGE)
            axes[s, "XYZ".index(order)] = 1.0
        else:
            types.append(JointType.BALL)
        if order:
            rot_file[:, s] = euler_to_matrix(np.deg2rad(values[:, rot_cols]), order)
    return offsets, types, axes, channels, orders, rot_file, root_position

def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _header_value(where: str, lines: Sequence[str], start: int, keywords: tuple[str, ...], kind, expected: str):
    """Parse ``Frames: N`` / ``Frame Time: t`` from the next non-blank line; returns (value, 1-based line)."""
    m = start
    while m < len(lines) and not lines[m].strip():
        m += 1
    if m >= len(lines):
        raise ValueError(f"{where}:{len(lines)}: expected {expected}, found the end of the file")
    text = lines[m].replace(":", " : ")
    parts = text.split()
    n = len(keywords)
    if (
        len(parts) != n + 2
        or [p.upper() for p in parts[:n]] != list(keywords)
        or parts[n] != ":"
    ):
        raise ValueError(f"{where}:{m + 1}: expected {expected}, found '{lines[m].strip()}'")
    try:
        value = kind(parts[n + 1])
    except ValueError:
        raise ValueError(f"{where}:{m + 1}: expected {expected}, found '{lines[m].strip()}'") from None
    return value, m + 1


# ---- writing ----------------------------------------------------------------------------------------


def _fmt(x: float) -> str:
    # Fixed notation with 10 decimals (every BVH reader parses it); 1e-10 deg or file units is far below
    # the 1e-9 m / 1e-9 rad round-trip target for ordinary units.
    s = f"{x:.10f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def write_bvh(
    path: str | os.PathLike,
    skeleton: Skeleton,
    motion: Motion,
    frame_time_s: float,
    *,
    length_unit_m: float = 1.0,
    up_axis: str = "y",
    euler_order: str = "ZXY",
) -> Path:
    """Write a skeleton and its motion as a standard BVH file (atomically: temp file + rename).

    Layout: the root gets 6 channels (``Xposition Yposition Zposition`` then 3 rotations in
    ``euler_order``); every other segment with children, and every non-FIXED leaf, is a ``JOINT`` with 3
    rotation channels (hinges too, since general readers expect 3; FIXED joints get their rotation, i.e.
    zeros for a valid motion); a FIXED leaf is written as an ``End Site`` (its name is lost: reading it
    back names it ``<parent>_end``); a non-FIXED leaf joint gets an ``End Site`` with a zero offset, as BVH
    requires every joint to have a child. Segments are written depth first, so reading the file back may
    number them differently from ``skeleton``; look segments up by name. Joint types are not stored in BVH:
    hinges come back as ball joints.

    Args:
        path: the output file.
        skeleton: the tree; names must not contain whitespace or braces.
        motion: ``F`` frames (``root_position (F, 3)``, ``rotations (F, J, 4)``); a single frame
            (``(3,)``, ``(J, 4)``) is written as one frame.
        frame_time_s: seconds between frames.
        length_unit_m: metres per file length unit (positions are divided by it).
        up_axis: up axis of the file: "y" (converted from bcmocap's Z up) or "z".
        euler_order: the three rotation channels' order, one of XYZ, XZY, YXZ, YZX, ZXY, ZYX.

    Returns:
        The path written.
    """
    path = Path(path)
    order = euler_order.upper()
    if order not in _TAIT_BRYAN_ORDERS:
        raise ValueError(f"write_bvh: euler_order must be one of {_TAIT_BRYAN_ORDERS}, got {euler_order!r}")
    if not frame_time_s > 0:
        raise ValueError(f"write_bvh: frame_time_s must be positive, got {frame_time_s}")
    if not length_unit_m > 0:
        raise ValueError(f"write_bvh: length_unit_m must be positive, got {length_unit_m}")
    basis = world_from_file(up_axis)
    root_position = np.asarray(motion.root_position, dtype=np.float64)
    quats = np.asarray(motion.rotations, dtype=np.float64)
    if root_position.ndim == 1:
        root_position, quats = root_position[None], quats[None]
    if root_position.ndim != 2 or quats.shape[:1] != root_position.shape[:1]:
        raise ValueError(
            "write_bvh: expected frames on one leading axis, root_position (F, 3) and rotations (F, J, 4), got "
            f"{root_position.shape} and {quats.shape}"
        )
    motion.check(skeleton, f"write_bvh: {path}")  # NaN or inf is never written
    if not np.all(np.isfinite(np.asarray(skeleton.offsets))):
        raise ValueError(f"write_bvh: {path}: the skeleton's offsets hold NaN or inf")
    for name in skeleton.names:
        if not name or any(ch.isspace() for ch in name) or "{" in name or "}" in name:
            raise ValueError(f"write_bvh: segment name {name!r} cannot be written to BVH (whitespace or braces)")

    quats = quats / np.linalg.norm(quats, axis=-1, keepdims=True)
    rot_file = basis.T @ matrix_from_quat(quats) @ basis
    angles_deg = np.rad2deg(matrix_to_euler(rot_file, order))  # (F, J, 3)
    pos_file = root_position @ basis / length_unit_m  # row-vector form of basis.T @ p
    offsets_file = np.asarray(skeleton.offsets) @ basis / length_unit_m

    n = skeleton.num_segments
    children = [[] for _ in range(n)]
    for j in range(1, n):
        children[skeleton.parents[j]].append(j)
    is_end = [j > 0 and not children[j] and skeleton.joint_types[j] == JointType.FIXED for j in range(n)]

    rot_names = " ".join(f"{a}rotation" for a in order)
    out: list[str] = ["HIERARCHY"]
    channel_segments: list[int] = []  # segments in the order their channels appear

    def offset_line(j: int, depth: int) -> str:
        o = (0.0, 0.0, 0.0) if j == 0 else offsets_file[j]
        return "\t" * depth + "OFFSET " + " ".join(_fmt(v) for v in o)

    # Depth-first walk with an explicit stack of (segment, depth, closing?).
    stack: list[tuple[int, int, bool]] = [(0, 0, False)]
    while stack:
        j, depth, closing = stack.pop()
        tab = "\t" * depth
        if closing:
            out.append(tab + "}")
            continue
        if is_end[j]:
            out += [tab + "End Site", tab + "{", offset_line(j, depth + 1), tab + "}"]
            continue
        out.append(tab + ("ROOT " if j == 0 else "JOINT ") + skeleton.names[j])
        out.append(tab + "{")
        out.append(offset_line(j, depth + 1))
        if j == 0:
            out.append(tab + "\tCHANNELS 6 Xposition Yposition Zposition " + rot_names)
        else:
            out.append(tab + "\tCHANNELS 3 " + rot_names)
        channel_segments.append(j)
        stack.append((j, depth, True))
        if not children[j]:
            inner = "\t" * (depth + 1)
            out += [inner + "End Site", inner + "{", inner + "\tOFFSET 0 0 0", inner + "}"]
        for c in reversed(children[j]):
            stack.append((c, depth + 1, False))

    num_frames = pos_file.shape[0]
    out += ["MOTION", f"Frames: {num_frames}", f"Frame Time: {frame_time_s:.10g}"]
    columns = np.concatenate([pos_file[:, None, :], angles_deg[:, channel_segments, :]], axis=1)
    columns = columns.reshape(num_frames, 3 + 3 * len(channel_segments))
    out += [" ".join(_fmt(v) for v in row) for row in columns]
    _write_atomic(path, "\n".join(out) + "\n")
    return path


def _write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` via a temporary file in the same folder and ``os.replace``."""
    folder = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
