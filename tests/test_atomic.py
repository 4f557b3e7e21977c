"""bcmocap.atomic: a file is replaced whole or not at all."""

import zipfile

import numpy as np
import pytest

from bcmocap.atomic import atomic_path, write_npz_atomic


def test_atomic_path_replaces_on_success_and_leaves_the_original_on_failure(tmp_path):
    target = tmp_path / "sub" / "out.npz"
    with atomic_path(target, suffix=".npz") as tmp:
        assert tmp.parent == target.parent and tmp.suffix == ".npz" and not target.exists()
        tmp.write_text("first")
    assert target.read_text() == "first"
    with pytest.raises(RuntimeError):
        with atomic_path(target, suffix=".npz") as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert target.read_text() == "first" and sorted(p.name for p in target.parent.iterdir()) == ["out.npz"]


def test_atomic_path_gives_the_permissions_of_a_plain_open(tmp_path):
    import os

    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    target = tmp_path / "atomic.txt"
    with atomic_path(target) as tmp:
        tmp.write_text("x")
    assert os.stat(target).st_mode & 0o777 == os.stat(plain).st_mode & 0o777


def test_npz_is_deterministic_and_stored_uncompressed_when_asked(tmp_path):
    arrays = {"a": np.arange(1000, dtype=np.int64), "tag": np.array("x")}
    for compress, method in ((True, zipfile.ZIP_DEFLATED), (False, zipfile.ZIP_STORED)):
        first, second = tmp_path / f"{compress}_1.npz", tmp_path / f"{compress}_2.npz"
        write_npz_atomic(first, arrays, compress=compress)
        write_npz_atomic(second, arrays, compress=compress)
        assert first.read_bytes() == second.read_bytes()
        with zipfile.ZipFile(first) as z:
            assert {i.compress_type for i in z.infolist()} == {method}
        with np.load(first) as data:
            assert np.array_equal(data["a"], arrays["a"]) and str(data["tag"]) == "x"
