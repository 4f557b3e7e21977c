"""Tests for audio synchronisation (bcmocap.frontend.sync): soundtracks made exactly as the capture
studio makes them (its timeline, clap positions and soundtrack generator), checked against its
ground-truth start frames."""

import numpy as np
import pytest
from test_frontend_capture import CAMERAS, make_capture

from bcmocap.frontend import (
    clap_candidates,
    given_offsets,
    read_capture,
    synchronize,
    synchronize_tracks,
)
from bcmocap.io.wav import write_wav
from bcmocap.sim.audio import soundtrack
from bcmocap.sim.studio import StudioSettings, _timeline, clap_samples


def studio_tracks(seed: int, cameras: int = 6, frames: int = 12, rate: int = 16000, fps: float = 60.0):
    settings = StudioSettings(seconds=frames / fps, fps=fps, audio_rate=rate)
    rng = np.random.default_rng(seed)
    timeline = _timeline(frames, cameras, fps, rng)
    claps = clap_samples(timeline, settings)
    tracks = [soundtrack(int(round(n * rate / fps)), claps[c].tolist(), rate, rng, gain=g)
              for c, (n, g) in enumerate(zip(timeline["num_video_frames"], timeline["audio_gain"]))]
    return tracks, timeline, claps


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_offsets_match_the_studio_start_frames_exactly(seed):
    tracks, timeline, claps = studio_tracks(seed)
    result = synchronize_tracks(tracks, 16000, 60.0)
    np.testing.assert_array_equal(result.offsets, timeline["video_start_frame"] + timeline["clap_frames"][0])
    np.testing.assert_array_equal(result.clap_samples, claps)
    assert result.agreeing == 6
    assert result.duration_s == pytest.approx(np.diff(timeline["clap_frames"])[0] / 60.0, abs=1 / 16000)


def test_a_louder_spurious_bang_in_one_camera_is_outvoted():
    tracks, timeline, _ = studio_tracks(4)
    rng = np.random.default_rng(0)
    bang = soundtrack(len(tracks[2]), [len(tracks[2]) // 2 + 123], 16000, rng, gain=1.0, noise_level=0.0)
    tracks[2] = np.clip(tracks[2] * 0.5 + bang, -1, 1)
    onsets, _ = clap_candidates(tracks[2], 16000)
    assert len(onsets) == 3
    result = synchronize_tracks(tracks, 16000, 60.0)
    np.testing.assert_array_equal(result.offsets, timeline["video_start_frame"] + timeline["clap_frames"][0])


def test_errors_and_given_offsets(tmp_path):
    tracks, _, _ = studio_tracks(5, cameras=3)
    tracks[1] = np.random.default_rng(1).normal(scale=0.01, size=len(tracks[1]))  # no claps at all
    with pytest.raises(ValueError, match=r"in cameras \['b'\]"):
        synchronize_tracks(tracks, 16000, 60.0, cameras=["a", "b", "c"])
    folder = make_capture(tmp_path / "capture")
    cap = read_capture(folder)
    assert given_offsets(cap, {"head": 3, "left_foot": 5}).offset("left_foot") == 5
    with pytest.raises(ValueError, match=r"missing cameras \['left_foot'\]"):
        given_offsets(cap, {"head": 3})
    # Through the capture folder: write studio-like tracks at the capture's 8 kHz / 30 fps.
    tracks, timeline, _ = studio_tracks(6, cameras=2, frames=9, rate=8000, fps=30.0)
    for name, track in zip(CAMERAS, tracks):
        write_wav(folder / "trials" / "rom" / f"{name}.wav", track, 8000)
    result = synchronize(cap, "rom")
    assert result.cameras == CAMERAS
    np.testing.assert_array_equal(result.offsets, timeline["video_start_frame"] + timeline["clap_frames"][0])
