"""Tests for reading a capture folder (bcmocap.frontend.capture) on a tiny hand-made folder."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from bcmocap.cameras import FOVCamera, OpenCVFisheyeCamera, PinholeCamera
from bcmocap.frontend import read_camera_json, read_capture
from bcmocap.io.opencv_calibration import write_opencv_fisheye_calibration
from bcmocap.io.wav import write_wav

CAMERAS = ("head", "left_foot")
FRAMES = 9


def make_capture(folder: Path) -> Path:
    """A minimal capture folder in the studio's layout: 2 cameras, 2 trials of 9 frames, 2 photos."""
    for sub in ("intrinsics", "reference", "trials/rom", "trials/capture"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    (folder / "capture.json").write_text(json.dumps({
        "format": "bcmocap-capture", "version": 1, "settings": {"fps": 30.0, "audio_rate": 8000},
        "cameras": list(CAMERAS), "trials": ["rom", "capture"], "complete": True}))
    (folder / "rig.json").write_text(json.dumps({
        "cameras": [{"name": n, "segment": s} for n, s in zip(CAMERAS, ("head", "left_foot"))],
        "segments": ["root", "head", "left_foot"]}))
    (folder / "intrinsics" / "head.json").write_text(json.dumps(
        {"model": "FOV", "width": 32, "height": 24, "params": [10.0, 10.0, 15.5, 11.5, 2.5]}))
    write_opencv_fisheye_calibration(folder / "intrinsics" / "left_foot.yml", OpenCVFisheyeCamera(
        width=32, height=24, focal=[9.0, 9.0], principal_point=[15.5, 11.5], distortion=[0.1, 0.0, 0.0, 0.0]))
    (folder / "reference" / "camera.json").write_text(json.dumps(
        {"model": "PINHOLE", "width": 32, "height": 24, "params": [30.0, 30.0, 15.5, 11.5]}))
    for i in range(2):
        cv2.imwrite(str(folder / "reference" / f"photo_{i:03d}.jpg"), np.full((24, 32, 3), 40 * i, np.uint8))
    for trial in ("rom", "capture"):
        for c, name in enumerate(CAMERAS):
            writer = cv2.VideoWriter(str(folder / "trials" / trial / f"{name}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"),
                                     30.0, (32, 24))
            for f in range(FRAMES):
                writer.write(np.full((24, 32, 3), 20 * f + c, np.uint8))
            writer.release()
            write_wav(folder / "trials" / trial / f"{name}.wav", np.zeros(FRAMES * 8000 // 30), 8000)
    return folder


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    return make_capture(tmp_path_factory.mktemp("frontend") / "capture")


def test_read_capture_and_decode_frames(capture_dir):
    cap = read_capture(capture_dir)
    assert cap.fps == 30.0 and cap.audio_rate == 8000 and cap.trials == ("rom", "capture")
    assert cap.camera_names == CAMERAS and [c.segment for c in cap.cameras] == ["head", "left_foot"]
    head, foot = (c.intrinsics for c in cap.cameras)
    assert isinstance(head, FOVCamera) and isinstance(foot, OpenCVFisheyeCamera)
    np.testing.assert_allclose(np.asarray(head.principal_point), [15.5, 11.5])  # OpenCV convention kept
    assert isinstance(cap.reference_camera, PinholeCamera) and len(cap.reference_photos) == 2
    info = cap.video_info("rom", "head")
    assert (info.num_frames, info.width, info.height) == (FRAMES, 32, 24)
    frames = list(cap.frames("capture", 1, stride=3, start=1))
    assert [i for i, _ in frames] == [1, 4, 7]
    for i, image in frames:  # the frame's grey level identifies it (mp4v is lossy: within a few levels)
        assert image.shape == (24, 32, 3) and abs(float(image.mean()) - (20 * i + 1)) < 4
    gray = list(cap.frames("rom", "head", stop=2, gray=True))
    assert [i for i, _ in gray] == [0, 1] and gray[0][1].shape == (24, 32)


def test_clear_errors(capture_dir, tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        read_capture(tmp_path / "nowhere")
    broken = shutil.copytree(capture_dir, tmp_path / "broken")
    (broken / "trials" / "rom" / "left_foot.wav").unlink()
    with pytest.raises(ValueError, match=r"left_foot\.wav: missing \(soundtrack of camera 'left_foot' in trial 'rom'\)"):
        read_capture(broken)
    cap = read_capture(broken, check_files=False)
    (broken / "trials" / "capture" / "head.mp4").write_bytes(b"not a video")
    with pytest.raises(ValueError, match=r"head\.mp4: (OpenCV cannot open|no frame)"):
        list(cap.frames("capture", "head"))
    with pytest.raises(ValueError, match="no camera 'chest'"):
        cap.video_path("rom", "chest")
    with pytest.raises(ValueError, match="no trial 'walk'"):
        cap.audio_path("walk", 0)
    (broken / "intrinsics" / "left_foot.yml").unlink()
    with pytest.raises(ValueError, match=r"left_foot\.yml: intrinsics of camera 'left_foot' missing"):
        read_capture(broken, check_files=False)
    (broken / "intrinsics" / "head.json").write_text('{"model": "FOV", "width": 32, "height": 24, "params": [1, 2]}')
    with pytest.raises(ValueError, match=r"head\.json: model 'FOV' with 2 params"):
        read_camera_json(broken / "intrinsics" / "head.json")
    (broken / "capture.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"capture\.json: not valid JSON"):
        read_capture(broken)
    (broken / "capture.json").write_text('{"format": "other"}')
    with pytest.raises(ValueError, match="format is 'other'"):
        read_capture(broken)


def test_with_lenses_replaces_the_intrinsics_and_changes_the_lens_fingerprint(capture_dir):
    from bcmocap.residuals.self_calibration import corrected_camera

    cap = read_capture(capture_dir)
    head, foot = (c.intrinsics for c in cap.cameras)
    moved = corrected_camera(foot, np.array([0.01, 0.5, 0.0]))
    other = cap.with_lenses([head, moved])
    assert other.cameras[1].intrinsics is moved and other.cameras[0].intrinsics is head
    assert [c.name for c in other.cameras] == list(CAMERAS) and cap.cameras[1].intrinsics is foot
    assert cap.lens_fingerprint() == read_capture(capture_dir).lens_fingerprint() != other.lens_fingerprint()
    with pytest.raises(ValueError, match="1 lenses for 2 cameras"):
        cap.with_lenses([head])
