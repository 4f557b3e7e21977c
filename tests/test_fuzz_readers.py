"""Fuzzed readers (issue 25, item 1): mutated and truncated copies of small valid files give only the
documented errors, naming the file, within a time box and without writing (benchmarks/_fuzz.py; the
figures come from benchmarks/reliability.py with many more cases)."""

import json
import time

import numpy as np
import pytest

from benchmarks._fuzz import READERS, Worker, fuzz_reader
from bcmocap.correspondence_store import CorrespondenceStore
from bcmocap.io.c3d import read_c3d
from bcmocap.io.model_json import rig_from_dict, skeleton_from_dict

@pytest.fixture(scope="module")
def worker():
    with Worker(timeout=20.0) as w:
        yield w


@pytest.mark.parametrize("reader", sorted(READERS))
def test_fuzzed_reader_gives_only_documented_errors_naming_the_file(worker, reader):
    def fail(target, data, detail):
        raise AssertionError(f"{reader} {target} ({len(data)} bytes): {detail}")

    result = fuzz_reader(reader, 8, worker, seed=1, on_escape=fail)
    assert result.cases == 8 * len(READERS[reader].targets) and result.escapes == 0


def _seed(reader, tmp_path):
    READERS[reader].make_seed(tmp_path)
    return tmp_path


def test_a_c3d_cut_inside_its_parameter_section_is_refused_not_a_hang(tmp_path):
    path = _seed("c3d", tmp_path) / "seed.c3d"
    path.write_bytes(path.read_bytes()[:783])  # ezc3d looped forever on this one
    start = time.perf_counter()
    with pytest.raises(ValueError, match=r"seed\.c3d: truncated: .* announce at least 1536 bytes, the file has 783"):
        read_c3d(path)
    assert time.perf_counter() - start < 5.0


def test_a_c3d_with_bytes_missing_from_its_parameter_section_is_refused_not_a_crash(worker, tmp_path):
    """50 bytes deleted inside a parameter record (found by the fuzzer): ezc3d crashed the process (SIGSEGV)."""
    folder = _seed("c3d", tmp_path)
    data = (folder / "seed.c3d").read_bytes()
    at = data.index(b"FORCE_PLATFORM") - 4
    kind, detail = worker.run("c3d", folder, "seed.c3d", data[:at] + data[at + 50:])  # in a process of its own
    assert kind == "error", detail
    assert "seed.c3d: not a readable C3D file (its parameter section is damaged: parameter record" in detail


def test_a_damaged_store_names_the_file(tmp_path):
    store = _seed("store", tmp_path) / "store"
    block = store / "block_000000.npz"
    data = block.read_bytes()
    block.write_bytes(data[:len(data) // 2])  # a BadZipFile before
    opened = CorrespondenceStore.open(store)
    with pytest.raises(ValueError, match=r"block_000000\.npz: not a readable block"):
        opened.frames(0, 2)
    index = json.loads((store / "index.json").read_text())
    for field, value, message in [("blocks", [[0, 3, "../../elsewhere.npz"], [3, 5, "b.npz"]], r"blocks\[0\]"),
                                  ("points", [6], r"field 'points' must be a non-negative integer"),
                                  ("fps", "30", r"field 'fps' must be a positive number")]:
        (store / "index.json").write_text(json.dumps({**index, field: value}))
        with pytest.raises(ValueError, match=r"index\.json: " + message):
            CorrespondenceStore.open(store)
    (store / "index.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"index\.json: format 'list'"):
        CorrespondenceStore.open(store)


def test_a_block_with_wrong_shapes_or_ids_names_the_file(tmp_path):
    store = _seed("store", tmp_path) / "store"
    block = store / "block_000000.npz"
    with np.load(block) as archive:
        data = dict(archive)
    np.savez(block, **{**data, "point_ids": np.full_like(data["point_ids"], 99)})
    with pytest.raises(ValueError, match=r"block_000000\.npz: point_ids outside \[-1, 6\)"):
        CorrespondenceStore.open(store).frames(0, 5)
    np.savez(block, **{**data, "pixels": data["pixels"][..., :1]})
    with pytest.raises(ValueError, match=r"block_000000\.npz: pixels has shape"):
        CorrespondenceStore.open(store).frames(0, 5)


def test_a_rig_with_a_malformed_number_names_the_file():
    skeleton = skeleton_from_dict({"names": ["root"], "parents": [-1], "offsets_m": [[0, 0, 0]],
                                   "joint_types": ["free"], "hinge_axes": [[1, 0, 0]]}, "skeleton.json")
    camera = {"name": "c", "segment": "root", "segment_from_camera": [1, 0, 0, 0, 0, 0, "a"],
              "intrinsics": {"model": "PINHOLE", "width": 4, "height": 4, "params": [1, 1, 2, 2]}}
    with pytest.raises(ValueError, match=r"^model/rig\.json: could not convert"):
        rig_from_dict({"cameras": [camera]}, skeleton, "model/rig.json")


def test_a_bvh_announcing_more_frames_than_lines_is_refused_before_allocating(tmp_path):
    path = _seed("bvh", tmp_path) / "seed.bvh"
    path.write_text(path.read_text().replace("Frames: 3", "Frames: 99999999999999999999"))
    with pytest.raises(ValueError, match=r"seed\.bvh:\d+: 'Frames: 99999999999999999999' but the file has only \d+ lines"):
        from bcmocap.io.bvh import read_bvh

        read_bvh(path)
