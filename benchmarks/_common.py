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
    """The machine, with :func:`machine_score` (measured once per process)."""
    import jax

    return {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "score": machine_score(),
    }


_SCORE: dict | None = None


def machine_score(repeats: int = 3) -> dict:
    """Seconds of a fixed small workload of what the pipeline uses, the best of ``repeats`` (lower is faster).

    Machines of one kind differ 2–3x in speed, so an absolute time in a results file means something only beside
    the speed of the machine it was measured on: ``sift_s`` (OpenCV SIFT on a fixed 640×480 image), ``jax_s`` (a
    jitted, vmapped float64 kernel: 20 000 rotations of 64 points, compile excluded), ``numpy_s`` (sorting 2 million
    numbers and a cumulative sum of their roots: no BLAS, whose thread spinning makes a busy machine's score
    erratic) and their sum ``total_s``. It takes a few seconds with the imports, once per process (later calls return
    the first result, whatever ``repeats``), when the results file is written: a machine busy then scores slower.
    ``jax_s`` runs on JAX's default backend, so scores compare between machines of one backend.
    """
    global _SCORE
    if _SCORE is not None:
        return _SCORE
    import time

    import cv2
    import jax
    import jax.numpy as jnp
    import numpy as np

    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur((rng.random((480, 640)) * 255).astype(np.uint8), (0, 0), 2.0)
    sift = cv2.SIFT_create(nfeatures=2000)
    with jax.enable_x64(True):
        angles = jnp.asarray(rng.normal(size=(20000, 3)))
        points = jnp.asarray(rng.normal(size=(64, 3)))

        @jax.jit
        def rotate(angles, points):
            def one(a):
                theta = jnp.linalg.norm(a) + 1e-12
                k = a / theta
                return (points * jnp.cos(theta) + jnp.cross(k, points) * jnp.sin(theta)
                        + k * (points @ k)[:, None] * (1 - jnp.cos(theta))).sum()
            return jax.vmap(one)(angles).sum()

        rotate(angles, points).block_until_ready()
        values = rng.random(2_000_000)

        def best(work) -> float:
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                work()
                times.append(time.perf_counter() - start)
            return min(times)

        parts = {
            "sift_s": best(lambda: sift.detectAndCompute(image, None)),
            "jax_s": best(lambda: rotate(angles, points).block_until_ready()),
            "numpy_s": best(lambda: (np.sort(values), np.cumsum(np.sqrt(values)))),
        }
    _SCORE = {**{k: round(v, 4) for k, v in parts.items()}, "total_s": round(sum(parts.values()), 4)}
    return _SCORE


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
