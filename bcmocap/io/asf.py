"""Acclaim skeleton (ASF) and motion (AMC) files, the format of the CMU motion capture database.

An ASF file describes bones: each has a unit ``direction`` and a ``length`` (in the world frame at rest),
an ``axis`` line giving the orientation ``C`` of its local frame, and the rotation ``dof`` it may move
along. An AMC file gives, per frame, the root's translation and rotation and each bone's dof values.

How bcmocap reads them (segment frames are world-aligned at rest, as for BVH):

* One segment per bone, plus the root (segment 0, named ``root``). Segment ``b``'s origin, joint ``b``,
  is the *start* of bone ``b``, i.e. the end of its parent bone: ``offsets[b] = direction[parent] *
  length[parent]``; bones attached to the root start at the root's ``position`` (zero in CMU files).
  The end of each leaf bone becomes a FIXED leaf segment ``<bone>_end`` when ``end_sites=True``.
* Bone axis ``axis a1 a2 a3 XYZ`` means ``C = Rz(a3) Ry(a2) Rx(a1)``: the rotation listed first is applied
  first (for another order, e.g. ``ZYX``, the first angle goes with Z and ``C = Rx(a3) Ry(a2) Rz(a1)``).
* A frame's dof values build ``M`` the same way, in the order the dofs are listed (``dof rx ry rz`` →
  ``M = Rz Ry Rx``), and the joint's local rotation relative to rest is ``L = C M C⁻¹`` (parent_from_child
  in world-aligned frames). So a 1-dof bone (CMU's tibia, radius, toes, fingers, wrist) is a HINGE about
  ``C e_axis``; 2 (clavicle, foot, hand, thumb) or 3 dofs make a BALL (a 2-dof rotation is a special ball
  rotation); 0 dofs make a FIXED joint (CMU's hip joints).
* The root: AMC values follow the ``:root order`` line (translations TX TY TZ in length units; rotations in
  the listed order, ``RX RY RZ`` → ``M = Rz Ry Rx``); ``world_from_root = C_root M C_root⁻¹`` with
  ``C_root`` built from ``:root orientation`` in the ``:root axis`` order (identity in CMU files). The AMC
  translation is the root's world position.
* Units: ``:units length 0.45`` means one length unit is 1/0.45 inch, so metres = value / 0.45 × 0.0254;
  ``angle deg`` or ``rad`` (an AMC ``:DEGREES``/``:RADIANS`` header overrides it for that file).
* Frames: Acclaim files are Y up; ``up_axis="y"`` maps vectors by ``A`` (+90° about X,
  ``(x, y, z) → (x, -z, y)``) and rotations by ``R ↦ A R Aᵀ`` into bcmocap's Z-up world.

Bone translation or length dofs (``tx ty tz l``) are rejected.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from pathlib import Path

import numpy as np

from ..geometry import euler_to_matrix, quat_from_matrix
from ..kinematics.skeleton import JointType, Motion, Skeleton
from .bvh import world_from_file

__all__ = ["AsfBone", "AsfData", "load_cmu", "read_amc", "read_asf"]

_INCH_M = 0.0254
_ROT_DOFS = ("rx", "ry", "rz")
_ROOT_CHANNELS = ("TX", "TY", "TZ", "RX", "RY", "RZ")


@dataclasses.dataclass(frozen=True, eq=False)
class AsfBone:
    """One bone of an ASF skeleton, as written in the file (ASF frame, file units).

    Attributes:
        name: bone name.
        id: the ``id`` field (or -1 if absent).
        segment: index of the bone's segment in :attr:`AsfData.skeleton`.
        direction: unit direction of the bone at rest (ASF frame).
        length: length in file units.
        axis_angles: the three ``axis`` angles, in the file's angle unit.
        axis_order: the ``axis`` order, e.g. "XYZ" (the axis of the first angle first).
        axis_matrix: ``(3, 3)`` ``C``, the bone's local frame in the ASF frame.
        dofs: rotation dofs in file order, e.g. ``("rx", "ry", "rz")``.
        limits: per dof, ``(low, high)`` in the file's angle unit.
        line: line of the bone's ``begin``.
    """

    name: str
    id: int
    segment: int
    direction: tuple[float, float, float]
    length: float
    axis_angles: tuple[float, float, float]
    axis_order: str
    axis_matrix: np.ndarray
    dofs: tuple[str, ...]
    limits: tuple[tuple[float, float], ...]
    line: int


@dataclasses.dataclass(frozen=True, eq=False)
class AsfData:
    """An ASF skeleton and what is needed to read AMC motions for it.

    Attributes:
        skeleton: segments ``root``, the bones (depth first) and, with ``end_sites``, ``<bone>_end``
            leaves; offsets in metres in the bcmocap world frame (Z up unless ``up_axis="z"``).
        bones: the bones in segment order (root and end sites excluded).
        root_order: the AMC root channels, e.g. ``("TX", "TY", "TZ", "RX", "RY", "RZ")``.
        root_axis_matrix: ``(3, 3)`` ``C_root`` from ``:root orientation`` and ``axis`` (ASF frame).
        root_position: the ``:root position`` in file units (ASF frame).
        length_unit_m: metres per file length unit.
        angle_unit: "deg" or "rad".
        up_axis: the ``up_axis`` the skeleton was converted with.
        name: the ``:name`` field.
        path: the file read.
    """

    skeleton: Skeleton
    bones: tuple[AsfBone, ...]
    root_order: tuple[str, ...]
    root_axis_matrix: np.ndarray
    root_position: tuple[float, float, float]
    length_unit_m: float
    angle_unit: str
    up_axis: str
    name: str
    path: str

    def bone(self, name: str) -> AsfBone:
        """The bone called ``name`` (ValueError listing the bones if unknown)."""
        for b in self.bones:
            if b.name == name:
                return b
        raise ValueError(f"unknown bone '{name}'; {self.path} has {[b.name for b in self.bones]}")


def _axis_matrix(angles_rad, order: str) -> np.ndarray:
    """Rotation applying the listed axes in the order listed: "XYZ", (a, b, c) → ``Rz(c) Ry(b) Rx(a)``."""
    angles_rad = np.asarray(angles_rad, dtype=np.float64)
    return euler_to_matrix(angles_rad[..., ::-1], order[::-1])


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.flags.writeable = False
    return a


def _lines(path: Path):
    """(1-based line number, tokens) of the non-blank lines, comments (#…) removed."""
    with open(path, encoding="utf-8", errors="replace", newline=None) as f:
        for n, text in enumerate(f, 1):
            text = text.split("#", 1)[0].strip()
            if text:
                yield n, text


def _floats(where: str, line: int, tokens: list[str], count: int, what: str) -> list[float]:
    if len(tokens) != count:
        raise ValueError(f"{where}:{line}: expected {count} numbers after '{what}', found {len(tokens)}")
    try:
        out = [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise ValueError(f"{where}:{line}: expected {count} numbers after '{what}', found '{bad}'") from None
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{where}:{line}: '{what}' has a value that is not finite: {tokens}")
    return out


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _check_order(where: str, line: int, order: str) -> str:
    order = order.upper()
    if len(order) != 3 or set(order) != set("XYZ"):
        raise ValueError(f"{where}:{line}: expected an axis order such as XYZ (each of X, Y, Z once), found '{order}'")
    return order


_LIMIT = re.compile(r"\(\s*([^\s()]+)\s+([^\s()]+)\s*\)")


@dataclasses.dataclass
class _AsfSections:
    """The sections of an ASF file that bcmocap uses, as tokens with their line numbers (not yet interpreted)."""

    name: str = ""
    units: dict[str, str] = dataclasses.field(default_factory=dict)
    units_line: dict[str, int] = dataclasses.field(default_factory=dict)
    root: dict[str, tuple[int, list[str]]] = dataclasses.field(default_factory=dict)
    bones: list[dict] = dataclasses.field(default_factory=list)  # as from _finish_bone
    hierarchy: list[tuple[int, str, list[str]]] = dataclasses.field(default_factory=list)  # (line, parent, children)


def read_asf(
    path: str | os.PathLike,
    *,
    up_axis: str = "y",
    end_sites: bool = True,
    length_unit_m: float | None = None,
) -> AsfData:
    """Read an Acclaim skeleton file.

    Args:
        path: the ``.asf`` file.
        up_axis: the file's up axis: "y" (Acclaim's, converted to bcmocap's Z up) or "z" (no conversion).
        end_sites: add a FIXED leaf segment ``<bone>_end`` at the end of each leaf bone (head top, toes,
            fingers, thumbs), so forward kinematics gives those positions.
        length_unit_m: metres per file length unit; default from ``:units length`` (0.0254 / value, since
            one unit is 1/value inch), or 0.0254 if the file has none.

    Returns:
        An :class:`AsfData` whose ``skeleton`` has segment 0 ``root`` (FREE), then the bones depth first.

    Raises:
        ValueError: naming the file, the line and what was expected.
    """
    path = Path(path)
    where = str(path)
    basis = world_from_file(up_axis)
    asf = _read_asf_sections(path, where)
    angle_unit, to_rad, length_unit_m = _asf_units(where, asf, length_unit_m)
    root_order, root_pos, root_c = _asf_root(where, asf.root, to_rad)
    by_name, children, parent_of, order = _asf_bone_order(where, asf.bones, asf.hierarchy)
    seg_names, parents, offsets, types, axes, bone_records = _asf_segments(
        order, by_name, children, parent_of, root_pos, length_unit_m, to_rad, end_sites
    )
    skeleton = Skeleton(
        seg_names,
        parents,
        np.array(offsets) @ basis.T,
        joint_types=types,
        hinge_axes=np.array(axes) @ basis.T,
    )
    return AsfData(
        skeleton=skeleton,
        bones=tuple(bone_records),
        root_order=root_order,
        root_axis_matrix=_readonly(root_c),
        root_position=tuple(root_pos),
        length_unit_m=float(length_unit_m),
        angle_unit=angle_unit,
        up_axis=up_axis.lower(),
        name=asf.name,
        path=where,
    )


def _read_asf_sections(path: Path, where: str) -> _AsfSections:
    """Split an ASF file into its sections, checking the structure (bones begun and ended, the sections
    bcmocap needs present); each bone's fields are checked by :func:`_finish_bone`."""
    out = _AsfSections()
    section = None
    bone: dict | None = None
    in_hierarchy = False
    last_key = None
    seen_sections: set[str] = set()
    last_line = 0

    for n, text in _lines(path):
        last_line = n
        tokens = text.split()
        if text.startswith(":"):
            if bone is not None:
                raise ValueError(
                    f"{where}:{n}: expected 'end' to close the bone begun on line {bone['line']}, found "
                    f"'{tokens[0]}'"
                )
            section = tokens[0][1:].lower()
            seen_sections.add(section)
            if section == "name":
                out.name = " ".join(tokens[1:])
            in_hierarchy = False
            continue
        if section == "units":
            if len(tokens) != 2:
                raise ValueError(f"{where}:{n}: expected '<quantity> <value>' in :units, found '{text}'")
            out.units[tokens[0].lower()] = tokens[1]
            out.units_line[tokens[0].lower()] = n
        elif section == "root":
            key = tokens[0].lower()
            if key not in ("order", "axis", "position", "orientation"):
                raise ValueError(
                    f"{where}:{n}: expected 'order', 'axis', 'position' or 'orientation' in :root, found "
                    f"'{tokens[0]}'"
                )
            out.root[key] = (n, tokens[1:])
        elif section == "bonedata":
            bone, last_key = _bonedata_line(where, n, text, tokens, bone, last_key, out.bones)
        elif section == "hierarchy":
            key = tokens[0].lower()
            if key == "begin" and not in_hierarchy:
                in_hierarchy = True
            elif key == "end" and in_hierarchy:
                in_hierarchy = False
            elif not in_hierarchy:
                raise ValueError(f"{where}:{n}: expected 'begin' in :hierarchy, found '{tokens[0]}'")
            else:
                out.hierarchy.append((n, tokens[0], tokens[1:]))
        # Other sections (:version, :documentation, :skin …) carry nothing bcmocap uses.
    if bone is not None:
        raise ValueError(
            f"{where}:{last_line}: expected 'end' to close the bone begun on line {bone['line']}, found the end of "
            "the file"
        )
    if in_hierarchy:
        raise ValueError(f"{where}:{last_line}: expected 'end' to close :hierarchy, found the end of the file")
    for needed in ("root", "bonedata", "hierarchy"):
        if needed not in seen_sections:
            raise ValueError(f"{where}:{last_line}: expected a ':{needed}' section, the file has none")
    return out


def _bonedata_line(where: str, n: int, text: str, tokens: list[str], bone: dict | None, last_key: str | None,
                   bones: list[dict]) -> tuple[dict | None, str | None]:
    """Read line ``n`` of :bonedata into ``bone``, the bone being read (None between bones; its ``end``
    appends it, finished, to ``bones``). Returns the bone being read after this line and its last field."""
    key = tokens[0].lower()
    if bone is None:
        if key != "begin":
            raise ValueError(f"{where}:{n}: expected 'begin' to start a bone in :bonedata, found '{tokens[0]}'")
        return {"line": n, "limits": []}, None
    if key == "begin":
        raise ValueError(
            f"{where}:{n}: expected 'end' to close the bone begun on line {bone['line']}, found "
            "'begin'"
        )
    if key == "end":
        bones.append(_finish_bone(where, n, bone))
        return None, last_key
    if text.startswith("("):
        if last_key != "limits":
            raise ValueError(f"{where}:{n}: a '(low high)' pair must follow a 'limits' line")
        bone["limits"].append((n, text))
        return bone, last_key
    if key in ("id", "name", "direction", "length", "axis", "dof", "limits", "bodymass", "cofmass"):
        if key in bone and key != "limits":
            raise ValueError(f"{where}:{n}: bone begun on line {bone['line']} has a second '{key}' line")
        if key == "limits":
            bone["limits"].append((n, " ".join(tokens[1:])))
        else:
            bone[key] = (n, tokens[1:])
        return bone, key
    raise ValueError(
        f"{where}:{n}: unknown bone field '{tokens[0]}' (expected id, name, direction, length, axis, dof, "
        "limits or end)"
    )


def _asf_units(where: str, asf: _AsfSections, length_unit_m: float | None) -> tuple[str, float, float]:
    """The angle unit ("deg" or "rad"), radians per file angle unit and metres per file length unit
    (``length_unit_m`` if given, else from ``:units``)."""
    units, units_line = asf.units, asf.units_line
    angle_unit = units.get("angle", "deg").lower()
    if angle_unit not in ("deg", "rad"):
        raise ValueError(
            f"{where}:{units_line.get('angle', 0)}: expected 'angle deg' or 'angle rad', found "
            f"'{angle_unit}'"
        )
    to_rad = math.pi / 180.0 if angle_unit == "deg" else 1.0
    if length_unit_m is None:
        if "length" in units:
            try:
                length = float(units["length"])
            except ValueError:
                length = float("nan")
            if not (math.isfinite(length) and length > 0):
                raise ValueError(
                    f"{where}:{units_line['length']}: expected a positive number after 'length', found "
                    f"'{units['length']}'"
                )
            length_unit_m = _INCH_M / length
        else:
            length_unit_m = _INCH_M
    elif not length_unit_m > 0:
        raise ValueError(f"read_asf: length_unit_m must be positive, got {length_unit_m}")
    return angle_unit, to_rad, length_unit_m


def _asf_root(where: str, root: dict[str, tuple[int, list[str]]], to_rad: float
              ) -> tuple[tuple[str, ...], list[float], np.ndarray]:
    """The :root section: the AMC channel order, the position (file units) and the axis matrix ``C_root``."""
    if "order" in root:
        line, toks = root["order"]
        root_order = tuple(t.upper() for t in toks)
        bad = [t for t in root_order if t not in _ROOT_CHANNELS]
        if bad or len(set(root_order)) != len(root_order):
            raise ValueError(
                f"{where}:{line}: expected root channels among {list(_ROOT_CHANNELS)}, each once, found "
                f"{list(toks)}"
            )
    else:
        root_order = _ROOT_CHANNELS
    root_axis = _check_order(where, root["axis"][0], "".join(root["axis"][1])) if "axis" in root else "XYZ"
    root_pos = _floats(where, *root["position"], 3, "position") if "position" in root else [0.0, 0.0, 0.0]
    root_ori = _floats(where, *root["orientation"], 3, "orientation") if "orientation" in root else [0.0, 0.0, 0.0]
    root_c = _axis_matrix(np.array(root_ori) * to_rad, root_axis)
    return root_order, root_pos, root_c


def _asf_bone_order(where: str, bones: list[dict], hierarchy: list[tuple[int, str, list[str]]]):
    """The bones by name, each bone's children and parent (by name, "root" for the root), and the
    depth-first order of the tree from "root"."""
    by_name = {}
    for b in bones:
        if b["name"] in by_name or b["name"].lower() == "root":
            raise ValueError(f"{where}:{b['name_line']}: duplicate bone name '{b['name']}'")
        by_name[b["name"]] = b
    children: dict[str, list[str]] = {"root": []}
    parent_of: dict[str, str] = {}
    for line, par, kids in hierarchy:
        if par != "root" and par not in by_name:
            raise ValueError(f"{where}:{line}: unknown bone '{par}' in :hierarchy")
        for kid in kids:
            if kid not in by_name:
                raise ValueError(f"{where}:{line}: unknown bone '{kid}' in :hierarchy")
            if kid in parent_of:
                raise ValueError(f"{where}:{line}: bone '{kid}' already has parent '{parent_of[kid]}'")
            parent_of[kid] = par
            children.setdefault(par, []).append(kid)
    order: list[str] = []
    stack = ["root"]
    while stack:
        b = stack.pop()
        if b in order:
            raise ValueError(f"{where}: :hierarchy has a cycle through bone '{b}'")
        order.append(b)
        stack.extend(reversed(children.get(b, [])))
    missing = [b["name"] for b in bones if b["name"] not in order]
    if missing:
        raise ValueError(
            f"{where}:{by_name[missing[0]]['line']}: bone(s) {missing} are not reachable from the root in :hierarchy"
        )
    return by_name, children, parent_of, order


def _asf_segments(order, by_name, children, parent_of, root_pos, length_unit_m: float, to_rad: float, end_sites: bool):
    """Segments in the file's frame (m): names, parent indices, offsets, joint types and hinge axes, one per
    bone of ``order`` (with a FIXED ``<bone>_end`` after each leaf bone when ``end_sites``), and the
    :class:`AsfBone` records."""
    seg_names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray] = []
    types: list[JointType] = []
    axes: list[np.ndarray] = []
    bone_records: list[AsfBone] = []
    index: dict[str, int] = {}
    for b in order:
        index[b] = len(seg_names)
        seg_names.append(b)
        if b == "root":
            parents.append(-1)
            offsets.append(np.zeros(3))
            types.append(JointType.FREE)
            axes.append(np.zeros(3))
            continue
        rec = by_name[b]
        par = parent_of[b]
        parents.append(index[par])
        if par == "root":
            offsets.append(np.array(root_pos) * length_unit_m)
        else:
            prec = by_name[par]
            offsets.append(np.array(prec["direction"]) * prec["length"] * length_unit_m)
        c = _axis_matrix(np.array(rec["axis_angles"]) * to_rad, rec["axis_order"])
        dofs = rec["dofs"]
        axis = np.zeros(3)
        if len(dofs) == 0:
            types.append(JointType.FIXED)
        elif len(dofs) == 1:
            types.append(JointType.HINGE)
            axis = c[:, "xyz".index(dofs[0][1])]
        else:
            types.append(JointType.BALL)
        axes.append(axis)
        bone_records.append(
            AsfBone(
                name=b,
                id=rec["id"],
                segment=index[b],
                direction=tuple(rec["direction"]),
                length=rec["length"],
                axis_angles=tuple(rec["axis_angles"]),
                axis_order=rec["axis_order"],
                axis_matrix=_readonly(c),
                dofs=dofs,
                limits=rec["limits"],
                line=rec["line"],
            )
        )
        if end_sites and not children.get(b):
            end = f"{b}_end"
            while end in by_name or end in seg_names:
                end += "_"
            seg_names.append(end)
            parents.append(index[b])
            offsets.append(np.array(rec["direction"]) * rec["length"] * length_unit_m)
            types.append(JointType.FIXED)
            axes.append(np.zeros(3))
    return seg_names, parents, offsets, types, axes, bone_records


def _finish_bone(where: str, end_line: int, bone: dict) -> dict:
    begin = bone["line"]
    for key in ("name", "direction", "length", "axis"):
        if key not in bone:
            raise ValueError(f"{where}:{end_line}: bone begun on line {begin} has no '{key}' line")
    n, toks = bone["name"]
    if len(toks) != 1:
        raise ValueError(f"{where}:{n}: expected one bone name after 'name', found {len(toks)} words")
    out = {"line": begin, "name": toks[0], "name_line": n}
    if "id" in bone:
        n, toks = bone["id"]
        try:
            out["id"] = int(toks[0]) if len(toks) == 1 else None
        except ValueError:
            out["id"] = None
        if out["id"] is None:
            raise ValueError(f"{where}:{n}: expected an integer after 'id', found '{' '.join(toks)}'")
    else:
        out["id"] = -1
    out["direction"] = _floats(where, *bone["direction"], 3, "direction")
    out["length"] = _floats(where, *bone["length"], 1, "length")[0]
    if out["length"] < 0:
        raise ValueError(f"{where}:{bone['length'][0]}: expected a non-negative length, found {out['length']}")
    n, toks = bone["axis"]
    if len(toks) != 4:
        raise ValueError(f"{where}:{n}: expected 3 angles and an order after 'axis' (e.g. '0 0 20 XYZ'), found {toks}")
    out["axis_angles"] = _floats(where, n, toks[:3], 3, "axis")
    out["axis_order"] = _check_order(where, n, toks[3])
    dofs: tuple[str, ...] = ()
    if "dof" in bone:
        n, toks = bone["dof"]
        dofs = tuple(t.lower() for t in toks)
        bad = [t for t in dofs if t not in _ROT_DOFS]
        if bad:
            raise ValueError(
                f"{where}:{n}: bone '{out['name']}' has dof {bad}; only rotation dofs rx, ry, rz are supported "
                "(translation and length dofs are not)"
            )
        if len(set(dofs)) != len(dofs):
            raise ValueError(f"{where}:{n}: bone '{out['name']}' repeats a dof: {list(toks)}")
    out["dofs"] = dofs
    limits = []
    for n, text in bone["limits"]:
        found = _LIMIT.findall(text)
        if not found or _LIMIT.sub("", text).strip():
            raise ValueError(f"{where}:{n}: expected '(low high)' limits, found '{text}'")
        for lo, hi in found:
            try:
                limits.append((float(lo), float(hi)))
            except ValueError:
                raise ValueError(f"{where}:{n}: expected numbers in '({lo} {hi})'") from None
            if math.isnan(limits[-1][0]) or math.isnan(limits[-1][1]):  # ±inf: no limit, as ASF allows
                raise ValueError(f"{where}:{n}: limits '({lo} {hi})' hold NaN")
    if limits and len(limits) != len(dofs):
        raise ValueError(
            f"{where}:{bone['limits'][0][0]}: bone '{out['name']}' has {len(dofs)} dofs but {len(limits)} limits"
        )
    out["limits"] = tuple(limits)
    return out


def read_amc(path: str | os.PathLike, asf: AsfData, *, fps: float = 120.0) -> Motion:
    """Read an Acclaim motion file for the skeleton ``asf``.

    Every frame must give the root and every bone that has dofs, each with as many values as it has dofs
    (bones may come in any order within a frame). AMC files carry no frame rate; ``fps`` (CMU trials are
    120 Hz) is only checked here, since :class:`Motion` holds no time stamps: keep it beside the motion.

    Args:
        path: the ``.amc`` file.
        asf: the skeleton it was recorded with, from :func:`read_asf`.
        fps: frames per second of the trial.

    Returns:
        A :class:`Motion` with ``F`` frames: ``root_position (F, 3)`` m and ``rotations (F, J, 4)`` for
        ``asf.skeleton`` (FIXED segments and end sites at identity).

    Raises:
        ValueError: naming the file, the line, the bone and the expected number of values.
    """
    path = Path(path)
    where = str(path)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"read_amc: fps must be positive, got {fps}")
    to_rad = math.pi / 180.0 if asf.angle_unit == "deg" else 1.0

    # Columns of one frame's values: the root's channels, then each bone's dofs.
    slots: dict[str, tuple[int, int, str]] = {"root": (0, len(asf.root_order), " ".join(asf.root_order))}
    width = len(asf.root_order)
    for b in asf.bones:
        slots[b.name] = (width, len(b.dofs), " ".join(b.dofs) if b.dofs else "none")
        width += len(b.dofs)
    required = [name for name, (_, count, _) in slots.items() if count > 0 or name == "root"]

    rows: list[np.ndarray] = []
    row: np.ndarray | None = None
    seen: set[str] = set()
    frame_line = 0
    frame_number = None

    def close_frame():
        lacking = [b for b in required if b not in seen]
        if lacking:
            raise ValueError(f"{where}:{frame_line}: frame {frame_number} lacks bone(s) {lacking}")
        rows.append(row)

    last_line = 0
    for n, text in _lines(path):
        last_line = n
        tokens = text.split()
        if text.startswith(":"):
            if rows or row is not None:
                raise ValueError(f"{where}:{n}: header line '{text}' after the first frame")
            flag = tokens[0].upper()
            if flag == ":DEGREES":
                to_rad = math.pi / 180.0
            elif flag == ":RADIANS":
                to_rad = 1.0
            continue
        if len(tokens) == 1 and tokens[0].isdigit():
            if row is not None:
                close_frame()
            row = np.zeros(width)
            seen = set()
            frame_line = n
            frame_number = int(tokens[0])
            continue
        bone = tokens[0]
        if row is None:
            raise ValueError(f"{where}:{n}: expected a frame number before the values of '{bone}'")
        if bone not in slots:
            raise ValueError(f"{where}:{n}: unknown bone '{bone}' (not in {asf.path})")
        if bone in seen:
            raise ValueError(f"{where}:{n}: bone '{bone}' appears twice in frame {frame_number}")
        start, count, dof_text = slots[bone]
        values = tokens[1:]
        if len(values) != count:
            raise ValueError(
                f"{where}:{n}: bone '{bone}' expects {count} values (dof {dof_text}), found {len(values)}"
            )
        try:
            row[start : start + count] = [float(v) for v in values]
        except ValueError:
            bad = next(v for v in values if not _is_float(v))
            raise ValueError(
                f"{where}:{n}: bone '{bone}' expects {count} numbers (dof {dof_text}), found "
                f"'{bad}'"
            ) from None
        if not np.all(np.isfinite(row[start : start + count])):
            raise ValueError(f"{where}:{n}: bone '{bone}' has a value that is not finite")
        seen.add(bone)
    if row is not None:
        close_frame()
    if not rows:
        raise ValueError(f"{where}:{last_line}: expected frames (a frame number, then one line per bone), found none")

    values = np.stack(rows)  # (F, width)
    num_frames = len(rows)
    basis = world_from_file(asf.up_axis)
    skeleton = asf.skeleton

    # Root: translation (file units) and rotation M in the listed order.
    root_cols = {ch: k for k, ch in enumerate(asf.root_order)}
    position = np.zeros((num_frames, 3))
    for k, axis in enumerate("XYZ"):
        if f"T{axis}" in root_cols:
            position[:, k] = values[:, root_cols[f"T{axis}"]]
    rot_channels = [ch for ch in asf.root_order if ch.startswith("R")]
    matrices = np.broadcast_to(np.eye(3), (num_frames, skeleton.num_segments, 3, 3)).copy()
    if rot_channels:
        angles = values[:, [root_cols[ch] for ch in rot_channels]] * to_rad
        m = _axis_matrix(angles, "".join(ch[1] for ch in rot_channels))
        c = asf.root_axis_matrix
        matrices[:, 0] = c @ m @ c.T
    for b in asf.bones:
        if not b.dofs:
            continue
        start, count, _ = slots[b.name]
        m = _axis_matrix(values[:, start : start + count] * to_rad, "".join(d[1].upper() for d in b.dofs))
        c = b.axis_matrix
        matrices[:, b.segment] = c @ m @ c.T
    matrices = basis @ matrices @ basis.T
    return Motion(position * asf.length_unit_m @ basis.T, quat_from_matrix(matrices))


def load_cmu(
    asf_path: str | os.PathLike,
    amc_path: str | os.PathLike,
    *,
    fps: float = 120.0,
    up_axis: str = "y",
    end_sites: bool = True,
) -> tuple[Skeleton, Motion]:
    """Read a CMU (Acclaim) skeleton and one of its trials: ``(skeleton, motion)``, Z up, metres.

    Args:
        asf_path: the subject's ``.asf`` file.
        amc_path: the trial's ``.amc`` file.
        fps: the trial's frame rate (CMU: 120 Hz); see :func:`read_amc`.
        up_axis: see :func:`read_asf`.
        end_sites: see :func:`read_asf`.
    """
    asf = read_asf(asf_path, up_axis=up_axis, end_sites=end_sites)
    return asf.skeleton, read_amc(amc_path, asf, fps=fps)
