"""GoPro telemetry (bcmocap.io.gopro) on GoPro's own sample file, and ``bcmocap init`` writing it as a trial's imu.npz
on the trial's clock (bcmocap.frontend.telemetry).

``tests/data/gopro/karma.mp4`` is GoPro's HERO5 Black sample on a Karma drone (``tests/data/gopro/README.md``): 12 s of
854×480 video at 29.97 frames/s, with the camera's gyroscope and accelerometer in its GPMF track.
"""

import shutil
from pathlib import Path

import av
import numpy as np
import pytest
from conftest import one_line_error
from test_init import CAMERAS, FPS, run_init, shoot  # noqa: F401  (the fixture)

from bcmocap.frontend import read_capture, synchronize
from bcmocap.frontend.telemetry import CameraTelemetry, trial_imu
from bcmocap.geometry import matrix_from_quat
from bcmocap.io.gopro import CAMERA_FROM_GOPRO_IMU, GoProImu, SensorSamples, _channel_axes, read_gopro_imu
from bcmocap.io.media import probe_media
from bcmocap.io.sensors import read_imu

SAMPLE = Path(__file__).parent / "data" / "gopro" / "karma.mp4"
VIDEO_S = 362 / (30000 / 1001)  # the sample's 362 frames at 29.97 frames/s


def test_the_sample_s_gyro_and_accelerometer_are_read_on_its_video_clock_in_gopro_s_axes():
    imu = read_gopro_imu(SAMPLE)
    assert imu.device == "Camera" and imu.channels == "table ZXY"  # HERO5 firmware: no ORIO, the README's order
    # about 400 Hz and 200 Hz on the file's clock (GoPro's figure for the HERO5: 400 and 200)
    assert 390 < imu.gyro.rate_hz < 405 and 195 < imu.accel.rate_hz < 202
    # the samples span the video (a payload per second; the last stops with the recording)
    for sensor in (imu.gyro, imu.accel):
        assert abs(sensor.time_s[0]) < 0.05 and abs(sensor.time_s[-1] - VIDEO_S) < 0.05
        assert np.all(np.diff(sensor.time_s) > 0) and sensor.values.shape == (len(sensor.time_s), 3)
    # the gimbal holds the camera level: gravity's reaction along +Z (up), little along X and Y
    mean = imu.accel.values.mean(axis=0)
    assert 9.5 < mean[2] < 10.1 and np.all(np.abs(mean[:2]) < 0.5)
    # the drone turns about the vertical: below the gimbal's vibration (averaged over 0.1 s), the Z gyro carries most
    # of the rotation
    kernel = np.ones(40) / 40
    smooth = np.stack([np.convolve(imu.gyro.values[:, k], kernel, mode="valid") for k in range(3)], axis=1)
    rms = np.sqrt(np.mean(smooth**2, axis=0))
    assert rms[2] > 3 * max(rms[0], rms[1])


def test_gopro_s_axes_in_the_camera_frame():
    # X to the camera's left, Y out of its back, Z up; the camera frame: x right, y down, z along the lens
    rotation = matrix_from_quat(CAMERA_FROM_GOPRO_IMU)
    np.testing.assert_allclose(rotation @ np.eye(3), [[-1, 0, 0], [0, 0, -1], [0, -1, 0]], atol=1e-12)
    imu = read_gopro_imu(SAMPLE)
    np.testing.assert_allclose(imu.camera_from_imu, CAMERA_FROM_GOPRO_IMU)


def test_channel_orders_from_orio_or_the_model_table_and_an_unknown_model_refused():
    path = Path("cam.mp4")
    description, to_axes = _channel_axes(path, "GoPro Max", {"ORIO": "ZXY"})
    assert description == "ORIO ZXY"
    np.testing.assert_array_equal(to_axes @ [1.0, 2.0, 3.0], [2.0, 3.0, 1.0])  # channels Z, X, Y -> X, Y, Z
    _, to_axes = _channel_axes(path, "Hero6 Black", {})  # the README's HERO6 order: Y, -X, Z
    np.testing.assert_array_equal(to_axes @ [1.0, 2.0, 3.0], [-2.0, 1.0, 3.0])
    _, to_axes = _channel_axes(path, "Fusion", {})  # -Y, X, Z
    np.testing.assert_array_equal(to_axes @ [1.0, 2.0, 3.0], [2.0, -1.0, 3.0])
    _, to_axes = _channel_axes(path, "any", {"ORIO": "zXy"})  # lowercase: a negative axis
    np.testing.assert_array_equal(to_axes @ [1.0, 2.0, 3.0], [2.0, -3.0, -1.0])
    with pytest.raises(ValueError, match=r"cam.mp4: GoPro device 'HERO99' gives no ORIO .* axes are unknown"):
        _channel_axes(path, "HERO99", {})
    with pytest.raises(ValueError, match=r"cam.mp4: IMU channel order 'XXY' \(ORIO\) is not a permutation"):
        _channel_axes(path, "any", {"ORIO": "XXY"})


def test_a_file_without_telemetry_gives_none_and_a_missing_one_an_error(shoot, tmp_path):  # noqa: F811
    assert read_gopro_imu(shoot / "videos" / "head.mp4") is None
    with pytest.raises(ValueError, match=r"nothing.mp4: missing"):
        read_gopro_imu(tmp_path / "nothing.mp4")
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"\0\0\0\x08ftyp" + bytes(range(256)) * 4)
    with pytest.raises(ValueError, match=r"bad.mp4: FFmpeg \(PyAV\) cannot open it"):
        read_gopro_imu(bad)


def _constant_imu(time_s: np.ndarray, values: np.ndarray) -> GoProImu:
    return GoProImu(Path("x.mp4"), "test", SensorSamples(time_s, values, 1.0 / (time_s[1] - time_s[0])),
                    SensorSamples(time_s, values + 9.81, 1.0 / (time_s[1] - time_s[0])), "ORIO XYZ")


def test_trial_imu_puts_each_camera_s_samples_on_the_trial_clock():
    # Camera a's file: a ramp gyro, value = time in its file; its trial starts at frame 30, first clap at frame 15
    # of the stretch (s 1.5 of the file at 30 fps). Camera b's file: value = 10 + its time; stretch from frame 0,
    # clap at frame 60 (s 2.0).
    t = np.arange(0, 8, 0.005)
    a = _constant_imu(t, np.repeat(t[:, None], 3, axis=1))
    b = _constant_imu(t, np.repeat(10 + t[:, None], 3, axis=1))
    recording = trial_imu([CameraTelemetry("a", a, 30, 120, 15, 30.0), CameraTelemetry("none", None, 0, 120, 3, 30.0),
                           CameraTelemetry("b", b, 0, 150, 60, 30.0)])
    assert recording.cameras == ("a", "b") and recording.rate == pytest.approx(200.0)
    np.testing.assert_allclose(recording.gyro[:, 0, 0], recording.time + 1.5, atol=1e-9)
    np.testing.assert_allclose(recording.gyro[:, 1, 0], 10 + recording.time + 2.0, atol=1e-9)
    # within both stretches, first frame to last: a's from -0.5 s to 3.467 s, b's from -2.0 s to 2.967 s
    last = (150 - 1 - 60) / 30.0
    assert recording.time[0] == pytest.approx(-0.5) and last - 1 / 200 < recording.time[-1] <= last
    np.testing.assert_allclose(recording.accel[:, 0, 0], recording.time + 1.5 + 9.81, atol=1e-9)
    assert trial_imu([CameraTelemetry("none", None, 0, 10, 0, 30.0)]) is None
    late = _constant_imu(t + 100, np.zeros((len(t), 3)))
    with pytest.raises(ValueError, match=r"trial 'x': the telemetry of cameras \['a', 'late'\] does not overlap"):
        trial_imu([CameraTelemetry("a", a, 30, 120, 15, 30.0), CameraTelemetry("late", late, 0, 120, 15, 30.0)],
                  where="trial 'x'")


def _with_gopro_telemetry(take: Path, out: Path, seconds: float = np.inf) -> None:
    """``take``'s video and audio, with the sample's GPMF track beside them (muxed as recorded; its payloads that start
    within ``seconds``)."""
    with av.open(str(take)) as source, av.open(str(SAMPLE)) as gopro, av.open(str(out), "w", format="mp4") as target:
        meta = next(s for s in gopro.streams.data if "GoPro MET" in s.metadata.get("handler_name", ""))
        streams = {s: target.add_stream_from_template(s) for s in (*source.streams.video, *source.streams.audio)}
        gpmf = target.add_stream_from_template(meta)
        for packet in source.demux():
            if packet.dts is not None:
                packet.stream = streams[packet.stream]
                target.mux(packet)
        for packet in gopro.demux(meta):
            if packet.dts is not None and packet.pts * packet.time_base < seconds:
                packet.stream = gpmf
                target.mux(packet)


def test_init_writes_the_cameras_telemetry_on_each_trial_s_clock(shoot, tmp_path, capsys):  # noqa: F811
    # Two of the three cameras carry the sample's telemetry (the same track, from each file's own first frame); the
    # third has none and is left out, with a note.
    videos = tmp_path / "shoot"
    shutil.copytree(shoot, videos, ignore=shutil.ignore_patterns("videos"))
    (videos / "videos").mkdir()
    for name in CAMERAS:
        if name == "left_foot":
            shutil.copy(shoot / "videos" / f"{name}.mp4", videos / "videos" / f"{name}.mp4")
        else:
            _with_gopro_telemetry(shoot / "videos" / f"{name}.mp4", videos / "videos" / f"{name}.mp4")
    target = tmp_path / "capture"
    assert run_init(videos, target) == 0
    out = capsys.readouterr().out
    assert "telemetry (GPMF: Camera) in 2 of 3 cameras; none in left_foot: their gyro terms are off" in out
    capture = read_capture(target)
    sample = read_gopro_imu(videos / "videos" / "head.mp4")
    for trial in capture.trials:
        imu = read_imu(target / "trials" / trial / "imu.npz")
        assert imu.cameras == ("head", "chest") and imu.gyro.shape == (len(imu.time), 2, 3)
        sync = synchronize(capture, trial)
        for s, name in enumerate(imu.cameras):
            source = capture.trial_video(trial, name)
            file_time = imu.time + (source.first_frame + sync.offset(name)) / FPS  # s of the camera's own file
            want = np.stack([np.interp(file_time, sample.gyro.time_s, sample.gyro.values[:, k]) for k in range(3)], 1)
            np.testing.assert_allclose(imu.gyro[:, s], want, atol=1e-12)
        np.testing.assert_allclose(imu.camera_from_imu[:, :4], np.tile(CAMERA_FROM_GOPRO_IMU, (2, 1)))


def test_a_take_s_chapters_telemetry_is_joined_on_the_joined_clock(shoot, tmp_path, capsys):  # noqa: F811
    # The head camera's take in two chapters, each with the sample's GPMF track from its own first frame: in the joined
    # take, the second chapter's samples follow from its start (global frame 90).
    from test_chapters import write_chapters
    from test_init import LAST, STARTS, write_rig

    folder = tmp_path / "shoot"
    shutil.copytree(shoot, folder)
    (folder / "videos" / "head.mp4").unlink()
    plain = write_chapters(tmp_path, ["GX010003.MP4", "GX020003.MP4"], 0, STARTS[0], LAST, [90])
    for chapter in plain:  # a chapter's telemetry ends with it
        _with_gopro_telemetry(chapter, folder / "videos" / chapter.name, probe_media(chapter).duration_s)
    write_rig(folder / "rig.toml", {"head": {"segment": "head", "lens": "wide", "video": "GX010003.MP4"},
                                    "chest": {"segment": "torso", "lens": "wide"},
                                    "left_foot": {"segment": "left_foot"}}, {"margin_s": 0.5})
    assert run_init(folder, tmp_path / "capture") == 0
    capture = read_capture(tmp_path / "capture")
    parts = [read_gopro_imu(folder / "videos" / c.name) for c in plain]
    second = (90 - STARTS[0]) / FPS  # s: where the second chapter starts in the joined take
    for trial in capture.trials:
        imu = read_imu(tmp_path / "capture" / "trials" / trial / "imu.npz")
        assert imu.cameras == ("head",)
        source = capture.trial_video(trial, "head")
        file_time = imu.time + (source.first_frame + synchronize(capture, trial).offset("head")) / FPS
        first = parts[0].gyro.time_s < second  # the first chapter's last payload's fit reaching past its end: dropped
        times = np.concatenate([parts[0].gyro.time_s[first], parts[1].gyro.time_s + second])
        values = np.concatenate([parts[0].gyro.values[first], parts[1].gyro.values])
        assert np.all(np.diff(times) > 0)
        want = np.stack([np.interp(file_time, times, values[:, k]) for k in range(3)], 1)
        np.testing.assert_allclose(imu.gyro[:, 0], want, atol=1e-12)


@pytest.mark.slow
def test_the_studio_writes_gopro_files_and_init_reads_their_imu_back_on_the_trial_clock(tmp_path, capsys):
    """A small studio capture with sub-frame starts, drifting clocks and an IMU clock offset, written as GoPro files
    (bcmocap.sim.gopro_files: the IMU in each file's GPMF track on its own clock); `bcmocap init` on them writes each
    trial's imu.npz on the trial's clock: the studio's own IMU (turned into the camera) within a shift of the claps'
    sub-frame part and the IMU offset, to the GPMF's int16 steps."""
    from bcmocap.cli import main
    from bcmocap.frontend.rig_file import format_rig_file
    from bcmocap.io.capture_folder import load_ground_truth
    from test_init import STUDIO_ARGS, studio_rig

    folder = tmp_path / "studio"
    args = [a if a != "0.1" else "2.5" for a in STUDIO_ARGS]  # 2.5 s trials: three GPMF payloads and more
    assert main(["simulate", str(folder), *args, "--container", "mp4-aac", "--start-subframe", "--clock-ppm", "50",
                 "--imu-offset-ms", "30"]) == 0
    assert main(["simulate", str(folder), "--gopro-files", str(tmp_path / "gopro")]) == 0
    assert "rom: 18 GoPro files in" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "gopro").iterdir()) == ["capture", "rom"]
    assert main(["simulate", str(folder), "--gopro-files", str(tmp_path / "gopro")]) == 2  # never over a folder
    one_line_error(capsys, "simulate", "exists and is not an empty folder")
    (tmp_path / "rig.toml").write_text(format_rig_file(studio_rig(folder, None)))
    assert main(["init", str(tmp_path / "capture"), "--videos", str(tmp_path / "gopro"), "--rig", str(tmp_path / "rig.toml"),
                 "--calibration", str(folder / "intrinsics")]) == 0
    assert "telemetry (GPMF: bcmocap studio) in 18 of 18 cameras" in capsys.readouterr().out
    truth = load_ground_truth(folder)
    for trial in ("rom", "capture"):
        ours, studio = read_imu(tmp_path / "capture" / "trials" / trial / "imu.npz"), read_imu(folder / "trials" / trial / "imu.npz")
        assert ours.cameras == studio.cameras
        bound = 1.0 / truth.trials[trial].fps + 0.031  # the claps' sub-frame part and the IMU offset
        # within the studio's own recording (a GoPro file's IMU runs from its first frame: the studio's subject holds
        # still before and after, and the GoPro files repeat the trial's first and last samples there)
        inside = (ours.time > studio.time[0] + 0.1) & (ours.time < studio.time[-1] - 0.1)
        assert ours.time[0] < studio.time[0] and ours.time[-1] > studio.time[-1]
        for s in range(len(ours.cameras)):
            mine = (ours.gyro[:, s] @ matrix_from_quat(ours.camera_from_imu[s, :4]).T)[inside]  # into the camera
            theirs = studio.gyro[:, s] @ matrix_from_quat(studio.camera_from_imu[s, :4]).T
            errors = []
            for shift in np.arange(-bound, bound, 0.0005):
                want = np.stack([np.interp(ours.time[inside] + shift, studio.time, theirs[:, k]) for k in range(3)], 1)
                errors.append(np.sqrt(np.mean((mine - want) ** 2)))
            best = int(np.argmin(errors))
            assert 0 < best < len(errors) - 1, (trial, s)  # the shift lies inside the bound
            # to the int16 steps, and two linear interpolations of 240 Hz samples (init's grid, this comparison's
            # shift) of a foot's sharpest turns: 2.6 % of its RMS rate at worst here
            assert errors[best] < 0.04 * np.sqrt(np.mean(theirs**2)) + 1e-3, (trial, s, errors[best])
