"""Acclaim ASF/AMC (CMU) reading, checked against an independent implementation of the Acclaim recursion."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import bcmocap
from bcmocap.io import AsfData, load_cmu, read_amc, read_asf
from bcmocap.kinematics import JointType, Motion, Skeleton, forward_kinematics, joint_positions

CMU = Path(bcmocap.__file__).parent / "data" / "cmu"
UNIT_M = 0.0254 / 0.45  # `:units length 0.45`: one unit is 1/0.45 inch
A = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # Y up → Z up


# ---- an independent Acclaim implementation (plain numpy, its own parser) ---------------------------


def rot(axis: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis.lower()[-1]]


def applied_in_order(axes, degs) -> np.ndarray:
    """The rotation applying ``axes[0]`` first: R_{axes[-1]} … R_{axes[0]}."""
    out = np.eye(3)
    for ax, d in zip(axes, degs):
        out = rot(ax, d) @ out
    return out


def parse_asf_plain(path: Path):
    bones, hierarchy, section, cur = {}, [], None, None
    for line in path.read_text().splitlines():
        t = line.split("#")[0].split()
        if not t:
            continue
        if t[0].startswith(":"):
            section = t[0]
            continue
        if section == ":bonedata":
            if t[0] == "begin":
                cur = {"dof": []}
            elif t[0] == "end":
                bones[cur["name"]] = cur
            elif t[0] == "name":
                cur["name"] = t[1]
            elif t[0] == "direction":
                cur["direction"] = np.array([float(v) for v in t[1:4]])
            elif t[0] == "length":
                cur["length"] = float(t[1])
            elif t[0] == "axis":
                cur["C"] = applied_in_order(t[4], [float(v) for v in t[1:4]])
            elif t[0] == "dof":
                cur["dof"] = t[1:]
        elif section == ":hierarchy" and t[0] not in ("begin", "end"):
            hierarchy.append((t[0], t[1:]))
    parent = {kid: par for par, kids in hierarchy for kid in kids}
    return bones, parent


def parse_amc_plain(path: Path):
    frames = []
    for line in path.read_text().splitlines():
        t = line.split()
        if not t or t[0].startswith((":", "#")):
            continue
        if len(t) == 1 and t[0].isdigit():
            frames.append({})
        else:
            frames[-1][t[0]] = [float(v) for v in t[1:]]
    return frames


def acclaim_positions(bones, parent, frame):
    """Start and end of every bone, Y up, file units: world_b = world_parent C M C⁻¹."""
    root = frame["root"]
    world = {"root": applied_in_order("xyz", root[3:6])}
    start, end = {}, {"root": np.array(root[:3])}
    todo = list(bones)
    while todo:
        for b in list(todo):
            p = parent[b]
            if p not in world:
                continue
            rec = bones[b]
            m = applied_in_order(rec["dof"], frame.get(b, [])) if rec["dof"] else np.eye(3)
            world[b] = world[p] @ rec["C"] @ m @ np.linalg.inv(rec["C"])
            start[b] = end[p]
            end[b] = start[b] + world[b] @ (rec["direction"] * rec["length"])
            todo.remove(b)
    return start, end


# ---- fixtures ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def asf35() -> AsfData:
    return read_asf(CMU / "35.asf")


@pytest.fixture(scope="module")
def walk(asf35) -> Motion:
    return read_amc(CMU / "35_01.amc", asf35)


# ---- structure --------------------------------------------------------------------------------------


def test_skeleton_35(asf35):
    sk = asf35.skeleton
    assert len(asf35.bones) == 30 and sk.names[0] == "root"
    ends = [n for n in sk.names if n.endswith("_end")]
    assert sk.num_segments == 31 + len(ends)
    assert sorted(ends) == sorted(["head_end", "lfingers_end", "lthumb_end", "ltoes_end", "rfingers_end", "rthumb_end", "rtoes_end"])
    assert read_asf(CMU / "35.asf", end_sites=False).skeleton.num_segments == 31
    assert asf35.length_unit_m == pytest.approx(UNIT_M) and asf35.angle_unit == "deg"
    assert asf35.root_order == ("TX", "TY", "TZ", "RX", "RY", "RZ")
    types = dict(zip(sk.names, sk.joint_types))
    assert types["root"] == JointType.FREE
    for name in ("ltibia", "rtibia", "lradius", "rradius", "lwrist", "ltoes"):
        assert types[name] == JointType.HINGE, name
    for name in ("lfemur", "lfoot", "lclavicle", "rthumb", "head"):  # 3 and 2 dofs
        assert types[name] == JointType.BALL, name
    for name in ("lhipjoint", "rhipjoint", "head_end"):
        assert types[name] == JointType.FIXED, name
    assert asf35.bone("lfemur").dofs == ("rx", "ry", "rz")
    assert asf35.bone("lfemur").limits[0] == (-160.0, 20.0)


def test_bone_lengths_and_offsets(asf35):
    sk = asf35.skeleton
    offsets = np.asarray(sk.offsets)
    for bone in asf35.bones:
        kids = [j for j in range(sk.num_segments) if sk.parents[j] == bone.segment]
        for j in kids:  # every child joint sits at the end of this bone
            np.testing.assert_allclose(np.linalg.norm(offsets[j]), bone.length * UNIT_M, rtol=1e-5)
            np.testing.assert_allclose(offsets[j], A @ np.array(bone.direction) * bone.length * UNIT_M, atol=1e-12)
    # Bones attached to the root start at the root.
    for name in ("lhipjoint", "rhipjoint", "lowerback"):
        np.testing.assert_array_equal(offsets[sk.index(name)], 0.0)
    np.testing.assert_allclose(
        offsets[sk.index("ltibia")], np.array([0.34202, 0.0, -0.939693]) * 7.41015 * UNIT_M, atol=1e-12
    )  # the femur, Z up


def test_hinge_axes(asf35):
    sk = asf35.skeleton
    for name in ("ltibia", "rtibia", "lradius", "rradius"):
        bone = asf35.bone(name)
        axis = np.asarray(sk.hinge_axes[bone.segment])
        np.testing.assert_allclose(axis, A @ bone.axis_matrix[:, 0], atol=1e-12)  # dof rx: C e_x
        # The knee and elbow axes are perpendicular to the bone.
        assert abs(axis @ (A @ np.array(bone.direction))) < 1e-5
    # ltibia: axis 0 0 20 XYZ → C = Rz(20°): e_x → (cos 20°, sin 20°, 0) Y up.
    c20, s20 = np.cos(np.deg2rad(20)), np.sin(np.deg2rad(20))
    np.testing.assert_allclose(sk.hinge_axes[sk.index("ltibia")], [c20, 0.0, s20], atol=1e-12)


def test_axis_matrix_order(asf35):
    # lhumerus: axis 180 -30 -90 XYZ → C = Rz(-90) Ry(-30) Rx(180), the X rotation applied first.
    c = asf35.bone("lhumerus").axis_matrix
    np.testing.assert_allclose(c, rot("z", -90) @ rot("y", -30) @ rot("x", 180), atol=1e-12)
    assert not np.allclose(c, rot("x", 180) @ rot("y", -30) @ rot("z", -90), atol=1e-3)


def test_rest_pose_height_z_up(asf35):
    sk = asf35.skeleton
    pos = np.asarray(joint_positions(sk, sk.rest_motion()))
    height = pos[sk.index("head_end"), 2] - pos[:, 2].min()
    assert 1.5 < height < 1.9, height
    assert pos[sk.index("head_end"), 2] > pos[sk.index("lowerback"), 2] > pos[sk.index("ltoes"), 2]


# ---- motion -----------------------------------------------------------------------------------------


def test_walk_35_01(asf35, walk):
    sk = asf35.skeleton
    assert walk.rotations.shape == (358, sk.num_segments, 4)
    pos = np.asarray(joint_positions(sk, walk))
    root = pos[:, 0]
    assert np.linalg.norm(root[-1, :2] - root[0, :2]) > 2.0  # walks metres forward
    assert np.ptp(root[:, 2]) < 0.15 and 0.8 < root[:, 2].mean() < 1.2  # pelvis height stays about 1 m
    head_over_feet = pos[:, sk.index("head_end"), 2] - pos[:, :, 2].min(axis=1)
    assert np.all(head_over_feet > 1.4)
    # Fixed joints and end sites do not rotate; hinges rotate about their axis only.
    for j, t in enumerate(sk.joint_types):
        q = np.asarray(walk.rotations[:, j])
        if t == JointType.FIXED:
            np.testing.assert_allclose(q, np.broadcast_to([1.0, 0, 0, 0], q.shape), atol=1e-15)
        elif t == JointType.HINGE:
            axis = np.asarray(sk.hinge_axes[j])
            np.testing.assert_allclose(q[:, 1:] - (q[:, 1:] @ axis)[:, None] * axis, 0.0, atol=1e-12)


@pytest.mark.parametrize("subject,trial,frames", [("35", "35_01", [0, 1, 150, 357]), ("02", "02_04", [0, 240, 482])])
def test_matches_independent_acclaim_recursion(subject, trial, frames):
    asf = read_asf(CMU / f"{subject}.asf")
    motion = read_amc(CMU / f"{trial}.amc", asf)
    sk = asf.skeleton
    bones, parent = parse_asf_plain(CMU / f"{subject}.asf")
    amc = parse_amc_plain(CMU / f"{trial}.amc")
    assert len(amc) == motion.num_frames
    got = np.asarray(joint_positions(sk, motion[np.array(frames)]))
    for k, f in enumerate(frames):
        start, end = acclaim_positions(bones, parent, amc[f])
        for name, p in start.items():
            np.testing.assert_allclose(got[k, sk.index(name)], A @ p * UNIT_M, rtol=0, atol=1e-9)
        for name in bones:
            if f"{name}_end" in sk.names:
                np.testing.assert_allclose(got[k, sk.index(f"{name}_end")], A @ end[name] * UNIT_M, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got[k, 0], A @ np.array(amc[f]["root"][:3]) * UNIT_M, atol=1e-12)


def test_orientations_match_independent_recursion(asf35, walk):
    bones, parent = parse_asf_plain(CMU / "35.asf")
    amc = parse_amc_plain(CMU / "35_01.amc")
    sk = asf35.skeleton
    world = np.asarray(forward_kinematics(sk, walk[100]).rotation().as_matrix())
    root = amc[100]["root"]
    w = {"root": applied_in_order("xyz", root[3:6])}
    for b in sk.names[1:]:
        if b in bones:
            rec = bones[b]
            m = applied_in_order(rec["dof"], amc[100].get(b, [])) if rec["dof"] else np.eye(3)
            w[b] = w[parent[b]] @ rec["C"] @ m @ np.linalg.inv(rec["C"])
    for b, r in w.items():
        np.testing.assert_allclose(world[sk.index(b)], A @ r @ A.T, atol=1e-12)


def test_run_and_jump_02():
    asf = read_asf(CMU / "02.asf")
    run = read_amc(CMU / "02_03.amc", asf)
    jump = read_amc(CMU / "02_04.amc", asf)
    assert run.num_frames == 173 and jump.num_frames == 483
    p = np.asarray(run.root_position)
    speed = np.linalg.norm(p[-1, :2] - p[0, :2]) / (run.num_frames / 120.0)
    assert speed > 2.0, speed  # running, m/s


def test_load_cmu_and_up_axis(asf35, walk):
    sk, motion = load_cmu(CMU / "35.asf", CMU / "35_01.amc")
    assert sk.names == asf35.skeleton.names
    np.testing.assert_array_equal(np.asarray(motion.rotations), np.asarray(walk.rotations))
    raw = read_asf(CMU / "35.asf", up_axis="z")
    np.testing.assert_allclose(np.asarray(raw.skeleton.offsets) @ A.T, np.asarray(asf35.skeleton.offsets), atol=1e-15)
    raw_motion = read_amc(CMU / "35_01.amc", raw)
    np.testing.assert_allclose(
        np.asarray(joint_positions(raw.skeleton, raw_motion[:5])) @ A.T,
        np.asarray(joint_positions(asf35.skeleton, walk[:5])),
        atol=1e-12,
    )


def test_root_position_and_orientation_fields(tmp_path):
    text = (CMU / "35.asf").read_text()
    text = text.replace("position 0 0 0", "position 1 2 3", 1).replace("orientation 0 0 0", "orientation 0 90 0", 1)
    path = tmp_path / "moved.asf"
    path.write_text(text)
    asf = read_asf(path)
    sk = asf.skeleton
    np.testing.assert_allclose(sk.offsets[sk.index("lowerback")], A @ np.array([1.0, 2, 3]) * UNIT_M, atol=1e-12)
    motion = read_amc(CMU / "35_01.amc", asf)
    # world_from_root = C_root M C_rootᵀ with C_root = Ry(90°).
    frame0 = parse_amc_plain(CMU / "35_01.amc")[0]["root"]
    c = rot("y", 90)
    expected = A @ c @ applied_in_order("xyz", frame0[3:6]) @ c.T @ A.T
    got = np.asarray(forward_kinematics(sk, motion[0]).rotation().as_matrix())[0]
    np.testing.assert_allclose(got, expected, atol=1e-12)


# ---- errors -----------------------------------------------------------------------------------------


def _edit(tmp_path: Path, source: Path, old: str, new: str, name: str) -> tuple[Path, int]:
    text = source.read_text()
    assert old in text
    line = text[: text.index(old)].count("\n") + 1
    path = tmp_path / name
    path.write_text(text.replace(old, new, 1))
    return path, line


@pytest.mark.parametrize(
    "old,new,message",
    [
        ("direction 0.34202 -0.939693 0  ", "direction 0.34202 -0.939693", "expected 3 numbers after 'direction', found 2"),
        ("length 7.41015", "length long", "expected 1 numbers after 'length', found 'long'"),
        ("axis 0 0 20  XYZ", "axis 0 0 20  XYQ", "expected an axis order such as XYZ (each of X, Y, Z once), found 'XYQ'"),
        ("dof rx ry rz\n    limits (-160.0 20.0)", "dof rx ry tz\n    limits (-160.0 20.0)",
         "bone 'lfemur' has dof ['tz']; only rotation dofs rx, ry, rz are supported"),
        ("lhipjoint lfemur", "lhipjoint lfemurr", "unknown bone 'lfemurr' in :hierarchy"),
        ("  angle deg", "  angle grad", "expected 'angle deg' or 'angle rad', found 'grad'"),
    ],
)  # fmt: skip
def test_asf_errors_name_file_and_line(tmp_path, old, new, message):
    path, line = _edit(tmp_path, CMU / "35.asf", old, new, "bad.asf")
    with pytest.raises(ValueError, match=re.escape(f"{path}:{line}: {message}")):
        read_asf(path)


def test_asf_error_unclosed_bone(tmp_path):
    path, line = _edit(tmp_path, CMU / "35.asf", "    limits (-10.0 170.0)\n end", "    limits (-10.0 170.0)\n", "open.asf")
    with pytest.raises(ValueError, match=re.escape(f"{path}:") + r"\d+: expected 'end' to close the bone begun on line \d+, found 'begin'"):
        read_asf(path)


@pytest.fixture(scope="module")
def short_amc(tmp_path_factory) -> Path:
    # The header and the first 3 frames of 35_01: enough for the error tests, quick to read.
    lines = (CMU / "35_01.amc").read_text().splitlines()
    cut = lines.index("4")
    path = tmp_path_factory.mktemp("amc") / "short.amc"
    path.write_text("\n".join(lines[:cut]) + "\n")
    return path


def test_amc_errors_name_file_line_and_bone(tmp_path, asf35, short_amc):
    assert read_amc(short_amc, asf35).num_frames == 3
    text = short_amc.read_text()
    cases = [
        ("lfemur -27.9936 -4.46438 -9.04925", "lfemur -27.9936 -4.46438", "bone 'lfemur' expects 3 values (dof rx ry rz), found 2"),
        ("rtibia 25.6934", "rtibia 25.6934 1.0", "bone 'rtibia' expects 1 values (dof rx), found 2"),
        ("ltoes 1.09177", "ltoe 1.09177", "unknown bone 'ltoe'"),
        ("lhand -24.5852 29.6298", "lhand -24.5852 abc", "bone 'lhand' expects 2 numbers (dof rx rz), found 'abc'"),
    ]  # fmt: skip
    for k, (old, new, message) in enumerate(cases):
        assert old in text, old
        line = text[: text.index(old)].count("\n") + 1
        path = tmp_path / f"bad{k}.amc"
        path.write_text(text.replace(old, new, 1))
        with pytest.raises(ValueError, match=re.escape(f"{path}:{line}: {message}")):
            read_amc(path, asf35)
    # A frame lacking a bone: the message names the frame's line.
    lines = text.splitlines()
    k = lines.index("rtibia 25.6934")
    path = tmp_path / "lacking.amc"
    path.write_text("\n".join(lines[:k] + lines[k + 1 :]) + "\n")
    with pytest.raises(ValueError, match=re.escape(f"{path}:{lines.index('1') + 1}: frame 1 lacks bone(s) ['rtibia']")):
        read_amc(path, asf35)
    with pytest.raises(ValueError, match="fps must be positive"):
        read_amc(short_amc, asf35, fps=0.0)


def test_skeleton_types_are_bcmocap_types(asf35, walk):
    assert isinstance(asf35.skeleton, Skeleton) and isinstance(walk, Motion)
    walk.check(asf35.skeleton)
