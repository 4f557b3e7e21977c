"""A BVH written by bcmocap loads in an independent reader (PyPI ``bvh``) and means the same motion there.

The ``bvh`` package only tokenises the file; joint positions are recomputed here from its offsets and
channel values with plain numpy (Rodrigues rotations multiplied in channel order, the usual BVH reading)
and compared with bcmocap's forward kinematics of the motion that was written.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_skeleton, quat_matrix, random_motion

from bcmocap.io import read_bvh, write_bvh
from bcmocap.kinematics import joint_positions

bvh = pytest.importorskip("bvh")

A = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # file (Y up) → bcmocap world (Z up)
UNIT_M = 0.01  # the file is written in centimetres
FRAME_TIME = 1 / 60
ORDER = "ZXY"
FRAMES = 5


def rodrigues(axis: str, degrees: float) -> np.ndarray:
    k = np.zeros(3)
    k["XYZ".index(axis)] = 1.0
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.deg2rad(degrees)
    return np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx


def channel_rotation(channels: list[str], values: list[float]) -> np.ndarray:
    out = np.eye(3)
    for name, v in zip(channels, values):
        if name.endswith("rotation"):
            out = out @ rodrigues(name[0].upper(), v)
    return out


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    skeleton = make_skeleton()  # pelvis torso head thigh shin(hinge) foot(fixed leaf)
    motion = random_motion(skeleton, FRAMES, np.random.default_rng(11), max_angle=1.0)
    path = tmp_path_factory.mktemp("bvh") / "toy.bvh"
    write_bvh(path, skeleton, motion, FRAME_TIME, length_unit_m=UNIT_M, up_axis="y", euler_order=ORDER)
    mocap = bvh.Bvh(path.read_text())
    return skeleton, motion, path, mocap


def test_structure_in_independent_reader(written):
    skeleton, _, _, mocap = written
    # The FIXED leaf 'foot' becomes the End Site of 'shin'; every other segment is a joint, depth first.
    assert mocap.get_joints_names() == ["pelvis", "torso", "head", "thigh", "shin"]
    assert [mocap.joint_parent_index(n) for n in mocap.get_joints_names()] == [-1, 0, 1, 0, 3]
    rot = [f"{a}rotation" for a in ORDER]
    assert mocap.joint_channels("pelvis") == ["Xposition", "Yposition", "Zposition", *rot]
    for name in ("torso", "head", "thigh", "shin"):
        assert mocap.joint_channels(name) == rot  # the hinge too: readers expect 3 channels
    assert mocap.nframes == FRAMES
    assert mocap.frame_time == pytest.approx(FRAME_TIME, rel=1e-9)
    assert all(len(frame) == 6 + 3 * 4 for frame in mocap.frames)
    offsets = np.asarray(skeleton.offsets)
    for name in ("torso", "head", "thigh", "shin"):
        np.testing.assert_allclose(mocap.joint_offset(name), offsets[skeleton.index(name)] @ A / UNIT_M, atol=1e-9)
    (end_site,) = list(mocap.get_joint("shin").filter("End"))
    np.testing.assert_allclose([float(v) for v in end_site["OFFSET"]], offsets[skeleton.index("foot")] @ A / UNIT_M, atol=1e-9)
    # 'head' is a BALL leaf: it gets a zero End Site so that the file stays valid BVH.
    (head_end,) = list(mocap.get_joint("head").filter("End"))
    assert [float(v) for v in head_end["OFFSET"]] == [0.0, 0.0, 0.0]


def test_channel_values_in_independent_reader(written):
    skeleton, motion, _, mocap = written
    root = np.asarray(motion.root_position)
    rotations = quat_matrix(np.asarray(motion.rotations))  # (F, J, 3, 3), textbook formula in conftest
    pos_channels = ["Xposition", "Yposition", "Zposition"]
    rot_channels = [f"{a}rotation" for a in ORDER]
    for f in range(FRAMES):
        # Y-up file: (x, y, z)_file = (x, z, -y)_world, in centimetres.
        np.testing.assert_allclose(mocap.frame_joint_channels(f, "pelvis", pos_channels), root[f] @ A / UNIT_M, atol=1e-8)
        for name in mocap.get_joints_names():
            got = channel_rotation(rot_channels, mocap.frame_joint_channels(f, name, rot_channels))
            want = A.T @ rotations[f, skeleton.index(name)] @ A
            np.testing.assert_allclose(got, want, atol=1e-9, err_msg=f"frame {f}, joint {name}")
    # Spot values, written with at most 10 decimals.
    x = mocap.frame_joint_channel(2, "pelvis", "Xposition")
    assert x == pytest.approx(root[2, 0] / UNIT_M, abs=1e-9)


def test_independent_forward_kinematics_matches_bcmocap(written):
    skeleton, motion, _, mocap = written
    names = mocap.get_joints_names()
    parents = [mocap.joint_parent_index(n) for n in names]
    want = np.asarray(joint_positions(skeleton, motion))  # (F, J, 3) m, Z up
    for f in range(FRAMES):
        world: list[np.ndarray] = []
        pos: list[np.ndarray] = []
        for j, name in enumerate(names):
            channels = mocap.joint_channels(name)
            r = channel_rotation(channels, mocap.frame_joint_channels(f, name, channels))
            if parents[j] < 0:
                pos.append(np.array(mocap.joint_offset(name)) + mocap.frame_joint_channels(f, name, channels[:3]))
                world.append(r)
            else:
                p = parents[j]
                pos.append(pos[p] + world[p] @ np.array(mocap.joint_offset(name)))
                world.append(world[p] @ r)
        (end_site,) = list(mocap.get_joint("shin").filter("End"))
        shin = names.index("shin")
        foot = pos[shin] + world[shin] @ np.array([float(v) for v in end_site["OFFSET"]])
        got = np.array(pos + [foot]) @ A.T * UNIT_M  # back to the Z-up world in metres
        order = [skeleton.index(n) for n in (*names, "foot")]
        np.testing.assert_allclose(got, want[f, order], atol=1e-6, err_msg=f"frame {f}")


def test_bcmocap_reads_the_same_file_back(written):
    skeleton, motion, path, mocap = written
    back = read_bvh(path, length_unit_m=UNIT_M, up_axis="y")
    assert back.num_frames == FRAMES
    assert back.frame_time_s == pytest.approx(FRAME_TIME, rel=1e-9)
    assert back.skeleton.names == ("pelvis", "torso", "head", "head_end", "thigh", "shin", "shin_end")
    assert [len(c) for c in back.channels] == [len(mocap.joint_channels(n)) if n in mocap.get_joints_names() else 0 for n in back.skeleton.names]
    want = np.asarray(joint_positions(skeleton, motion))
    got = np.asarray(joint_positions(back.skeleton, back.motion))
    pairs = [(n, n) for n in ("pelvis", "torso", "head", "thigh", "shin")] + [("foot", "shin_end"), ("head", "head_end")]
    for ours, theirs in pairs:
        np.testing.assert_allclose(
            got[:, back.skeleton.index(theirs)], want[:, skeleton.index(ours)], atol=1e-6, err_msg=f"{ours} vs {theirs}"
        )
