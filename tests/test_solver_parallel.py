"""Windows solved independently (for a cluster) and joined: the same window solve as solve(), the blend, the seam
pass, and the accuracy of the sequential solve."""

import pickle

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bcmocap.eval import evaluate_motion
from bcmocap.kinematics import Motion, joint_positions
from bcmocap.residuals import FrameTerm, JointSmoothness, Reprojection, RootSmoothness, pair_mask
from bcmocap.solver import (Problem, SolverOptions, WindowReport, WindowSolution, join_windows, seam_windows, sequence_cost,
                            solve, solve_window, solve_windows_independently, window_starts)

from conftest import make_rig, make_skeleton, random_motion, scene_points
from test_solver import observe

T = 30
OPTIONS = SolverOptions(window=10, overlap=3)
STARTS = [0, 7, 14, 20]  # four windows, the last shifted back (it shares 6 frames with the third)


@pytest.fixture(scope="module")
def capture():
    """A simulated capture of T frames (6 cameras, 40 scene points) started 0.1 rad / 10 cm off the truth, and its
    sequential solve (the first window's result kept aside)."""
    rng = np.random.default_rng(7)
    skeleton = make_skeleton()
    rig = make_rig(skeleton)
    base = random_motion(skeleton, None, rng, max_angle=0.6)
    steps = 0.03 * rng.normal(size=(T, skeleton.num_dofs))
    truth = skeleton.retract(jax.tree.map(lambda a: jnp.broadcast_to(a, (T, *a.shape)), base), jnp.cumsum(steps, axis=0))
    points = scene_points(rng, 40)
    ids, pix, w = observe(skeleton, rig, truth, points, rng)
    init = skeleton.retract(truth, 0.1 * rng.normal(size=(T, skeleton.num_dofs)))
    problem = Problem(skeleton, rig, [
        Reprojection({"point_ids": ids, "pixels": pix, "weights": w}, points=points),
        RootSmoothness(pair_mask(T), weight=10.0),
        JointSmoothness(pair_mask(T), skeleton=skeleton, weight=1.0),
    ])
    assert window_starts(T, OPTIONS.window, OPTIONS.overlap) == STARTS
    first = {}
    sequential = solve(problem, init, OPTIONS, checkpoint=lambda i, report, so_far: first.setdefault(i, so_far))
    return problem, truth, init, sequential, first[0]


@pytest.fixture(scope="module")
def independent(capture):
    """The independent solve with the seam pass, through a map that records its calls."""
    problem, _, init, _, _ = capture
    calls = []

    def recording_map(fn, items):
        items = list(items)
        calls.append(items)
        return map(fn, items)

    return solve_windows_independently(problem, init, OPTIONS, map=recording_map), calls


def _same_report(a: WindowReport, b: WindowReport) -> bool:
    return all(getattr(a, f) == getattr(b, f) for f in ("start", "stop", "initial_cost", "final_cost", "num_steps",
                                                          "num_accepted_steps", "converged"))


def test_window_0_is_solves_first_window_bit_for_bit(capture):
    problem, _, init, sequential, after_first = capture
    window = solve_window(problem, init, OPTIONS, 0)
    assert (window.start, window.stop) == (0, 10)
    assert np.array_equal(window.root_position, np.asarray(after_first.motion.root_position)[:10])
    assert np.array_equal(window.rotations, np.asarray(after_first.motion.rotations)[:10])
    assert _same_report(window.report, sequential.reports[0])
    assert window.statics == {} and window.frame_values == {}
    # a later window from the same starting frames as solve() resuming there is solve()'s window too
    later = {}
    solve(problem, init, OPTIONS, skip_windows=2, checkpoint=lambda i, report, so_far: later.setdefault(i, so_far))
    window = solve_window(problem, init, OPTIONS, 2)
    assert np.array_equal(window.rotations, np.asarray(later[2].motion.rotations)[14:24])
    assert _same_report(window.report, later[2].reports[-1])
    # small and picklable, for a worker process
    back = pickle.loads(pickle.dumps(window))
    assert np.array_equal(back.root_position, window.root_position) and back.report == window.report


def test_independent_windows_reach_the_sequential_accuracy_and_cost(capture, independent):
    problem, truth, init, sequential, _ = capture
    solution, _ = independent
    without_seams = solve_windows_independently(problem, init, OPTIONS, seam_pass=False)
    skeleton = problem.skeleton
    before = evaluate_motion(skeleton, init, truth)
    seq = evaluate_motion(skeleton, sequential.motion, truth)
    cost_seq = sequence_cost(problem, sequential.motion, chunk=OPTIONS.window)
    for result, cost_tolerance in ((solution, 1e-5), (without_seams, 1e-4)):
        ours = evaluate_motion(skeleton, result.motion, truth)
        assert ours["joint_position_error_cm"]["mean"] < 0.2 * before["joint_position_error_cm"]["mean"]
        assert ours["joint_position_error_cm"]["mean"] == pytest.approx(seq["joint_position_error_cm"]["mean"], abs=0.002)
        assert ours["joint_angle_error_deg"]["mean"] == pytest.approx(seq["joint_angle_error_deg"]["mean"], abs=0.002)
        assert sequence_cost(problem, result.motion, chunk=OPTIONS.window) == pytest.approx(cost_seq, rel=cost_tolerance)
        assert result.converged
    # the seam pass moves the joined motion towards the sequential one
    gap = lambda m: evaluate_motion(skeleton, m, sequential.motion)["joint_position_error_cm"]["max"]  # noqa: E731
    assert gap(solution.motion) < gap(without_seams.motion)


def test_the_joined_motion_has_no_jump_at_the_seams(capture, independent):
    problem, _, _, sequential, _ = capture
    solution, _ = independent

    def steps(motion):  # largest joint displacement between consecutive frames (cm), (T - 1,)
        p = np.asarray(joint_positions(problem.skeleton, motion))
        return 100.0 * np.linalg.norm(np.diff(p, axis=0), axis=-1).max(axis=1)

    ours, theirs = steps(solution.motion), steps(sequential.motion)
    seam = np.zeros(T - 1, bool)
    for a, b in zip(STARTS, STARTS[1:]):
        seam[b - 2 : a + OPTIONS.window + 1] = True
    assert ours[seam].max() <= 1.2 * ours[~seam].max()
    assert np.abs(ours - theirs)[seam].max() < 0.01 * theirs.mean()  # the same steps as the sequential solve's


def test_every_window_goes_through_the_given_map(capture, independent):
    solution, calls = independent
    seams = [start for start, _ in seam_windows(STARTS, OPTIONS.window, T)]
    assert calls == [STARTS, seams]  # the windows, then the seam windows: nothing solved outside the map
    assert [(r.start, r.stop) for r in solution.reports] == [(s, s + 10) for s in STARTS + seams]


def test_joining_one_window_gives_that_window(capture):
    problem, _, init, _, _ = capture
    window = solve_window(problem, init, OPTIONS, 1)
    joined = join_windows(init, [window], OPTIONS)
    root, rotations = np.asarray(joined.motion.root_position), np.asarray(joined.motion.rotations)
    assert np.array_equal(root[7:17], window.root_position) and np.array_equal(rotations[7:17], window.rotations)
    outside = np.r_[0:7, 17:T]
    assert np.array_equal(root[outside], np.asarray(init.root_position)[outside])
    assert np.array_equal(rotations[outside], np.asarray(init.rotations)[outside])
    assert joined.reports == [window.report]
    for index in (-1, 4, 1.0):
        with pytest.raises(ValueError, match=r"index must be in \[0, 4\)"):
            solve_window(problem, init, OPTIONS, index)
    with pytest.raises(ValueError, match="no window solutions"):
        join_windows(init, [], OPTIONS)
    with pytest.raises(ValueError, match="two solutions of the window starting at frame 7"):
        join_windows(init, [window, window], OPTIONS)
    with pytest.raises(ValueError, match="has 10 frames; options give 12"):
        join_windows(init, [window], SolverOptions(window=12, overlap=3))


def _quaternion(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def _window(start, stop, rotation, root, statics, frame_values=None, kinds=None):
    n = stop - start
    report = WindowReport(start, stop, 1.0, 0.5, 3, 3, True, 0.0)
    rotations = np.broadcast_to(rotation, (n, 2, 4)).copy()
    return WindowSolution(start, stop, np.broadcast_to(root, (n, 3)).copy(), rotations, statics, frame_values or {},
                          report, static_kinds=kinds or {}, frame_kinds=kinds or {})


def test_blend_ramps_across_the_overlap_on_the_rotation_manifold():
    """Two windows sharing 3 frames, with rotations about one (hinge) axis given with opposite quaternion signs:
    the blend ramps 1/4, 2/4, 3/4 in angle (nlerp ≈ slerp), stays about the axis, and statics are weighted by
    the frames each window contributes."""
    axis = np.array([2.0, 0.4, 0.0])
    qa, qb = _quaternion(axis, 0.2), -_quaternion(axis, 0.6)  # -q: the same rotation
    kinds = {"bias": "euclidean", "mount": "rotation"}
    a = _window(0, 6, qa, [0.0, 0, 0], {"bias": np.array([1.0]), "mount": qa}, {"bias": np.zeros((6, 1))}, kinds)
    b = _window(3, 9, qb, [1.0, 0, 0], {"bias": np.array([3.0]), "mount": qb}, {"bias": np.ones((6, 1))}, kinds)
    init = Motion(np.full((12, 3), 5.0), np.broadcast_to(_quaternion([0, 0, 1], 1.0), (12, 2, 4)))
    joined = join_windows(init, [b, a], SolverOptions(window=6, overlap=3))
    root, rotations = np.asarray(joined.motion.root_position), np.asarray(joined.motion.rotations)
    assert np.allclose(root[:9, 0], [0, 0, 0, 0.25, 0.5, 0.75, 1, 1, 1]) and np.all(root[9:] == 5.0)
    assert np.allclose(joined.frame_variables["bias"][:9, 0], root[:9, 0])
    q = rotations[:9, 0] * np.sign(rotations[:9, 0, :1])
    angle = 2 * np.arctan2(np.linalg.norm(q[:, 1:], axis=1), q[:, 0])
    assert np.allclose(angle, [0.2, 0.2, 0.2, 0.3, 0.4, 0.5, 0.6, 0.6, 0.6], atol=2e-3)
    assert np.allclose(np.cross(q[:, 1:], axis), 0.0, atol=1e-15)  # still a rotation about the hinge's axis
    assert np.allclose(np.linalg.norm(rotations, axis=-1), 1.0)
    # each window contributes 4.5 frames: the mean of the biases, the mid-rotation of the mounts
    assert joined.statics["bias"] == pytest.approx([2.0])
    mount = joined.statics["mount"] * np.sign(joined.statics["mount"][0])
    assert np.allclose(mount, _quaternion(axis, 0.4), atol=1e-3)
    assert [r.start for r in joined.reports] == [0, 3]


@pytest.mark.parametrize("window, overlap, num_frames", [(10, 3, 30), (60, 10, 600), (10, 6, 40), (10, 0, 30)])
def test_seam_windows_weigh_each_frame_once(window, overlap, num_frames):
    """Seam windows fit the sequence, weigh the frames two windows share fully and never weigh a frame twice, even
    when (overlap ≥ window / 2) they overlap each other."""
    starts = window_starts(num_frames, window, overlap)
    seams = seam_windows(starts, window, num_frames)
    assert len(seams) == len(starts) - 1
    total = np.zeros(num_frames)
    for k, (start, weights) in enumerate(seams):
        assert 0 <= start <= num_frames - window and weights.shape == (window,)
        assert np.all((weights >= 0) & (weights <= 1))
        total[start:start + window] += weights
        shared = np.arange(starts[k + 1], starts[k] + window) - start
        if 2 * overlap < window:
            assert np.all(weights[shared] == 1.0)
    assert np.all(total <= 1.0)


class _BrokenPrior(FrameTerm):
    """A user term with a bug: the log of a negative number at the frames where ``data`` is 1 (NaN residual)."""

    def residual(self, state, data, variables):
        return jnp.log(data - 2.5 + state.motion.root_position[0] * 0.0)[None, None], jnp.ones(1, bool)


@pytest.mark.slow  # its own compiled solve (~15 s), like test_solver's non-finite window test

def test_a_non_finite_window_is_refused_naming_it():
    """As in solve(): a window whose cost goes non-finite raises FloatingPointError naming its frames and the term;
    the windows before it solve (a problem without cameras: quick to compile)."""
    skeleton = make_skeleton()
    motion = skeleton.rest_motion(T)
    problem = Problem(skeleton, None, [_BrokenPrior(np.where(np.arange(T) == 15, 1.0, 3.0), name="broken prior"),
                                       RootSmoothness(pair_mask(T))])
    assert solve_window(problem, motion, OPTIONS, 0).report.converged
    with pytest.raises(FloatingPointError, match=r"window of frames \[7, 17\) has a non-finite cost or motion: "
                                                 r"term\(s\) 'broken prior' are non-finite"):
        solve_window(problem, motion, OPTIONS, 1)
    with pytest.raises(FloatingPointError, match=r"window of frames \[7, 17\)"):
        solve_windows_independently(problem, motion, OPTIONS)
