"""BVH reading and writing: a real CMU excerpt, hand-written files, round trips and error messages."""

from __future__ import annotations

import itertools
import os
import re
from pathlib import Path

import numpy as np
import pytest

from bcmocap.geometry import euler_to_matrix, matrix_from_quat, rotation_angle
from bcmocap.io import BvhData, read_bvh, write_bvh
from bcmocap.io.bvh import matrix_to_euler
from bcmocap.kinematics import JointType, Motion, Skeleton, joint_positions

DATA = Path(__file__).parent / "data" / "cmu"
EXCERPT = DATA / "131_02_first40.bvh"
CMU_UNIT_M = 0.0254 / 0.45  # 0.056444 m
A = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # Y up → Z up


def axis_angle(axis: str, angle: float) -> np.ndarray:
    """Rodrigues' formula, independent of bcmocap.geometry."""
    k = np.zeros(3)
    k["XYZ".index(axis.upper())] = 1.0
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def euler_reference(angles_rad, order: str) -> np.ndarray:
    out = np.eye(3)
    for a, ax in zip(angles_rad, order):
        out = out @ axis_angle(ax, a)
    return out


def fk_reference(parents, offsets, rotations, root):
    """Plain numpy forward kinematics: world_j = world_parent @ R_j, p_j = p_parent + world_parent @ o_j."""
    n = len(parents)
    world = [None] * n
    pos = np.zeros((n, 3))
    for j in range(n):
        if parents[j] < 0:
            world[j], pos[j] = rotations[j], root
        else:
            p = parents[j]
            world[j] = world[p] @ rotations[j]
            pos[j] = pos[p] + world[p] @ offsets[j]
    return pos


# ---- Euler conventions -----------------------------------------------------------------------------


@pytest.mark.parametrize("order", ["".join(p) for p in itertools.permutations("XYZ")] + ["ZXZ", "X", "YZ"])
def test_euler_to_matrix_matches_rodrigues(order):
    rng = np.random.default_rng(0)
    angles = rng.uniform(-np.pi, np.pi, size=(5, len(order)))
    got = euler_to_matrix(angles, order)
    for a, g in zip(angles, got):
        np.testing.assert_allclose(g, euler_reference(a, order), atol=1e-14)


@pytest.mark.parametrize("order", ["".join(p) for p in itertools.permutations("XYZ")])
def test_matrix_to_euler_inverts_euler_to_matrix(order):
    rng = np.random.default_rng(1)
    angles = rng.uniform(-np.pi, np.pi, size=(200, 3))
    angles[:, 1] = rng.uniform(-1.5, 1.5, size=200)
    back = matrix_to_euler(euler_to_matrix(angles, order), order)
    np.testing.assert_allclose(back, angles, atol=1e-12)
    # Gimbal lock: angles are not unique but the matrix must be reproduced.
    locked = angles[:5].copy()
    locked[:, 1] = np.pi / 2 * np.array([1, -1, 1, -1, 1])
    m = euler_to_matrix(locked, order)
    np.testing.assert_allclose(euler_to_matrix(matrix_to_euler(m, order), order), m, atol=1e-12)


# ---- the real CMU excerpt -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cmu() -> BvhData:
    return read_bvh(EXCERPT, length_unit_m=CMU_UNIT_M)


def test_cmu_excerpt_structure(cmu):
    sk = cmu.skeleton
    joints = [n for n in sk.names if not n.endswith("_end")]
    assert len(joints) == 31
    assert sk.num_segments == 31 + 7  # 7 End Sites: toes, head, fingers, thumbs
    assert cmu.motion.rotations.shape == (40, 38, 4)
    assert cmu.num_frames == 40
    assert cmu.frame_time_s == pytest.approx(1 / 120, abs=1e-6)
    assert sk.joint_types[0] == JointType.FREE
    assert all(sk.joint_types[sk.index(n)] == JointType.BALL for n in joints[1:])
    assert all(sk.joint_types[j] == JointType.FIXED for j, n in enumerate(sk.names) if n.endswith("_end"))
    assert cmu.channels[0] == ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")
    assert cmu.euler_orders[sk.index("LeftHip")] == "ZYX"
    assert cmu.euler_orders[sk.index("RThumb")] == "ZXY"  # this file mixes orders
    assert cmu.channels[sk.index("Head_end")] == () and cmu.euler_orders[sk.index("Head_end")] == ""

    no_ends = read_bvh(EXCERPT, length_unit_m=CMU_UNIT_M, end_sites=False)
    assert no_ends.skeleton.num_segments == 31
    assert no_ends.skeleton.names == tuple(joints)


def test_cmu_excerpt_units_and_up_axis(cmu):
    sk = cmu.skeleton
    # OFFSET 2.49329 -6.85026 0.00000 of LeftKnee, Y up, in 1/0.45 inch → Z up metres.
    np.testing.assert_allclose(sk.offsets[sk.index("LeftKnee")], np.array([2.49329, 0.0, -6.85026]) * CMU_UNIT_M, atol=1e-12)
    np.testing.assert_allclose(sk.offsets[sk.index("LeftToe_end")], np.array([0.0, -1.13491, 0.0]) * CMU_UNIT_M, atol=1e-12)
    # First frame's root position 4.8105 17.0973 -20.3817 (x, y up, z).
    np.testing.assert_allclose(cmu.motion.root_position[0], np.array([4.8105, 20.3817, 17.0973]) * CMU_UNIT_M, atol=1e-12)
    raw = read_bvh(EXCERPT, up_axis="z")
    np.testing.assert_allclose(raw.skeleton.offsets[sk.index("LeftKnee")], [2.49329, -6.85026, 0.0], atol=1e-12)

    head, feet = sk.index("Head"), [sk.index("LeftToe"), sk.index("RightToe")]
    for pos in (joint_positions(sk, sk.rest_motion()), joint_positions(sk, cmu.motion)):
        pos = np.asarray(pos)
        height = pos[..., head, 2] - pos[..., feet, 2].max(axis=-1)
        assert np.all(height > 1.0), height
        assert np.all(height < 2.0), height


def test_cmu_excerpt_rotations_follow_channel_order(cmu):
    """A joint's rotation equals A (R_c1 R_c2 R_c3) Aᵀ built from the file's numbers."""
    lines = EXCERPT.read_text().splitlines()
    first = np.array(lines[lines.index("Frame Time: .0083333") + 1].split(), dtype=float)
    sk = cmu.skeleton
    # Channel columns: root 0..5, then 3 per joint in file order.
    col = {n: 6 + 3 * (k - 1) for k, n in enumerate(x for x in sk.names if not x.endswith("_end"))}
    for name in ("Hips", "LeftHip", "LeftKnee", "RThumb"):
        j = sk.index(name)
        vals = first[3:6] if j == 0 else first[col[name] : col[name] + 3]
        expected = A @ euler_reference(np.deg2rad(vals), cmu.euler_orders[j]) @ A.T
        np.testing.assert_allclose(matrix_from_quat(np.asarray(cmu.motion.rotations[0, j])), expected, atol=1e-12)


# ---- round trips ----------------------------------------------------------------------------------


def _compare_by_name(sk_a, m_a, sk_b, m_b, names):
    pa, pb = np.asarray(joint_positions(sk_a, m_a)), np.asarray(joint_positions(sk_b, m_b))
    ia = [sk_a.index(n) for n in names]
    ib = [sk_b.index(n) for n in names]
    np.testing.assert_allclose(pb[:, ib], pa[:, ia], rtol=0, atol=1e-9)
    ang = np.asarray(rotation_angle(m_a.rotations[:, ia], m_b.rotations[:, ib]))
    assert ang.max() < 1e-9, ang.max()


@pytest.mark.parametrize("order", ["ZXY", "XYZ", "YZX"])
def test_round_trip_cmu(cmu, tmp_path, order):
    out = write_bvh(tmp_path / "out.bvh", cmu.skeleton, cmu.motion, cmu.frame_time_s, length_unit_m=CMU_UNIT_M, euler_order=order)
    back = read_bvh(out, length_unit_m=CMU_UNIT_M)
    assert back.skeleton.names == cmu.skeleton.names
    assert back.frame_time_s == pytest.approx(cmu.frame_time_s, rel=1e-9)
    assert set(back.euler_orders[j] for j, n in enumerate(back.skeleton.names) if not n.endswith("_end")) == {order}
    np.testing.assert_allclose(back.skeleton.offsets, cmu.skeleton.offsets, atol=1e-10)
    _compare_by_name(cmu.skeleton, cmu.motion, back.skeleton, back.motion, cmu.skeleton.names)
    assert [p.name for p in tmp_path.iterdir()] == ["out.bvh"]  # no temporary file left behind


def _toy_skeleton() -> Skeleton:
    # Level-ordered (not depth-first) numbering, a hinge, a FIXED joint with a child, a FIXED leaf and a
    # BALL leaf without an end site.
    names = ["pelvis", "spine", "thigh", "neck", "knee", "head", "toe_tip", "hand"]
    parents = [-1, 0, 0, 1, 2, 3, 4, 1]
    offsets = [[0, 0, 0], [0, 0, 0.2], [0.1, 0, -0.1], [0, 0.02, 0.4], [0, 0, -0.45], [0, 0, 0.1], [0, 0.1, -0.4], [0.3, 0, 0.1]]
    types = ["free", "ball", "ball", "fixed", "hinge", "ball", "fixed", "ball"]
    axes = np.zeros((8, 3))
    axes[4] = [1.0, 0.2, 0.0]
    return Skeleton(names, parents, offsets, types, axes)


def _random_motion(sk: Skeleton, frames: int, seed: int) -> Motion:
    import jax.numpy as jnp

    from bcmocap.geometry import SO3

    rng = np.random.default_rng(seed)
    rotvec = rng.uniform(-0.6, 0.6, size=(frames, sk.num_segments, 3))  # far from Euler gimbal lock
    q = np.asarray(SO3.exp(jnp.asarray(rotvec)).wxyz)
    q = np.asarray(sk.project_rotations(jnp.asarray(q)))
    return Motion(rng.normal(size=(frames, 3)) * [1.0, 1.0, 0.1] + [0, 0, 1.0], q)


@pytest.mark.parametrize("up_axis,unit,order", [("y", 1.0, "ZXY"), ("z", 0.01, "ZYX"), ("y", CMU_UNIT_M, "XZY")])
def test_round_trip_toy_skeleton(tmp_path, up_axis, unit, order):
    sk = _toy_skeleton()
    motion = _random_motion(sk, 7, seed=3)
    path = write_bvh(tmp_path / "toy.bvh", sk, motion, 0.04, length_unit_m=unit, up_axis=up_axis, euler_order=order)
    back = read_bvh(path, length_unit_m=unit, up_axis=up_axis)
    # Depth first: pelvis spine neck head (head_end) hand (hand_end) thigh knee toe_tip→End Site.
    assert back.skeleton.names == ("pelvis", "spine", "neck", "head", "head_end", "hand", "hand_end", "thigh", "knee", "knee_end")
    assert back.frame_time_s == pytest.approx(0.04)
    assert back.skeleton.joint_types[back.skeleton.index("knee")] == JointType.BALL  # hinges are written with 3 channels
    np.testing.assert_allclose(back.skeleton.offsets[back.skeleton.index("knee_end")], sk.offsets[sk.index("toe_tip")], atol=1e-12)
    names = [n for n in sk.names if n != "toe_tip"]
    _compare_by_name(sk, motion, back.skeleton, back.motion, names)
    p_tip = np.asarray(joint_positions(sk, motion))[:, sk.index("toe_tip")]
    np.testing.assert_allclose(np.asarray(joint_positions(back.skeleton, back.motion))[:, back.skeleton.index("knee_end")], p_tip, atol=1e-9)


def test_write_is_atomic_and_overwrites(tmp_path, cmu):
    path = tmp_path / "motion.bvh"
    path.write_text("old contents")
    write_bvh(path, cmu.skeleton, cmu.motion[:3], cmu.frame_time_s)
    assert read_bvh(path).num_frames == 3
    assert sorted(os.listdir(tmp_path)) == ["motion.bvh"]
    with pytest.raises(ValueError, match="euler_order"):
        write_bvh(path, cmu.skeleton, cmu.motion, 0.01, euler_order="XYX")
    assert read_bvh(path).num_frames == 3  # a refused write leaves the file alone
    bad = Skeleton(["root", "left hand"], [-1, 0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="'left hand'"):
        write_bvh(tmp_path / "x.bvh", bad, bad.rest_motion(1), 0.01)


# ---- hand-written files ---------------------------------------------------------------------------

HAND = """HIERARCHY
ROOT Base
{
\tOFFSET 1 2 3
\tCHANNELS 6 Yrotation Xposition Xrotation Zposition Zrotation Yposition
\tJOINT Upper
\t{
\t\tOFFSET 0 1 0
\t\tCHANNELS 3 Xrotation Yrotation Zrotation
\t\tJOINT Elbow
\t\t{
\t\t\tOFFSET 0 0.5 0.2
\t\t\tCHANNELS 1 Zrotation
\t\t\tJOINT Wrist
\t\t\t{
\t\t\t\tOFFSET 0.5 0 0
\t\t\t\tCHANNELS 2 Yrotation Xrotation
\t\t\t\tEnd Site
\t\t\t\t{
\t\t\t\t\tOFFSET 0.1 0 0
\t\t\t\t}
\t\t\t}
\t\t}
\t}
\tJOINT Side Bar
\t{
\t\tOFFSET -1 0 0
\t\tCHANNELS 0
\t\tJOINT Tip {
\t\t\tOFFSET 0 0 -1
\t\t\tCHANNELS 3 Yrotation Zrotation Xrotation
\t\t\tEnd Site
\t\t\t{
\t\t\t\tOFFSET 0 0 -0.3
\t\t\t}
\t\t}
\t}
}
MOTION
Frames:    3
Frame Time: 0.5
10 0.5 20 -0.25 30 1.5   15 -25 35   40   -5 12   50 -60 70
0 0 0 0 0 0   0 0 0   0   0 0   0 0 0
-80 0 45 0 -120 0   89 10 -170   -90   33 -44   -10 20 -30
"""


def _hand_file(tmp_path, text=HAND, newline="\r\n", name="hand.bvh") -> Path:
    path = tmp_path / name
    path.write_bytes(text.replace("\n", newline).encode())
    return path


def test_hand_written_channel_orders(tmp_path):
    data = read_bvh(_hand_file(tmp_path), length_unit_m=0.5)
    sk = data.skeleton
    assert sk.names == ("Base", "Upper", "Elbow", "Wrist", "Wrist_end", "Side Bar", "Tip", "Tip_end")
    assert sk.joint_types == (
        JointType.FREE, JointType.BALL, JointType.HINGE, JointType.BALL, JointType.FIXED,
        JointType.FIXED, JointType.BALL, JointType.FIXED,
    )  # fmt: skip
    assert data.euler_orders == ("YXZ", "XYZ", "Z", "YX", "", "", "YZX", "")
    # The hinge axis is the file's Z, i.e. -Y in the Z-up world.
    np.testing.assert_allclose(sk.hinge_axes[2], [0.0, -1.0, 0.0], atol=1e-15)
    assert data.frame_time_s == 0.5

    file_offsets = np.array([[0, 0, 0], [0, 1, 0], [0, 0.5, 0.2], [0.5, 0, 0], [0.1, 0, 0], [-1, 0, 0], [0, 0, -1], [0, 0, -0.3]])
    parents = [-1, 0, 1, 2, 3, 0, 5, 6]
    rows = [np.array(r.split(), dtype=float) for r in HAND.split("Frame Time: 0.5\n")[1].splitlines()]
    for f, row in enumerate(rows):
        # Root: Yrot Xpos Xrot Zpos Zrot Ypos (+ OFFSET 1 2 3).
        root = np.array([1 + row[1], 2 + row[5], 3 + row[3]])
        rots = [
            euler_reference(np.deg2rad([row[0], row[2], row[4]]), "YXZ"),
            euler_reference(np.deg2rad(row[6:9]), "XYZ"),
            euler_reference(np.deg2rad(row[9:10]), "Z"),
            euler_reference(np.deg2rad(row[10:12]), "YX"),
            np.eye(3),
            np.eye(3),
            euler_reference(np.deg2rad(row[12:15]), "YZX"),
            np.eye(3),
        ]
        expected = fk_reference(parents, file_offsets, rots, root) @ A.T * 0.5
        got = np.asarray(joint_positions(sk, data.motion[f]))
        np.testing.assert_allclose(got, expected, atol=1e-12)
        # The hinge's rotation is about its axis.
        q = np.asarray(data.motion.rotations[f, 2])
        assert abs(np.dot(q[1:], [1.0, 0, 0])) < 1e-12 and abs(np.dot(q[1:], [0, 0, 1.0])) < 1e-12


def test_line_endings_and_blank_lines(tmp_path):
    crlf = read_bvh(_hand_file(tmp_path, newline="\r\n", name="a.bvh"))
    lf = read_bvh(_hand_file(tmp_path, newline="\n", name="b.bvh"))
    cr = read_bvh(_hand_file(tmp_path, text=HAND.replace("MOTION\n", "\nMOTION\n\n") + "\n\n", newline="\r", name="c.bvh"))
    for other in (lf, cr):
        np.testing.assert_array_equal(np.asarray(other.motion.rotations), np.asarray(crlf.motion.rotations))
        np.testing.assert_array_equal(np.asarray(other.skeleton.offsets), np.asarray(crlf.skeleton.offsets))


# ---- errors ---------------------------------------------------------------------------------------


def _line_of(text: str, needle: str) -> int:
    return next(k for k, line in enumerate(text.split("\n"), 1) if needle in line)


def test_error_truncated_frame(tmp_path):
    lines = EXCERPT.read_bytes().decode().splitlines()
    lines[-1] = " ".join(lines[-1].split()[:90])  # the last frame line is cut short
    path = tmp_path / "cut.bvh"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=re.escape(f"{path}:{len(lines)}: expected 96 numbers per frame, found 90")):
        read_bvh(path)


def test_error_missing_frames(tmp_path):
    lines = EXCERPT.read_bytes().decode().splitlines()
    path = tmp_path / "short.bvh"
    path.write_text("\n".join(lines[:-2]) + "\n")
    frames_line = next(k for k, line in enumerate(lines, 1) if line.startswith("Frames:"))
    msg = f"{path}:{len(lines) - 2}: expected 40 frames ('Frames:' on line {frames_line}), the file ends after 38"
    with pytest.raises(ValueError, match=re.escape(msg)):
        read_bvh(path)


def test_error_extra_numbers_and_bad_number(tmp_path):
    text = HAND.replace("0 0 0 0 0 0   0 0 0   0   0 0   0 0 0", "0 0 0 0 0 0   0 0 0   0   0 0   0 0 0 7")
    path = _hand_file(tmp_path, text)
    line = _line_of(text, " 0 0 0 7")
    with pytest.raises(ValueError, match=re.escape(f"{path}:{line}: expected 15 numbers per frame, found 16")):
        read_bvh(path)
    text = HAND.replace("0 0 0 0 0 0   0 0 0   0   0 0   0 0 0", "0 0 0 0 0 0   0 0 0   0   0 x   0 0 0")
    path = _hand_file(tmp_path, text)
    with pytest.raises(ValueError, match=re.escape(f"{path}:{_line_of(text, ' 0 x ')}: expected 15 numbers per frame, found 'x'")):
        read_bvh(path)


@pytest.mark.parametrize(
    "old,new,needle,message",
    [
        ("CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 3 Xrotation Yposition Zrotation", "Xrotation Yposition",
         "joint 'Upper' has position channels ['Yposition']; only the ROOT may translate"),
        ("CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 3 Xrotation Yrotation Wrotation", "Wrotation",
         "expected 3 channel names for 'Upper' (Xposition … Zrotation), found 'Wrotation'"),
        ("OFFSET 0 0.5 0.2", "OFFSET 0 0.5 z", "OFFSET 0 0.5 z", "expected 3 numbers for OFFSET, found 'z'"),
        ("Frames:    3", "Frames: three", "Frames: three", "expected 'Frames: <count>', found 'Frames: three'"),
        ("\t\t\t\tEnd Site", "\t\t\t\tEnd Point", "End Point", "expected 'Site' after 'End', found 'Point'"),
    ],
)  # fmt: skip
def test_error_messages_name_file_and_line(tmp_path, old, new, needle, message):
    text = HAND.replace(old, new)
    assert text != HAND
    path = _hand_file(tmp_path, text)
    with pytest.raises(ValueError, match=re.escape(f"{path}:{_line_of(text, needle)}: {message}")):
        read_bvh(path)


def test_error_missing_motion_section(tmp_path):
    text = HAND.split("MOTION")[0]
    path = _hand_file(tmp_path, text)
    with pytest.raises(ValueError, match=re.escape(f"{path}:") + r"\d+: expected a 'MOTION' line"):
        read_bvh(path)
    text = HAND.replace("\t\t}\n\t}\n}\nMOTION", "\t\t}\n\t}\nMOTION")  # a brace missing
    path = _hand_file(tmp_path, text)
    with pytest.raises(ValueError, match=re.escape(f"{path}:{_line_of(text, 'MOTION') - 1}: expected 'JOINT', 'End Site' or '}}', found the end")):
        read_bvh(path)
