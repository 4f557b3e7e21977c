"""The on-disk feature store: streamed writes, memory-mapped reads, settings checks, no partial caches."""

import json

import numpy as np
import pytest

from bcmocap.frontend.features import read_camera_features, write_camera_features

SETTINGS = {"start": 3, "stride": 2, "num_frames": 5, "max_features": 100}


def _frames(rng, counts):
    return [(rng.uniform(0, 640, (n, 2)), rng.integers(0, 256, (n, 128)).astype(np.uint8)) for n in counts]


def test_round_trip_is_exact_and_memory_mapped(tmp_path):
    frames = _frames(np.random.default_rng(0), [4, 0, 7])
    write_camera_features(tmp_path / "cam", SETTINGS, iter(frames))
    back = read_camera_features(tmp_path / "cam", SETTINGS)
    assert len(back) == 3 and [len(k) for k, _ in back] == [4, 0, 7]
    for (k, d), (k2, d2) in zip(frames, back):
        assert np.array_equal(k, k2) and np.array_equal(d, d2) and d2.dtype == np.uint8 and k2.dtype == np.float64
    assert isinstance(back[2][1], np.memmap) and not back[2][1].flags.writeable
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cam"]  # no temporary folder left
    assert json.loads((tmp_path / "cam" / "features.json").read_text())["counts"] == [4, 0, 7]


def test_float_descriptors_are_rounded_to_uint8(tmp_path):
    write_camera_features(tmp_path / "cam", SETTINGS, [(np.zeros((1, 2)), np.full((1, 128), 2.6, np.float32))])
    assert np.all(read_camera_features(tmp_path / "cam")[0][1] == 3)


def test_other_settings_or_damaged_files_read_as_missing(tmp_path):
    assert read_camera_features(tmp_path / "none", SETTINGS) is None
    write_camera_features(tmp_path / "cam", SETTINGS, _frames(np.random.default_rng(1), [5, 6]))
    assert read_camera_features(tmp_path / "cam", {**SETTINGS, "stride": 1}) is None
    assert read_camera_features(tmp_path / "cam", SETTINGS) is not None
    with open(tmp_path / "cam" / "descriptors.u8", "r+b") as f:
        f.truncate(128 * 10)
    assert read_camera_features(tmp_path / "cam", SETTINGS) is None
    (tmp_path / "cam" / "features.json").write_text("{not json")
    assert read_camera_features(tmp_path / "cam", SETTINGS) is None


def test_zero_frames_and_zero_features(tmp_path):
    write_camera_features(tmp_path / "none", SETTINGS, [])
    assert read_camera_features(tmp_path / "none", SETTINGS) == []
    write_camera_features(tmp_path / "empty", SETTINGS, [(np.zeros((0, 2)), np.zeros((0, 128), np.uint8))] * 2)
    back = read_camera_features(tmp_path / "empty", SETTINGS)
    assert [k.shape for k, _ in back] == [(0, 2), (0, 2)] and [d.shape for _, d in back] == [(0, 128), (0, 128)]


def test_an_interrupted_write_keeps_the_previous_features(tmp_path):
    frames = _frames(np.random.default_rng(2), [3, 3])
    write_camera_features(tmp_path / "cam", SETTINGS, frames)

    def failing():
        yield frames[0]
        raise RuntimeError("video ended early")

    with pytest.raises(RuntimeError, match="video ended early"):
        write_camera_features(tmp_path / "cam", {**SETTINGS, "stride": 1}, failing())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cam"]
    back = read_camera_features(tmp_path / "cam", SETTINGS)
    assert np.array_equal(back[1][1], frames[1][1])
    with pytest.raises(ValueError, match="frame 0 has 2 keypoints and 3 descriptors"):
        write_camera_features(tmp_path / "bad", SETTINGS, [(np.zeros((2, 2)), np.zeros((3, 128), np.uint8))])
