"""Tests for bcmocap.correspondences: validation messages, atomic save, load round trip and errors."""

import dataclasses
import os

import numpy as np
import pytest

from bcmocap.correspondences import Correspondences

T, C, N, M, P = 3, 2, 4, 3, 5


def arrays(seed=0) -> dict:
    rng = np.random.default_rng(seed)
    point_ids = rng.integers(0, P, size=(T, C, N)).astype(np.int32)
    point_ids[0, 1, 3] = -1
    weights = np.ones((T, C, N))
    weights[point_ids < 0] = 0.0
    registered = np.ones((T, C), bool)
    registered[2, 1] = False
    h_w = np.zeros((T, C, M))
    h_w[2, 1] = 1.0
    return dict(
        points=rng.normal(size=(P, 3)),
        point_ids=point_ids,
        pixels=rng.uniform(0, 100, size=(T, C, N, 2)),
        weights=weights,
        homography_pixels=rng.uniform(0, 100, size=(T, C, M, 2)),
        homography_pixels_prev=rng.uniform(0, 100, size=(T, C, M, 2)),
        homography_weights=h_w,
        world_from_camera=np.tile([1.0, 0, 0, 0, 0, 0, 0], (T, C, 1)),
        registered=registered,
        fps=60.0,
    )


def test_valid_correspondences_and_sizes():
    c = Correspondences(**arrays())
    assert (c.num_frames, c.num_cameras) == (T, C)
    part = c.frames(1, 3)
    assert part.num_frames == 2
    np.testing.assert_array_equal(part.pixels, c.pixels[1:3])
    np.testing.assert_array_equal(part.registered, c.registered[1:3])
    np.testing.assert_array_equal(part.points, c.points)


def test_concatenate_appends_frames_and_points_and_pads_slots():
    a = Correspondences(**arrays())
    wide = arrays(seed=1)
    wide["points"] = wide["points"][:2]
    wide["point_ids"] = np.concatenate([wide["point_ids"] % 2, np.full((T, C, 2), -1, np.int32)], axis=2)
    wide["pixels"] = np.concatenate([wide["pixels"], np.zeros((T, C, 2, 2))], axis=2)
    wide["weights"] = np.concatenate([wide["weights"], np.zeros((T, C, 2))], axis=2)
    b = Correspondences(**wide)
    both = Correspondences.concatenate([a, b])
    assert (both.num_frames, both.point_ids.shape[2], len(both.points)) == (2 * T, N + 2, P + 2)
    np.testing.assert_array_equal(both.point_ids[:T, :, :N], a.point_ids)
    assert (both.point_ids[:T, :, N:] == -1).all() and (both.weights[:T, :, N:] == 0).all()
    # The second part's ids point at its own points, now after the first part's.
    has = b.point_ids >= 0
    np.testing.assert_array_equal(both.points[both.point_ids[T:][has]], b.points[b.point_ids[has]])
    np.testing.assert_array_equal(both.registered, np.concatenate([a.registered, b.registered]))
    assert Correspondences.concatenate([a]).point_ids.shape == a.point_ids.shape
    with pytest.raises(ValueError, match="part 1 has 2 cameras at 30 fps, part 0 2 at 60"):
        Correspondences.concatenate([a, Correspondences(**dict(arrays(), fps=30.0))])
    with pytest.raises(ValueError, match="no parts"):
        Correspondences.concatenate([])


def test_save_load_round_trip(tmp_path):
    c = Correspondences(**arrays())
    path = tmp_path / "sub" / "capture.npz"
    c.save(path)
    loaded = Correspondences.load(path)
    for f in dataclasses.fields(Correspondences):
        a, b = getattr(c, f.name), getattr(loaded, f.name)
        np.testing.assert_array_equal(a, b, err_msg=f.name)
    assert loaded.registered.dtype == bool
    assert loaded.point_ids.dtype == np.int32
    assert isinstance(loaded.fps, float) and loaded.fps == 60.0
    # Saving again over the file replaces it.
    other = Correspondences(**dict(arrays(seed=1), fps=30.0))
    other.save(path)
    assert Correspondences.load(path).fps == 30.0


def test_save_is_atomic_and_leaves_no_temporary_files(tmp_path, monkeypatch):
    c = Correspondences(**arrays())
    path = tmp_path / "capture.npz"
    c.save(path)
    assert sorted(os.listdir(tmp_path)) == ["capture.npz"]
    before = path.read_bytes()

    def failing_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        Correspondences(**arrays(seed=2)).save(path)
    # The old file is intact and the temporary file is gone.
    assert sorted(os.listdir(tmp_path)) == ["capture.npz"]
    assert path.read_bytes() == before


def bad(**changes) -> dict:
    a = arrays()
    for key, fn in changes.items():
        a[key] = fn(a[key])
    return a


def set_at(index, value):
    def fn(x):
        x = np.array(x, dtype=np.float64 if np.asarray(x).dtype.kind == "f" else np.asarray(x).dtype)
        x[index] = value
        return x

    return fn


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(pixels=lambda x: x[..., :1]), r"pixels has shape \(3, 2, 4, 1\), expected \(3, 2, 4, 2\)"),
        (dict(weights=lambda x: x[:2]), r"weights has shape \(2, 2, 4\), expected \(3, 2, 4\)"),
        (dict(world_from_camera=lambda x: x[..., :6]), r"world_from_camera has shape \(3, 2, 6\), expected \(3, 2, 7\)"),
        (dict(registered=lambda x: x[:, :1]), r"registered has shape \(3, 1\), expected \(3, 2\)"),
        (dict(homography_pixels_prev=lambda x: x[:, :, :2]),
         r"homography_pixels_prev has shape \(3, 2, 2, 2\), expected \(3, 2, 3, 2\)"),
        (dict(points=lambda x: x[:, :2]), r"points has shape \(5, 2\), expected \(5, 3\)"),
        (dict(point_ids=lambda x: x[0]), r"point_ids must have shape \(T, C, N\), got \(2, 4\)"),
        (dict(pixels=set_at((1, 0, 2, 1), np.nan)), "pixels has NaN/inf at frame 1, camera 0, slot 2"),
        (dict(homography_pixels=set_at((2, 1, 0, 0), np.inf)), "homography_pixels has NaN/inf at frame 2, camera 1, slot 0"),
        (dict(weights=set_at((0, 0, 1), -1.0)), "weights must be finite and non-negative"),
        (dict(homography_weights=set_at((0, 0, 1), np.nan)), "homography_weights must be finite and non-negative"),
        (dict(point_ids=set_at((1, 1, 1), P)), "point_ids reach 5 but there are 5 points"),
        (dict(points=set_at((2, 0), np.nan)), "points contain NaN/inf"),
        (dict(world_from_camera=set_at((1, 0, 4), np.nan)), "world_from_camera has NaN/inf at registered frame 1, camera 0"),
        (dict(fps=lambda x: 0.0), "fps must be positive, got 0.0"),
    ],
)
def test_validate_names_the_field(changes, message):
    with pytest.raises(ValueError, match=r"^Correspondences: " + message):
        Correspondences(**bad(**changes))


def test_nan_is_allowed_where_it_is_not_used():
    a = arrays()
    a["pixels"] = np.array(a["pixels"])
    a["pixels"][0, 1, 3] = np.nan  # an empty slot (weight 0)
    a["world_from_camera"] = np.array(a["world_from_camera"])
    a["world_from_camera"][2, 1] = np.nan  # an unregistered camera-frame
    a["homography_pixels_prev"][0] = np.nan  # frame 0 has no homography slots in use
    Correspondences(**a)


def test_load_errors_name_the_file_and_field(tmp_path):
    a = arrays()
    path = tmp_path / "partial.npz"
    np.savez(path, **{k: v for k, v in a.items() if k != "homography_weights"})
    with pytest.raises(ValueError, match=r"partial\.npz: missing field 'homography_weights'"):
        Correspondences.load(path)
    broken = tmp_path / "broken.npz"
    np.savez(broken, **dict(a, weights=-np.ones((T, C, N))))
    with pytest.raises(ValueError, match=r"broken\.npz: weights must be finite and non-negative"):
        Correspondences.load(broken)
    garbage = tmp_path / "garbage.npz"
    garbage.write_text("not an archive")
    with pytest.raises(ValueError, match=r"garbage\.npz: not a readable correspondences file"):
        Correspondences.load(garbage)
    with pytest.raises(ValueError, match=r"missing\.npz: not a readable correspondences file"):
        Correspondences.load(tmp_path / "missing.npz")


def test_validate_names_homography_weights_of_the_wrong_rank():
    with pytest.raises(ValueError, match=r"homography_weights .*shape.*\(3, 2\)"):
        Correspondences(**bad(homography_weights=lambda x: x[..., 0]))


def test_validate_rejects_non_integer_point_ids():
    with pytest.raises(ValueError, match="point_ids"):
        Correspondences(**bad(point_ids=lambda x: x.astype(np.float64)))
