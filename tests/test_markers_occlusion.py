"""Markers hidden by the body (issue 24): the occlusion model, gap-robust segmentation and topology, and
the pieces made faster (inverse kinematics' Jacobian and initial poses, merging only broken labels)."""

import warnings
from importlib import resources
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bcmocap.io.asf import load_cmu
from bcmocap.kinematics import Motion
from bcmocap.markers import (
    MarkerOptions,
    MarkerTrajectories,
    concurrent_labels,
    fit_marker_skeleton,
    joint_cost_matrix,
    merge_identities,
    pair_statistics,
    preprocess,
    segment_markers,
)
from bcmocap.markers import ik as marker_ik
from bcmocap.markers.joints import MIN_COVERAGE, UNKNOWN_COST_FACTOR
from bcmocap.markers.rigid import RigidSkeleton
from bcmocap.sim import reduce_motion, resample
from bcmocap.sim.markers import (
    MarkerNoise,
    Occlusion,
    calibrate_occlusion,
    calibration_motion,
    full_body_markers,
    linkage_markers,
    linkage_motion,
    linkage_skeleton,
    occlusion_margins,
    simulate_markers,
)

FLOOR = Path(__file__).parent / "data" / "cmu_floor" / "02_06_first600.amc"
LENGTHS = (0.30, 0.341, 0.30)
LABELLED = MarkerNoise(gap_rate_hz=0.0, relabel_after_gap=0.0, label_break_rate_hz=0.0)


def floor_motion(fps: float):
    """The CMU 'bend over, scoop up' excerpt (two crouches to the floor) on the camera skeleton."""
    asf = Path(str(resources.files("bcmocap") / "data" / "cmu" / "02.asf"))
    skeleton, motion = reduce_motion(*load_cmu(asf, FLOOR, fps=120.0))
    return skeleton, resample(motion, 120.0, fps)


def gap_lengths(hidden: np.ndarray) -> np.ndarray:
    """Lengths (frames) of every run of True in each column."""
    out = []
    for m in range(hidden.shape[1]):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], hidden[:, m].astype(int), [0]])))
        out += list(edges[1::2] - edges[::2])
    return np.array(out)


# ---- the occlusion model ------------------------------------------------------------------------------------


@pytest.mark.slow  # ~7 s: the heavy tier
def test_occlusion_hits_its_target_with_long_gaps_that_follow_the_motion():
    fps = 20.0
    skeleton, motion = floor_motion(fps)
    markers = full_body_markers(skeleton, jitter_m=0.01, seed=2)
    margins = occlusion_margins(skeleton, motion, markers)
    for target in (0.10, 0.25, 0.40):
        occlusion, hidden_share = calibrate_occlusion(skeleton, motion, markers, target, margins=margins)
        assert hidden_share == pytest.approx(target, abs=0.01)
    # the simulator reports exactly the markers the model leaves in sight
    sim = simulate_markers(skeleton, motion, markers, fps, LABELLED, seed=2, occlusion=occlusion)
    hidden = ~np.isfinite(sim.identified_positions()[..., 0])
    assert hidden.mean() == pytest.approx(0.40, abs=0.01)
    np.testing.assert_array_equal(hidden, margins < occlusion.margin_m)
    # Long gaps: at 25 %, most of what is missing is missing for a quarter of a second or more.
    occlusion, _ = calibrate_occlusion(skeleton, motion, markers, 0.25, margins=margins)
    hidden = margins < occlusion.margin_m
    gaps = gap_lengths(hidden)
    assert gaps[gaps >= 0.25 * fps].sum() > 0.6 * gaps.sum()
    # ... that follow the motion: more is hidden while crouching than while standing,
    pelvis = np.asarray(motion.root_position)[:, 2]
    assert hidden[pelvis < 0.8].mean() > 1.3 * hidden[pelvis > 0.95].mean()
    # ... and are shared by the markers of a segment far more than by independent dropouts.
    seg = np.array([skeleton.index(m.segment) for m in markers])
    same = [np.corrcoef(hidden[:, i], hidden[:, j])[0, 1] for i in range(len(seg)) for j in range(i + 1, len(seg))
            if seg[i] == seg[j] and hidden[:, i].std() > 0 and hidden[:, j].std() > 0]
    assert np.mean(same) > 0.15
    # Bigger capsules hide more, and so do fewer cameras.
    shares = [(margins < mu).mean() for mu in (-0.02, 0.0, 0.05, 0.1)]
    assert shares == sorted(shares) and shares[0] < shares[-1]
    few = occlusion_margins(skeleton, motion, markers, Occlusion(num_cameras=4))
    assert (few < 0.0).mean() > (margins < 0.0).mean()


# ---- gap-robust segmentation --------------------------------------------------------------------------------


def two_links_still_then_moving(hide: bool = True, fps: float = 60.0, seconds: float = 6.0):
    """Two rods joined by a hinge, turning about in space; the hinge is still in the first half and swings in
    the second. Marker b1 (on the second rod) is seen only in the first half (``hide``)."""
    n = int(seconds * fps)
    t = np.arange(n) / fps
    base = Rotation.from_rotvec(np.stack([0.3 * np.sin(0.5 * t), 0.2 * np.cos(0.4 * t), 0.4 * t], -1))
    angle = np.where(t < seconds / 2, 0.3, 0.3 + 0.9 * np.sin(2.0 * (t - seconds / 2)))
    turned = base * Rotation.from_rotvec(np.outer(angle, [0.0, 0.0, 1.0]))
    a = ([0.05, 0.02, 0.0], [0.15, -0.02, 0.01], [0.25, 0.0, 0.03])  # first rod; the hinge at (0.3, 0, 0)
    b = ([0.08, 0.02, 0.0], [0.15, -0.02, 0.02], [0.25, 0.01, -0.02])  # second rod, from the hinge
    joint = base.apply([0.3, 0.0, 0.0])
    p = np.stack([base.apply(x) for x in a] + [joint + turned.apply(x) for x in b], 1) + [0.0, 0.0, 1.0]
    p = p + np.random.default_rng(0).normal(scale=5e-4, size=p.shape)
    if hide:
        p[n // 2 :, 3] = np.nan
    return MarkerTrajectories.from_array(p, fps, ["a1", "a2", "a3", "b1", "b2", "b3"])


def test_a_pair_seen_together_only_while_still_is_not_called_rigid():
    traj = two_links_still_then_moving()
    stats = pair_statistics(traj.positions)
    # over the frames where both are seen, a1–b1 keeps its distance like a rigid pair would ...
    assert stats.std[0, 3] < 0.002 and stats.std[0, 4] > 0.01
    # ... but those frames show none of the motion around the pair: unknown, not rigid
    assert stats.coverage[0, 3] < MIN_COVERAGE and stats.coverage[0, 4] > 0.9 and stats.coverage[4, 5] == pytest.approx(1.0)
    seg = segment_markers(traj, 2)
    assert np.isnan(seg.distance_std[0, 3]) and not seg.known[0, 3]
    assert list(seg.left_out) == [3]  # b1 was never seen moving relative to anything: it cannot be placed
    assert len({*seg.groups[:3]}) == 1 and len({*seg.groups[4:]}) == 1 and seg.groups[0] != seg.groups[4]
    # seen throughout, the pair is known, and not rigid
    stats = pair_statistics(two_links_still_then_moving(hide=False).positions)
    assert stats.coverage[0, 3] > 0.9 and stats.std[0, 3] > 0.01
    assert segment_markers(two_links_still_then_moving(hide=False), 2).groups.tolist() in ([0, 0, 0, 1, 1, 1], [1, 1, 1, 0, 0, 0])


@pytest.mark.slow
def test_the_pipeline_leaves_out_a_marker_it_cannot_place():
    with pytest.warns(UserWarning, match=r"markers \['b1'\] are seen together with too few others"):
        result = fit_marker_skeleton(two_links_still_then_moving(), MarkerOptions(num_groups=2))
    assert result.trajectories.labels == ("a1", "a2", "a3", "b2", "b3") and result.skeleton.num_segments == 2


def test_joint_cost_of_groups_seen_together_only_while_still_is_unknown():
    """The linkage with its second joint still for the first half. In the second half only one marker of
    rod 2 and one of rod 3 are seen: their distance shows the joint moving, but two markers cannot place a
    joint, so the only frames that could are still ones: the pair (rod 2, rod 3) is unknown, and its cost
    is set apart."""
    skeleton = linkage_skeleton(LENGTHS)
    motion = linkage_motion(8.0, 60.0, seed=3)
    rot = np.array(motion.rotations)
    half = motion.num_frames // 2
    rot[:half, 2] = rot[half, 2]
    sim = simulate_markers(skeleton, Motion(motion.root_position, rot), linkage_markers(LENGTHS, seed=3), 60.0,
                           MarkerNoise(sigma_m=0.0005, spike_probability=0.0, gap_rate_hz=0.0, label_break_rate_hz=0.0), seed=3)
    p = sim.positions.copy()
    p[half:, [3, 4, 6, 7]] = np.nan  # rod 2 keeps marker 5 and rod 3 marker 8 in sight
    traj = MarkerTrajectories.from_array(p, 60.0, sim.labels)
    groups = np.repeat([0, 1, 2], 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        q, sols = joint_cost_matrix(traj, groups, max_frames=240)
    by = {s.groups: s for s in sols}
    assert by[(1, 2)].frames_used == 120 and by[(1, 2)].coverage < MIN_COVERAGE
    assert q[1, 2] == pytest.approx(UNKNOWN_COST_FACTOR * by[(1, 2)].cost * 6 / 3)  # K / (K − 3), unknown
    assert by[(0, 1)].coverage > 0.9 and by[(0, 2)].coverage > 0.9 and q[0, 1] < 1e-3 < q[1, 2]


@pytest.mark.slow
def test_segmentation_at_25_percent_realistic_occlusion_gives_the_true_groups():
    """68 markers on the floor-work excerpt and a range of motion, a quarter of the samples hidden by the body:
    the eigengap finds the 15 segments and every group is one segment (with the old statistics, pairs seen
    together only in some poses made groups that mix limbs)."""
    skeleton, motion = floor_motion(30.0)
    motion = Motion.concatenate([motion, calibration_motion(skeleton, motion[-1], 8.0, 30.0, seed=4)])
    markers = full_body_markers(skeleton, jitter_m=0.01, seed=4, count=68)
    occlusion, hidden = calibrate_occlusion(skeleton, motion, markers, 0.25)
    sim = simulate_markers(skeleton, motion, markers, 30.0, LABELLED, seed=4, occlusion=occlusion)
    assert hidden == pytest.approx(0.25, abs=0.01)
    clean, report = preprocess(MarkerTrajectories.from_array(sim.positions, 30.0, sim.labels), warn=False)
    seg = segment_markers(clean, None, rigid_tolerance_m=0.015)
    truth = sim.marker_segments[sim.label_marker[list(report.kept)]]
    assert seg.num_groups == 15 and len(seg.left_out) == 0
    assert all(len(set(truth[seg.groups == g])) == 1 for g in range(15))
    assert len({truth[seg.groups == g][0] for g in range(15)}) == 15


# ---- identities: only broken labels are merged -------------------------------------------------------------


def test_a_labelled_capture_with_gaps_everywhere_is_not_merged():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(300, 6, 3)) * 0.001 + rng.uniform(-0.05, 0.05, size=(6, 3))  # a rigid cluster
    for m in range(6):  # no frame sees all six markers
        p[50 * m : 50 * m + 50, m] = np.nan
    vis = np.isfinite(p[..., 0])
    assert vis.sum(1).max() == 5 and concurrent_labels(vis) == 6
    traj = MarkerTrajectories.from_array(p, 100.0)
    assert merge_identities(traj)[1].num_markers == 6
    # a marker whose label breaks after a gap: two labels one after the other, never overlapping, merged
    broken = np.concatenate([p, np.full((300, 1, 3), np.nan)], axis=1)
    broken[200:, 6], broken[200:, 0] = broken[200:, 0], np.nan
    assert concurrent_labels(np.isfinite(broken[..., 0])) == 6
    merged, ident = merge_identities(MarkerTrajectories.from_array(broken, 100.0))
    assert ident.num_markers == 6 and ident.marker_of_label[6] == ident.marker_of_label[0]


# ---- inverse kinematics ------------------------------------------------------------------------------------------


def test_inverse_kinematics_jacobian_matches_autodiff():
    skeleton = linkage_skeleton(LENGTHS)
    markers = linkage_markers(LENGTHS, seed=1)
    sim = simulate_markers(skeleton, linkage_motion(1.0, 10.0, seed=1), markers, 10.0, MarkerNoise(gap_rate_hz=3.0), seed=1)
    seen = np.isfinite(sim.identified_positions()[4, :, 0])
    assert 0 < seen.sum() < len(markers)
    seg = sim.marker_segments
    below = np.zeros((3, 3))
    for j in range(3):
        below[list(skeleton.subtree(j)), j] = 1.0
    frame = (skeleton, sim.motion[4], jnp.asarray(np.nan_to_num(sim.identified_positions()[4])), jnp.asarray(seen.astype(float)),
             jnp.asarray(seg), jnp.asarray(np.array([m.offset for m in markers])), 1e-3, jnp.asarray(below[seg]))
    y = jnp.asarray(np.random.default_rng(0).normal(scale=0.3, size=(1, skeleton.num_dofs)))
    jac = jax.jit(jax.jacfwd(marker_ik._frame_residual))(y, frame)[:, 0]
    r = jax.jit(marker_ik._frame_residual)(y, frame)
    system = jax.jit(marker_ik._frame_system)(frame, y)
    np.testing.assert_allclose(system.diag[0], jac.T @ jac, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(system.grad[0], jac.T @ r, rtol=1e-9, atol=1e-12)


def test_initial_pose_rotations_round_trip():
    r = Rotation.random(500, random_state=3).as_matrix()
    r = np.concatenate([r, np.eye(3)[None], np.diag([1.0, -1, -1])[None], np.diag([-1.0, 1, -1])[None], np.diag([-1.0, -1, 1])[None]])
    q = marker_ik._quaternions(r)
    np.testing.assert_allclose(Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix(), r, atol=1e-12)
    assert (q[:, 0] >= 0).all()


def test_initial_pose_is_exact_where_seen_and_follows_the_parent_over_a_gap():
    """A rod hidden for a second (with its joint) keeps its pose relative to its parent, interpolated in time."""
    from bcmocap.kinematics import joint_positions

    skeleton = linkage_skeleton(LENGTHS)
    motion = linkage_motion(4.0, 60.0, seed=5)
    sim = simulate_markers(skeleton, motion, linkage_markers(LENGTHS, seed=5), 60.0, MarkerNoise.clean(), seed=5)
    p = sim.positions.copy()
    p[60:120, 6:9] = np.nan  # rod 3 hidden for a second
    seg = np.repeat([0, 1, 2], 3)
    offsets = np.array([m.offset for m in sim.markers])
    rigid = RigidSkeleton(skeleton, np.arange(3), seg, offsets, np.zeros(3), 0)
    jp = np.asarray(joint_positions(skeleton, motion))
    joints = {(0, 1): jp[:, 1], (1, 2): np.where(np.isfinite(p[:, 6:7, 0]), jp[:, 2], np.nan)}
    start = marker_ik.initial_motion(rigid, p, joints)
    err = np.linalg.norm(np.asarray(marker_ik.marker_model_positions(skeleton, start, seg, offsets)) - sim.true_positions, axis=-1)
    assert err[:60].max() < 1e-6 and err[120:].max() < 1e-6 and err[:, :6].max() < 1e-6
    assert np.median(err[60:120, 6:9]) < 0.05 and err[60:120, 6:9].max() < 0.15
