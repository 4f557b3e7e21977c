"""Reliability as figures (issue 25): fuzzed readers, kill -9 anywhere, determinism, the output lock, path safety.

    python benchmarks/reliability.py --json benchmarks/results/reliability.json

1. **fuzz** — every reader of ``benchmarks/_fuzz.py`` on ``--fuzz-examples`` mutated and truncated copies of
   each of its files (hypothesis, seeded): cases and escapes (another exception type, a message not naming
   the file, a hang past ``--fuzz-timeout`` s, a crash, a write).
2. **kill -9** — each command killed at seeded points and resumed; after every kill each output under its
   final name must load, and the final outputs must equal those of an uninterrupted run (arrays within
   ``--tolerance``, other files byte for byte):

   - ``bcmocap simulate`` on a tiny capture, at ``--kill-points`` seeded random times;
   - the stages after the frontend of ``bcmocap run`` (world, skeleton, initial, solve, outputs:
     ``run_pipeline`` in a subprocess on a simulated capture whose frontend output is given, as in
     tests/test_pipeline_run.py);
   - on pixels: ``bcmocap frontend`` (global registration, 6 frames per trial) and ``bcmocap run`` (tracking
     registration, every stage) on a small rendered capture (``PIXELS_SIMULATE``: 18 cameras, 3 s of range
     of motion and 0.5 s of walk at 8 fps, 640×360, 20 reference photos).

   The staged commands are killed ``--points-per-stage`` times in every stage (half as often, at least once, for
   ``bcmocap run`` on pixels, which has ten): the stages' start lines
   and lengths come from an uninterrupted run, and each kill waits for its stage's line in the (resumed)
   run (a stage of ``bcmocap run`` the resumed run had finished is first forgotten in its ``run.json``, as a
   settings change would), then a seeded fraction of the stage's length. ``--atomic-points`` more kills each fall inside an
   atomic write: the command is killed as soon as a seeded how-many-th temporary file (``.name.*``, the
   temporaries of :mod:`bcmocap.atomic` and of the feature cache) appears in its output folder.
3. **determinism** — each uninterrupted command run twice: files bitwise equal, and the largest difference of
   those that are not.
4. **concurrent runs** — ``bcmocap run`` on an ``--out`` a running pipeline holds must be refused.
5. **path escapes** — tests/test_path_safety.py's hostile captures (failures counted).
6. **faults of a shared machine** (issue 48, :mod:`_faults`; needs root, for tmpfs mounts and a memory cgroup):
   ``disk_full`` (``--disk-points`` sizes of a full disk for ``bcmocap simulate`` and for the stages after the
   frontend, each resumed after space is freed), ``changing_folders`` (a read-only ``--out``, one deleted and
   a capture file rewritten mid-run), ``corrupt_cache`` (ten damaged entries of the two caches) and
   ``concurrent_edits`` (``--edit-clients`` viewer saves at once, ``--edit-rounds`` times, and a save during a
   run).

7. **a memory cap** — ``bcmocap run`` with its default settings on a ``--memory-seconds`` capture (rendered at
   ``--memory-fps``, or the capture given by ``--memory-capture``) inside a memory cgroup of ``--memory-cap-gb``:
   whether it finishes, the cgroup's peak and each stage's peak from ``run.json`` (``memory_cap``).

``--only-faults --update`` runs sections 6 and 7 alone and replaces its rows in an existing results file, whose other
sections keep the commit and date they were measured at (``sections``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_json  # noqa: E402
from _fuzz import READERS, Worker, fuzz_reader  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
PYTHON = sys.executable
BCMOCAP = [str(Path(PYTHON).parent / "bcmocap")]
SIMULATE = ["--seconds", "0.5", "--rom-seconds", "0.5", "--fps", "20", "--width", "160", "--height", "90",
            "--reference-photos", "4", "--reference-size", "320x240", "--no-progress"]
FPS = 20.0
VOLATILE = {"log.txt", "run.json", "run.lock"}  # times and pids
# The small rendered capture of the pixel commands, and their settings (a few minutes per run on 2 cores).
PIXELS_SIMULATE = ["--seconds", "0.5", "--rom-seconds", "3", "--fps", "8", "--width", "640", "--height", "360",
                   "--reference-photos", "20", "--reference-size", "640x480", "--seed", "1", "--no-progress"]
PIXELS_FRONTEND = ["--max-features", "2000", "--frames", "6", "--registration", "global", "--max-measurements", "0",
                   "--points", "all"]
PIXELS_RUN_CONFIG = """[frontend]
stride = 1
rom_stride = 1
max_features = 2000
registration = "tracking"
max_measurements = 400

[skeleton]
max_centre_std_cm = 30.0  # about 25 range-of-motion frames: a loose skeleton is enough here

[solver]
window = 10
overlap = 3
"""
# Stages of the staged commands: (name, pattern of the line that starts it).
RUN_STAGES = [(name, rf"\[{k}/6\] {name} \.\.\.") for k, name in enumerate(
    ("frontend", "world", "skeleton", "initial", "solve", "outputs"), start=1)]
FRONTEND_STAGES = [("reference", r"^reference: \d+ photos \.\.\."), ("rom features", r"^rom: first clap"),
                   ("rom registration", r"^  rom (absolute|new points|relative)"),
                   ("capture features", r"^capture: first clap"),
                   ("capture registration", r"^  capture (absolute|new points|relative)")]
PIXEL_RUN_STAGES = [("reference", r"^reference: \d+ photos \.\.\."), ("rom tracking", r"^rom: first clap"),
                    ("rom registration", r"^rom: tracking registered"), ("capture tracking", r"^capture: first clap"),
                    ("capture registration", r"^capture: tracking registered")] + RUN_STAGES[1:]


# ---- the run driver (a subprocess: the stages after the frontend on a simulated capture) ------------------

def _fake_capture(root: Path):
    """The simulated capture and run settings of tests/test_pipeline_run.py (a smaller solve)."""
    import dataclasses

    import numpy as np

    from bcmocap.cameras import camera_at
    from bcmocap.correspondences import Correspondences
    from bcmocap.frontend.capture import Capture, CaptureCamera
    from bcmocap.geometry import SO3
    from bcmocap.pipeline import RunConfig, Similarity
    from bcmocap.sim import standard_capture
    from bcmocap.sim.rom import range_of_motion_trial
    from bcmocap.sim.studio import studio_subject

    capture = standard_capture("walk", seconds=1.5, fps=FPS, seed=2)
    skeleton, rig = capture.skeleton, capture.rig
    rom = range_of_motion_trial(skeleton, rig, fps=FPS, hold_seconds=1.0, seconds_per_joint=2.0,
                                rotation_sigma_deg=0.3, position_sigma_m=0.003, seed=3)
    t, c = rom.registered.shape
    empty = lambda *shape: np.zeros(shape)  # noqa: E731
    rom_corr = Correspondences(np.zeros((1, 3)), np.full((t, c, 1), -1, np.int32), empty(t, c, 1, 2), empty(t, c, 1),
                               empty(t, c, 1, 2), empty(t, c, 1, 2), empty(t, c, 1), rom.world_from_camera,
                               rom.registered, FPS)
    sfm_from_world = Similarity(0.37, np.asarray(SO3.exp(np.array([0.4, -1.1, 2.0])).as_matrix()),
                                np.array([3.0, -1.0, 0.5]))
    config = RunConfig().with_overrides({"frontend.stride": 1, "frontend.rom_stride": 1, "solver.window": 10,
                                         "solver.overlap": 3})
    trials = {trial: dataclasses.replace(corr, points=sfm_from_world.points(corr.points),
                                         world_from_camera=sfm_from_world.poses(corr.world_from_camera))
              for trial, corr in (("rom", rom_corr), ("capture", capture.correspondences()))}
    subject = studio_subject(skeleton, 0, FPS)
    subject["rest"] = {"trial": "rom", "after_first_clap_s": [0.0, 0.9]}
    cameras = tuple(CaptureCamera(n, skeleton.names[s], camera_at(rig.intrinsics, i), None)
                    for i, (n, s) in enumerate(zip(rig.names, rig.segments)))
    fake = Capture(root / "capture", {"subject": subject}, FPS, None, cameras, tuple(skeleton.names),
                   ("rom", "capture"), (), None)
    return fake, config, trials, rig


def _write_frontend(out: Path) -> None:
    """``out/frontend`` as a finished frontend stage would leave it."""
    import pycolmap

    from bcmocap.correspondence_store import write_store
    from bcmocap.frontend.command import trial_settings

    fake, config, trials, rig = _fake_capture(out.parent)
    f = config.frontend
    for trial, sfm in trials.items():
        write_store(out / "frontend" / trial / "correspondences", [sfm], block_frames=7)
        settings = trial_settings(stride=1, frames=None, max_features=f.max_features, homographies=trial == "capture",
                                  chunk_frames=f.chunk_frames, registration=f.registration,
                                  max_measurements=f.max_measurements or None, points=f.points)
        (out / "frontend" / trial / "registration.json").write_text(json.dumps(
            {"stride": 1, "frames": sfm.num_frames, "registered_fraction": float(sfm.registered.mean()),
             "cameras": list(rig.names), "settings": settings}))
    (out / "frontend" / "reference" / "model").mkdir(parents=True)
    pycolmap.Reconstruction().write(str(out / "frontend" / "reference" / "model"))


def _drive(out: Path) -> int:
    from bcmocap.compilation_cache import enable_compilation_cache
    from bcmocap.pipeline import run_pipeline
    from bcmocap.precision import enable_float64

    enable_float64()
    enable_compilation_cache()
    from bcmocap.io.messages import one_line_error

    fake, config, _, _ = _fake_capture(out.parent)
    try:
        run_pipeline(fake, out, config, log=lambda line: print(line, flush=True))
    except (ValueError, OSError, MemoryError) as exc:  # as bcmocap's command line reports them
        print(f"bcmocap run: {one_line_error(exc, out)}", file=sys.stderr)
        return 2
    return 0


# ---- comparing output folders -------------------------------------------------------------------------

def _outputs(folder: Path) -> dict[str, Path]:
    """Files under their final names (temporaries of atomic writes start with a dot)."""
    return {str(p.relative_to(folder)): p for p in sorted(folder.rglob("*")) if p.is_file()
            and not any(part.startswith(".") for part in p.relative_to(folder).parts)}


NUMBER = re.compile(rb"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def _difference(a: Path, b: Path) -> float | None:
    """0.0 when bitwise equal; the largest difference of numbers; None when not comparable (other content)."""
    import numpy as np

    x, y = a.read_bytes(), b.read_bytes()
    if x == y:
        return 0.0
    if a.suffix == ".json":  # timings ("seconds") are not outputs
        try:
            p, q = (_without_timings(json.loads(z)) for z in (x, y))
        except ValueError:
            return None
        x, y = (json.dumps(z, sort_keys=True).encode() for z in (p, q))
        if x == y:
            return TIMINGS_ONLY
    if a.suffix == ".npz":
        with np.load(a) as p, np.load(b) as q:
            if sorted(p.files) != sorted(q.files) or any(p[k].shape != q[k].shape for k in p.files):
                return None
            diffs = [float(np.nanmax(np.abs(p[k].astype(float) - q[k].astype(float)), initial=0.0))
                     for k in p.files if p[k].dtype.kind in "fiub"]
            equal = all(np.array_equal(p[k], q[k]) for k in p.files if p[k].dtype.kind not in "fiub")
            return max(diffs, default=0.0) if equal else None
    if a.suffix == ".db":  # SQLite (COLMAP's database): the same rows can sit in other pages; compare the rows
        return 0.0 if _sqlite_rows(a) == _sqlite_rows(b) else None
    if a.suffix in (".png", ".bin", ".f64") or b"\0" in x[:4096]:
        if a.suffix == ".f64" and len(x) == len(y):
            return float(np.max(np.abs(np.frombuffer(x, "<f8") - np.frombuffer(y, "<f8")), initial=0.0))
        return None
    nx, ny = NUMBER.findall(x), NUMBER.findall(y)
    if len(nx) != len(ny) or NUMBER.sub(b"#", x) != NUMBER.sub(b"#", y):
        return None
    return max(abs(float(u) - float(v)) for u, v in zip(nx, ny))


TIMINGS_ONLY = -1.0  # _difference: equal once the "seconds" fields are left out


def _sqlite_rows(path: Path) -> dict:
    """Every table of an SQLite file as its sorted rows (read as immutable: the comparison writes nothing beside it)."""
    import sqlite3

    with sqlite3.connect(f"file:{path}?immutable=1", uri=True) as db:  # immutable: no -shm or -wal file is made
        tables = [t for (t,) in db.execute("SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")]
        return {t: sorted(db.execute(f'SELECT * FROM "{t}"').fetchall(), key=repr) for t in tables}


def _without_timings(value):
    if isinstance(value, dict):
        return {k: _without_timings(v) for k, v in value.items() if k != "seconds"}
    return [_without_timings(v) for v in value] if isinstance(value, list) else value


def compare(reference: Path, other: Path, tolerance: float) -> dict:
    """``{"bitwise_equal": n, "differing": [{"file", "max_difference"}], "mismatches": [...],
    "equal_but_timings": [files equal once their "seconds" fields are left out]}``."""
    ref, oth = _outputs(reference), _outputs(other)
    equal, differing, mismatches, timings = 0, [], [], []
    for name in sorted(set(ref) | set(oth)):
        if name in VOLATILE or name.startswith("capture/"):
            continue
        if name not in ref or name not in oth:
            mismatches.append({"file": name, "why": "only in " + ("reference" if name in ref else "other")})
            continue
        d = _difference(ref[name], oth[name])
        if d == 0.0:
            equal += 1
            continue
        if d == TIMINGS_ONLY:
            timings.append(name)
            continue
        differing.append({"file": name, "max_difference": d})
        if d is None or d > tolerance:
            mismatches.append({"file": name, "why": "not comparable" if d is None else f"differs by {d:.3g}"})
    return {"bitwise_equal": equal, "differing": differing, "mismatches": mismatches, "equal_but_timings": timings}


def partial_files(folder: Path) -> list[str]:
    """Outputs under their final names that do not load (a partial file would not)."""
    import numpy as np

    from bcmocap.io.bvh import read_bvh
    from bcmocap.io.ply import read_ply_elements

    bad = []
    for name, path in _outputs(folder).items():
        try:
            if path.suffix == ".json" and name not in VOLATILE:
                json.loads(path.read_text())
            elif path.suffix == ".npz":
                with np.load(path) as archive:
                    [archive[k] for k in archive.files]
            elif path.suffix == ".ply":
                read_ply_elements(path)
            elif path.suffix == ".bvh":
                read_bvh(path)
        except Exception as exc:  # noqa: BLE001 - any failure to load is a partial file
            bad.append(f"{name}: {type(exc).__name__}: {str(exc)[:100]}")
    return bad


# ---- kill -9 and resume ----------------------------------------------------------------------------------

def _timed(command: list[str], log: Path) -> float:
    start = time.perf_counter()
    with open(log, "ab") as fh:
        subprocess.run(command, stdout=fh, stderr=subprocess.STDOUT, check=True, cwd=REPO)
    return time.perf_counter() - start


def _stage_of(out: Path) -> str:
    """The stage a run was in, from its log (``[k/6] stage ...``)."""
    log = out / "log.txt"
    if not log.is_file():
        return "start"
    lines = log.read_text(errors="replace").splitlines()
    stage = next((m.group(1) for line in reversed(lines) if (m := re.search(r"\[\d/6\] (\w+)", line))), "start")
    return stage


def _rewind_run(out: Path, stage: str) -> None:
    """Forget ``stage`` and the stages after it in a run's ``run.json`` (as a settings change would), so a
    kill aimed at a stage the resumed run already finished finds it again; other stages are left alone."""
    from bcmocap.pipeline.run import STAGES

    log = out / "run.json"
    if stage in STAGES and log.is_file():
        data = json.loads(log.read_text())
        if stage not in data.get("stages", {}):
            return  # not done yet: the resumed run comes to it
        data["stages"] = {k: v for k, v in data["stages"].items() if STAGES.index(k) < STAGES.index(stage)}
        log.write_text(json.dumps(data, indent=2) + "\n")
        if STAGES.index(stage) <= STAGES.index("solve"):  # the solve would resume after its last window
            for name in ("checkpoint.npz", "checkpoint.json"):
                (out / "solve" / name).unlink(missing_ok=True)


def _restart_if_finished(out: Path) -> None:
    """A run that finished before its kill starts its stages again, so later kills still find them."""
    if (out / "run.json").is_file() and "outputs" in json.loads((out / "run.json").read_text()).get("stages", {}):
        for p in (out / "run.json", out / "motion.bvh"):
            p.unlink(missing_ok=True)


def kill_resume(command: list[str], out: Path, reference: Path, points: int, duration: float, rng,
                tolerance: float, log: Path, stage=_stage_of, restart=_restart_if_finished) -> dict:
    """Kill ``command`` at ``points`` seeded times, checking for partial files after each kill, then let it
    finish and compare with ``reference``. Times are drawn from [0.05, 1] of ``duration`` (a warm run) after
    each (re)start; an attempt that finishes first is not counted, and ``restart(out)`` gives the next one
    work to do."""
    kills, partial, attempts = [], [], 0
    with open(log, "ab") as fh:
        while len(kills) < points and attempts < 3 * points:
            attempts += 1
            delay = float(rng.uniform(0.05, 1.0)) * duration
            process = subprocess.Popen(command, stdout=fh, stderr=subprocess.STDOUT, cwd=REPO, start_new_session=True)
            try:
                process.wait(delay)
                restart(out)
                continue  # finished before the kill: not a kill point (the outputs are compared at the end)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
            kills.append({"after_s": round(delay, 2), "stage": stage(out)})
            partial += partial_files(out)
    return _finish(command, out, reference, tolerance, log, kills, partial)


def _restart_simulate(out: Path) -> None:
    """A finished capture loses every other video and is marked unfinished, so the next attempt renders again."""
    manifest = out / "capture.json"
    if manifest.is_file() and json.loads(manifest.read_text()).get("complete"):
        for video in sorted(out.glob("trials/*/*.mp4"))[::2]:
            video.unlink()
        manifest.write_text(json.dumps({**json.loads(manifest.read_text()), "complete": False}, indent=1))


def _finish(command, out: Path, reference: Path, tolerance: float, log: Path, kills: list, partial: list) -> dict:
    """Run ``command`` to the end after its kills and compare its outputs with ``reference``'s."""
    _timed(command, log)
    result = compare(reference, out, tolerance)
    return {"points": len(kills), "kills": kills, "partial_files": partial, **result,
            "mismatches": len(result["mismatches"]) + len(partial), "mismatch_list": result["mismatches"]}


# ---- staged commands: stage lines, kills inside each stage and inside atomic writes ----------------------

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


class _Watched:
    """A command whose output lines are timed (and appended to the log) as they come; ``stage`` is the index
    of the last stage whose start line was seen (−1 before the first)."""

    def __init__(self, command: list[str], log, stages: list[tuple[str, str]]):
        import threading

        self.patterns = [re.compile(p) for _, p in stages]
        self.start = time.perf_counter()
        self.lines: list[tuple[float, str]] = []
        self.stage = -1
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=REPO, env=ENV,
                                        start_new_session=True, text=True, errors="replace")
        self.log = log
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        for line in self.process.stdout:
            now = time.perf_counter() - self.start
            self.lines.append((now, line.rstrip("\n")))
            self.log.write(line)
            for k, pattern in enumerate(self.patterns):
                if k > self.stage and pattern.search(line):
                    self.stage = k
        self.log.flush()

    def kill(self) -> float:
        t = time.perf_counter() - self.start
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.wait()
        return t

    def wait(self) -> int:
        code = self.process.wait()
        self.thread.join()
        return code


def timeline(command: list[str], log: Path, stages: list[tuple[str, str]]) -> tuple[float, dict]:
    """Run ``command`` uninterrupted: ``(seconds, {stage: (start_s, length_s)})`` from its stage lines."""
    with open(log, "a") as fh:
        watched = _Watched(command, fh, stages)
        if watched.wait() != 0:
            raise RuntimeError(f"{' '.join(command)} failed; see {log}")
    total = time.perf_counter() - watched.start
    starts = {}
    for t, line in watched.lines:
        for name, pattern in stages:
            if name not in starts and re.search(pattern, line):
                starts[name] = t
    names = [n for n, _ in stages if n in starts]
    ends = [starts[n] for n in names[1:]] + [total]
    return total, {n: (round(starts[n], 2), round(e - starts[n], 2)) for n, e in zip(names, ends)}


def _temporaries(out: Path) -> set[str]:
    """Temporary files and folders of atomic writes under ``out`` (their names start with a dot)."""
    found = set()
    for folder, dirs, files in os.walk(out):
        for name in dirs + files:
            if name.startswith("."):
                found.add(os.path.relpath(os.path.join(folder, name), out))
        dirs[:] = [d for d in dirs if not d.startswith(".")]
    return found


def staged_kill_resume(command: list[str], out: Path, reference: Path, stages: list[tuple[str, str]], lengths: dict,
                       per_stage: int, atomic: int, rng, tolerance: float, log: Path, restart=None,
                       rewind=None) -> dict:
    """Kill ``command`` ``per_stage`` times in each stage of ``lengths`` (``{stage: (start_s, length_s)}`` of an
    uninterrupted run; each kill waits for the stage's line, then a seeded fraction of its length) and
    ``atomic`` times inside an atomic write, resuming after each; then compare with ``reference``.
    ``restart(out)`` starts a finished command's work again (so later kills still find their stage);
    ``rewind(out, stage)``, before a kill aimed at ``stage``, makes the resumed command do it again if it was
    done."""
    names = [n for n, _ in stages]
    plan = [("stage", names.index(n), float(rng.uniform(0.02, 0.9))) for n in lengths for _ in range(per_stage)]
    for _ in range(atomic):  # at seeded places among the stage kills, so they fall in different stages
        plan.insert(int(rng.integers(0, len(plan) + 1)), ("atomic", None, int(rng.integers(0, 8))))
    kills, partial, missed = [], [], []
    plan = [(*item, True) for item in plan]  # True: may be tried again once if the command ends first
    with open(log, "a") as fh:
        while plan:
            kind, target, draw, again = plan.pop(0)
            before = _temporaries(out) if out.exists() else set()
            if kind == "stage" and rewind is not None:
                rewind(out, names[target])
            watched = _Watched(command, fh, stages)
            if kind == "stage":
                while watched.stage < target and watched.process.poll() is None:
                    time.sleep(0.02)
                deadline = time.perf_counter() + draw * lengths[names[target]][1]
                while time.perf_counter() < deadline and watched.process.poll() is None:
                    time.sleep(0.01)
            else:
                seen: set[str] = set()
                while watched.process.poll() is None:
                    new = (_temporaries(out) if out.exists() else set()) - before - seen
                    seen |= new
                    if len(seen) > draw:
                        break
                    time.sleep(0.001)
            if watched.process.poll() is not None:
                watched.wait()
                missed.append({"kind": kind, "target": names[target] if target is not None else "atomic write"})
                if restart is not None:
                    restart(out)
                if again:
                    plan.append((kind, target, draw * 0.5, False))
                continue
            after = watched.kill()
            temps = sorted(_temporaries(out) - before)
            kills.append({"target": names[target] if kind == "stage" else "atomic write",
                          "stage": names[watched.stage] if watched.stage >= 0 else "start", "after_s": round(after, 2),
                          "temporaries_left": temps[:5], "in_atomic_write": bool(temps)})
            partial += partial_files(out)
    result = _finish(command, out, reference, tolerance, log, kills, partial)
    hit: dict = {}
    for k in kills:
        hit[k["stage"]] = hit.get(k["stage"], 0) + 1
    result.update({"stages": lengths, "kills_per_stage": hit, "missed": missed,
                   "in_atomic_write": sum(k["in_atomic_write"] for k in kills)})
    return result


def _simulate_stage(out: Path) -> str:
    done = [p.name for p in (out / "trials").glob("*") if p.is_dir()] if (out / "trials").is_dir() else []
    return f"rendering ({len(list(out.rglob('*.mp4')))} videos, trials {sorted(done)})" if out.exists() else "start"


def concurrent(drive: list[str], capture: Path, folder: Path, log: Path) -> dict:
    """Start the pipeline on ``folder/out``; once it holds the lock, ``bcmocap run`` on the same --out."""
    out = folder / "out"
    with open(log, "ab") as fh:
        first = subprocess.Popen(drive + [str(out)], stdout=fh, stderr=subprocess.STDOUT, cwd=REPO,
                                 start_new_session=True)
        deadline = time.time() + 300
        while time.time() < deadline and not ((out / "run.lock").is_file() and (out / "run.lock").read_text().strip()):
            time.sleep(0.2)
        second = subprocess.run(BCMOCAP + ["run", str(capture), "--out", str(out)], capture_output=True, text=True,
                                cwd=REPO)
        still_running = first.poll() is None
        os.killpg(first.pid, signal.SIGKILL)
        first.wait()
    message = second.stderr.strip().splitlines()[-1] if second.stderr.strip() else ""
    refused = still_running and second.returncode != 0 and "another bcmocap command" in message
    return {"refused": refused, "exit": second.returncode, "message": message, "first_still_running": still_running}


def _escape_saver(folder: str | None, reader: str):
    """``on_escape`` of :func:`fuzz_reader` writing each escaping case's bytes into ``folder`` (or None)."""
    if folder is None:
        return None
    Path(folder).mkdir(parents=True, exist_ok=True)
    count = iter(range(10**9))

    def save(target: str, data: bytes, detail: str) -> None:
        path = Path(folder) / f"{reader}-{next(count)}-{Path(target).name}"
        path.write_bytes(data)
        print(f"  escape saved to {path}: {detail}", flush=True)

    return save


def path_safety() -> dict:
    """tests/test_path_safety.py's cases, run as they are: failures are path escapes."""
    report = Path(tempfile.mkdtemp()) / "report.xml"
    subprocess.run([PYTHON, "-m", "pytest", "-n", "0", "-q", "-p", "no:cacheprovider", f"--junitxml={report}",
                    "tests/test_path_safety.py"], cwd=REPO, capture_output=True)
    text = report.read_text()
    cases = int(re.search(r'tests="(\d+)"', text).group(1))
    failures = sum(int(x) for x in re.findall(r'(?:failures|errors)="(\d+)"', text)[:2])
    shutil.rmtree(report.parent)
    return {"cases": cases, "escapes": failures}


# ---- main ----------------------------------------------------------------------------------------------

def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", help="write the figures here")
    parser.add_argument("--fuzz-examples", type=int, default=100, help="hypothesis cases per reader file")
    parser.add_argument("--fuzz-timeout", type=float, default=10.0, help="time box per case (s)")
    parser.add_argument("--kill-points", type=int, default=10, help="kills of bcmocap simulate")
    parser.add_argument("--points-per-stage", type=int, default=2, help="kills in each stage of the staged commands")
    parser.add_argument("--atomic-points", type=int, default=2,
                        help="kills inside an atomic write, per staged command")
    parser.add_argument("--tolerance", type=float, default=1e-6, help="largest array difference after resume")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip", nargs="*", default=[],
                        choices=["fuzz", "kill", "paths", "simulate", "pixels", "faults", "memory"])
    parser.add_argument("--keep", help="keep the runs in this folder (and reuse its rendered capture)")
    parser.add_argument("--save-escapes", metavar="DIR",
                        help="write each escaping fuzz case's file here (READER-N-NAME), to reproduce it")
    parser.add_argument("--disk-points", type=int, default=10, help="full-disk attempts per command")
    parser.add_argument("--edit-clients", type=int, default=4, help="viewer saves at the same instant")
    parser.add_argument("--edit-rounds", type=int, default=4, help="rounds of simultaneous saves")
    parser.add_argument("--memory-cap-gb", type=float, default=4.0, help="the memory cgroup's limit")
    parser.add_argument("--memory-seconds", type=float, default=60.0, help="length of the capture run under the cap")
    parser.add_argument("--memory-fps", type=float, default=30.0, help="its frame rate")
    parser.add_argument("--memory-capture", help="run under the cap on this capture instead of rendering one")
    parser.add_argument("--memory-config", help="bcmocap run's --config under the cap (default: its defaults)")
    parser.add_argument("--memory-row", default="memory_cap", help="the results' key for this memory row")
    parser.add_argument("--only-faults", action="store_true", help="run sections 6 and 7 (faults, memory) alone")
    parser.add_argument("--fault-rows", nargs="*", default=list(FAULT_SECTIONS), choices=FAULT_SECTIONS,
                        help="the rows of section 6 to run")
    parser.add_argument("--update", action="store_true",
                        help="replace only the sections run in the existing --json file")
    args = parser.parse_args()
    if args.only_faults:
        args.skip = sorted(set(args.skip) | {"fuzz", "kill", "paths"})

    import numpy as np

    from bcmocap.precision import enable_float64

    enable_float64()
    rng = np.random.default_rng(args.seed)
    start = time.perf_counter()
    payload: dict = {"settings": {k: v for k, v in vars(args).items() if k != "json"}}

    if "fuzz" not in args.skip:
        payload["fuzz"], escapes = {}, {}
        with Worker(timeout=args.fuzz_timeout) as worker:
            for name in READERS:
                t = time.perf_counter()
                r = fuzz_reader(name, args.fuzz_examples, worker, seed=args.seed,
                                on_escape=_escape_saver(args.save_escapes, name))
                payload["fuzz"][name] = {"cases": r.cases, "escapes": r.escapes, "accepted": r.valid,
                                         "seconds": round(time.perf_counter() - t, 1)}
                escapes[name] = r.examples
                print(f"fuzz {name:16s} {r.cases:5d} cases {r.escapes:4d} escapes ({r.valid} accepted)", flush=True)
        payload["fuzz_escape_examples"] = {k: v for k, v in escapes.items() if v}

    if "paths" not in args.skip:
        paths = path_safety()
        payload["path_escapes"], payload["path_cases"] = paths["escapes"], paths["cases"]
        print(f"path safety: {paths['cases']} cases, {paths['escapes']} escapes", flush=True)

    if "kill" not in args.skip:
        folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bcmocap-reliability-"))
        folder.mkdir(parents=True, exist_ok=True)
        log = folder / "commands.log"
        kills, determinism, seconds = {}, {}, {}
        staged = dict(per_stage=args.points_per_stage, atomic=args.atomic_points, rng=rng, log=log)

        # bcmocap simulate: twice uninterrupted, then killed at random times
        simulate = lambda out: BCMOCAP + ["simulate", str(out), *SIMULATE, "--seed", "1"]  # noqa: E731
        if "simulate" not in args.skip or not (folder / "sim_a" / "capture.json").is_file():
            seconds["simulate"] = [_timed(simulate(folder / f"sim_{k}"), log) for k in "ab"]
            determinism["simulate"] = compare(folder / "sim_a", folder / "sim_b", 0.0)
        if "simulate" not in args.skip:
            kills["simulate"] = kill_resume(simulate(folder / "sim_k"), folder / "sim_k", folder / "sim_a",
                                            args.kill_points, min(seconds["simulate"]), rng, 0.0, log,
                                            stage=_simulate_stage, restart=_restart_simulate)
            _report_kills("simulate", kills["simulate"], determinism["simulate"])

        # the stages after the frontend of bcmocap run, on simulated frontend output
        drive = [PYTHON, str(Path(__file__).resolve()), "--drive"]
        for k in "abk":
            shutil.rmtree(folder / f"run_{k}", ignore_errors=True)
            (folder / f"run_{k}").mkdir()
            _write_frontend(folder / f"run_{k}" / "out")
        stages = RUN_STAGES[1:]
        first, lengths = timeline(drive + [str(folder / "run_a" / "out")], log, stages)
        seconds["run"] = [first, _timed(drive + [str(folder / "run_b" / "out")], log)]
        determinism["run"] = compare(folder / "run_a" / "out", folder / "run_b" / "out", 0.0)
        kills["run"] = staged_kill_resume(drive + [str(folder / "run_k" / "out")], folder / "run_k" / "out",
                                          folder / "run_a" / "out", stages, lengths, tolerance=args.tolerance,
                                          restart=_restart_if_finished, rewind=_rewind_run, **staged)
        _report_kills("run", kills["run"], determinism["run"])

        shutil.rmtree(folder / "lock", ignore_errors=True)
        (folder / "lock").mkdir()
        _write_frontend(folder / "lock" / "out")
        lock = concurrent(drive, folder / "sim_a", folder / "lock", log)
        print(f"concurrent run refused: {lock['refused']} ({lock['message']})", flush=True)

        if "pixels" not in args.skip:  # the frontend on pixels, and bcmocap run from pixels
            capture = folder / "pixels"
            if not (capture / "capture.json").is_file() or not json.loads(
                    (capture / "capture.json").read_text()).get("complete"):
                seconds["render"] = _timed(BCMOCAP + ["simulate", str(capture), *PIXELS_SIMULATE], log)
            for name in ("frontend_a", "frontend_b", "frontend_k", "pixels_a", "pixels_b", "pixels_k"):
                shutil.rmtree(folder / name, ignore_errors=True)  # a kept folder's runs start afresh
            frontend = lambda out: BCMOCAP + ["frontend", str(capture), "--out", str(out), *PIXELS_FRONTEND]  # noqa: E731
            first, lengths = timeline(frontend(folder / "frontend_a"), log, FRONTEND_STAGES)
            seconds["frontend"] = [first, _timed(frontend(folder / "frontend_b"), log)]
            determinism["frontend"] = compare(folder / "frontend_a", folder / "frontend_b", 0.0)
            kills["frontend"] = staged_kill_resume(frontend(folder / "frontend_k"), folder / "frontend_k",
                                                   folder / "frontend_a", FRONTEND_STAGES, lengths, tolerance=0.0,
                                                   **staged)
            _report_kills("frontend", kills["frontend"], determinism["frontend"])

            (folder / "pixels.toml").write_text(PIXELS_RUN_CONFIG)
            run = lambda out: BCMOCAP + ["run", str(capture), "--out", str(out), "--config",  # noqa: E731
                                         str(folder / "pixels.toml")]
            first, lengths = timeline(run(folder / "pixels_a"), log, PIXEL_RUN_STAGES)
            seconds["run_pixels"] = [first, _timed(run(folder / "pixels_b"), log)]
            determinism["run_pixels"] = compare(folder / "pixels_a", folder / "pixels_b", 0.0)
            kills["run_pixels"] = staged_kill_resume(run(folder / "pixels_k"), folder / "pixels_k",
                                                     folder / "pixels_a", PIXEL_RUN_STAGES, lengths,
                                                     tolerance=args.tolerance, restart=_restart_if_finished,
                                                     rewind=_rewind_run,
                                                     **{**staged, "per_stage": max(1, args.points_per_stage // 2)})
            _report_kills("run_pixels", kills["run_pixels"], determinism["run_pixels"])

        payload["kill_resume"] = {"points": sum(r["points"] for r in kills.values()),
                                  "mismatches": sum(r["mismatches"] for r in kills.values()), **kills}
        differing = [{"command": name, **d} for name, r in determinism.items() for d in r["differing"]]
        payload["determinism"] = {"runs": 2, "differing_outputs": differing,
                                  "bitwise_equal": {name: r["bitwise_equal"] for name, r in determinism.items()},
                                  "equal_but_timings": {name: r["equal_but_timings"] for name, r in determinism.items()},
                                  "seconds": seconds}
        payload["concurrent_runs_refused"] = lock["refused"]
        payload["concurrent"] = lock
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)

    if "faults" not in args.skip:
        faults_start = time.perf_counter()
        payload.update(faults(args, rng))
        print(f"faults: {time.perf_counter() - faults_start:.0f} s", flush=True)

    if "memory" not in args.skip:
        payload[args.memory_row] = memory(args)
        m = payload[args.memory_row]
        print(f"memory cap {m['limit_gb']:g} GB: finished {m['finished']} (peak {m['peak_mb_cgroup']:,.0f} MB in the "
              f"cgroup; per stage {m['peak_mb_per_stage']}; {m['message']})", flush=True)

    payload["seconds"] = round(time.perf_counter() - start, 1)
    if args.update and args.json and Path(args.json).is_file():
        payload = _updated(json.loads(Path(args.json).read_text()), payload)
    if "fuzz" in payload:
        total = sum(v["cases"] for v in payload["fuzz"].values())
        print(f"fuzz: {total} cases, {sum(v['escapes'] for v in payload['fuzz'].values())} escapes")
    if "kill_resume" in payload:
        print(f"kill -9: {payload['kill_resume']['points']} points, {payload['kill_resume']['mismatches']} mismatches; "
              f"determinism: {len(payload['determinism']['differing_outputs'])} outputs differ")
    print(f"{payload['seconds']:.0f} s")
    write_json(args.json, payload)


FAULT_SECTIONS = ("disk_full", "changing_folders", "corrupt_cache", "concurrent_edits")


def faults(args, rng) -> dict:
    """Section 6: the rows of :mod:`_faults`, each with its own reference runs."""
    import _faults

    folder = Path(args.keep or tempfile.mkdtemp(prefix="bcmocap-faults-")) / "faults"
    folder.mkdir(parents=True, exist_ok=True)
    log = folder / "commands.log"
    drive = [PYTHON, str(Path(__file__).resolve()), "--drive"]
    shutil.rmtree(folder / "reference", ignore_errors=True)
    simulate = lambda out: BCMOCAP + ["simulate", str(out), *SIMULATE, "--seed", "1"]  # noqa: E731
    run_reference = folder / "reference" / "run" / "out"
    if {"disk_full", "concurrent_edits"} & set(args.fault_rows):
        _timed(simulate(folder / "reference" / "sim"), log)
        _write_frontend(run_reference)
        _timed(drive + [str(run_reference)], log)
    out = {}
    if "disk_full" in args.fault_rows:
        out.update(_disk_full(args, rng, folder, log, drive, simulate, run_reference))
    if "changing_folders" in args.fault_rows:
        out["changing_folders"] = _faults.changing_folders(drive, _write_frontend, folder, log)
        for case, r in out["changing_folders"].items():
            print(f"{case}: one line {r['one_line']}, traceback {r['traceback']}, nothing else lost "
                  f"{r['nothing_else_lost']} ({r['message'][:120]})", flush=True)
    if "corrupt_cache" in args.fault_rows:
        out["corrupt_cache"] = _faults.corrupt_caches(drive, _write_frontend, folder, compare, log)
        print(f"corrupt cache: {out['corrupt_cache']['cases']} cases, {out['corrupt_cache']['recovered']} recovered",
              flush=True)
    if "concurrent_edits" in args.fault_rows:
        out["concurrent_edits"] = _faults.concurrent_edits(run_reference, drive, _write_frontend, folder,
                                                           args.edit_clients, args.edit_rounds)
        print(f"concurrent edits: {out['concurrent_edits']['cases']} cases, "
              f"{out['concurrent_edits']['lost_or_mixed']} lost or mixed", flush=True)
    if not args.keep:
        shutil.rmtree(folder.parent, ignore_errors=True)
    return out


def _disk_full(args, rng, folder: Path, log: Path, drive: list[str], simulate, run_reference: Path) -> dict:
    """The rows of ``disk_full``: ``bcmocap simulate`` and the stages after the frontend."""
    import _faults

    out, rows = {}, {}
    for name, command, prepare, reference, stage_of, stage_bytes in (
            ("simulate", simulate, lambda out: None, folder / "reference" / "sim", _simulate_stage, None),
            ("run", lambda out: drive + [str(out)], _write_frontend, run_reference, _stage_of,
             _faults.run_stage_bytes(run_reference))):
        rows[name] = _faults.disk_full(name, command, prepare, reference, args.disk_points, folder, rng, stage_of,
                                       compare, partial_files, args.tolerance, log, stage_bytes)
        r = rows[name]
        print(f"disk full {name:8s} {r['points']} points (stages: {r['stages']}), {r['corrupted']} corrupted, "
              f"{r['tracebacks']} tracebacks, {r['messages_naming_the_folder']} messages naming the folder, "
              f"{r['resume_mismatches']} resume mismatches", flush=True)
    out["disk_full"] = {key: sum(r[key] for r in rows.values()) for key in
                        ("points", "corrupted", "tracebacks", "resume_mismatches", "messages_naming_the_folder")}
    out["disk_full"]["how"] = "a tmpfs of fixed size mounted as the output folder (the kernel's ENOSPC)"
    out["disk_full"]["commands"] = rows
    return out


def memory(args) -> dict:
    """Section 7: ``bcmocap run`` (default settings) under a memory cap."""
    import _faults

    folder = Path(args.keep or tempfile.mkdtemp(prefix="bcmocap-memory-")) / "memory"
    folder.mkdir(parents=True, exist_ok=True)
    log = folder / "commands.log"
    capture = Path(args.memory_capture) if args.memory_capture else folder / "capture"
    if not args.memory_capture:
        _timed(BCMOCAP + ["simulate", str(capture), "--seconds", f"{args.memory_seconds:g}", "--rom-seconds", "2.5",
                          "--fps", f"{args.memory_fps:g}", "--reference-photos", "24", "--reference-size", "640x480",
                          "--seed", "0", "--no-progress"], log)
    manifest = json.loads((capture / "capture.json").read_text())
    shutil.rmtree(folder / "out", ignore_errors=True)
    config = Path(args.memory_config) if args.memory_config else None
    result = _faults.memory_cap(capture, folder / "out", config, args.memory_cap_gb, log)
    settings = manifest.get("settings", {})
    result["capture"] = {key: settings.get(key) for key in ("motion", "seconds", "rom_seconds", "fps", "width", "height",
                                                            "seed")}
    result["settings"] = config.read_text() if config else "bcmocap run's defaults (no --config)"
    if not args.keep:
        shutil.rmtree(folder.parent, ignore_errors=True)
    return result


def _updated(previous: dict, payload: dict) -> dict:
    """``previous`` with the sections of ``payload`` replaced; ``sections`` says at which commit and on which
    machine each section was measured (the earlier ones keep the file's earlier machine)."""
    import datetime

    from _common import machine

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO).stdout
    now = {"commit": commit.strip(), "date": datetime.date.today().isoformat(), "machine": machine(),
           "settings": payload["settings"], "seconds": payload["seconds"]}
    merged = {k: v for k, v in previous.items() if k not in ("sections", "machine")}
    sections = previous.get("sections") or {
        k: {"commit": "the run that wrote the file", "machine": previous.get("machine")}
        for k in previous if k not in ("settings", "seconds", "machine")}
    for key, value in payload.items():
        if key not in ("settings", "seconds"):
            merged[key] = value
            sections[key] = now
    merged["sections"] = sections
    return merged


def _report_kills(name: str, kills: dict, determinism: dict) -> None:
    stages = kills.get("kills_per_stage") or {k["stage"]: None for k in kills["kills"]}
    atomic = f", {kills['in_atomic_write']} inside an atomic write" if "in_atomic_write" in kills else ""
    print(f"kill -9 {name:10s} {kills['points']} points (stages: {', '.join(f'{k} {v}' if v else k for k, v in stages.items())}"
          f"{atomic}), {kills['mismatches']} mismatches, {kills['bitwise_equal']} files bitwise equal, "
          f"{len(kills['differing'])} within tolerance / differing", flush=True)
    worst = max((x["max_difference"] for x in determinism["differing"] if x["max_difference"] is not None), default=0.0)
    print(f"determinism {name:10s} {determinism['bitwise_equal']} files bitwise equal, {len(determinism['differing'])} "
          f"differ (largest difference {worst:.3g}; {[x['file'] for x in determinism['differing']][:8]}); equal but "
          f"timings: {determinism['equal_but_timings'][:6]}", flush=True)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--drive":
        sys.exit(_drive(Path(sys.argv[2])))
    main()
