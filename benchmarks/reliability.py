"""Reliability as figures (issue 25): fuzzed readers, kill -9 anywhere, determinism, the output lock, path safety.

    python benchmarks/reliability.py --json benchmarks/results/reliability.json

1. **fuzz** — every reader of ``benchmarks/_fuzz.py`` on ``--fuzz-examples`` mutated and truncated copies of
   each of its files (hypothesis, seeded): cases and escapes (another exception type, a message not naming
   the file, a hang past ``--fuzz-timeout`` s, a crash, a write).
2. **kill -9** — ``bcmocap simulate`` on a tiny capture, and the stages after the frontend of ``bcmocap run``
   (world, skeleton, initial, solve, outputs: ``run_pipeline`` in a subprocess on a simulated capture whose
   frontend output is given, as in tests/test_pipeline_run.py), killed at ``--kill-points`` seeded random
   times each and resumed; after every kill each output under its final name must load, and the final
   outputs must equal those of an uninterrupted run (arrays within ``--tolerance``, other files byte for byte).
3. **determinism** — the uninterrupted command run twice: files bitwise equal, and the largest difference of
   those that are not.
4. **concurrent runs** — ``bcmocap run`` on an ``--out`` a running pipeline holds must be refused.
5. **path escapes** — tests/test_path_safety.py's hostile captures (failures counted).

The frontend on pixels is not killed here (minutes per run on 2 cores); see the README.
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
    from bcmocap.sim.studio import subject_record

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
    subject = subject_record(skeleton, 0, FPS)
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
                                  chunk_frames=f.chunk_frames, registration=f.registration, max_measurements=None)
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
    fake, config, _, _ = _fake_capture(out.parent)
    try:
        run_pipeline(fake, out, config, log=lambda line: print(line, flush=True))
    except ValueError as exc:
        print(f"refused: {exc}", file=sys.stderr)
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
    if a.suffix in (".png", ".bin", ".f64") or b"\0" in x[:4096]:
        if a.suffix == ".f64" and len(x) == len(y):
            return float(np.max(np.abs(np.frombuffer(x, "<f8") - np.frombuffer(y, "<f8")), initial=0.0))
        return None
    nx, ny = NUMBER.findall(x), NUMBER.findall(y)
    if len(nx) != len(ny) or NUMBER.sub(b"#", x) != NUMBER.sub(b"#", y):
        return None
    return max(abs(float(u) - float(v)) for u, v in zip(nx, ny))


TIMINGS_ONLY = -1.0  # _difference: equal once the "seconds" fields are left out


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
    """The stage a run was in, from its log (``[k/6] stage ...``) and solver window lines."""
    log = out / "log.txt"
    if not log.is_file():
        return "start"
    lines = log.read_text(errors="replace").splitlines()
    stage = next((m.group(1) for line in reversed(lines) if (m := re.search(r"\[\d/6\] (\w+)", line))), "start")
    return stage


def kill_resume(command: list[str], out: Path, reference: Path, points: int, duration: float, rng,
                tolerance: float, log: Path, stage=_stage_of) -> dict:
    """Kill ``command`` at ``points`` seeded times, checking for partial files after each kill, then let it
    finish and compare with ``reference``. Times are drawn from [0.05, 1] of ``duration`` (a warm run) after
    each (re)start; an attempt that finishes first is not counted."""
    kills, partial, attempts = [], [], 0
    with open(log, "ab") as fh:
        while len(kills) < points and attempts < 3 * points:
            attempts += 1
            delay = float(rng.uniform(0.05, 1.0)) * duration
            process = subprocess.Popen(command, stdout=fh, stderr=subprocess.STDOUT, cwd=REPO, start_new_session=True)
            try:
                process.wait(delay)
                continue  # finished before the kill: not a kill point (the outputs are compared at the end)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
            kills.append({"after_s": round(delay, 2), "stage": stage(out)})
            partial += partial_files(out)
            if (out / "run.json").is_file() and "outputs" in json.loads((out / "run.json").read_text()).get("stages", {}):
                for p in (out / "run.json", out / "motion.bvh"):  # start the stages again: kills spread over all
                    p.unlink(missing_ok=True)
    _timed(command, log)
    result = compare(reference, out, tolerance)
    return {"points": len(kills), "kills": kills, "partial_files": partial, **result,
            "mismatches": len(result["mismatches"]) + len(partial), "mismatch_list": result["mismatches"]}


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
    parser.add_argument("--kill-points", type=int, default=10, help="kills per command")
    parser.add_argument("--tolerance", type=float, default=1e-6, help="largest array difference after resume")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip", nargs="*", default=[], choices=["fuzz", "kill", "paths"])
    parser.add_argument("--keep", help="keep the runs in this folder")
    args = parser.parse_args()

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
                r = fuzz_reader(name, args.fuzz_examples, worker, seed=args.seed)
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
        simulate = lambda out: BCMOCAP + ["simulate", str(out), *SIMULATE, "--seed", "1"]  # noqa: E731
        drive = [PYTHON, str(Path(__file__).resolve()), "--drive"]
        # determinism: each command twice, uninterrupted
        sim_seconds = [_timed(simulate(folder / f"sim_{k}"), log) for k in "ab"]
        sim_det = compare(folder / "sim_a", folder / "sim_b", 0.0)
        for k in "ab":
            (folder / f"run_{k}").mkdir()
            _write_frontend(folder / f"run_{k}" / "out")
        run_seconds = [_timed(drive + [str(folder / f"run_{k}" / "out")], log) for k in "ab"]
        run_det = compare(folder / "run_a" / "out", folder / "run_b" / "out", 0.0)
        print(f"simulate {sim_seconds[0]:.0f} s, run stages {run_seconds[0]:.0f} s per uninterrupted command", flush=True)
        # kill -9 and resume
        sim_kill = kill_resume(simulate(folder / "sim_k"), folder / "sim_k", folder / "sim_a", args.kill_points,
                               min(sim_seconds), rng, 0.0, log, stage=_simulate_stage)
        (folder / "run_k").mkdir()
        _write_frontend(folder / "run_k" / "out")
        run_kill = kill_resume(drive + [str(folder / "run_k" / "out")], folder / "run_k" / "out",
                               folder / "run_a" / "out", args.kill_points, min(run_seconds), rng, args.tolerance, log)
        (folder / "lock").mkdir()
        _write_frontend(folder / "lock" / "out")
        lock = concurrent(drive, folder / "sim_a", folder / "lock", log)
        payload["kill_resume"] = {"points": sim_kill["points"] + run_kill["points"],
                                  "mismatches": sim_kill["mismatches"] + run_kill["mismatches"],
                                  "simulate": sim_kill, "run": run_kill}
        differing = [{"command": "simulate", **d} for d in sim_det["differing"]] + \
                    [{"command": "run", **d} for d in run_det["differing"]]
        payload["determinism"] = {"runs": 2, "differing_outputs": differing,
                                  "bitwise_equal": {"simulate": sim_det["bitwise_equal"], "run": run_det["bitwise_equal"]},
                                  "seconds": {"simulate": sim_seconds, "run": run_seconds}}
        payload["concurrent_runs_refused"] = lock["refused"]
        payload["concurrent"] = lock
        for name, r in (("simulate", sim_kill), ("run", run_kill)):
            stages = sorted({k["stage"] for k in r["kills"]})
            print(f"kill -9 {name:8s} {r['points']} points (stages: {', '.join(stages)}), {r['mismatches']} mismatches, "
                  f"{r['bitwise_equal']} files bitwise equal, {len(r['differing'])} within tolerance / differing", flush=True)
        for name, d in (("simulate", sim_det), ("run", run_det)):
            worst = max((x["max_difference"] for x in d["differing"] if x["max_difference"] is not None), default=0.0)
            print(f"determinism {name:8s} {d['bitwise_equal']} files bitwise equal, {len(d['differing'])} differ "
                  f"(largest difference {worst:.3g}; {[x['file'] for x in d['differing']][:8]})", flush=True)
        print(f"concurrent run refused: {lock['refused']} ({lock['message']})", flush=True)
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)

    payload["seconds"] = round(time.perf_counter() - start, 1)
    if "fuzz" in payload:
        total = sum(v["cases"] for v in payload["fuzz"].values())
        print(f"fuzz: {total} cases, {sum(v['escapes'] for v in payload['fuzz'].values())} escapes")
    print(f"{payload['seconds']:.0f} s")
    write_json(args.json, payload)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--drive":
        sys.exit(_drive(Path(sys.argv[2])))
    main()
