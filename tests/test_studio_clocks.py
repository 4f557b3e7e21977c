"""Tests for the studio's clocks (settings start_subframe, clock_ppm, audio_latency_ms, imu_offset_ms): each camera
starts at a sub-frame time, counts time with its own clock, its audio lags its video, and the IMU's timestamps are
offset; the ground truth says by how much."""

import numpy as np
import pytest

from bcmocap.io.capture_folder import TrialTruth
from bcmocap.sim.studio import (
    StudioSettings,
    clap_samples,
    preset_settings,
    trial_timelines,
    video_frame_times,
)

CAMERAS = 18


def _timelines(settings: StudioSettings, frames=(30, 60)):
    return trial_timelines(settings, dict(zip(("rom", "capture"), frames)), CAMERAS)


def test_without_time_errors_the_clocks_are_the_whole_frame_timeline():
    settings = StudioSettings(seed=4)
    for timeline in _timelines(settings).values():
        np.testing.assert_array_equal(timeline["video_start_time"], timeline["video_start_frame"])
        np.testing.assert_array_equal(timeline["clock_rate"], 1.0)
        np.testing.assert_array_equal(timeline["audio_latency_s"], 0.0)
        assert timeline["imu_clock_offset_s"] == 0.0
        # video frame i shows trial frame clip(i - start, 0, T - 1): whole frames
        times = video_frame_times(timeline, 2, 60)
        start = timeline["video_start_frame"][2]
        np.testing.assert_array_equal(times, np.clip(np.arange(len(times)) - start, 0, 59))
        # the claps at the samples the studio always wrote
        expected = np.round((timeline["clap_frames"][None] + timeline["video_start_frame"][:, None]) * 800)
        np.testing.assert_array_equal(clap_samples(timeline, settings), expected)


def test_clocks_are_drawn_per_camera_within_their_settings():
    settings = StudioSettings(seed=4, start_subframe=True, clock_ppm=20.0, audio_latency_ms=5.0, imu_offset_ms=30.0)
    rom, capture = _timelines(settings).values()
    for timeline in (rom, capture):
        phase = timeline["video_start_time"] - timeline["video_start_frame"]
        assert np.all((phase >= 0) & (phase < 1)) and phase.std() > 0.1
        assert np.all(np.abs(timeline["clock_rate"] - 1) <= 20e-6) and np.ptp(timeline["clock_rate"]) > 10e-6
        assert np.all((timeline["audio_latency_s"] >= 0) & (timeline["audio_latency_s"] <= 0.005))
        assert abs(timeline["imu_clock_offset_s"]) <= 0.030
    # a camera's crystal and audio path are the same in both trials; its start and the IMU clock are new
    np.testing.assert_array_equal(rom["clock_rate"], capture["clock_rate"])
    np.testing.assert_array_equal(rom["audio_latency_s"], capture["audio_latency_s"])
    assert not np.array_equal(rom["video_start_time"] % 1, capture["video_start_time"] % 1)
    assert rom["imu_clock_offset_s"] != capture["imu_clock_offset_s"]
    # the same seed draws the same clocks, another seed others
    again = _timelines(settings)["capture"]
    np.testing.assert_array_equal(again["clock_rate"], capture["clock_rate"])
    other = _timelines(StudioSettings(seed=5, start_subframe=True, clock_ppm=20.0))["capture"]
    assert not np.array_equal(other["clock_rate"], capture["clock_rate"])


def test_video_times_and_claps_follow_each_cameras_clock():
    settings = StudioSettings(seed=2, start_subframe=True, clock_ppm=500.0, audio_latency_ms=5.0)
    timeline = _timelines(settings, frames=(30, 600))["capture"]
    truth = TrialTruth(
        name="capture", motion=None, joint_positions=None, world_rotations=None, world_from_camera=None,
        video_start_frame=timeline["video_start_frame"], num_video_frames=timeline["num_video_frames"],
        clap_frames=timeline["clap_frames"], clap_samples=None, audio_gain=None, markers=None, fps=60.0,
        audio_rate=48000, world_from_mount=None, camera_offsets=None, video_start_time=timeline["video_start_time"],
        clock_rate=timeline["clock_rate"], audio_latency_s=timeline["audio_latency_s"])
    for camera in (0, 7):
        times = video_frame_times(timeline, camera, 600)
        inside = (times > 0) & (times < 599)
        index = np.flatnonzero(inside)
        # TrialTruth.video_frame_of inverts the video's times
        np.testing.assert_allclose(truth.video_frame_of(camera, times[inside]), index, atol=1e-9)
        # a fast clock shows less trial time per video frame
        step = np.diff(times[inside]).mean()
        np.testing.assert_allclose(step, 1.0 / timeline["clock_rate"][camera], rtol=1e-12)
    # each clap lands at its video time on the camera's clock plus the camera's audio latency
    samples = clap_samples(timeline, settings)
    at_video = truth.video_frame_of(np.arange(CAMERAS)[:, None], timeline["clap_frames"][None]) * 800
    lag = samples - at_video
    expected = np.broadcast_to((timeline["audio_latency_s"] * timeline["clock_rate"] * 48000)[:, None], lag.shape)
    np.testing.assert_allclose(lag, expected, atol=0.5)
    # the two claps are further apart in a fast camera's track
    spread = samples[:, 1] - samples[:, 0]
    assert np.corrcoef(spread, timeline["clock_rate"])[0, 1] > 0.9


def test_the_realistic_preset_turns_the_clocks_on():
    settings = preset_settings("realistic", seed=1)
    assert settings.start_subframe and settings.clock_ppm == 20.0
    assert settings.audio_latency_ms == 5.0 and settings.imu_offset_ms == 30.0


@pytest.mark.parametrize("field, value", [("clock_ppm", -1.0), ("clock_ppm", 2000.0), ("audio_latency_ms", float("nan")),
                                          ("imu_offset_ms", True), ("start_subframe", 1)])
def test_bad_clock_settings_are_refused_naming_the_field(field, value):
    with pytest.raises(ValueError, match=f"StudioSettings.{field}"):
        StudioSettings(**{field: value})


@pytest.mark.slow  # ~7 s: the heavy tier
def test_claps_give_sub_frame_offsets_and_clock_rates_to_the_audio_latency():
    """synchronize_tracks on the studio's soundtracks: the first clap's video time to a fraction of a frame (its
    error is the camera's audio latency, which audio cannot tell) and each clock's rate against the median."""
    from bcmocap.frontend.sync import synchronize_tracks
    from bcmocap.sim.studio import _plan, camera_soundtrack

    for latency_ms in (0.0, 5.0):
        settings = StudioSettings(seconds=10.0, rom_seconds=0.1, seed=6, start_subframe=True, clock_ppm=50.0,
                                  audio_latency_ms=latency_ms)
        plan = _plan(settings)
        timeline = plan.timelines["capture"]
        tracks = [camera_soundtrack(plan.settings, timeline, 1, c) for c in range(CAMERAS)]
        sync = synchronize_tracks(tracks, settings.audio_rate, settings.fps)
        first_clap = timeline["video_start_time"] + timeline["clock_rate"] * timeline["clap_frames"][0]
        lag = timeline["audio_latency_s"] * timeline["clock_rate"] * settings.fps
        error = sync.frame_offsets - (first_clap + lag)
        assert np.abs(error).max() < 0.02  # frames: the audio's own precision
        if latency_ms == 0:
            assert np.abs(sync.frame_offsets - first_clap).max() < 0.02
        else:  # the latency is in the offsets: up to 0.3 frames at 60 fps
            assert np.abs(sync.frame_offsets - first_clap).max() > 0.1
        np.testing.assert_array_equal(sync.offsets, np.round(sync.frame_offsets))
        truth = timeline["clock_rate"] / np.median(timeline["clock_rate"])
        assert np.abs(sync.clock_rates - truth).max() < 5e-6  # 5 ppm over a 10.5 s take


@pytest.mark.slow  # renders a small capture
def test_each_video_frame_shows_the_trial_at_its_cameras_clock(tmp_path):
    """A capture with sub-frame starts and fast clocks: each decoded video frame matches a render of the trial at
    the time its camera's clock says better than renders 0.4 frames before or after it."""
    import cv2

    from bcmocap.cameras import camera_at
    from bcmocap.sim.render import Renderer
    from bcmocap.sim.studio import _plan, capsule_ends, load_ground_truth, write_capture

    settings = StudioSettings(seconds=0.25, rom_seconds=0.05, width=96, height=54, reference_photos=1,
                              reference_width=64, reference_height=48, seed=3, read_noise_dn=0.0,
                              start_subframe=True, clock_ppm=1000.0)
    folder = write_capture(tmp_path / "capture", settings, progress=False)
    truth = load_ground_truth(folder).trials["capture"]
    plan = _plan(settings)
    camera = int(np.argmax(np.abs(truth.video_start_time % 1 - 0.5) < 0.3))  # a phase far from a whole frame
    video = cv2.VideoCapture(str(folder / "trials" / "capture" / f"{plan.rig.names[camera]}.mp4"))
    frames = []
    while True:
        ok, image = video.read()
        if not ok:
            break
        frames.append(image[..., ::-1].astype(np.float64))
    assert len(frames) == truth.num_video_frames[camera]
    renderer = Renderer(plan.scene, camera_at(plan.rig.intrinsics, camera), settings.render_options())
    ends, radii, colors = capsule_ends(plan.skeleton, plan.trials["capture"])
    times = video_frame_times(plan.timelines["capture"], camera, truth.motion.num_frames)
    inside = np.flatnonzero((times > 1) & (times < truth.motion.num_frames - 2))[:4]
    np.testing.assert_allclose(truth.video_frame_of(camera, times[inside]), inside, atol=1e-9)

    def render(at):
        rot, org = renderer.poses_at(plan.camera_poses["capture"][:, camera], at)
        return renderer.render(rot, org, renderer.capsules_at(ends, at), radii, colors).astype(np.float64)

    decoded = np.stack([frames[i] for i in inside])
    error = {shift: np.abs(render(times[inside] + shift) - decoded).mean() for shift in (-0.4, 0.0, 0.4)}
    assert error[0.0] < min(error[-0.4], error[0.4]), error  # the codec's own error is most of error[0]
