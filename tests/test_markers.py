"""The marker pipeline's pieces: preprocessing, spectral clustering, segmentation, joints, rigid fit, identities."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bcmocap.io import read_c3d
from bcmocap.kinematics import joint_positions
from bcmocap.markers import (
    MarkerTrajectories,
    build_skeleton,
    distance_std,
    eigengap,
    joint_cost_matrix,
    joint_objective,
    merge_identities,
    minimum_spanning_tree,
    preprocess,
    procrustes,
    segment_markers,
    solve_joints,
    spectral_clustering,
)
from bcmocap.sim.markers import MarkerNoise, linkage_markers, linkage_motion, linkage_skeleton, simulate_markers
from conftest import central_difference

SAMPLE = Path(__file__).parent / "data" / "c3d" / "BTKData_c3d.org_sample01_Eb015pr.c3d"
FULL_BODY = Path(__file__).parent / "data" / "c3d" / "BTKData_PiG_PiG_Motion-FlatFoot-Full.c3d"
LENGTHS = (0.30, 0.341, 0.30)


@pytest.fixture(scope="module")
def linkage():
    """A clean-ish 8 s linkage capture at 60 Hz with its truth (identities kept)."""
    skeleton = linkage_skeleton(LENGTHS)
    markers = linkage_markers(LENGTHS, seed=3)
    motion = linkage_motion(8.0, 60.0, seed=3)
    noise = MarkerNoise(sigma_m=0.0005, spike_probability=0.0, gap_rate_hz=0.0, relabel_after_gap=0.0, label_break_rate_hz=0.0)
    sim = simulate_markers(skeleton, motion, markers, 60.0, noise, seed=3)
    return sim, MarkerTrajectories.from_array(sim.positions, 60.0, sim.marker_names)


# ---- preprocessing --------------------------------------------------------------------------------------


def test_preprocess_trims_stretch_ends_and_drops_short_markers():
    p = np.random.default_rng(0).normal(size=(200, 4, 3)) * 0.001 + np.arange(4)[None, :, None]
    p[140:150, 0] = np.nan  # a gap: 2 frames trimmed on each side
    p[:, 1] = np.nan
    p[10:30, 1] = 1.0  # seen for 20 frames = 0.2 s at 100 Hz
    p[:, 2] = np.nan  # never seen
    traj = MarkerTrajectories.from_array(p, 100.0, ["a", "b", "c", "d"])
    with pytest.warns(UserWarning, match=r"markers with no data were ignored: \['c'\]"):
        clean, rep = preprocess(traj, spike_threshold_m=None)
    assert clean.labels == ("a", "d") and rep.kept == (0, 3)
    assert dict(rep.dropped)["b"].startswith("longest visible stretch 0.16 s")
    seen = clean.visible[:, 0]
    assert not seen[138:152].any() and seen[:138].all() and seen[152:].all()
    assert rep.trimmed_samples == 4 + 4  # marker a's gap, and marker b's stretch before it was dropped


def test_preprocess_removes_jumps():
    t = np.linspace(0, 2, 200)
    p = np.stack([np.sin(t), np.cos(t), t], -1)[:, None, :].repeat(2, 1)
    p[100, 0] += [0.05, 0.0, 0.0]
    clean, rep = preprocess(MarkerTrajectories.from_array(p, 100.0), trim_frames=0)
    assert rep.spikes_removed == 1 and np.isnan(clean.positions[100, 0]).all()


def test_trajectories_reject_bad_arrays():
    with pytest.raises(ValueError, match=r"shape \(frames, markers, 3\)"):
        MarkerTrajectories.from_array(np.zeros((10, 3)), 100.0)
    with pytest.raises(ValueError, match="inf"):
        MarkerTrajectories.from_array(np.full((10, 2, 3), np.inf), 100.0)
    with pytest.raises(ValueError, match=r"duplicate marker labels \['x'\]"):
        MarkerTrajectories.from_array(np.zeros((10, 2, 3)), 100.0, ["x", "x"])
    with pytest.raises(ValueError, match="no marker left"):
        preprocess(MarkerTrajectories.from_array(np.full((10, 2, 3), np.nan), 100.0), warn=False)


# ---- spectral clustering and segmentation -----------------------------------------------------------


def test_spectral_clustering_and_eigengap_find_blocks():
    rng = np.random.default_rng(0)
    truth = np.repeat([0, 1, 2], [3, 4, 2])
    w = np.where(truth[:, None] == truth[None], 0.9, 0.02) + rng.uniform(0, 0.01, (9, 9))
    n, values = eigengap(w, max_groups=6)
    assert n == 3 and values[0] == pytest.approx(1.0)
    labels = spectral_clustering(w, 3, rng)
    assert all(len(set(labels[truth == g])) == 1 for g in range(3)) and len(set(labels)) == 3


def test_distance_std_matches_numpy():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(30, 3, 3))
    p[3, 1] = np.nan
    a = distance_std(p)
    d01 = np.linalg.norm(p[:, 0] - p[:, 1], axis=-1)
    assert a[0, 1] == pytest.approx(np.nanstd(d01, ddof=1))
    assert a[1, 0] == a[0, 1] and a[2, 2] == 0


def test_segmentation_of_the_linkage(linkage):
    sim, traj = linkage
    seg = segment_markers(traj, 3)
    truth = np.array([m.segment for m in sim.markers])
    assert all(len(set(truth[seg.groups == g])) == 1 for g in range(3))
    assert segment_markers(traj, None).num_groups == 3  # eigengap


def test_an_eigengap_that_merges_segments_is_raised_until_groups_are_rigid(linkage, monkeypatch):
    import bcmocap.markers.segmentation as segmentation

    sim, traj = linkage
    real = segmentation.eigengap
    monkeypatch.setattr(segmentation, "eigengap", lambda *args, **kwargs: (2, real(*args, **kwargs)[1]))
    merged = segment_markers(traj, None)
    assert merged.num_groups == 2 and segmentation.least_rigid(merged.distance_std, merged.groups) > 0.02
    seg = segment_markers(traj, None, rigid_tolerance_m=0.01)
    assert seg.num_groups == 3 and seg.chosen_by == "eigengap 2, raised for rigid groups (tolerance 10 mm)"
    truth = np.array([m.segment for m in sim.markers])
    assert all(len(set(truth[seg.groups == g])) == 1 for g in range(3))
    assert segmentation.least_rigid(seg.distance_std, seg.groups) < 0.01


def test_segmentation_of_a_real_c3d_file():
    """A c3d.org lower-body gait trial: pelvis, thighs, shanks and feet come out by the eigengap."""
    clean, _ = preprocess(MarkerTrajectories.from_c3d(read_c3d(SAMPLE)))
    seg = segment_markers(clean)
    assert seg.chosen_by == "eigengap" and seg.num_groups == 7
    prefix = np.array([label[:2].upper() for label in clean.labels])
    pure = sum(np.unique(prefix[seg.groups == g], return_counts=True)[1].max() for g in range(7))
    assert pure >= 24  # of 26: skin motion puts one foot and one pelvis marker with the next segment


def test_a_real_full_body_file_gives_a_human_topology():
    """Plug-in Gait, 3 s of barely moving: the eigengap's 5 groups mix a thigh into the trunk, so the count is
    raised until groups are rigid (7); the paper's Q then hangs the right thigh on the left one (two
    2-marker groups fit a joint easily), the corrected cost on the trunk with both arms and the left thigh."""
    clean, _ = preprocess(MarkerTrajectories.from_c3d(read_c3d(FULL_BODY)))
    seg = segment_markers(clean, None, rigid_tolerance_m=0.015)
    assert seg.num_groups == 7 and seg.chosen_by.startswith("eigengap 5, raised")
    group_of = {label: int(seg.groups[i]) for i, label in enumerate(clean.labels)}
    trunk, thighs = group_of["C7"], (group_of["LTHI"], group_of["RTHI"])
    assert all(group_of[x] == trunk for x in ("LASI", "RPSI", "STRN", "LFHD"))
    limbs = [group_of[x] for x in ("LELB", "RELB", "LTHI", "RTHI")]
    assert len(set(limbs)) == 4 and trunk not in limbs
    q, _ = joint_cost_matrix(clean, seg.groups, max_frames=100)
    edges = {tuple(sorted(e)) for e in minimum_spanning_tree(q)}
    assert {tuple(sorted((trunk, g))) for g in limbs} <= edges, edges
    assert tuple(sorted((group_of["LTIB"], thighs[0]))) in edges and tuple(sorted((group_of["RTIB"], thighs[1]))) in edges
    raw, _ = joint_cost_matrix(clean, seg.groups, max_frames=100, dof_corrected=False)
    assert tuple(sorted(thighs)) in {tuple(sorted(e)) for e in minimum_spanning_tree(raw)}


def test_fewer_markers_than_groups_is_an_error(linkage):
    _, traj = linkage
    with pytest.raises(ValueError, match=r"cannot split 9 markers into 12 groups \(fewer markers than groups\)"):
        segment_markers(traj, 12)


# ---- joints -----------------------------------------------------------------------------------------------


def test_joint_objective_gradient_matches_finite_differences():
    rng = np.random.default_rng(2)
    points = rng.normal(size=(6, 4, 3))
    seen = (rng.uniform(size=(6, 4)) > 0.2).astype(float)
    valid = np.array([1.0, 1.0, 1.0, 0.0])
    c = rng.normal(size=(6, 3)) * 0.3
    d = rng.uniform(0.5, 1.5, size=4)

    @jax.jit
    def f(x):
        return joint_objective(x[:18].reshape(6, 3), x[18:], points, seen, valid, 1e-3)

    x = np.concatenate([c.ravel(), d])
    grad = np.asarray(jax.grad(f)(jnp.asarray(x)))
    np.testing.assert_allclose(grad, central_difference(lambda y: np.asarray(f(y)), x), rtol=1e-6, atol=1e-9)


def test_joint_solve_recovers_the_universal_joints(linkage):
    sim, traj = linkage
    groups = np.array([int(m.segment[-1]) - 1 for m in sim.markers])
    joints = np.asarray(joint_positions(sim.skeleton, sim.motion))
    sols = solve_joints(traj, groups, [(0, 1), (1, 2)], alpha=(1e-2, 1e-4))
    for sol, j in zip(sols, (1, 2)):
        err = np.linalg.norm(sol.positions - joints[:, j], axis=-1)
        assert np.nanmedian(err) < 0.004 and np.nanmean(err) < 0.006 and sol.null_dims == 0 and sol.converged
        assert sol.rms_m < 0.002


def test_joint_costs_give_the_chain_topology(linkage):
    sim, traj = linkage
    groups = np.array([int(m.segment[-1]) - 1 for m in sim.markers])
    q, _ = joint_cost_matrix(traj, groups, max_frames=120)
    assert q[0, 2] > 3 * max(q[0, 1], q[1, 2])  # rods 1 and 3 are not connected
    assert sorted(tuple(sorted(e)) for e in minimum_spanning_tree(q)) == [(0, 1), (1, 2)]
    raw, sols = joint_cost_matrix(traj, groups, max_frames=120, dof_corrected=False)
    for sol in sols:  # each pair's cost times K / (K − 3) for its K markers
        a, b = sol.groups
        k = int((groups == a).sum() + (groups == b).sum())
        assert raw[a, b] == sol.cost and q[a, b] == pytest.approx(sol.cost * k / (k - 3))
    with pytest.raises(ValueError, match=r"no finite joint cost reaches \['c'\]"):
        minimum_spanning_tree(np.array([[np.inf, 1, np.inf], [1, np.inf, np.inf], [np.inf] * 3]), ["a", "b", "c"])


# ---- rigid bodies -----------------------------------------------------------------------------------------


def test_procrustes_recovers_a_rigid_shape_with_gaps():
    rng = np.random.default_rng(5)
    shape = rng.normal(size=(5, 3)) * 0.1
    rots = Rotation.random(40, random_state=6).as_matrix()
    pts = np.einsum("fij,nj->fni", rots, shape) + rng.normal(size=(40, 1, 3))
    pts[3, 2] = np.nan
    mean, r, t, used = procrustes(pts)
    fitted = np.einsum("fij,nj->fni", r, mean) + t[:, None]
    np.testing.assert_allclose(fitted[np.isfinite(pts)], pts[np.isfinite(pts)], atol=1e-9)
    assert used.all()


def test_rigid_skeleton_of_the_linkage(linkage):
    sim, traj = linkage
    groups = np.array([int(m.segment[-1]) - 1 for m in sim.markers])
    sols = solve_joints(traj, groups, [(0, 1), (1, 2)], alpha=(1e-2, 1e-4))
    rigid = build_skeleton(traj.positions, groups, sols, names=["a", "b", "c"])
    s = rigid.skeleton
    assert s.names[0] == "b" and s.parents == (-1, 0, 0)  # the centre of the chain is the root
    middle = np.linalg.norm(np.asarray(s.offsets[1]) - np.asarray(s.offsets[2]))
    assert middle == pytest.approx(LENGTHS[1], abs=0.003)
    assert rigid.shape_rms_m.max() < 0.003


# ---- identities -------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_identity_merging_on_the_linkage():
    skeleton = linkage_skeleton(LENGTHS)
    markers = linkage_markers(LENGTHS, seed=8)
    motion = linkage_motion(12.0, 60.0, seed=8)
    noise = MarkerNoise(spike_probability=0.0, gap_rate_hz=0.15, gap_seconds=(0.1, 0.3), label_break_rate_hz=0.0)
    sim = simulate_markers(skeleton, motion, markers, 60.0, noise, seed=8)
    assert len(sim.labels) > 12
    traj = MarkerTrajectories.from_array(sim.positions, 60.0, sim.labels)
    merged, ident = merge_identities(traj, radius_m=0.15)
    assert ident.num_markers == 9 and merged.num_markers == 9
    for k in range(9):
        assert len(set(sim.label_marker[ident.marker_of_label == k])) == 1
    with pytest.raises(ValueError, match="more than num_markers=5"):
        merge_identities(traj, 5)


def test_a_still_marker_far_from_the_body_is_dropped():
    """A marker left on the floor 2 m away (c3d.org's zerowire trial has one) is not on the body; a still foot
    among the others is kept."""
    rng = np.random.default_rng(0)
    frames = 200
    walk = np.cumsum(rng.normal(size=(frames, 1, 3)) * 0.01, axis=0)
    body = rng.normal(size=(1, 6, 3)) * 0.2 + walk
    foot = np.zeros((frames, 1, 3)) + rng.normal(size=(frames, 1, 3)) * 3e-4  # still, beside the body's start
    floor = np.array([2.0, 0.0, 0.0]) + rng.normal(size=(frames, 1, 3)) * 3e-4
    positions = np.concatenate([body, foot + body[:1, :1], floor], axis=1)
    labels = [f"m{k}" for k in range(6)] + ["foot", "floor"]
    clean, report = preprocess(MarkerTrajectories.from_array(positions, 100.0, labels), spike_threshold_m=None)
    assert "floor" not in clean.labels and "foot" in clean.labels
    assert report.dropped == (("floor", "still (within 2 mm) and over 0.4 m from every other marker: not on the body"),)
