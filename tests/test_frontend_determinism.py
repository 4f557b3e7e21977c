"""Registration is reproducible and resumable (issue 25, items 2 and 3): FLANN's randomised trees and the
RANSACs are seeded, whatever thread runs them and whatever it ran before, and a registration killed part
way continues from its checkpoint to the result of an uninterrupted one.

The registration tests use a synthetic scene (no rendering): keypoints are exact projections of 3D points,
each point with its own random descriptor. Cameras 0 and 1 see enough reference points to register on
their own; camera 2 sees too few of them and is registered in the first round from the points cameras 0 and
1 triangulate; camera 3 sees nothing, so a second round runs.
"""

import threading

import cv2
import numpy as np
import pytest

from bcmocap.cameras import PinholeCamera
from bcmocap.frontend import relative
from bcmocap.frontend.reference import DescriptorIndex, match_descriptors, verify_matches
from bcmocap.frontend.register import ReferenceIndex
from bcmocap.frontend.relative import RegistrationCheckpoint, RelativeOptions, register_capture
from bcmocap.geometry import quat_from_matrix


def _disturb_rng(seed: int) -> None:
    """Leave this thread's OpenCV RNG somewhere else, as earlier work in a pool thread would."""
    cv2.setRNGSeed(seed)
    cv2.randu(np.zeros((1, 17)), 0, 1)


def test_flann_trees_do_not_depend_on_the_thread_or_its_history():
    rng = np.random.default_rng(0)
    data = rng.integers(0, 256, (3000, 128)).astype(np.uint8)
    query = rng.integers(0, 256, (1000, 128)).astype(np.uint8)
    found = []

    def search(seed):
        _disturb_rng(seed)
        found.append(DescriptorIndex(data, checks=8).nearest(query, 0.9))

    for seed in (1, 2):
        search(seed)
        thread = threading.Thread(target=search, args=(seed + 10,))  # a fresh thread, a fresh RNG
        thread.start()
        thread.join()
    for nearest, good in found[1:]:  # approximate (8 checks): unseeded trees give other neighbours
        assert np.array_equal(nearest, found[0][0]) and np.array_equal(good, found[0][1])
    _disturb_rng(3)
    pairs = match_descriptors(data[:500], query, checks=8)
    _disturb_rng(4)
    assert np.array_equal(match_descriptors(data[:500], query, checks=8), pairs)


def test_a_used_index_pickles_to_one_that_finds_the_same_neighbours():
    """A cluster task receives the index by pickle: the descriptors travel, its trees are built again."""
    import pickle

    rng = np.random.default_rng(1)
    data, query = rng.integers(0, 256, (2000, 128)).astype(np.uint8), rng.integers(0, 256, (300, 128)).astype(np.uint8)
    index = DescriptorIndex(data, checks=8)
    found = index.nearest(query, 0.9)  # its trees are built and held per thread now
    copy = pickle.loads(pickle.dumps(index))
    again = copy.nearest(query, 0.9)
    assert np.array_equal(found[0], again[0]) and np.array_equal(found[1], again[1])


def test_mutual_matching_searches_back_only_the_rows_chosen():
    """The way back of mutual matching searches only the rows the first way chose; the matches are those of
    searching every row back (each query's neighbours do not depend on the other queries)."""
    rng = np.random.default_rng(2)
    a = rng.integers(0, 256, (800, 128)).astype(np.uint8)
    b = np.concatenate([a[:300] + rng.integers(0, 6, (300, 128)).astype(np.uint8),
                        rng.integers(0, 256, (600, 128)).astype(np.uint8)])
    ab, good_ab = DescriptorIndex(b, checks=16).nearest(a, 0.8)
    ba, good_ba = DescriptorIndex(a, checks=16).nearest(b, 0.8)
    idx = np.flatnonzero(good_ab)
    idx = idx[(ba[ab[idx]] == idx) & good_ba[ab[idx]]]
    pairs = match_descriptors(a, b, checks=16)
    assert len(pairs) > 200
    assert np.array_equal(pairs, np.stack([idx, ab[idx]], 1).astype(np.uint32))
    rows = rng.permutation(len(b))[:450]  # e.g. the features of a registered frame that observe a point
    assert np.array_equal(match_descriptors(a, b, checks=16, rows_b=rows), pairs[np.isin(pairs[:, 1], rows)])
    with pytest.raises(ValueError, match="rows_b needs mutual"):
        match_descriptors(a, b, mutual=False, rows_b=rows)


def test_index_cache_shares_each_frames_trees_and_stays_bounded():
    rng = np.random.default_rng(3)
    states = [[relative.CameraFrameRegistration(np.zeros((300, 2)), rng.integers(0, 256, (300, 128)).astype(np.uint8),
                                                np.full(300, -1), np.full(7, np.nan)) for _ in range(2)] for _ in range(3)]
    cache = relative._IndexCache(states, 16, 3)
    first = cache((0, 0))
    assert cache((0, 0)) is first
    for tc in ((0, 1), (1, 0), (1, 1)):
        cache(tc)
    assert len(cache.cache) == 3 and (0, 0) not in cache.cache  # the least recently used went
    da, db = states[0][0].descriptors, states[2][1].descriptors
    assert np.array_equal(match_descriptors(da, db, checks=16, index_a=cache((0, 0)), index_b=cache((2, 1))),
                          match_descriptors(da, db, checks=16))


def test_index_cache_keeps_its_memory_estimate_under_the_budget():
    """Each index counts (1 + 1.6 · its tree copies) × its float32 descriptors (300 × 128 × 4 B here): searched by
    two threads, one holds 4.2 × 153.6 kB; a 1.5 MB budget keeps two such, where unsearched ones (1 ×) fit more."""
    rng = np.random.default_rng(4)
    states = [[relative.CameraFrameRegistration(np.zeros((300, 2)), rng.integers(0, 256, (300, 128)).astype(np.uint8),
                                                np.full(300, -1), np.full(7, np.nan)) for _ in range(2)] for _ in range(3)]
    cache = relative._IndexCache(states, 16, 100, memory_bytes=1.5e6)
    query = states[2][1].descriptors[:5]

    def search_from_two_threads(index):
        index.nearest(query, 0.8)
        worker = threading.Thread(target=index.nearest, args=(query, 0.8))
        worker.start()
        worker.join()

    for tc in ((0, 0), (0, 1), (1, 0), (1, 1)):
        search_from_two_threads(cache(tc))
        assert len(cache.cache) <= 3 and cache.held <= 1.5e6 + 2 * 4.2 * 300 * 128 * 4
    assert [i.copies for i in cache.cache.values()] == [2] * len(cache.cache)
    cache((2, 0))  # a new index: the least recently used go until the estimate is under the budget again
    assert list(cache.cache)[-1] == (2, 0) and cache.held <= 1.5e6
    fresh = relative._IndexCache(states, 16, 100, memory_bytes=1.5e6)
    for tc in ((0, 0), (0, 1), (1, 0), (1, 1), (2, 0), (2, 1)):
        fresh(tc)  # never searched: 153.6 kB each, all six fit
    assert len(fresh.cache) == 6


def test_a_registration_with_room_for_two_indexes_gives_the_same_result(trial, whole):
    """A memory budget too small for the frames in use: indexes are dropped and built again, the result is the
    same (their trees are seeded)."""
    features, index = trial
    _same(register_capture(features, [CAMERA] * 4, index, RelativeOptions(workers=2, index_memory_mb=1e-6)), whole)


def test_f_ransac_does_not_draw_on_the_rng_flann_reseeds():
    """OpenCV's F-RANSAC seeds a generator of its own, so FLANN reseeding the thread's RNG (and whatever ran
    before in a pool thread) leaves the reference's verified matches as they are. A guard on that assumption:
    an OpenCV whose RANSAC drew on ``cv2.setRNGSeed``'s generator would fail here (30 iterations, 75 % outliers:
    the samples decide the inliers)."""
    rng = np.random.default_rng(1)
    xy_a = rng.uniform(0, 640, (200, 2))
    xy_b = xy_a + rng.normal(0, 0.6, (200, 2)) + [5.0, 0.0]
    xy_b[:150] = rng.uniform(0, 640, (150, 2))
    runs = []
    for disturb in (5, 6, 7, 8):
        _disturb_rng(disturb)
        runs.append(cv2.findFundamentalMat(xy_a, xy_b, cv2.FM_RANSAC, 0.5, 0.99, 30)[1])
    assert all(np.array_equal(r, runs[0]) for r in runs)
    matches = np.stack([np.arange(200), np.arange(200)], 1).astype(np.uint32)
    _disturb_rng(9)
    first = verify_matches(xy_a, xy_b, matches, threshold_px=0.5, min_inliers=8)
    _disturb_rng(10)
    assert len(first) and np.array_equal(verify_matches(xy_a, xy_b, matches, threshold_px=0.5, min_inliers=8), first)


# ---- a synthetic trial -------------------------------------------------------------------------------

W, H = 640, 480
CAMERA = PinholeCamera(width=W, height=H, focal=[400.0, 400.0], principal_point=[(W - 1) / 2, (H - 1) / 2])


def _pose(position, yaw):
    """world_from_camera wxyz_xyz looking along +y turned by ``yaw`` about z (camera y down)."""
    f = np.array([np.sin(yaw), np.cos(yaw), 0.0])
    r = np.cross(f, [0.0, 0.0, 1.0])
    return np.concatenate([quat_from_matrix(np.stack([r, np.cross(f, r), f], axis=1)), position])


def _project(pose, xyz):
    from bcmocap.geometry import matrix_from_quat

    local = (xyz - pose[4:]) @ np.asarray(matrix_from_quat(pose[:4]))
    uv = 400.0 * local[:, :2] / local[:, 2:] + [(W - 1) / 2, (H - 1) / 2]
    inside = (local[:, 2] > 0.1) & (uv[:, 0] > 1) & (uv[:, 1] > 1) & (uv[:, 0] < W - 2) & (uv[:, 1] < H - 2)
    return uv, inside


@pytest.fixture(scope="module")
def trial():
    """``(features[t][c], ReferenceIndex)`` of 3 frames of 4 cameras."""
    rng = np.random.default_rng(7)
    reference = np.column_stack([rng.uniform(-3, 3, 300), rng.uniform(5, 7, 300), rng.uniform(-2, 2, 300)])
    other = np.column_stack([rng.uniform(-3, 3, 300), rng.uniform(4, 6, 300), rng.uniform(-2, 2, 300)])
    ref_desc = rng.integers(0, 256, (300, 128)).astype(np.uint8)
    other_desc = rng.integers(0, 256, (300, 128)).astype(np.uint8)
    index = ReferenceIndex(ref_desc.astype(np.float32), np.arange(300, dtype=np.int64) + 1000, reference)
    features = []
    for t in range(3):
        row = []
        for c, (x, yaw) in enumerate([(-0.4, 0.05), (0.4, -0.05), (0.0, 0.0), (0.2, 0.1)]):
            pose = _pose(np.array([x + 0.05 * t, 0.02 * t, 0.0]), yaw)
            seen_ref = np.arange(300) if c < 2 else np.arange(40)  # camera 2: too few for absolute registration
            if c == 3:
                row.append((np.zeros((0, 2)), np.zeros((0, 128), np.uint8)))
                continue
            uv_r, in_r = _project(pose, reference[seen_ref])
            uv_o, in_o = _project(pose, other)
            seen = np.clip(other_desc[in_o] + rng.normal(0, 30, (int(in_o.sum()), 128)), 0, 255)  # not exact:
            row.append((np.concatenate([uv_r[in_r], uv_o[in_o]]),  # FLANN's trees decide some matches
                        np.concatenate([ref_desc[seen_ref][in_r], seen.astype(np.uint8)])))
        features.append(row)
    return features, index


@pytest.fixture(scope="module")
def whole(trial):
    """The uninterrupted registration every resumed one must equal."""
    features, index = trial
    return register_capture(features, [CAMERA] * 4, index, RelativeOptions(workers=2))


def _same(a, b) -> None:
    assert a.rounds == b.rounds and a.new_point_ids == b.new_point_ids
    assert np.array_equal(a.world_from_camera, b.world_from_camera, equal_nan=True)
    for row_a, row_b in zip(a.states, b.states):
        for sa, sb in zip(row_a, row_b):
            assert (sa.how, sa.round) == (sb.how, sb.round) and np.array_equal(sa.point_ids, sb.point_ids)
    assert list(a.points) == list(b.points)
    assert all(np.array_equal(a.points[k], b.points[k]) for k in a.points)


class Killed(Exception):
    """Stands for a kill -9 at a chosen progress report."""


def _kill_at(stage: str, done: int, seen: list):
    def progress(name, k, total):
        seen.append(name)
        if name == stage and k == done:
            raise Killed(stage)
    return progress


def test_the_synthetic_trial_registers_in_two_rounds(whole):
    result = whole
    how = np.array([[s.how for s in row] for row in result.states])
    assert (how[:, :2] == "absolute").all() and (how[:, 2] == "relative").all() and (how[:, 3] == "").all()
    assert [r["registered"] for r in result.rounds] == [6, 3, 0]


def test_a_registration_killed_during_absolute_registration_continues_from_its_checkpoint(trial, whole, tmp_path,
                                                                                          monkeypatch):
    features, index = trial
    options = RelativeOptions(workers=2)
    checkpoint = RegistrationCheckpoint(tmp_path / "progress", {"settings": 1}, every=2)
    with pytest.raises(Killed):
        register_capture(features, [CAMERA] * 4, index, options, checkpoint=checkpoint,
                         progress=_kill_at("absolute", 7, []))
    assert sorted(p.name for p in (tmp_path / "progress").iterdir()) == [
        "absolute_000000.npz", "absolute_000002.npz", "absolute_000004.npz"]
    calls = []
    real = relative.register_features
    monkeypatch.setattr(relative, "register_features", lambda *a, **k: calls.append(1) or real(*a, **k))
    resumed = register_capture(features, [CAMERA] * 4, index, options, checkpoint=checkpoint)
    assert len(calls) == 12 - 6  # the six camera-frames saved are not registered again
    _same(resumed, whole)
    # Other settings or other inputs: the checkpoint is not used.
    calls.clear()
    fresh = register_capture(features, [CAMERA] * 4, index, options,
                             checkpoint=RegistrationCheckpoint(tmp_path / "progress", {"settings": 2}))
    assert len(calls) == 12
    _same(fresh, whole)


def test_a_registration_killed_in_a_later_round_continues_after_the_last_round_saved(trial, whole, tmp_path):
    features, index = trial
    options = RelativeOptions(workers=2)
    checkpoint = RegistrationCheckpoint(tmp_path / "progress", {"settings": 1})
    with pytest.raises(Killed):
        register_capture(features, [CAMERA] * 4, index, options, checkpoint=checkpoint,
                         progress=_kill_at("relative round 2", 1, []))
    assert [p.name for p in (tmp_path / "progress").iterdir()] == ["round_01.npz"]
    seen = []
    resumed = register_capture(features, [CAMERA] * 4, index, options, checkpoint=checkpoint,
                               progress=lambda name, k, total: seen.append(name))
    assert "relative round 2" in seen
    assert not [s for s in seen if s == "absolute" or s.endswith("round 1")]  # not done again
    _same(resumed, whole)
    seen.clear()
    finished = register_capture(features, [CAMERA] * 4, index, options, checkpoint=checkpoint,
                                progress=lambda name, k, total: seen.append(name))
    assert seen == []  # a finished registration is only read back
    _same(finished, whole)


def test_registration_does_not_depend_on_threads_or_the_rng_they_inherit(trial, whole):
    features, index = trial
    _disturb_rng(8)
    _same(register_capture(features, [CAMERA] * 4, index, RelativeOptions(workers=1)), whole)


def test_relative_registration_from_the_keypoints_with_points_equals_whole_matching(trial, whole, monkeypatch):
    """Relative registration matches a frame only to its registered neighbours' keypoints that observe a point
    (``rows_b``, searched again each round only where points appeared): the result is that of matching
    whole frames and keeping those keypoints' matches."""
    features, index = trial
    searched = []

    def whole_frames(desc_a, desc_b, *, rows_b=None, index_a=None, index_b=None, **kw):
        m = match_descriptors(desc_a, desc_b, **kw)
        if rows_b is not None:
            searched.append(len(rows_b))
            m = m[np.isin(m[:, 1], rows_b)]
        return m

    monkeypatch.setattr(relative, "match_descriptors", whole_frames)
    _same(register_capture(features, [CAMERA] * 4, index, RelativeOptions(workers=2)), whole)
    assert searched  # the keypoints-with-points path was taken
