"""benchmarks/clock_sync.py (issue 42): the studio's soundtracks written as the studio writes them and read back,
synchronised, compared with the timeline that made them."""

import numpy as np
import pytest

from benchmarks import clock_sync
from bcmocap.sim.studio import preset_settings, trial_timelines


@pytest.mark.parametrize("container", ["wav", "aac"])
def test_a_take_s_soundtracks_give_the_clocks_back(tmp_path, container):
    seed, seconds, cameras = 1, 10.0, 4
    row = clock_sync.take(seed, seconds, cameras, tmp_path, container)
    assert not list(tmp_path.iterdir())  # the files are removed
    settings = preset_settings("realistic", seed=seed, seconds=seconds)
    rates = trial_timelines(settings, {"rom": 1, "capture": 600}, cameras)["capture"]["clock_rate"]
    truth = rates / np.median(rates)
    assert 1e6 * np.abs(truth - 1).max() > 10  # answering "all clocks alike" would fail the check below
    onsets = np.asarray(row["onset_error_samples"]).reshape(cameras, 2)
    exact = (onsets == 0).all(axis=1)
    if container == "wav":
        assert exact.all()  # 16-bit PCM keeps every clap to the sample
    assert exact.sum() >= cameras // 2  # AAC moves a clap now and then, not most
    errors = np.abs(np.asarray(row["rate_error_ppm"]))
    # a span dated to a sample at each end (the truth is rounded to one) over 10.48 s: 2 ppm, and the median's as much
    assert errors[exact].max() < 4.5
    assert np.abs(row["audio_offset_error_frames"])[exact].max() < 0.01


def test_the_summary_is_of_magnitudes():
    s = clock_sync._summary([3.0, -4.0])
    assert s["max"] == 4.0 and s["rms"] == np.sqrt(12.5) and 3.0 < s["p90"] <= 4.0
    rows = [{"rate_error_ppm": [1.0, -2.0], "onset_error_samples": [0, 3, 0, 0], "audio_offset_error_frames": [0.0, 0.1]}]
    summary = clock_sync._length_summary(rows)
    assert summary["onsets_off"] == 1 and summary["onsets"] == 4 and summary["onset_error_samples_max"] == 3
