"""benchmarks/clock_sync.py (issue 42): the studio's soundtracks through AAC and back, synchronised, compared with the
timeline that made them."""

import numpy as np

from benchmarks import clock_sync


def test_a_take_s_soundtracks_survive_aac_and_give_the_clocks_back(tmp_path):
    row = clock_sync.take(seed=1, seconds=2.0, cameras=4, workdir=tmp_path)
    assert not list(tmp_path.iterdir())  # the MP4s are removed
    assert row["clap_span_s"] == np.float64(row["clap_span_s"]) and 2.0 < row["clap_span_s"] < 3.0
    onsets = np.asarray(row["onset_error_samples"])
    assert onsets.shape == (8,) and np.abs(onsets).max() < 100  # AAC smears an onset now and then, never by a frame
    # one audio sample in a 2.5 s span is 8 ppm; the clocks are drawn within ±20 ppm of each other
    assert np.abs(row["rate_error_ppm"]).max() < 1e6 * np.abs(onsets).max() / (row["clap_span_s"] * 48000) + 10
    assert np.abs(row["audio_offset_error_frames"]).max() < 0.15


def test_the_summary_is_of_magnitudes():
    s = clock_sync._summary([3.0, -4.0])
    assert s["max"] == 4.0 and s["rms"] == np.sqrt(12.5) and 3.0 < s["p90"] <= 4.0
