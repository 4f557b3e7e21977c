"""bcmocap.correspondence_store: a trial's correspondences on disk in blocks, read a window at a time,
and the solver's StoredProblem that reads them so: same measurements, same solution as in memory."""

import json

import numpy as np
import pytest

from bcmocap.correspondence_store import CorrespondenceStore, write_store
from bcmocap.sim import standard_capture
from bcmocap.solver import Problem, SolverOptions, solve
from bcmocap.solver.objective import ObjectiveWeights, StoredProblem, paper_terms


@pytest.fixture(scope="module")
def capture():
    return standard_capture("walk", seconds=1.0, fps=20.0, seed=4)


@pytest.fixture(scope="module")
def corr(capture):
    return capture.correspondences()


def _measured(c, name):
    """Per camera-frame, the measured slots' world points and pixels in slot order (padding dropped)."""
    out = []
    for t in range(c.num_frames):
        for k in range(c.num_cameras):
            keep = c.weights[t, k] > 0 if name == "reprojection" else c.homography_weights[t, k] > 0
            if name == "reprojection":
                out.append((c.points[c.point_ids[t, k, keep]], c.pixels[t, k, keep], c.weights[t, k, keep]))
            else:
                out.append((c.homography_pixels[t, k, keep], c.homography_pixels_prev[t, k, keep],
                            c.homography_weights[t, k, keep]))
    return out


def _assert_same(a, b):
    assert (a.num_frames, a.num_cameras, a.fps) == (b.num_frames, b.num_cameras, b.fps)
    np.testing.assert_array_equal(a.registered, b.registered)
    np.testing.assert_array_equal(a.world_from_camera, b.world_from_camera)
    for name in ("reprojection", "homography"):
        for x, y in zip(_measured(a, name), _measured(b, name), strict=True):
            for u, v in zip(x, y):
                np.testing.assert_array_equal(u, v)


def test_store_returns_the_frames_it_was_given(tmp_path, corr):
    assert (corr.homography_weights > 0).any() and (~corr.registered).any()
    cut = 8
    # two chunks, each with its own copy of the points, written in blocks of 3 frames
    store = write_store(tmp_path / "store", [corr.frames(0, cut), corr.frames(cut, corr.num_frames)], block_frames=3)
    assert store.num_frames == corr.num_frames and len(store.points) == 2 * len(corr.points)
    assert [b.start for b in store.blocks] == [0, 3, 6, 8, 11, 14, 17]
    assert store.slots <= corr.point_ids.shape[2]
    _assert_same(store.load(), corr)
    for start, stop in ((0, 20), (2, 9), (7, 8), (10, 20)):
        window = store.frames(start, stop)
        assert window.point_ids.shape[2] == store.slots  # every window has the store's widths
        assert window.homography_weights.shape[2] == store.homography_slots
        assert len(window.points) == len(np.unique(window.point_ids[window.point_ids >= 0]))
        _assert_same(window, corr.frames(start, stop))
    reopened = CorrespondenceStore.open(tmp_path / "store")
    _assert_same(reopened.frames(5, 12), corr.frames(5, 12))
    assert reopened.num_observations() == int((corr.weights > 0).sum())
    mask = reopened.used_mask()
    pieces = list(reopened.iter_points(mask, piece=7))
    assert len(pieces) == -(-reopened.num_points // 7)
    np.testing.assert_array_equal(np.concatenate(pieces), np.asarray(reopened.points)[mask])
    np.testing.assert_array_equal(np.unique(reopened.points[reopened.used_points()], axis=0),
                                  np.unique(corr.points[np.unique(corr.point_ids[corr.weights > 0])], axis=0))
    with pytest.raises(ValueError, match=r"frames \[15, 21\) outside \[0, 20\)"):
        store.frames(15, 21)


@pytest.mark.slow
def test_stored_problem_solves_as_the_problem_in_memory(tmp_path, capture, corr):
    store = write_store(tmp_path / "store", [corr], block_frames=7)
    weights = ObjectiveWeights()
    options = SolverOptions(window=8, overlap=3)
    initial = capture.initial_motion(corr)
    in_memory = solve(Problem(capture.skeleton, capture.rig, paper_terms(corr, capture.skeleton, weights,
                                                                         include_homography=True)), initial, options)
    stored_problem = StoredProblem(store, capture.skeleton, capture.rig, weights)
    assert stored_problem.include_homography and stored_problem.num_frames == corr.num_frames
    from_disk = solve(stored_problem, initial, options)
    assert len(from_disk.reports) == len(in_memory.reports)
    for a, b in zip(from_disk.reports, in_memory.reports):
        assert a.final_cost == pytest.approx(b.final_cost, rel=1e-9)
    np.testing.assert_allclose(from_disk.motion.rotations, in_memory.motion.rotations, atol=1e-9)
    np.testing.assert_allclose(from_disk.motion.root_position, in_memory.motion.root_position, atol=1e-9)


def test_a_homography_filter_replaces_each_windows_homography_weights(tmp_path, capture, corr):
    """StoredProblem's homography_filter gets each window (its frames and measurements) and its weights are the
    homography term's; weights of another shape are one line."""
    store = write_store(tmp_path / "store", [corr], block_frames=7)
    seen = []

    def halve_odd_frames(window):
        seen.append((window.start, window.stop))
        w = np.array(window.correspondences.homography_weights)
        w[(window.start + np.arange(window.num_frames)) % 2 == 1] = 0.0
        return w

    problem = StoredProblem(store, capture.skeleton, capture.rig, ObjectiveWeights(), homography_filter=halve_odd_frames)
    (term,) = [t for t in problem.window(4, 10) if t.name == "homography"]
    plain = [t for t in StoredProblem(store, capture.skeleton, capture.rig, ObjectiveWeights()).window(4, 10)
             if t.name == "homography"][0]
    assert seen == [(4, 10)]
    weights, before = np.asarray(term.data["weights"]), np.asarray(plain.data["weights"])
    assert (weights[1::2] == 0).all() and np.array_equal(weights[::2], before[::2]) and (before[1::2] > 0).any()
    broken = StoredProblem(store, capture.skeleton, capture.rig, ObjectiveWeights(),
                           homography_filter=lambda window: np.zeros(3))
    with pytest.raises(ValueError, match=r"homography_filter: weights of shape \(3,\) for a window's \(6, "):
        broken.window(4, 10)


def test_transformed_copy_maps_points_and_poses(tmp_path, corr):
    store = write_store(tmp_path / "a", [corr], block_frames=6)
    moved = store.transformed(tmp_path / "b", lambda p: 2.0 * p + 1.0,
                              lambda q: np.concatenate([q[..., :4], 2.0 * q[..., 4:] + 1.0], axis=-1))
    np.testing.assert_allclose(moved.points, 2.0 * np.asarray(store.points) + 1.0)
    np.testing.assert_allclose(moved.world_from_camera[..., 4:], 2.0 * store.world_from_camera[..., 4:] + 1.0)
    np.testing.assert_array_equal(moved.frames(3, 9).pixels, store.frames(3, 9).pixels)
    np.testing.assert_allclose(np.asarray(store.points), corr.points)  # the source is untouched
    # other poses and registration (re-fitted ones) mapped in place of the store's
    poses, registered = store.world_from_camera.copy(), store.registered.copy()
    poses[..., 4:] += 0.5
    registered[0] = False
    other = store.transformed(tmp_path / "c", lambda p: p, lambda q: q, world_from_camera=poses, registered=registered)
    np.testing.assert_array_equal(other.world_from_camera, poses)
    np.testing.assert_array_equal(other.registered, registered)
    with pytest.raises(ValueError, match=r"world_from_camera \(\d+, 7\), registered"):
        store.transformed(tmp_path / "d", lambda p: p, lambda q: q, world_from_camera=poses[0])
    # dropped camera-frames (made on a repeated pattern's copy) keep their measurements at weight 0; the rest as given
    dropped = np.zeros_like(registered)
    dropped[7, 1] = dropped[8] = True
    cut = store.transformed(tmp_path / "e", lambda p: p, lambda q: q, dropped=dropped)
    before, after = store.frames(0, store.num_frames), cut.frames(0, cut.num_frames)
    assert (np.asarray(before.weights)[dropped] > 0).any() and not np.asarray(after.weights)[dropped].any()
    np.testing.assert_array_equal(np.asarray(after.weights)[~dropped], np.asarray(before.weights)[~dropped])
    np.testing.assert_array_equal(after.pixels, before.pixels)
    np.testing.assert_array_equal(after.homography_weights, before.homography_weights)


def test_errors_name_the_file_and_a_failed_write_keeps_the_earlier_store(tmp_path, corr):
    with pytest.raises(ValueError, match="no correspondence store"):
        CorrespondenceStore.open(tmp_path / "missing")
    store = write_store(tmp_path / "s", [corr.frames(0, 5)])
    other = corr.frames(0, 5)
    other.fps = 30.0
    with pytest.raises(ValueError, match="part 1 has 18 cameras at 30 fps, part 0 18 at 20"):
        write_store(tmp_path / "s", [corr.frames(0, 5), other])
    assert CorrespondenceStore.open(tmp_path / "s").num_frames == 5 and not (tmp_path / "s.tmp").exists()
    with open(store.path / "points.f64", "ab") as f:
        f.write(b"\0" * 8)
    with pytest.raises(ValueError, match=r"points\.f64: expected \d+ points"):
        CorrespondenceStore.open(tmp_path / "s")
    index = json.loads((tmp_path / "s" / "index.json").read_text())
    del index["slots"]
    (tmp_path / "s" / "index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match="index.json: missing field 'slots'"):
        CorrespondenceStore.open(tmp_path / "s")
