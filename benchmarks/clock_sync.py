"""Clock rates and clap offsets from the soundtracks, against take length (issue 42: "clock rates within 10 ppm").

The suite's takes are 2 s long, too short to date a clock rate: one audio sample in the 2.48 s between their claps
is 8 ppm. This benchmark renders no pictures, only what the studio's ``realistic`` preset records as sound: for
each seed and take length, the 18 cameras' soundtracks of the capture trial (:func:`bcmocap.sim.studio.
trial_timelines` and :func:`~bcmocap.sim.studio.camera_soundtrack`: clocks within ±20 ppm of nominal, sub-frame
starts, audio latencies, the claps and the room noise), each written as the studio writes it and read back as
``bcmocap run`` reads it: ``aac``, the AAC track of an MP4 (:class:`bcmocap.io.media.MediaWriter`, 192 kbit/s;
the realistic preset's container), and ``wav``, 16-bit PCM (:func:`bcmocap.io.wav.write_wav`; the default
container's), the control. :func:`bcmocap.frontend.sync.synchronize_tracks` then finds the claps. A seed draws the
same clocks, starts and latencies at every length, so the lengths compare the same cameras.

Reported per container and take length (the claps are the length plus 0.5 s less a frame apart), over seeds ×
cameras:

- ``rate_error_ppm``: the clock rate against the truth (each relative to the cameras' median, as sync gives it);
- ``onset_error_samples``: each clap's first sample against where the studio put it (rounded to a sample);
- ``audio_offset_error_frames``: the first clap's time in each camera's video against the truth's, latency
  included (the audio latency itself is not observable from sound; the suite's time offsets come from the gyros).

    python benchmarks/clock_sync.py --json benchmarks/results/clock_sync.json
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json


def aac_roundtrip(track: np.ndarray, rate: int, fps: float, path: Path) -> np.ndarray:
    """``track`` written as the AAC soundtrack of an MP4 (one small black frame of video) and read back."""
    from bcmocap.io.media import MediaWriter, read_audio_track

    writer = MediaWriter(path, fps, (16, 16), audio_rate=rate)
    writer.write([np.zeros((16, 16, 3), np.uint8)])
    writer.write_audio(track)
    writer.close()
    samples, got = read_audio_track(path)
    if got != rate:
        raise RuntimeError(f"{path}: read back at {got} Hz, written at {rate} Hz")
    return samples


def wav_roundtrip(track: np.ndarray, rate: int, path: Path) -> np.ndarray:
    """``track`` written as a 16-bit PCM WAV (the studio's default container) and read back."""
    from bcmocap.io.wav import read_wav, write_wav

    write_wav(path, track, rate)
    samples, got = read_wav(path)
    if got != rate:
        raise RuntimeError(f"{path}: read back at {got} Hz, written at {rate} Hz")
    return samples


def take(seed: int, seconds: float, cameras: int, workdir: Path, container: str = "aac") -> dict:
    """One take's sync against its truth; ``container`` "aac" or "wav" (see the module docstring)."""
    if container not in ("aac", "wav"):
        raise ValueError(f"container must be 'aac' or 'wav', got {container!r}")
    from bcmocap.frontend.sync import synchronize_tracks
    from bcmocap.io.capture_folder import video_frame_at
    from bcmocap.sim.studio import (
        camera_soundtrack,
        clap_samples,
        preset_settings,
        trial_timelines,
    )

    settings = preset_settings("realistic", seed=seed, seconds=seconds)
    frames = round(seconds * settings.fps)
    timeline = trial_timelines(settings, {"rom": round(settings.rom_seconds * settings.fps), "capture": frames},
                               cameras)["capture"]
    truth_samples = clap_samples(timeline, settings)
    tracks = []
    for c in range(cameras):
        path = workdir / f"s{seed}-{seconds:g}-{c}.{'mp4' if container == 'aac' else 'wav'}"
        track = camera_soundtrack(settings, timeline, 1, c)
        tracks.append(aac_roundtrip(track, settings.audio_rate, settings.fps, path) if container == "aac"
                      else wav_roundtrip(track, settings.audio_rate, path))
        path.unlink()
    sync = synchronize_tracks(tracks, settings.audio_rate, settings.fps)
    rates = timeline["clock_rate"] / np.median(timeline["clock_rate"])
    audio_first_clap = (video_frame_at(timeline["video_start_time"], timeline["clock_rate"], timeline["clap_frames"][0])
                        + timeline["audio_latency_s"] * timeline["clock_rate"] * settings.fps)
    return {"container": container, "seed": seed, "seconds": seconds, "clap_span_s": float(sync.duration_s),
            "rate_error_ppm": (1e6 * (sync.clock_rates - rates)).tolist(),
            "onset_error_samples": (np.asarray(sync.clap_samples) - truth_samples).ravel().tolist(),
            "audio_offset_error_frames": (sync.frame_offsets - audio_first_clap).tolist()}


def _pooled(rows: list[dict], key: str) -> list[float]:
    """``key``'s values of every row, in one list."""
    return list(itertools.chain.from_iterable(r[key] for r in rows))


def _summary(values: list[float]) -> dict:
    a = np.abs(np.asarray(values, np.float64))
    return {"rms": float(np.sqrt(np.mean(a**2))), "p90": float(np.percentile(a, 90)), "max": float(a.max())}


def _length_summary(rows: list[dict]) -> dict:
    onset = np.asarray(_pooled(rows, "onset_error_samples"))
    return {"takes": len(rows), "rate_error_ppm": _summary(_pooled(rows, "rate_error_ppm")),
            "onsets_off": int((onset != 0).sum()), "onsets": int(onset.size),
            "onset_error_samples_max": int(np.abs(onset).max()),
            "audio_offset_error_frames": _summary(_pooled(rows, "audio_offset_error_frames"))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 (default 3)")
    ap.add_argument("--seconds", type=float, nargs="+", default=[2.0, 30.0, 120.0, 600.0],
                    help="take lengths (s; default 2 30 120 600)")
    ap.add_argument("--containers", nargs="+", default=["aac", "wav"], choices=["aac", "wav"],
                    help="how the soundtracks are written and read back (default: both)")
    ap.add_argument("--cameras", type=int, default=18)
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()

    clock = time.perf_counter()
    rows, results = [], {}
    with tempfile.TemporaryDirectory(prefix="bcmocap-clock-sync-") as tmp:
        for container in args.containers:
            for seconds in args.seconds:
                chosen = [take(seed, seconds, args.cameras, Path(tmp), container) for seed in range(args.seeds)]
                rows += chosen
                row = results.setdefault(container, {})[f"{seconds:g}"] = _length_summary(chosen)
                rate, offset = row["rate_error_ppm"], row["audio_offset_error_frames"]
                print(f"{container} {seconds:6.1f} s takes: clock rate error {rate['rms']:.2f} ppm RMS, p90 "
                      f"{rate['p90']:.2f}, max {rate['max']:.2f}; onsets off in {row['onsets_off']} of {row['onsets']} "
                      f"claps (max {row['onset_error_samples_max']} samples); first clap {offset['max']:.4f} frames max",
                      flush=True)
    if args.json:
        write_json(args.json, {"containers": results, "cameras": args.cameras, "takes": rows,
                               "settings": vars(args) | {"json": None},
                               "seconds": round(time.perf_counter() - clock, 1), "machine": machine()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
