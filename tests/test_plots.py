"""PNG figures: each function writes a real PNG, overwrites atomically, survives NaN and rejects bad shapes."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from bcmocap.eval.plots import (
    plot_camera_centres,
    plot_joint_angles,
    plot_joint_positions,
    plot_skeleton_poses,
    plot_top_view,
)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
T, J, C = 12, 5, 3
PARENTS = np.array([-1, 0, 1, 0, 3])
NAMES = ["pelvis", "spine", "head", "thigh", "foot"]
DPI = 40


@pytest.fixture
def data():
    rng = np.random.default_rng(0)
    times = np.arange(T) / 60.0
    angles = rng.uniform(0, 90, size=(T, J))
    positions = rng.normal(size=(T, J, 3)) * 0.3 + [0, 0, 1]
    cams = rng.normal(size=(T, C, 3))
    scene = rng.normal(size=(300, 3)) * [4, 4, 1]
    angles[3, 1] = np.nan
    positions[4, 2] = np.nan
    cams[5, 1] = np.nan
    cams[:, 2] = np.nan  # a camera never registered
    scene[7] = np.nan
    return {"times": times, "angles": angles, "positions": positions, "cams": cams, "scene": scene}


def calls(d):
    """One (name, function of a path) per plotting function, with truth and NaN where they apply."""
    return {
        "angles": lambda p: plot_joint_angles(p, d["times"], d["angles"], NAMES, d["angles"] + 1.0, max_joints=4, dpi=DPI),
        "positions": lambda p: plot_joint_positions(p, d["times"], d["positions"], NAMES, d["positions"] + 0.01, parents=PARENTS, dpi=DPI),
        "centres": lambda p: plot_camera_centres(p, d["cams"] + 0.05, d["cams"], d["cams"] - 0.02, dpi=DPI),
        "top": lambda p: plot_top_view(p, d["scene"], d["positions"][:, 0], d["cams"], d["positions"][:, 0] + 0.02, dpi=DPI),
        "skeleton": lambda p: plot_skeleton_poses(p, d["positions"], PARENTS, [0, 4, -1], d["scene"], dpi=DPI),
    }


@pytest.mark.slow
@pytest.mark.parametrize("name", ["angles", "positions", "centres", "top", "skeleton"])
def test_writes_png_and_overwrites_atomically(tmp_path, data, name):
    draw = calls(data)[name]
    target = tmp_path / "out" / f"{name}.png"  # the folder is created
    stale = b"not a png"
    target.parent.mkdir()
    target.write_bytes(stale)
    got = draw(target)
    assert got == target
    first = target.read_bytes()
    assert first[:8] == PNG_SIGNATURE and len(first) > 1000
    inode = target.stat().st_ino
    data["positions"] *= 1.5
    data["angles"] += 10.0
    data["cams"] *= 2.0
    draw(target)
    second = target.read_bytes()
    assert second[:8] == PNG_SIGNATURE
    assert target.stat().st_ino != inode  # replaced by rename, not rewritten in place
    assert second != first
    assert sorted(p.name for p in target.parent.iterdir()) == [f"{name}.png"]  # no temporary left


def test_optional_arguments_absent(tmp_path, data):
    """Without ground truth, scene or cameras, and with a whole NaN column, every function still draws."""
    d = data
    d["angles"][:, 0] = np.nan
    outs = [
        plot_joint_angles(tmp_path / "a.png", d["times"], d["angles"], NAMES, dpi=DPI),
        plot_joint_positions(tmp_path / "b.png", d["times"], d["positions"], NAMES, joints=[2], dpi=DPI),
        plot_camera_centres(tmp_path / "c.png", d["cams"], d["cams"], dpi=DPI),
        plot_top_view(tmp_path / "d.png", np.zeros((0, 3)), d["positions"][:, 0], dpi=DPI),
        plot_skeleton_poses(tmp_path / "e.png", d["positions"], PARENTS, [1], dpi=DPI),
    ]
    for out in outs:
        assert out.read_bytes()[:8] == PNG_SIGNATURE


@pytest.mark.parametrize(
    "call,message",
    [
        (lambda d, p: plot_joint_angles(p, d["times"][:-1], d["angles"], NAMES), r"angles_deg must have shape \(11, ·\)"),
        (lambda d, p: plot_joint_angles(p, d["times"], d["angles"], NAMES[:3]), "names must have 5 entries"),
        (lambda d, p: plot_joint_angles(p, d["times"], d["angles"], NAMES, d["angles"][:, :2]), r"truth_deg must have shape \(12, 5\)"),
        (lambda d, p: plot_joint_angles(p, d["times"][:, None], d["angles"], NAMES), r"times must have shape \(·,\)"),
        (lambda d, p: plot_joint_positions(p, d["times"], d["positions"][..., :2], NAMES), r"positions must have shape \(12, ·, 3\)"),
        (lambda d, p: plot_joint_positions(p, d["times"], d["positions"], NAMES, d["positions"][:3]), "truth must have shape"),
        (lambda d, p: plot_joint_positions(p, d["times"], d["positions"], NAMES, joints=[9]), "joints must be 1 to 8 indices"),
        (lambda d, p: plot_camera_centres(p, d["cams"], d["cams"][:, :2]), r"after must have shape \(12, 3, 3\)"),
        (lambda d, p: plot_camera_centres(p, d["cams"][0], d["cams"]), r"before must have shape \(·, ·, 3\)"),
        (lambda d, p: plot_top_view(p, d["scene"][:, :2], d["positions"][:, 0]), r"scene_points must have shape \(·, 3\)"),
        (lambda d, p: plot_top_view(p, d["scene"], d["positions"][:, 0], d["cams"][:5]), r"camera_paths must have shape \(12, ·, 3\)"),
        (lambda d, p: plot_top_view(p, d["scene"], d["positions"][:, 0], None, d["positions"][:4, 0]), "truth_root_path must have shape"),
        (lambda d, p: plot_skeleton_poses(p, d["positions"], PARENTS[:3], [0]), r"parents must be \(5,\) integers"),
        (lambda d, p: plot_skeleton_poses(p, d["positions"], [-1, 0, 2, 0, 3], [0]), r"parents\[2\] = 2"),
        (lambda d, p: plot_skeleton_poses(p, d["positions"], PARENTS, list(range(7))), "frames must be 1 to 6 indices"),
        (lambda d, p: plot_skeleton_poses(p, d["positions"], PARENTS, [12]), "frames must be 1 to 6 indices"),
        (lambda d, p: plot_skeleton_poses(p, d["positions"], PARENTS, [0], d["scene"].T), r"scene_points must have shape"),
    ],
)
def test_shape_errors_name_the_argument(tmp_path, data, call, message):
    with pytest.raises(ValueError, match=message):
        call(data, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()
