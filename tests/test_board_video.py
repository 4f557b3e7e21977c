"""Rendered calibration videos (bcmocap.sim.board_video): the board is drawn where the lens projects it, as
printed (not mirrored), and a written video is read back and calibrated to the rendered lens."""

import numpy as np
import pytest

from bcmocap.calibrate import calibrate, detect_views, parse_board, select_views
from bcmocap.calibrate.compare import camera_difference
from bcmocap.cameras import FOVCamera
from bcmocap.sim import board_video
from bcmocap.sim.rig import fov_camera_for

CHARUCO = "charuco:7x5:0.06:0.045:DICT_4X4_50"


@pytest.fixture(scope="module")
def lens():
    base = fov_camera_for(640, 360, 170.0, 1.2)
    return FOVCamera(640, 360, focal=np.asarray(base.focal) * [1.0, 1.004], principal_point=[322.3, 178.1],
                     omega=base.omega)


@pytest.mark.parametrize("spec", [CHARUCO, "chessboard:9x6:0.04"])
def test_rendered_board_is_detected_where_the_lens_projects_it(lens, spec):
    board = parse_board(spec)
    poses = board_video.board_video_poses(lens, board, 5, 1, np.random.default_rng(0), distance_m=(0.35, 0.6))
    pattern, rays = board_video.board_pattern(board), board_video._rays(lens, 2)
    errors = []
    for pose in poses:
        frame = np.clip(np.round(board_video.render_board_frame(rays, pattern, 3000.0, pose)), 0, 255).astype(np.uint8)
        found = board.detect(frame)
        if found is None:
            continue
        truth = np.asarray(lens.project(board.points[found.ids] @ pose[:3, :3].T + pose[:3, 3])[0])
        # A chessboard's corner order is ambiguous up to a half turn; ChArUco ids are not (a mirrored print fails).
        candidates = [truth, truth[::-1]] if board.kind == "chessboard" else [truth]
        errors.append(min(np.sqrt(np.mean(np.sum((c - found.pixels) ** 2, axis=-1))) for c in candidates))
    assert len(errors) >= 2 and max(errors) < 0.3, errors


@pytest.mark.slow  # about a minute: 20 frames rendered and encoded, then a calibration
def test_board_video_calibrates_to_the_rendered_lens(lens, tmp_path):
    board = parse_board(CHARUCO)
    path = tmp_path / "board.mp4"
    poses = board_video.write_board_video(path, lens, board, views=10, frames_per_view=2, samples=2, seed=1,
                                          distance_m=(0.3, 0.6))
    assert poses.shape == (20, 4, 4) and path.is_file() and not list(tmp_path.glob(".*"))
    views = detect_views(path, board)
    assert views.examined == 20 and views.found >= 15
    fitted = calibrate(views.subset(select_views(views, 40)), "fov")
    assert fitted.rms_px < 0.3
    assert camera_difference(fitted.camera, lens).max_px < 0.5
