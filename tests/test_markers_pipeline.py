"""The whole marker pipeline and `bcmocap markers` on small simulated captures (and its errors)."""

import json

import numpy as np
import pytest

from bcmocap.cli import main
from bcmocap.io import read_bvh
from bcmocap.markers import MarkerOptions, MarkerTrajectories, fit_marker_skeleton
from bcmocap.sim.markers import MarkerNoise, linkage_markers, linkage_motion, linkage_skeleton, simulate_markers
from conftest import one_line_error
from test_io_c3d import write_c3d

LENGTHS = (0.30, 0.341, 0.30)


def linkage_capture(seed=5, seconds=8.0, fps=60.0, noise=None, frozen_second_joint=False):
    skeleton = linkage_skeleton(LENGTHS)
    motion = linkage_motion(seconds, fps, seed=seed)
    if frozen_second_joint:
        rot = np.array(motion.rotations)
        rot[:, 2] = rot[0, 2]
        motion = type(motion)(motion.root_position, rot)
    noise = noise or MarkerNoise(sigma_m=0.0005, spike_probability=1e-3, gap_rate_hz=0.05, gap_seconds=(0.05, 0.2),
                                 relabel_after_gap=1.0, label_break_rate_hz=0.0)
    return simulate_markers(skeleton, motion, linkage_markers(LENGTHS, seed=seed), fps, noise, seed=seed)


def middle_length(result):
    s = result.skeleton
    j = int(np.argmax([sum(label.startswith("R2") for label in result.segment_markers(k)) for k in range(3)]))
    pts = ([np.zeros(3)] if j else []) + [np.asarray(s.offsets[c]) for c in s.children(j)]
    return float(np.linalg.norm(pts[0] - pts[1]))


@pytest.mark.slow
def test_cli_on_a_c3d_file_with_broken_labels(tmp_path, capsys):
    sim = linkage_capture()
    assert len(sim.labels) > 9  # gaps gave new labels: the pipeline must merge them back
    path = write_c3d(tmp_path / "linkage.c3d", sim.positions, sim.labels, rate=60.0, units="mm")
    out = tmp_path / "out"
    assert main(["markers", str(path), "--out", str(out), "--groups", "3"]) == 0
    text = capsys.readouterr().out
    assert "merged" in text and "topology (root first" in text
    assert "verdict: NOT a human body" in text and "try: --groups 4" in text  # three rods are no body
    desc = json.loads((out / "skeleton.json").read_text())
    assert desc["verdict"]["human"] is False and "left_leg" in desc["verdict"]["wrong_limbs"]
    assert desc["verdict"]["fixes"]["left_leg"].startswith("--groups 4")
    assert all(segment["label"] == "extra" for segment in desc["segments"])
    assert len(desc["segments"]) == 3 and desc["fps"] == 60.0 and len(desc["markers"]) == 9
    lengths = [v for k, v in desc["segment_lengths_m"].items() if k.startswith(desc["segments"][0]["name"])]
    assert lengths == pytest.approx([LENGTHS[1]], abs=0.005)  # the middle rod is the root, two joints
    bvh = read_bvh(out / "skeleton.bvh", up_axis="z")
    assert bvh.num_frames == sim.positions.shape[0] and bvh.frame_time_s == pytest.approx(1 / 60)
    poses = np.load(out / "poses.npz")
    assert poses["marker_positions"].shape == (sim.positions.shape[0], 9, 3)
    assert (out / "report.txt").read_text().startswith(f"{sim.positions.shape[0]} frames at 60 Hz")


@pytest.mark.slow
def test_pipeline_on_an_array_fills_gaps_and_recovers_the_middle_rod():
    sim = linkage_capture(seed=6, noise=MarkerNoise(sigma_m=0.0005, spike_probability=0.0, gap_rate_hz=0.1,
                                                       gap_seconds=(0.1, 0.3), relabel_after_gap=0.0, label_break_rate_hz=0.0))
    traj = MarkerTrajectories.from_array(sim.positions, sim.fps, sim.labels)
    result = fit_marker_skeleton(traj, MarkerOptions(num_groups=3))
    assert middle_length(result) == pytest.approx(LENGTHS[1], abs=0.004)
    gaps = ~np.isfinite(result.trajectories.positions[..., 0])
    assert gaps.any()
    # the model markers fill the gaps where the true (noise-free) markers are
    truth = sim.true_positions[:, [sim.marker_names.index(x) for x in result.trajectories.labels]]
    err = np.linalg.norm(result.ik.marker_positions - truth, axis=-1)
    assert np.median(err[gaps]) < 0.005 and np.median(err[~gaps]) < 0.003
    assert result.skeleton.joint_types[0].name == "FREE" and all(t.name == "BALL" for t in result.skeleton.joint_types[1:])


@pytest.mark.slow
def test_a_joint_not_exercised_is_reported():
    sim = linkage_capture(seed=7, frozen_second_joint=True,
                          noise=MarkerNoise(sigma_m=0.0005, spike_probability=0.0, gap_rate_hz=0.0, label_break_rate_hz=0.0))
    traj = MarkerTrajectories.from_array(sim.positions, sim.fps, sim.labels)
    with pytest.warns(UserWarning, match=r"the joint between segments '.*' and '.*' is not exercised"):
        fit_marker_skeleton(traj, MarkerOptions(num_groups=3))


@pytest.mark.slow
def test_too_few_segments_are_reported_as_not_rigid():
    """Three rods forced into two groups: one group spans a joint, and the report says which markers show it;
    with the right count no segment is flagged."""
    sim = linkage_capture(seed=9, seconds=4.0, noise=MarkerNoise.clean())
    traj = MarkerTrajectories.from_array(sim.positions, sim.fps, sim.labels)
    with pytest.warns(UserWarning, match=r"segment '.*' is not rigid: R\d\S* and R\d\S* vary in distance by \d+ mm .* try more"):
        two = fit_marker_skeleton(traj, MarkerOptions(num_groups=2))
    assert any("is not rigid" in n for n in two.notes) and "is not rigid" in two.report()
    three = fit_marker_skeleton(traj, MarkerOptions(num_groups=3))
    assert not any("is not rigid" in n for n in three.notes)


def test_bad_input_is_named(tmp_path, capsys):
    sim = linkage_capture(seed=8, noise=MarkerNoise.clean())
    p = sim.positions.copy()
    p[:, 4] = np.nan
    traj = MarkerTrajectories.from_array(p, sim.fps, sim.labels)
    with pytest.raises(ValueError, match=r"cannot split 8 markers into 9 groups"):
        with pytest.warns(UserWarning, match=r"markers with no data were ignored: \['R2M2'\]"):
            fit_marker_skeleton(traj, MarkerOptions(num_groups=9))
    assert main(["markers", str(tmp_path / "missing.c3d"), "--out", str(tmp_path / "o")]) == 2
    assert "no such file" in capsys.readouterr().err
    np.save(tmp_path / "a.npy", sim.positions)
    assert main(["markers", str(tmp_path / "a.npy"), "--out", str(tmp_path / "o")]) == 2
    assert "needs --fps" in capsys.readouterr().err


@pytest.mark.parametrize("frames, culprit", [("abc", "--frames must be FIRST:LAST"), ("7", "--frames must be FIRST:LAST"),
                                             ("5:5", "leaves 0 of the 30 frames"), ("5:6", "leaves 1 of the 30 frames"),
                                             ("20:10", "leaves 0 of the 30 frames")])
def test_a_bad_frame_range_is_named(tmp_path, capsys, frames, culprit):
    np.save(tmp_path / "a.npy", np.random.default_rng(0).normal(size=(30, 4, 3)))
    out = tmp_path / "out"
    assert main(["markers", str(tmp_path / "a.npy"), "--fps", "60", "--frames", frames, "--out", str(out)]) == 2
    one_line_error(capsys, "markers", culprit)
    assert not out.exists()


def test_markers_left_out_with_drop_and_an_unknown_one_named(tmp_path, capsys):
    np.save(tmp_path / "a.npy", np.random.default_rng(0).normal(size=(30, 4, 3)))
    out = tmp_path / "out"
    assert main(["markers", str(tmp_path / "a.npy"), "--fps", "60", "--drop", "m9", "--out", str(out)]) == 2
    one_line_error(capsys, "markers", "--drop m9: no such marker in")
    assert not out.exists()
    from argparse import Namespace

    from bcmocap.markers.command import _load

    trajectories, note = _load(Namespace(file=str(tmp_path / "a.npy"), fps=60.0, frames=None, drop=["m1", "m3"],
                                         markers=None, keep_modelled=False))
    assert trajectories.labels == ("m0", "m2") and "dropped 2 markers" in note


@pytest.mark.slow  # two fits of a real 3 s file
def test_the_full_body_file_is_human_with_the_names_and_the_names_can_be_left_out(tmp_path, capsys):
    """BTK's Plug-in Gait walk: with its names (LTHI, RKNE…) a human body; `--ignore-names` fits it from the
    motion alone, into other segments."""
    from test_markers import FULL_BODY

    assert main(["markers", str(FULL_BODY), "--out", str(tmp_path / "named")]) == 0
    named = json.loads((tmp_path / "named" / "skeleton.json").read_text())
    assert named["verdict"]["human"] and any("names follow a known marker set" in n for n in named["notes"])
    assert main(["markers", str(FULL_BODY), "--out", str(tmp_path / "unnamed"), "--ignore-names"]) == 0
    unnamed = json.loads((tmp_path / "unnamed" / "skeleton.json").read_text())
    assert not any("names follow" in n for n in unnamed["notes"])
    groups = lambda fit: {frozenset(s["markers"]) for s in fit["segments"]}  # noqa: E731
    assert groups(unnamed) != groups(named)
