"""Clock rates and clap offsets from the soundtracks, against take length (issue 42: "clock rates within 10 ppm").

The suite's takes are 2 s long, too short to date a clock rate: one audio sample in a 2.5 s span between the
claps is 8 ppm. This benchmark renders no pictures, only what the studio's ``realistic`` preset records as sound:
for each seed and take length, the 18 cameras' soundtracks of the capture trial (:func:`bcmocap.sim.studio.
trial_timelines` and :func:`~bcmocap.sim.studio.camera_soundtrack`: the clocks' rates of ±20 ppm, sub-frame starts,
audio latencies, the claps and the room noise), each encoded as the AAC track of an MP4 the way the studio writes
one (:class:`bcmocap.io.media.MediaWriter`, 192 kbit/s) and read back as ``bcmocap run`` reads it
(:func:`bcmocap.io.media.read_audio_track`). :func:`bcmocap.frontend.sync.synchronize_tracks` then finds the claps.

Reported per take length (the time between the two claps is the length plus 0.5 s), over seeds × cameras:

- ``rate_error_ppm``: the clock rate against the truth (each relative to the cameras' median, as sync gives it);
- ``onset_error_samples``: each clap's first sample against where the studio put it (the AAC encoder smears an
  onset now and then);
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


def take(seed: int, seconds: float, cameras: int, workdir: Path) -> dict:
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
    tracks = [aac_roundtrip(camera_soundtrack(settings, timeline, 1, c), settings.audio_rate, settings.fps,
                            workdir / f"s{seed}-{seconds:g}-{c}.mp4") for c in range(cameras)]
    for c in range(cameras):
        (workdir / f"s{seed}-{seconds:g}-{c}.mp4").unlink()
    sync = synchronize_tracks(tracks, settings.audio_rate, settings.fps)
    rates = timeline["clock_rate"] / np.median(timeline["clock_rate"])
    audio_first_clap = (video_frame_at(timeline["video_start_time"], timeline["clock_rate"], timeline["clap_frames"][0])
                        + timeline["audio_latency_s"] * timeline["clock_rate"] * settings.fps)
    return {"seed": seed, "seconds": seconds, "clap_span_s": float(sync.duration_s),
            "rate_error_ppm": (1e6 * (sync.clock_rates - rates)).tolist(),
            "onset_error_samples": (np.asarray(sync.clap_samples) - truth_samples).ravel().tolist(),
            "audio_offset_error_frames": (sync.frame_offsets - audio_first_clap).tolist()}


def _pooled(rows: list[dict], key: str) -> list[float]:
    """``key``'s values of every row, in one list."""
    return list(itertools.chain.from_iterable(r[key] for r in rows))


def _summary(values: list[float]) -> dict:
    a = np.abs(np.asarray(values, np.float64))
    return {"rms": float(np.sqrt(np.mean(a**2))), "p90": float(np.percentile(a, 90)), "max": float(a.max())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=5, help="seeds 0..N-1 (default 5)")
    ap.add_argument("--seconds", type=float, nargs="+", default=[2.0, 30.0, 120.0, 600.0],
                    help="take lengths (s; default 2 30 120 600)")
    ap.add_argument("--cameras", type=int, default=18)
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()

    clock = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bcmocap-clock-sync-") as tmp:
        for seconds in args.seconds:
            for seed in range(args.seeds):
                rows.append(take(seed, seconds, args.cameras, Path(tmp)))
            chosen = [r for r in rows if r["seconds"] == seconds]
            rate = _summary(_pooled(chosen, "rate_error_ppm"))
            onset = np.asarray(_pooled(chosen, "onset_error_samples"))
            offset = _summary(_pooled(chosen, "audio_offset_error_frames"))
            print(f"{seconds:6.1f} s takes: clock rate error {rate['rms']:.2f} ppm RMS, p90 {rate['p90']:.2f}, max "
                  f"{rate['max']:.2f}; onsets off in {int((onset != 0).sum())} of {onset.size} claps (max "
                  f"{int(np.abs(onset).max())} samples); first clap {offset['max']:.4f} frames max", flush=True)
    lengths = {}
    for seconds in args.seconds:
        chosen = [r for r in rows if r["seconds"] == seconds]
        onset = np.asarray(_pooled(chosen, "onset_error_samples"))
        lengths[f"{seconds:g}"] = {
            "takes": len(chosen), "cameras": args.cameras,
            "rate_error_ppm": _summary(_pooled(chosen, "rate_error_ppm")),
            "onsets_off": int((onset != 0).sum()), "onsets": int(onset.size),
            "onset_error_samples_max": int(np.abs(onset).max()),
            "audio_offset_error_frames": _summary(_pooled(chosen, "audio_offset_error_frames"))}
    if args.json:
        write_json(args.json, {"lengths": lengths, "takes": rows, "settings": vars(args) | {"json": None},
                               "seconds": round(time.perf_counter() - clock, 1), "machine": machine()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
