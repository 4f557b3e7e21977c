"""The faults of a long shoot on a shared machine, as rows of ``benchmarks/reliability.py`` (issue 48).

- **disk full**: a command runs with its output folder on a filesystem of fixed size (a tmpfs, mounted by this
  root process: a real ``ENOSPC`` from the kernel, not an injected one), at sizes spread between what its inputs
  take and what its finished outputs take. Each attempt that fails is a point: its error must be one line naming
  the folder (no traceback), every output under its final name must load, and a rerun after the filesystem is
  enlarged must end with outputs equal to an uninterrupted run's.
- **folders that change under a run**: a read-only ``--out`` (a read-only mount: root ignores permission bits),
  an ``--out`` deleted and a capture file rewritten while ``bcmocap run`` goes on: one line, nothing else lost.
- **corrupt caches**: JAX's compilation cache and the solver's stored programs, warmed by one run, then one entry
  damaged per case (truncated, emptied, overwritten, a flipped byte); the next run must note it, drop it, give
  the same outputs bit for bit and leave a whole entry again.
- **concurrent edits**: viewer saves from several processes at once, and a save while ``bcmocap run`` holds the
  folder: every save a whole version of its own, or refused with one line.
- **a memory cap**: ``bcmocap run`` in a memory cgroup with a hard limit (:class:`MemoryCap`), as a container
  or a cluster worker runs it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from _small_disk import resize, small_disk

REPO = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def _run(command: list[str], env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(command, capture_output=True, text=True, cwd=REPO, env={**ENV, **(env or {})})


def _error_line(done: subprocess.CompletedProcess) -> str:
    lines = [line for line in done.stderr.splitlines() if line.startswith("bcmocap ")]
    return lines[-1] if lines else (done.stderr.strip().splitlines() or [""])[-1]


def folder_bytes(folder: Path) -> int:
    """Bytes the files under ``folder`` take on a tmpfs (each rounded up to 4 KiB pages)."""
    return sum(-(-p.stat().st_size // 4096) * 4096 for p in folder.rglob("*") if p.is_file())


# ---- a full disk -----------------------------------------------------------------------------------------

def run_stage_bytes(reference: Path) -> list[tuple[str, int]]:
    """``[(stage, bytes written by its end)]`` of a finished ``bcmocap run`` folder after the frontend (its files
    assigned to the stage that writes them; the run log and settings to the first)."""
    def stage(rel: str) -> str | None:
        if rel.startswith("frontend/") or rel == "run.lock":
            return None
        if rel.startswith("world/") or rel in ("run.json", "config.json", "log.txt"):
            return "world"
        if rel.startswith("model/"):
            return "skeleton"
        if rel.startswith(("solve/correspondences/", "solve/initial.npz")):
            return "initial"
        return "solve" if rel.startswith("solve/") else "outputs"

    sizes = dict.fromkeys(("world", "skeleton", "initial", "solve", "outputs"), 0)
    for path in reference.rglob("*"):
        if path.is_file() and (s := stage(path.relative_to(reference).as_posix())):
            sizes[s] += -(-path.stat().st_size // 4096) * 4096
    total, out = 0, []
    for s, size in sizes.items():
        total += size
        out.append((s, total))
    return out


def disk_full(name: str, command, prepare, reference: Path, points: int, work: Path, rng, stage_of, compare,
              partial_files, tolerance: float, log: Path, stage_bytes: list[tuple[str, int]] | None = None) -> dict:
    """``points`` attempts of ``command(out)`` with ``out`` on a tmpfs too small for it.

    Args:
        command: ``out → argv``; prepare: ``out → None``, what the command needs in ``out`` before it starts
            (the frontend's files of a run), written before the space is taken away.
        reference: an uninterrupted run's output folder: its size bounds the sizes tried, and the resumed
            outputs are compared with it (``compare(reference, out, tolerance)``).
        stage_of: ``out → stage`` the command was in when the disk filled.
        stage_bytes: ``[(stage, bytes written by its end)]``: the points go round the stages, each at a seeded
            size within what its stage writes; without it the sizes are stratified over the outputs' size.
    """
    whole = folder_bytes(reference)
    rows, finished_first, attempts = [], 0, 0
    while len(rows) < points and attempts < 3 * points:
        attempts += 1
        mount = work / f"{name}_disk"
        u = float(rng.uniform(0.05, 0.95))
        with small_disk(mount, 64 * 1024 * 1024) as folder:
            out = folder / "out"
            prepare(out)
            base = folder_bytes(folder)
            if stage_bytes:
                k = attempts % len(stage_bytes)
                low = stage_bytes[k - 1][1] if k else 0
                share = (low + u * (stage_bytes[k][1] - low)) / max(stage_bytes[-1][1], 1)
                size = base + low + int(u * (stage_bytes[k][1] - low))
            else:
                share = (len(rows) + u) / points  # stratified over the outputs' size
                size = base + int(share * max(whole - base, 4096))
            resize(folder, size)
            done = _run(command(out))
            with open(log, "a") as fh:
                fh.write(done.stdout + done.stderr)
            if done.returncode == 0:
                finished_first += 1  # the space was enough after all (temporaries come and go): not a point
                continue
            line = _error_line(done)
            row = {"size_bytes": size, "share_of_outputs": round(share, 3), "stage": stage_of(out),
                   "message": line[:300], "traceback": "Traceback" in done.stderr + done.stdout,
                   "names_the_folder": "no space left on the disk of " in line and str(folder) in line,
                   "partial_files": partial_files(out)}
            resize(folder, 4 * whole + 64 * 1024 * 1024)  # space freed: the same command resumes
            again = _run(command(out))
            if again.returncode != 0:
                row["resume"] = {"failed": _error_line(again)[:300]}
                row["resume_mismatches"] = 1
            else:
                result = compare(reference, out, tolerance)
                row["resume_mismatches"] = len(result["mismatches"])
                row["resume_mismatch_list"] = result["mismatches"][:5]
            rows.append(row)
    return {"points": len(rows), "finished_before_the_disk_filled": finished_first,
            "corrupted": sum(1 for r in rows if r["partial_files"]),
            "tracebacks": sum(1 for r in rows if r["traceback"]),
            "messages_naming_the_folder": sum(1 for r in rows if r["names_the_folder"]),
            "resume_mismatches": sum(1 for r in rows if r["resume_mismatches"]),
            "stages": {s: sum(1 for r in rows if r["stage"] == s) for s in dict.fromkeys(r["stage"] for r in rows)},
            "rows": rows}


# ---- folders that change under a run ----------------------------------------------------------------------

def changing_folders(drive: list[str], write_frontend, work: Path, log: Path) -> dict:
    """A read-only ``--out``, an ``--out`` deleted mid-run, a capture file rewritten mid-run (``drive`` runs the
    stages after the frontend; ``write_frontend(out)`` gives it its input). Each: one line, no traceback."""
    cases = {}
    # read-only: the folder holds a finished frontend; the filesystem is then remounted read-only
    with small_disk(work / "readonly", 256 * 1024 * 1024) as folder:
        write_frontend(folder / "out")
        before = sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))
        subprocess.run(["mount", "-o", "remount,ro", str(folder)], check=True)
        done = _run(drive + [str(folder / "out")])
        after = sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))
        cases["read_only_out"] = _case(done, str(folder / "out"), kept=before == after)
        subprocess.run(["mount", "-o", "remount,rw", str(folder)], check=True)
    # deleted mid-run: wait for the solve stage, then remove the folder
    out = work / "deleted" / "out"
    shutil.rmtree(out.parent, ignore_errors=True)
    write_frontend(out)
    process = subprocess.Popen(drive + [str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                               env=ENV)
    wait_for_stage(out, "solve")
    shutil.rmtree(out)
    stdout, stderr = process.communicate()
    done = subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)
    cases["out_deleted_mid_run"] = _case(done, "was deleted or replaced while the run was going",
                                         kept=not (out / "run.json").exists())
    # a capture file rewritten mid-run (the drive's capture folder is out/../capture)
    out = work / "changed" / "out"
    shutil.rmtree(out.parent, ignore_errors=True)
    write_frontend(out)
    video = out.parent / "capture" / "trials" / "capture" / "cam00.mp4"
    video.parent.mkdir(parents=True)
    video.write_bytes(os.urandom(100_000))
    process = subprocess.Popen(drive + [str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                               env=ENV)
    wait_for_stage(out, "solve")
    with open(video, "ab") as fh:  # a camera's file copied again over the one being read
        fh.write(os.urandom(1000))
    stdout, stderr = process.communicate()
    done = subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)
    stages = list(json.loads((out / "run.json").read_text())["stages"]) if (out / "run.json").is_file() else []
    cases["capture_changed_mid_run"] = _case(done, "changed while the run was reading the capture",
                                             kept=stages == ["frontend", "world", "skeleton", "initial"])
    with open(log, "a") as fh:
        fh.write(json.dumps(cases) + "\n")
    return cases


def _case(done: subprocess.CompletedProcess, expected: str, kept: bool) -> dict:
    line = _error_line(done)
    return {"exit": done.returncode, "message": line[:300], "one_line": done.returncode != 0 and expected in line,
            "traceback": "Traceback" in done.stderr + done.stdout, "nothing_else_lost": kept}


# ---- damaged caches ---------------------------------------------------------------------------------------

JAX_DAMAGE = {
    "truncated (a crash while JAX wrote it)": lambda b: b[: len(b) // 2],
    "emptied": lambda b: b"",
    "overwritten with zeros": lambda b: bytes(len(b)),
    "header overwritten": lambda b: b"\xff" * 8 + b[8:],
    "one byte flipped after it was recorded": lambda b: b[:-20] + bytes([b[-20] ^ 0x01]) + b[-19:],
}
PROGRAM_DAMAGE = {
    "truncated": lambda b: b[: len(b) // 2],
    "emptied": lambda b: b"",
    "garbage": lambda b: os.urandom(len(b)),
    "one byte flipped in the program": lambda b: b[:-100] + bytes([b[-100] ^ 0x01]) + b[-99:],
    "checksum line missing (an older writer)": lambda b: b[b.index(b"\n") + 1:],
}


def _age(path: Path, seconds: float = 3600.0) -> None:
    old = time.time() - seconds
    os.utime(path, (old, old))


def corrupt_caches(drive: list[str], write_frontend, work: Path, compare, log: Path) -> dict:
    """Warm a fresh cache with one run of ``drive``, then per case restore it, damage one entry and run again. The
    cache stays at one path, as a user's does (JAX's settings, the cache's own path included, are part of a stored
    program's key)."""
    from bcmocap.compilation_cache import VERIFIED, check_compilation_cache, entry_decodes
    from bcmocap.solver.program_cache import is_whole

    cache, pristine = work / "caches" / "cache", work / "caches" / "pristine"
    shutil.rmtree(work / "caches", ignore_errors=True)
    reference = work / "caches" / "reference" / "out"
    write_frontend(reference)
    done = _run(drive + [str(reference)], env={"BCMOCAP_CACHE_DIR": str(cache)})
    if done.returncode:
        raise RuntimeError(f"the warming run failed: {_error_line(done)}")
    for entry in cache.rglob("*"):  # written by a run that ended long ago, and recorded by a later check
        if entry.is_file():
            _age(entry)
    check_compilation_cache(cache)
    shutil.copytree(cache, pristine)
    jax_entries = sorted(cache.glob("*-cache"), key=lambda p: -p.stat().st_size)
    programs = sorted((cache / "bcmocap_programs").glob("*.bin"))
    cases = [("jax", kind, damage, jax_entries[k % len(jax_entries)].name) for k, (kind, damage) in
             enumerate(JAX_DAMAGE.items())]
    cases += [("program", kind, damage, programs[k % len(programs)].name) for k, (kind, damage) in
              enumerate(PROGRAM_DAMAGE.items())]
    rows = []
    for k, (kind_of_cache, kind, damage, name) in enumerate(cases):
        shutil.rmtree(cache)
        shutil.copytree(pristine, cache)
        entry = cache / name if kind_of_cache == "jax" else cache / "bcmocap_programs" / name
        entry.write_bytes(damage(entry.read_bytes()))
        _age(entry, 1800.0)
        if kind_of_cache == "jax" and kind.startswith("truncated"):  # a crash while writing: not recorded yet
            record = cache / VERIFIED
            record.write_text(json.dumps({k: v for k, v in json.loads(record.read_text()).items() if k != name}))
        out = work / "caches" / f"case{k}" / "out"
        write_frontend(out)
        done = _run(drive + [str(out)], env={"BCMOCAP_CACHE_DIR": str(cache)})
        with open(log, "a") as fh:
            fh.write(done.stdout + done.stderr)
        result = compare(reference, out, 0.0) if done.returncode == 0 else {"mismatches": ["the run failed"]}
        rebuilt = entry.is_file() and (entry_decodes(entry.read_bytes()) if kind_of_cache == "jax" else is_whole(entry))
        noted = "note: dropped" in done.stderr and name.removesuffix(".bin") in done.stderr
        rows.append({"cache": kind_of_cache, "damage": kind, "entry": name, "exit": done.returncode, "noted": noted,
                     "same_outputs": not result["mismatches"], "rebuilt": rebuilt,
                     "jax_warned": "Error reading persistent compilation cache" in done.stderr,
                     "recovered": done.returncode == 0 and noted and not result["mismatches"] and rebuilt})
    return {"cases": len(rows), "recovered": sum(r["recovered"] for r in rows), "rows": rows}


# ---- concurrent edits -------------------------------------------------------------------------------------

_SAVE = """
import sys, time
from pathlib import Path
import equinox as eqx, numpy as np
from bcmocap.pipeline import model_edit
from bcmocap.pipeline.run import load_model
from bcmocap.precision import enable_float64
enable_float64()
folder, k, start, wait, base = Path(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4]), sys.argv[5]
model_edit.SAVE_WAIT_S = wait
skeleton, rig = load_model(base)  # the model as the run estimated it: each client's edit is its own, whatever was saved
offsets = np.asarray(skeleton.offsets).copy()
offsets[3, 0] += 0.001 * (k + 1)
edited = eqx.tree_at(lambda s: s.offsets, skeleton, offsets)
time.sleep(max(0.0, start - time.time()))
print(model_edit.save_model_version(folder, edited, rig, note=f"client {k}"))
"""


def wait_for_stage(out: Path, stage: str, timeout_s: float = 600.0) -> bool:
    """Wait until a run's ``log.txt`` says ``stage`` started; False after ``timeout_s``."""
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        log = out / "log.txt"
        if log.is_file() and f"] {stage} ..." in log.read_text(errors="replace"):
            return True
        time.sleep(0.1)
    return False


def concurrent_edits(run_folder: Path, drive: list[str], write_frontend, work: Path, clients: int, rounds: int) -> dict:
    """``rounds`` times, ``clients`` processes save a model edit at the same instant into a finished run; then
    one save while a run holds the folder. Lost or mixed: a save without its own version, or a version's files
    that are not one client's edit whole."""
    from bcmocap.pipeline.model_edit import model_versions

    base_offset = json.loads((run_folder / "model" / "skeleton.json").read_text())["offsets_m"][3][0]
    rows = []
    for r in range(rounds):
        folder = work / "edits" / f"round{r}"
        shutil.rmtree(folder, ignore_errors=True)
        shutil.copytree(run_folder, folder)
        start = time.time() + 8.0  # every client has started and loaded the model by then
        procs = [subprocess.Popen([sys.executable, "-c", _SAVE, str(folder), str(k), str(start), "10", str(run_folder)],
                                  cwd=REPO, env=ENV,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for k in range(clients)]
        outs = [p.communicate() for p in procs]
        failed = [e.strip().splitlines()[-1] for p, (_, e) in zip(procs, outs) if p.returncode]
        versions = model_versions(folder)
        saved = [v for v in versions if v["source"].startswith("client ")]
        whole = 0
        for v in saved:
            k = int(v["source"].split()[1])
            data = json.loads((folder / "model" / "versions" / v["folder"] / "skeleton.json").read_text())
            rig_ok = json.loads((folder / "model" / "versions" / v["folder"] / "rig.json").read_text()) is not None
            expected = base_offset + 0.001 * (k + 1)
            whole += int(abs(data["offsets_m"][3][0] - expected) < 1e-12 and rig_ok)
        current = json.loads((folder / "model" / "skeleton.json").read_text())
        last = json.loads((folder / "model" / "versions" / versions[-1]["folder"] / "skeleton.json").read_text())
        lost_or_mixed = (clients - len(saved)) + (len(saved) - whole) + int(current != last)
        rows.append({"clients": clients, "versions_saved": len(saved), "whole": whole, "failed": failed,
                     "lost_or_mixed": lost_or_mixed})
    # a save while bcmocap run holds the folder: refused with one line after the wait, the model untouched
    out = work / "edits" / "during_run" / "out"
    shutil.rmtree(out.parent, ignore_errors=True)
    write_frontend(out)
    running = subprocess.Popen(drive + [str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO,
                               env=ENV)
    wait_for_stage(out, "solve")  # the model exists; the run holds the folder through the solve
    before = (out / "model" / "skeleton.json").read_text()
    save = subprocess.run([sys.executable, "-c", _SAVE, str(out), "0", "0", "1", str(out)], capture_output=True,
                          text=True, cwd=REPO, env=ENV)
    during = running.poll() is None
    running.kill()
    running.wait()
    message = (save.stderr.strip().splitlines() or [""])[-1]
    refused = save.returncode != 0 and "another bcmocap command" in message and during
    untouched = (out / "model" / "skeleton.json").read_text() == before or not during
    rows.append({"save_during_run": {"refused": refused, "message": message[-300:], "model_untouched": untouched}})
    lost = sum(r.get("lost_or_mixed", 0) for r in rows) + int(not refused) + int(not untouched)
    return {"cases": rounds + 1, "lost_or_mixed": lost, "rows": rows}



# ---- a memory cap -----------------------------------------------------------------------------------------

def _own_memory_cgroup() -> tuple[Path, str] | None:
    """``(folder of this process's memory cgroup, "v1" | "v2")``, or None where there is no writable one."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        number, controllers, path = line.split(":", 2)
        if "memory" in controllers.split(","):
            folder = Path("/sys/fs/cgroup/memory") / path.lstrip("/")
            if (folder / "memory.limit_in_bytes").exists():
                return folder, "v1"
    for line in lines:
        if line.startswith("0::"):
            folder = Path("/sys/fs/cgroup") / line[3:].lstrip("/")
            if (folder / "cgroup.controllers").exists():
                return folder, "v2"
    return None


class MemoryCap:
    """A child memory cgroup with a hard limit (cgroup v1 ``memory.limit_in_bytes`` or v2 ``memory.max``): a
    command run through :meth:`argv` and every process it starts are held under it, as in a container; the
    kernel's OOM killer ends them past it. ``peak_bytes`` is the cgroup's high-water mark."""

    def __init__(self, limit_bytes: int):
        own = _own_memory_cgroup()
        if own is None:
            raise PermissionError("no writable memory cgroup (needs root and cgroup v1's or v2's memory controller)")
        parent, self.version = own
        self.folder = parent / f"bcmocap-cap-{os.getpid()}"
        self.folder.mkdir(exist_ok=True)
        if self.version == "v1":
            (self.folder / "memory.limit_in_bytes").write_text(str(limit_bytes))
        else:
            (self.folder / "memory.max").write_text(str(limit_bytes))
            (self.folder / "memory.swap.max").write_text("0")
        self.limit_bytes = limit_bytes

    def argv(self, command: list[str]) -> list[str]:
        return ["sh", "-c", f'echo $$ > {self.folder}/cgroup.procs && exec "$@"', "sh", *command]

    @property
    def peak_bytes(self) -> int:
        name = "memory.max_usage_in_bytes" if self.version == "v1" else "memory.peak"
        return int((self.folder / name).read_text().split()[0])

    @property
    def oom_kills(self) -> int:
        if self.version == "v1":
            text = (self.folder / "memory.oom_control").read_text()
        else:
            text = (self.folder / "memory.events").read_text()
        return next((int(line.split()[1]) for line in text.splitlines() if line.startswith("oom_kill ")), 0)

    def close(self) -> None:
        try:
            self.folder.rmdir()
        except OSError:
            pass


def memory_cap(capture: Path, out: Path, config: Path | None, limit_gb: float, log: Path) -> dict:
    """``bcmocap run`` on ``capture`` in a memory cgroup of ``limit_gb``: finished, the cgroup's peak, each stage's
    peak from ``run.json``."""
    cap = MemoryCap(int(limit_gb * 1024 ** 3))
    try:
        command = [str(Path(sys.executable).parent / "bcmocap"), "run", str(capture), "--out", str(out)]
        command += ["--config", str(config)] if config else []
        start = time.perf_counter()
        with open(log, "a") as fh:
            done = subprocess.run(cap.argv(command), stdout=fh, stderr=subprocess.PIPE, text=True, cwd=REPO, env=ENV)
            fh.write(done.stderr)
        seconds = time.perf_counter() - start
        stages = json.loads((out / "run.json").read_text())["stages"] if (out / "run.json").is_file() else {}
        lines = (out / "log.txt").read_text(errors="replace").splitlines() if (out / "log.txt").is_file() else []
        return {"limit_gb": limit_gb, "cgroup": cap.version, "finished": done.returncode == 0 and len(stages) == 6,
                "last_log_line": lines[-1][20:220] if lines else "",
                "exit": done.returncode, "message": (done.stderr.strip().splitlines() or [""])[-1][:300],
                "oom_kills": cap.oom_kills, "peak_mb_cgroup": round(cap.peak_bytes / 1024 ** 2, 1),
                "peak_mb_per_stage": {s: r.get("peak_mb", r.get("peak_mb_since_start")) for s, r in stages.items()},
                "seconds_per_stage": {s: r.get("seconds") for s, r in stages.items()}, "seconds": round(seconds, 1)}
    finally:
        cap.close()
