"""Fuzzing the readers (issue 25, item 1): mutated and truncated copies of small valid files.

Every reader gets a seed folder of small valid files (made with the project's own writers or cut from the
bundled data) and a list of target files in it to mutate. A case copies the seed folder, replaces one target
by a mutated version (hypothesis draws the mutation: truncation, byte flips, deleted, inserted or repeated
runs, a number replaced by an awkward value) and calls the reader in a worker process, time-boxed. The case
*escapes* when the reader

- raises anything but the documented error types (ValueError; OSError where documented),
- raises a documented error whose message does not name the file (its name must appear),
- takes longer than the time box (a hang) or kills the worker (a crash),
- writes anything: the case folder must hold exactly the seed's files afterwards, the worker's working
  directory (an empty temporary folder) must stay empty.

``fuzz_reader`` is shared by ``benchmarks/reliability.py`` (the figures) and ``tests/test_fuzz_readers.py``.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import re
import shutil
import tempfile
import traceback
from pathlib import Path
from typing import Callable

import numpy as np

REPO = Path(__file__).resolve().parent.parent
AWKWARD = ["nan", "inf", "-inf", "1e309", "-1", "0", "1e9", "99999999999999999999", "x", "", '"a"', "[]", "{}",
           "null", "true", "-0", "0.5", "1e-320", "\x00", "\u00e9"]
NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


@dataclasses.dataclass(frozen=True)
class Reader:
    """A reader under test: ``make_seed(folder)`` writes valid files, ``targets`` are the ones to mutate
    (paths relative to the folder), ``read(folder)`` reads them; ``errors`` are the documented types."""

    make_seed: Callable[[Path], None]
    targets: tuple[str, ...]
    read: Callable[[Path], object]
    errors: tuple[type, ...] = (ValueError,)


# ---- seeds ----------------------------------------------------------------------------------------------

def _bvh_seed(folder: Path) -> None:
    text = (REPO / "tests" / "data" / "cmu" / "131_02_first40.bvh").read_text().splitlines()
    motion = next(i for i, line in enumerate(text) if line.strip().upper() == "MOTION")
    head = text[:motion + 1] + ["Frames: 3", next(l for l in text[motion:] if l.startswith("Frame Time"))]
    first = next(i for i, l in enumerate(text) if l.startswith("Frame Time")) + 1
    (folder / "seed.bvh").write_text("\n".join(head + text[first:first + 3]) + "\n")


def _read_bvh(folder: Path):
    from bcmocap.io.bvh import read_bvh

    return read_bvh(folder / "seed.bvh")


def _asf_seed(folder: Path) -> None:
    data = REPO / "bcmocap" / "data" / "cmu"
    shutil.copyfile(data / "35.asf", folder / "seed.asf")
    lines = (data / "35_01.amc").read_text().splitlines()
    starts = [i for i, l in enumerate(lines) if l.strip().isdigit()]
    (folder / "seed.amc").write_text("\n".join(lines[:starts[3]]) + "\n")  # the header and 3 frames


def _read_asf(folder: Path):
    from bcmocap.io.asf import read_asf

    return read_asf(folder / "seed.asf")


def _read_amc(folder: Path):
    from bcmocap.io.asf import read_amc, read_asf

    return read_amc(folder / "seed.amc", read_asf(folder / "seed.asf"))


def _c3d_seed(folder: Path) -> None:
    import ezc3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = ("A", "B", "C")
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    data = np.ones((4, 3, 4))
    data[:3] = np.arange(36, dtype=float).reshape(3, 3, 4) * 10.0 + 1.0
    c["data"]["points"] = data
    c.write(str(folder / "seed.c3d"))


def _read_c3d(folder: Path):
    from bcmocap.io.c3d import read_c3d

    return read_c3d(folder / "seed.c3d")


def _capture_seed(folder: Path) -> None:
    for sub in ("intrinsics", "reference", "trials/rom"):
        (folder / sub).mkdir(parents=True)
    (folder / "capture.json").write_text(json.dumps({
        "format": "bcmocap-capture", "version": 1, "settings": {"fps": 30.0, "audio_rate": 8000},
        "cameras": ["head", "foot"], "trials": ["rom"], "complete": True,
        "subject": {"topology": [["root", None, "free"], ["head", "root", "ball"]],
                    "measurements": [{"from": "root", "to": "head", "metres": 0.5}],
                    "rest": {"after_first_clap_s": 0.5}}}, indent=1))
    (folder / "rig.json").write_text(json.dumps({
        "cameras": [{"name": "head", "segment": "head"}, {"name": "foot", "segment": "root"}],
        "segments": ["root", "head"]}, indent=1))
    (folder / "intrinsics" / "head.json").write_text(json.dumps(
        {"model": "FOV", "width": 32, "height": 24, "params": [10.0, 10.0, 15.5, 11.5, 2.5]}))
    _yaml_seed(folder / "intrinsics", "foot.yml")
    (folder / "reference" / "camera.json").write_text(json.dumps(
        {"model": "PINHOLE", "width": 32, "height": 24, "params": [30.0, 30.0, 15.5, 11.5]}))


def _read_capture(folder: Path):
    from bcmocap.frontend.capture import read_capture

    return read_capture(folder, check_files=False)


def _yaml_seed(folder: Path, name: str = "seed.yml") -> None:
    from bcmocap.cameras import OpenCVFisheyeCamera
    from bcmocap.io.opencv_calibration import write_opencv_fisheye_calibration

    write_opencv_fisheye_calibration(folder / name, OpenCVFisheyeCamera(
        width=32, height=24, focal=[9.0, 9.0], principal_point=[15.5, 11.5], distortion=[0.1, 0.0, 0.0, 0.0]))


def _read_yaml(folder: Path):
    from bcmocap.io.opencv_calibration import read_opencv_fisheye_calibration

    return read_opencv_fisheye_calibration(folder / "seed.yml")


def _intrinsics_json_seed(folder: Path) -> None:
    (folder / "seed.json").write_text(json.dumps(
        {"model": "OPENCV_FISHEYE", "width": 32, "height": 24, "params": [9.0, 9.0, 15.5, 11.5, 0.1, 0.0, 0.0, 0.0]}))


def _read_intrinsics_json(folder: Path):
    from bcmocap.frontend.capture import read_camera_json

    return read_camera_json(folder / "seed.json")


def _model_seed(folder: Path) -> None:
    (folder / "model").mkdir()
    (folder / "model" / "skeleton.json").write_text(json.dumps({
        "names": ["root", "head"], "parents": [-1, 0], "offsets_m": [[0, 0, 0], [0, 0, 0.5]],
        "joint_types": ["free", "ball"], "hinge_axes": [[1, 0, 0], [1, 0, 0]]}, indent=1))
    (folder / "model" / "rig.json").write_text(json.dumps({"cameras": [
        {"name": "head", "segment": "head", "segment_from_camera": [1, 0, 0, 0, 0, 0.1, 0],
         "intrinsics": {"model": "FOV", "width": 32, "height": 24, "params": [10.0, 10.0, 15.5, 11.5, 2.5]}}]},
        indent=1))


def _read_model(folder: Path):
    from bcmocap.pipeline.run import load_model

    return load_model(folder)


def _store_seed(folder: Path) -> None:
    from bcmocap.correspondence_store import write_store
    from bcmocap.correspondences import Correspondences

    rng = np.random.default_rng(0)
    t, c, n, m, p = 5, 2, 3, 2, 6
    poses = np.zeros((t, c, 7))
    poses[..., 0] = 1.0
    ids = rng.integers(0, p, (t, c, n)).astype(np.int32)
    ids[0, 0, 2] = -1
    weights = np.where(ids >= 0, 1.0, 0.0)
    corr = Correspondences(rng.normal(size=(p, 3)), ids, rng.uniform(0, 30, (t, c, n, 2)), weights,
                           rng.uniform(0, 30, (t, c, m, 2)), rng.uniform(0, 30, (t, c, m, 2)),
                           np.ones((t, c, m)), poses, np.ones((t, c), bool), 30.0)
    write_store(folder / "store", [corr], block_frames=3)


def _read_store(folder: Path):
    from bcmocap.correspondence_store import CorrespondenceStore

    store = CorrespondenceStore.open(folder / "store")
    return store.frames(0, store.num_frames), store.frames(store.num_frames - 1, store.num_frames)


_CONFIG = {"frontend": {"stride": 2, "max_features": 1000}, "skeleton": {"rest_seconds": [0.0, 1.0]},
           "solver": {"window": 30, "overlap": 5, "root_smoothness": 10.0, "loss": "huber", "loss_scale": 2.0},
           "outputs": {"pictures": False}}


def _config_toml_seed(folder: Path) -> None:
    lines = []
    for section, values in _CONFIG.items():
        lines.append(f"[{section}]")
        lines += [f"{k} = {json.dumps(v)}" for k, v in values.items()]
    (folder / "seed.toml").write_text("\n".join(lines).replace("false", "false") + "\n")


def _config_json_seed(folder: Path) -> None:
    (folder / "seed.json").write_text(json.dumps(_CONFIG, indent=1))


def _read_config(name: str):
    def read(folder: Path):
        from bcmocap.pipeline.config import load_config

        return load_config(folder / name)
    return read


def _ply_seed(folder: Path) -> None:
    from bcmocap.io.ply import write_camera_paths_ply, write_ply

    points = np.arange(12, dtype=float).reshape(4, 3) / 7.0
    write_ply(folder / "binary.ply", points, np.full((4, 3), 200, np.uint8))
    write_ply(folder / "ascii.ply", points, binary=False)
    write_camera_paths_ply(folder / "paths.ply", np.arange(18, dtype=float).reshape(3, 2, 3))


def _read_ply(folder: Path):
    from bcmocap.io.ply import read_ply, read_ply_elements

    return [read_ply(folder / name) for name in ("binary.ply", "ascii.ply")] + [read_ply_elements(folder / "paths.ply")]


def _sensors_seed(folder: Path) -> None:
    from bcmocap.io.sensors import ContactRecording, ImuRecording, write_contacts, write_imu

    time = np.arange(4) / 100.0
    write_imu(folder / "imu.npz", ImuRecording(time, 100.0, ("head", "foot"), np.tile([1.0, 0, 0, 0, 0, 0, 0], (2, 1)),
                                               np.zeros((4, 2, 3)), np.full((4, 2, 3), 9.81)))
    write_contacts(folder / "contacts.npz", ContactRecording(time, ("left_foot",), np.ones((4, 1), bool)))


def _read_sensors(folder: Path):
    from bcmocap.io.sensors import read_contacts, read_imu

    return read_imu(folder / "imu.npz"), read_contacts(folder / "contacts.npz")


READERS: dict[str, Reader] = {
    "bvh": Reader(_bvh_seed, ("seed.bvh",), _read_bvh),
    "asf": Reader(_asf_seed, ("seed.asf",), _read_asf),
    "amc": Reader(_asf_seed, ("seed.amc",), _read_amc),
    "c3d": Reader(_c3d_seed, ("seed.c3d",), _read_c3d),
    "capture_json": Reader(_capture_seed, ("capture.json", "rig.json"), _read_capture),
    "intrinsics_yaml": Reader(lambda f: _yaml_seed(f), ("seed.yml",), _read_yaml),
    "intrinsics_json": Reader(_intrinsics_json_seed, ("seed.json",), _read_intrinsics_json),
    "model_json": Reader(_model_seed, ("model/skeleton.json", "model/rig.json"), _read_model),
    "store": Reader(_store_seed, ("store/index.json", "store/block_000000.npz", "store/poses.npz"), _read_store),
    "config_toml": Reader(_config_toml_seed, ("seed.toml",), _read_config("seed.toml")),
    "config_json": Reader(_config_json_seed, ("seed.json",), _read_config("seed.json")),
    "ply": Reader(_ply_seed, ("binary.ply", "ascii.ply", "paths.ply"), _read_ply),
    "sensors": Reader(_sensors_seed, ("imu.npz", "contacts.npz"), _read_sensors),
}


# ---- mutations ------------------------------------------------------------------------------------------

def mutations():
    """A hypothesis strategy of functions ``bytes -> bytes`` (one to three edits)."""
    from hypothesis import strategies as st

    def at(fraction: float, data: bytes) -> int:
        return min(len(data), int(fraction * (len(data) + 1)))

    fractions = st.floats(0.0, 1.0, allow_nan=False)
    truncate = st.builds(lambda f: lambda d: d[:at(f, d)], fractions)
    flip = st.builds(lambda f, b: lambda d: d[:at(f, d)] + bytes([b]) + d[at(f, d) + 1:], fractions,
                     st.integers(0, 255))
    delete = st.builds(lambda f, n: lambda d: d[:at(f, d)] + d[at(f, d) + n:], fractions, st.integers(1, 64))
    insert = st.builds(lambda f, b: lambda d: d[:at(f, d)] + b + d[at(f, d):], fractions, st.binary(min_size=1, max_size=16))
    repeat = st.builds(lambda f, n, k: lambda d: d[:at(f, d) + n] + d[at(f, d):at(f, d) + n] * k + d[at(f, d) + n:],
                       fractions, st.integers(1, 64), st.integers(1, 3))

    def swap_number(f, value):
        def edit(d: bytes) -> bytes:
            numbers = list(NUMBER.finditer(d))
            if not numbers:
                return d
            hit = numbers[min(len(numbers) - 1, int(f * len(numbers)))]
            return d[:hit.start()] + value.encode() + d[hit.end():]
        return edit

    number = st.builds(swap_number, fractions, st.sampled_from(AWKWARD))
    edit = st.one_of(truncate, flip, delete, insert, repeat, number)

    def compose(edits):
        def apply(d: bytes) -> bytes:
            for e in edits:
                d = e(d)
            return d
        return apply

    return st.lists(edit, min_size=1, max_size=3).map(compose)


# ---- the worker -----------------------------------------------------------------------------------------

def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _case(reader_name: str, seed: str, target: str, data: bytes, work: str) -> tuple[str, str]:
    """Run one case in the worker: ``("ok" | "error" | "escape", detail)``."""
    import gc
    import warnings

    reader = READERS[reader_name]
    folder = Path(work) / "case"
    shutil.rmtree(folder, ignore_errors=True)
    shutil.copytree(seed, folder)
    (folder / target).write_bytes(data)
    expected = _files(folder)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reader.read(folder)
        outcome = ("ok", "")
    except reader.errors as exc:
        message = str(exc)
        name = Path(target).name
        if name in message or (reader_name == "store" and "store" in message):
            outcome = ("error", message.splitlines()[0][:200] if message else "")
        else:
            outcome = ("escape", f"{type(exc).__name__} not naming {name}: {message[:200]}")
    except BaseException as exc:  # noqa: BLE001 - any other type is what we count
        tb = traceback.extract_tb(exc.__traceback__)
        where = f"{Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else "?"
        outcome = ("escape", f"{type(exc).__name__} at {where}: {str(exc)[:200]}")
    gc.collect()  # memory maps of a store are closed before the folder is compared and removed
    if _files(folder) != expected:
        outcome = ("escape", f"wrote files: {sorted(set(_files(folder)) - set(expected))}")
    strays = [p for p in Path(work).iterdir() if p.name != "case"]
    if strays:
        outcome = ("escape", f"wrote outside the case folder: {[p.name for p in strays]}")
        for p in strays:
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink()
    return outcome


def _worker(conn, work: str) -> None:
    import os

    os.chdir(work)
    from bcmocap.precision import enable_float64

    enable_float64()
    while True:
        job = conn.recv()
        if job is None:
            return
        try:
            conn.send(_case(*job, work))
        except BaseException as exc:  # noqa: BLE001
            conn.send(("escape", f"harness: {type(exc).__name__}: {exc}"))


class Worker:
    """A reader process with a time box per case; restarted after a hang or a crash."""

    def __init__(self, timeout: float = 10.0):
        self.timeout = timeout
        self._tmp = tempfile.TemporaryDirectory(prefix="bcmocap-fuzz-")
        self.work = Path(self._tmp.name) / "work"
        self.work.mkdir()
        self._process = None

    def _start(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_worker, args=(child, str(self.work)), daemon=True)
        self._process.start()

    def run(self, reader: str, seed: Path, target: str, data: bytes, timeout: float | None = None) -> tuple[str, str]:
        if self._process is None or not self._process.is_alive():
            self._start()
        self._conn.send((reader, str(seed), target, data))
        if self._conn.poll(timeout or self.timeout):
            try:
                return self._conn.recv()
            except (EOFError, OSError):
                pass
        code = self._process.exitcode
        self._process.kill()
        self._process.join()
        self._process = None
        return ("escape", f"crash (exit code {code})" if code is not None else f"hang (> {timeout or self.timeout:g} s)")

    def close(self) -> None:
        if self._process is not None and self._process.is_alive():
            self._conn.send(None)
            self._process.join(5)
            if self._process.is_alive():
                self._process.kill()
        self._tmp.cleanup()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


@dataclasses.dataclass
class FuzzResult:
    cases: int = 0
    escapes: int = 0
    valid: int = 0  # mutations the reader accepted (not an escape: many edits keep a file valid)
    examples: list[str] = dataclasses.field(default_factory=list)  # the first few escapes, deduplicated


def fuzz_reader(name: str, examples: int, worker: Worker, seed: int = 0, on_escape: Callable | None = None) -> FuzzResult:
    """``examples`` hypothesis cases per target file of reader ``name``; the seed run must read cleanly."""
    reader = READERS[name]
    result = FuzzResult()
    with tempfile.TemporaryDirectory(prefix=f"bcmocap-seed-{name}-") as tmp:
        folder = Path(tmp) / "seed"
        folder.mkdir()
        reader.make_seed(folder)
        for target in reader.targets:
            _fuzz_target(name, folder, target, examples, worker, seed, result, on_escape)
    return result


def _fuzz_target(name, folder, target, examples, worker, seed, result, on_escape) -> None:
    from hypothesis import HealthCheck, given, settings
    from hypothesis import seed as hypothesis_seed

    original = (folder / target).read_bytes()
    kind, detail = worker.run(name, folder, target, original, timeout=max(60.0, worker.timeout))
    if kind != "ok":
        raise RuntimeError(f"{name}: the valid seed {target} does not read: {detail}")

    @hypothesis_seed(seed)
    @settings(max_examples=examples, deadline=None, database=None, derandomize=False,
              suppress_health_check=list(HealthCheck))
    @given(mutation=mutations())
    def case(mutation):
        data = mutation(original)
        kind, detail = worker.run(name, folder, target, data)
        result.cases += 1
        result.valid += kind == "ok"
        if kind == "escape":
            result.escapes += 1
            line = f"{target}: {detail}"
            key = re.sub(r"\d+", "#", line)[:120]
            if len(result.examples) < 20 and key not in {re.sub(r"\d+", "#", e)[:120] for e in result.examples}:
                result.examples.append(line)
            if on_escape is not None:
                on_escape(target, data, detail)

    case()
