"""Shared bits of the benchmark scripts: machine description and JSON output."""

from __future__ import annotations

import json
import os
import platform
import resource
import sys
import tempfile
from pathlib import Path


def machine() -> dict:
    import jax

    return {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
    }


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB).

    Reads ``VmHWM`` from /proc: ``ru_maxrss`` survives ``execve`` on Linux, so a child started by a
    large parent would report the parent's peak instead of its own.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cpu_seconds() -> float:
    """CPU time (user + system, s) this process has used so far."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def write_json(path: str | None, payload: dict) -> None:
    """Write ``payload`` (plus the machine) atomically to ``path`` if given."""
    if not path:
        return
    payload = {**payload, "machine": machine()}
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, suffix=".json")
    with os.fdopen(fd, "w") as fh:
        json.dump(payload, fh, indent=2)
        fh.write("\n")
    os.replace(tmp, target)
    print(f"wrote {target}")


def solve_summary(solution, correspondences, solve_seconds: float, num_frames: int) -> dict:
    """Solver figures shared by the accuracy rows: frames, time, converged windows, observation density."""
    return {
        "frames": num_frames,
        "solve_seconds": solve_seconds,
        "converged_windows": sum(r.converged for r in solution.reports),
        "windows": len(solution.reports),
        "observations_per_camera_frame": float((correspondences.weights > 0).sum() / correspondences.registered.sum()),
    }
