"""How fast `bcmocap view` shows a run, and how smoothly it plays in headless Chromium.

1. Time to the first drawn frame: from starting the command `bcmocap view RUN_DIR` (a new process, as a
   user types it; Chromium is already open, as a user's browser is) to the browser's screenshot showing
   the skeleton's bones; with, on the way, the time until the server answers HTTP and until the command
   says its first frame's scene is built.
2. Playback in the browser: "Play" clicked in the page, then for --seconds the rate at which the page
   draws (requestAnimationFrame callbacks per second: WebGL in software, SwiftShader, on this CPU) and the
   rate at which distinct motion frames reach the page's frame field (the playback frames the user sees).
3. Where the command's own time goes (``--phases``, no browser): a new process times importing the
   command, starting the server, reading the run for the first frame, building the scene, and the reading
   deferred until after the first frame (scene points, ground truth, videos, pictures).

    python benchmarks/viewer.py RUN_DIR --json benchmarks/results/viewer.json   # RUN_DIR: a bcmocap run of the 10 s walk

RUN_DIR is a `bcmocap run` folder (the paper's 10 s walk: 315 frames, 15 joints, 18 cameras). The viewer
is started with --read-only, so the folder is not written.
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
import threading
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_json  # noqa: E402

import numpy as np  # noqa: E402

from bcmocap.viewer.app import BONE  # noqa: E402
from bcmocap.viewer.browser import Browser, colour_pixels, find_chromium, free_port  # noqa: E402


def _command(run_dir: str, port: int) -> list[str]:
    entry = shutil.which("bcmocap") or str(Path(sys.executable).with_name("bcmocap"))
    if Path(entry).is_file():
        return [entry, "view", run_dir, "--port", str(port), "--read-only"]
    return [sys.executable, "-m", "bcmocap.cli", "view", run_dir, "--port", str(port), "--read-only"]


def _until(condition, timeout: float, what: str, poll: float = 0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(poll)
    raise SystemExit(f"benchmarks/viewer.py: timed out after {timeout:g} s waiting for {what}")


def _answers(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=1) as page:
            return page.status == 200
    except OSError:
        return False


_ALL_INPUTS = "Array.from(document.querySelectorAll('input')).map(i => i.value)"
_CLICK_PLAY = ("(() => { const b = Array.from(document.querySelectorAll('button'))"
               ".find(x => x.innerText.trim() === 'Play'); if (b) b.click(); return !!b; })()")


def measure(args) -> dict:
    """One measurement: a new `bcmocap view` process and a fresh Chromium profile (nothing cached)."""
    port = free_port()
    url = f"http://127.0.0.1:{port}/"
    with Browser(args.width, args.height, timeout=120) as browser:
        start = time.perf_counter()
        process = subprocess.Popen(_command(args.run_dir, port), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                   text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        lines: list[tuple[float, str]] = []  # (s after the start, line) of everything the command prints
        reader = threading.Thread(target=lambda: lines.extend((time.perf_counter() - start, line.strip())
                                                              for line in process.stdout), daemon=True)
        reader.start()
        try:
            _until(lambda: process.poll() is not None or _answers(url), 120, "the server", poll=0.02)
            if process.poll() is not None:
                reader.join(5)
                raise SystemExit(f"bcmocap view exited: {' '.join(line for _, line in lines)}")
            server_s = time.perf_counter() - start
            browser.open(url)  # the page loads while the command reads the run
            _until(lambda: colour_pixels(browser.screenshot(), BONE, left_fraction=0.65) > 40, 120,
                   "the skeleton to be drawn", poll=0.0)
            first_frame_s = time.perf_counter() - start
            built_s, banner = _until(lambda: next(((t, x) for t, x in lines if "open http" in x), None), 60,
                                     "the command's line")
            browser.dismiss_notifications()
            idle_fps = browser.animation_frame_rate(2.0)
            before = browser.evaluate(_ALL_INPUTS)
            if not browser.evaluate(_CLICK_PLAY):
                raise SystemExit("benchmarks/viewer.py: no Play button in the page")
            (field,) = _until(lambda: next(((k,) for k, v in enumerate(browser.evaluate(_ALL_INPUTS))
                                            if k < len(before) and v != before[k]), None), 30,
                              "the frame field to change", poll=0.02)
            distinct_start = time.perf_counter()
            distinct, last = 0, None
            while time.perf_counter() - distinct_start < args.seconds:
                value = browser.evaluate(_ALL_INPUTS)[field]
                distinct += value != last
                last = value
                time.sleep(0.03)  # polling must not take the page's CPU
            playback_fps = (distinct - 1) / (time.perf_counter() - distinct_start)
            playing_fps = browser.animation_frame_rate(2.0)
        finally:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
    ready = re.search(r"ready in ([0-9.]+) s", banner)
    counts = re.search(r"(\d+) frames, (\d+) joints, (\d+) cameras", banner)
    return {"frames": int(counts.group(1)) if counts else None, "joints": int(counts.group(2)) if counts else None,
            "cameras": int(counts.group(3)) if counts else None, "server_answers_s": round(server_s, 2),
            "scene_built_s": round(built_s, 2), "viewer_ready_in_process_s": float(ready.group(1)) if ready else None,
            "first_drawn_frame_s": round(first_frame_s, 2), "browser_draw_fps_idle": round(idle_fps, 1),
            "browser_draw_fps_playing": round(playing_fps, 1), "playback_frames_per_s_in_page": round(playback_fps, 1),
            "load_average": os.getloadavg()}


# Run by a fresh `python -c` (this file's own imports would be timed otherwise): the steps of `bcmocap view`
# up to the first frame's scene, then the deferred reading; prints JSON {step: seconds}.
_PHASES = r"""
import json, sys, time
start = time.perf_counter()
steps, last = {}, start
def step(name):
    global last
    now = time.perf_counter()
    steps[name] = round(now - last, 3)
    last = now
import bcmocap.cli
from bcmocap.precision import enable_float64
enable_float64()
step("import the command (every subcommand's parser)")
from bcmocap.pipeline.view_input import check_run_folder
from bcmocap.viewer.server import start_server
check_run_folder(sys.argv[1])
server = start_server("127.0.0.1", 0)
step("import viser, start the server (a browser can load the page from here)")
from bcmocap.pipeline.view_input import load_view_input
from bcmocap.viewer.app import Viewer
step("import the viewer and the model's classes (JAX)")
data = load_view_input(sys.argv[1], editable=False, defer=True)
step("read the run for the first frame (model, motions, store index)")
viewer = Viewer(data, server)
step("build the scene and panel, draw frame 0")
steps["= first frame's scene built"] = round(time.perf_counter() - start, 3)
last = time.perf_counter()
viewer.ready.wait()
step("after it: scene points, ground truth, videos, pictures")
viewer.close()
server.stop()
print(json.dumps(steps))
"""


def phases(run_dir: str) -> dict:
    """Seconds per step of `bcmocap view` in a new process (no browser)."""
    done = subprocess.run([sys.executable, "-c", _PHASES, run_dir], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"benchmarks/viewer.py: the timed steps failed: {done.stderr.strip()[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="a `bcmocap run` folder")
    parser.add_argument("--phases", action="store_true",
                        help="also time the command's steps in a new process, --repeat times (no browser)")
    parser.add_argument("--seconds", type=float, default=5.0, help="how long playback is measured (s)")
    parser.add_argument("--repeat", type=int, default=3, help="measurements (medians and ranges are reported)")
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=800)
    parser.add_argument("--json", help="write the figures to this JSON file")
    args = parser.parse_args()
    if find_chromium() is None:
        raise SystemExit("benchmarks/viewer.py: Chromium not found (apt-get install chromium)")
    steps = [phases(args.run_dir) for _ in range(max(1, args.repeat))] if args.phases else []
    runs = [measure(args) for _ in range(max(1, args.repeat))]
    keys = ("server_answers_s", "scene_built_s", "first_drawn_frame_s", "browser_draw_fps_idle",
            "browser_draw_fps_playing", "playback_frames_per_s_in_page")
    summary = {k: {"median": float(np.median([r[k] for r in runs])), "min": min(r[k] for r in runs),
                   "max": max(r[k] for r in runs)} for k in keys}
    first = runs[0]
    result = {"run_dir": str(Path(args.run_dir).resolve()), "frames": first["frames"], "joints": first["joints"],
              "cameras": first["cameras"], "window_px": [args.width, args.height], "playback_seconds_measured":
              args.seconds, "chromium": subprocess.run([find_chromium(), "--version"], capture_output=True,
                                                       text=True).stdout.strip(),
              "goal_first_frame_s": 5.0, **summary, "runs": runs}
    if steps:
        result["steps_s"] = {k: {"median": float(np.median([x[k] for x in steps])), "min": min(x[k] for x in steps),
                                 "max": max(x[k] for x in steps)} for k in steps[0]}
        result["steps_runs"] = steps
    print(f"bcmocap view {result['run_dir']} ({result['frames']} frames, {result['joints']} joints, "
          f"{result['cameras']} cameras), headless Chromium {args.width}x{args.height}, software WebGL; "
          f"median [min, max] of {len(runs)}:")

    def row(label, key, unit):
        f = summary[key]
        print(f"  {label:<34}{f['median']:6.2f} [{f['min']:.2f}, {f['max']:.2f}] {unit}")

    row("server answers HTTP", "server_answers_s", "s after the command started")
    row("first frame's scene built", "scene_built_s", "s after the command started")
    row("first frame drawn", "first_drawn_frame_s", "s (goal ≤ 5 s)")
    row("browser draws, idle", "browser_draw_fps_idle", "frames/s")
    row("browser draws, playing", "browser_draw_fps_playing", "frames/s")
    row("playback frames reaching the page", "playback_frames_per_s_in_page", "frames/s (1×: the run's frame rate)")
    print("  load average during the runs      " + ", ".join(f"{r['load_average'][0]:.2f}" for r in runs))
    if steps:
        print(f"the command's steps, new process, no browser (s; median [min, max] of {len(steps)}):")
        for name, f in result["steps_s"].items():
            print(f"  {name:<66}{f['median']:6.2f} [{f['min']:.2f}, {f['max']:.2f}]")
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
