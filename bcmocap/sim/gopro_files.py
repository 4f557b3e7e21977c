"""A studio capture's camera files as GoPro cameras write them: video, audio and the IMU in a GPMF track.

``bcmocap simulate --container mp4-aac`` writes each camera's trial as an H.264 + AAC MP4, and the trial's IMU as the
studio's own ``imu.npz`` on the synchronised clock. A GoPro keeps its gyroscope and accelerometer in its file, on its
own clock. :func:`write_gopro_files` writes ``OUT/<trial>/<camera>.mp4``: the capture's video and audio packets,
unchanged, with a GPMF track (:func:`bcmocap.io.gopro.write_gopro_file`) of that camera's IMU, so that ``bcmocap init
NEW --videos OUT`` reads the telemetry back as it reads a real GoPro's (:mod:`bcmocap.frontend.telemetry`).

**Time.** A sample the studio took at true trial time ``t`` (s from the first clap) is written at the time of the
camera's file that instant falls in: its video frame ``video_frame_of(c, t · fps + clap)`` over the frame rate (each
camera's sub-frame start and clock rate from the ground truth), plus the trial's IMU clock offset (``imu_offset_ms``:
a GoPro's telemetry timing is known to tens of milliseconds). The studio records its IMU over the trial, a camera from
its first frame: before the trial and after it, where the subject holds still, the trial's first and last samples are
repeated (:func:`_recording`). **Axes.** The studio's IMU frame (``camera_from_imu`` of
``imu.npz``) turned into GoPro's IMU axes (:data:`bcmocap.io.gopro.CAMERA_FROM_GOPRO_IMU`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..geometry import matrix_from_quat
from ..io.gopro import CAMERA_FROM_GOPRO_IMU, SensorSamples, write_gopro_file
from ..io.names import checked_name
from ..io.sensors import IMU_FILE, read_imu

__all__ = ["write_gopro_files"]


def _recording(file_s: np.ndarray, duration_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The times of a camera's IMU over its whole file, ``[0, duration_s)``, at the samples' own spacing, and for each
    the studio sample it reads: the studio records its IMU over the trial, a camera from its first frame to its last;
    before the trial and after it the subject holds still (as the studio's frames show), so those samples repeat the
    trial's first and last."""
    step = float(np.median(np.diff(file_s)))
    before = np.arange(int(np.floor(file_s[0] / step)), 0, -1)
    after = np.arange(1, int(np.floor((duration_s - file_s[-1]) / step)) + 1)
    times = np.concatenate([file_s[0] - before * step, file_s, file_s[-1] + after * step])
    index = np.concatenate([np.zeros(len(before), np.int64), np.arange(len(file_s)), np.full(len(after), len(file_s) - 1)])
    keep = (times >= 0.0) & (times < duration_s)
    return times[keep], index[keep]


def write_gopro_files(capture: str | os.PathLike, out: str | os.PathLike) -> dict[str, dict[str, Path]]:
    """``OUT/<trial>/<camera>.mp4`` for every trial and camera of a studio capture written with
    ``container = "mp4-aac"`` (module docstring); ``{trial: {camera: file}}``. ValueError naming what is missing."""
    from .studio import load_ground_truth

    capture, out = Path(capture), Path(out)
    truth = load_ground_truth(capture)
    gopro_from_camera = matrix_from_quat(CAMERA_FROM_GOPRO_IMU).T
    made = not out.exists()
    try:
        return _write_all(capture, out, truth, gopro_from_camera)
    except BaseException:
        if made:  # nothing half-written is left: a rerun finds no folder in its way
            import shutil

            shutil.rmtree(out, ignore_errors=True)
        raise


def _write_all(capture: Path, out: Path, truth, gopro_from_camera: np.ndarray) -> dict[str, dict[str, Path]]:
    written: dict[str, dict[str, Path]] = {}
    for trial in truth.trials:
        checked_name(trial, "a trial name", str(capture / "capture.json"))  # an untrusted folder: plain names only
        imu_path = capture / "trials" / trial / IMU_FILE
        if not imu_path.is_file():
            raise ValueError(f"{imu_path}: missing; the studio writes each trial's IMU there")
        imu = read_imu(imu_path)
        timeline = truth.trials[trial]
        true_s = imu.time - float(timeline.imu_clock_offset_s)  # the instants the samples were taken
        written[trial] = {}
        for c, camera in enumerate(truth.rig.names):
            checked_name(camera, "a camera name", str(capture / "ground_truth" / "rig.json"))
            source = capture / "trials" / trial / f"{camera}.mp4"
            if not source.is_file():
                raise ValueError(f"{source}: missing; write the capture with --container mp4-aac")
            if camera not in imu.cameras:
                raise ValueError(f"{imu_path}: no IMU for camera {camera!r}")
            s = imu.index(camera)
            frame = timeline.video_frame_of(c, true_s * timeline.fps + float(timeline.clap_frames[0]))
            file_s = frame / timeline.fps + float(timeline.imu_clock_offset_s)
            turn = gopro_from_camera @ matrix_from_quat(imu.camera_from_imu[s, :4])
            duration = float(timeline.num_video_frames[c]) / timeline.fps
            times, index = _recording(file_s, duration)
            gyro = SensorSamples(times, imu.gyro[index, s] @ turn.T, imu.rate)
            accel = SensorSamples(times, imu.accel[index, s] @ turn.T, imu.rate)
            target = out / trial / f"{camera}.mp4"
            target.parent.mkdir(parents=True, exist_ok=True)
            written[trial][camera] = write_gopro_file(source, target, gyro, accel, device="bcmocap studio")
    return written
