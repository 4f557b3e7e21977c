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


# ---- a full disk -------------------------------------------------------------------------------------------

@pytest.fixture
def full_disk(tmp_path):
    """A folder on a 64 KiB tmpfs whose space is all taken (skipped where this process may not mount)."""
    from benchmarks._small_disk import fill, small_disk

    try:
        with small_disk(tmp_path / "disk", 64 * 1024) as folder:
            (folder / "kept.json").write_text('{"complete": true}\n')
            fill(folder)
            yield folder
    except PermissionError as exc:
        pytest.skip(str(exc))


def test_a_full_disk_fails_a_write_with_one_line_naming_the_folder_and_the_bytes(full_disk):
    from bcmocap.atomic import DiskFull, write_json_atomic

    payload = {"values": list(range(3000))}
    with pytest.raises(DiskFull) as err:
        write_json_atomic(full_disk / "kept.json", payload)
    message = str(err.value)
    assert "\n" not in message and str(full_disk) in message and "kept.json" in message
    needed = len((__import__("json").dumps(payload, indent=2) + "\n").encode())
    assert f"needed {needed:,} bytes" in message and "bytes free" in message
    assert (full_disk / "kept.json").read_text() == '{"complete": true}\n'  # the complete file is kept
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler", "kept.json"]  # no temporary left


@pytest.mark.slow  # ~10 s: the heavy tier
def test_writers_outside_atomic_path_name_the_full_disk_too(full_disk):
    """A correspondence store (a folder written whole), the OpenCV calibration files (OpenCV's own writer would
    leave an empty file) and a raw OSError met by the command line."""
    from bcmocap.atomic import DiskFull
    from bcmocap.correspondence_store import write_store
    from bcmocap.io.messages import one_line_error
    from bcmocap.io.opencv_calibration import write_opencv_storage
    from bcmocap.sim import standard_capture

    corr = standard_capture("walk", seconds=0.3, fps=10, seed=0).correspondences()
    with pytest.raises(DiskFull, match=f"no space left on the disk of {full_disk}: writing store/"):
        write_store(full_disk / "store", [corr])
    with pytest.raises(OSError):
        write_opencv_storage(full_disk / "lens.yml", {"camera_matrix": np.eye(3) * 1000.0})
    assert not (full_disk / "store").exists()
    try:
        open(full_disk / "raw.bin", "wb").write(b"\0" * 100_000)
    except OSError as exc:
        line = one_line_error(exc, folder=full_disk)  # a raw write's error names no file: the command's --out
    assert line.startswith(f"no space left on the disk of {full_disk}: writing its outputs needed more space")


def test_an_injected_full_disk_inside_an_atomic_write_names_what_was_written(tmp_path):
    """Where no filesystem can be mounted: ENOSPC raised at the write call, as the kernel would."""
    import errno

    from bcmocap.atomic import DiskFull, atomic_path

    with pytest.raises(DiskFull, match=r"writing out\.bin needed more than the 5 bytes written"):
        with atomic_path(tmp_path / "out.bin") as tmp:
            tmp.write_bytes(b"12345")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert list(tmp_path.iterdir()) == []
