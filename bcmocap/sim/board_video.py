"""Rendered calibration videos: a board held in front of a lens and moved about, drawn pixel by pixel.

Every pixel is the average of ``samples × samples`` rays through it (the lens's own ``unproject``), each
intersected with the board's plane and looked up in an image of the board's printed pattern (bilinear,
printed at ``px_per_m``); rays that miss the board, or meet its back, see a plain grey wall. Sensor noise
is added and the frames are encoded as H.264 (:class:`~bcmocap.io.media.MediaWriter`), so that
``bcmocap calibrate VIDEO`` meets what it meets on a real lens: anti-aliased corners, noise and
compression, not exact projections.

The hand-held path visits ``views`` board poses spread over the sensor (those of
:func:`~bcmocap.sim.board_views.simulate_board_views`) and moves smoothly from one to the next.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..atomic import atomic_path, write_json_atomic
from ..cameras import CameraModel
from ..geometry import matrix_from_quat, quat_from_matrix, slerp
from .board_views import simulate_board_views

__all__ = ["board_pattern", "render_board_frame", "board_video_poses", "write_board_video"]

WALL, PAPER, INK = 110.0, 235.0, 20.0  # grey levels (0-255)


def board_pattern(board, px_per_m: float = 3000.0) -> tuple[np.ndarray, np.ndarray]:
    """The printed board as a grey image and the map from board coordinates to it.

    Args:
        board: a :class:`~bcmocap.calibrate.Board` (chessboard or ChArUco).
        px_per_m: printing resolution (texture pixels per metre).

    Returns:
        ``(image (h, w) float32 grey levels, offset (2,))``: board point ``(x, y)`` m is at texture pixel
        ``offset + (x, y) · px_per_m`` (pixel centres at integers).
    """
    margin = board.spacing  # white paper around the pattern, as detectors need
    if board.kind == "charuco":
        squares = np.array([board.cols, board.rows]) * board.spacing
        size = np.round((squares + 2 * margin) * px_per_m).astype(int)
        pad = int(round(margin * px_per_m))
        image = board.charuco().generateImage((int(size[0]), int(size[1])), marginSize=pad, borderBits=1)
        grey = np.where(image > 127, PAPER, INK).astype(np.float32)
        return grey, np.array([pad - 0.5, pad - 0.5])
    if board.kind != "chessboard":
        raise ValueError(f"board_pattern: a {board.kind} board is not drawn (chessboard or charuco)")
    # (cols + 1) x (rows + 1) squares around the inner corners; the first inner corner is the board's origin.
    size = np.round((np.array([board.cols + 1, board.rows + 1]) * board.spacing + 2 * margin) * px_per_m).astype(int)
    y, x = np.mgrid[0:size[1], 0:size[0]] + 0.5
    u, v = x / px_per_m - margin, y / px_per_m - margin  # metres from the pattern's outer corner
    i, j = np.floor(u / board.spacing), np.floor(v / board.spacing)
    inside = (u >= 0) & (v >= 0) & (i <= board.cols) & (j <= board.rows)
    grey = np.where(inside & ((i + j) % 2 == 0), INK, PAPER).astype(np.float32)
    return grey, np.array([(margin + board.spacing) * px_per_m - 0.5] * 2)


def _rays(camera: CameraModel, samples: int) -> np.ndarray:
    """``(H, W, S², 3)`` unit rays of ``samples × samples`` points spread evenly over each pixel."""
    steps = (np.arange(samples) + 0.5) / samples - 0.5
    du, dv = np.meshgrid(steps, steps)
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    pixels = np.stack([u[..., None] + du.ravel(), v[..., None] + dv.ravel()], axis=-1)
    return np.asarray(camera.unproject(pixels), np.float32)  # float32: a 1e-7 relative error is 1e-4 px here


def render_board_frame(rays: np.ndarray, pattern: tuple[np.ndarray, np.ndarray], px_per_m: float,
                       camera_from_board: np.ndarray) -> np.ndarray:
    """One frame ``(H, W)`` float32 grey levels: the board at ``camera_from_board`` ``(4, 4)``, seen along
    ``rays`` ``(H, W, S², 3)`` (:func:`_rays`); no noise. The board frame is OpenCV's: x along its rows, y down
    its columns as printed, z into the board (a lens sees the print when the board's z axis points away)."""
    import cv2

    image, offset = pattern
    rotation = camera_from_board[:3, :3].astype(np.float32)
    translation = camera_from_board[:3, 3].astype(np.float32)
    along = rays @ rotation[:, 2]  # (H, W, S²): cosine between each ray and the board's normal
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (translation @ rotation[:, 2]) / along
    hit = (depth > 0) & (along > 1e-6)  # in front of the lens, the printed side towards it (z points into the board)
    # Board coordinates of the hits: Rᵀ(depth · ray − t), x and y only; in texture pixels.
    scale = np.float32(px_per_m)
    tex = [np.where(hit, (depth * (rays @ rotation[:, k]) - translation @ rotation[:, k]) * scale + offset[k], -1e4)
           .astype(np.float32) for k in (0, 1)]
    h, w, s = depth.shape
    looked_up = cv2.remap(image, tex[0].reshape(h, w * s), tex[1].reshape(h, w * s), cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=WALL)
    return looked_up.reshape(h, w, s).mean(axis=-1)


def board_video_poses(camera: CameraModel, board, views: int, frames_per_view: int, rng: np.random.Generator,
                      **placement) -> np.ndarray:
    """``(views · frames_per_view, 4, 4)`` camera-from-board poses: ``views`` placements spread over the sensor
    (``placement``: keywords of :func:`~bcmocap.sim.board_views.simulate_board_views`), each held for a third of
    its frames, then moved to the next (smooth in time, rotations by slerp)."""
    _, _, keys = simulate_board_views(camera, board.points, views, rng, **placement)
    # simulate_board_views turns the board's z axis towards the lens; turn the board over about its centre line
    # (x, y, z) -> (x, -y, -z) so that the lens sees the print, not its mirror image, on the same area.
    centre = board.points.mean(axis=0)
    flip = np.diag([1.0, -1.0, -1.0])
    keys = keys.copy()
    keys[:, :3, 3] += keys[:, :3, :3] @ (centre - flip @ centre)
    keys[:, :3, :3] = keys[:, :3, :3] @ flip
    hold = frames_per_view // 3
    t = np.clip((np.arange(frames_per_view) - hold) / max(frames_per_view - hold, 1), 0.0, 1.0)
    t = t * t * (3 - 2 * t)  # ease in and out
    quats = quat_from_matrix(keys[:, :3, :3])
    poses = []
    for a in range(views):
        b = min(a + 1, views - 1)
        q = slerp(quats[a], quats[b], t)
        pose = np.tile(np.eye(4), (frames_per_view, 1, 1))
        pose[:, :3, :3] = matrix_from_quat(q)
        pose[:, :3, 3] = (1 - t)[:, None] * keys[a, :3, 3] + t[:, None] * keys[b, :3, 3]
        poses.append(pose)
    return np.concatenate(poses)


def write_board_video(path: str | os.PathLike, camera: CameraModel, board, *, views: int = 32,
                      frames_per_view: int = 6, fps: float = 30.0, samples: int = 3, noise_dn: float = 2.0,
                      px_per_m: float = 3000.0, seed: int = 0, crf: int = 16, **placement) -> np.ndarray:
    """Render and encode a calibration video of ``board`` through ``camera``; return its
    ``(frames, 4, 4)`` camera-from-board poses (the ground truth).

    Args:
        path: the MP4 to write (H.264, grey frames as RGB; written under a temporary name, then renamed).
        camera: the lens (its ``width`` and ``height`` must be even).
        board: a chessboard or ChArUco :class:`~bcmocap.calibrate.Board`.
        views, frames_per_view: placements spread over the sensor and frames spent at each.
        samples: rays per pixel along each axis (anti-aliasing).
        noise_dn: standard deviation of the sensor noise (grey levels).
        crf: x264 constant rate factor (16: a good camera's recording quality).
        placement: keywords of :func:`~bcmocap.sim.board_views.simulate_board_views` (distance, tilt).
    """
    from ..io.media import MediaWriter

    rng = np.random.default_rng(seed)
    poses = board_video_poses(camera, board, views, frames_per_view, rng, **placement)
    pattern = board_pattern(board, px_per_m)
    rays = _rays(camera, samples)
    with atomic_path(path, suffix=".mp4") as tmp:
        writer = MediaWriter(tmp, fps, (camera.width, camera.height), crf=crf)
        try:
            for pose in poses:
                grey = render_board_frame(rays, pattern, px_per_m, pose) + rng.normal(scale=noise_dn, size=rays.shape[:2])
                frame = np.clip(np.round(grey), 0, 255).astype(np.uint8)
                writer.write([np.repeat(frame[..., None], 3, axis=-1)])
        finally:
            writer.close()
    return poses


#: The board of the studio's calibration videos: markers of about 4 px cells at 0.3–0.7 m through its lenses.
STUDIO_BOARD = "charuco:7x5:0.06:0.045:DICT_4X4_50"


def write_board_videos(capture_path: str | os.PathLike, *, board: str = STUDIO_BOARD, views: int = 32,
                       frames_per_view: int = 6, seed: int | None = None, progress=None) -> dict[str, list[str]]:
    """Add calibration videos to a studio capture: ``calibration/lens_K.mp4``, one per distinct rendered lens of
    ``ground_truth/rig.json`` (what the cameras really are, not the ``intrinsics/`` given to the user), and
    ``calibration/lenses.json`` ``{"board": board, "fps", "lenses": {"lens_K": [camera names]}}``, so that
    ``bcmocap calibrate calibration/lens_K.mp4 --board BOARD`` can be checked against the truth.

    Args:
        capture_path: a capture folder written by the studio.
        board: the ``--board`` text of the board filmed.
        views, frames_per_view, seed: see :func:`write_board_video` (seed: the capture's by default).
        progress: called with each lens name before it is rendered.

    Returns:
        ``{lens name: camera names}``.

    Raises:
        ValueError: not a studio capture, or a malformed ground truth (naming the file).
    """
    import json

    from ..cameras import camera_at
    from ..io.board import parse_board
    from ..io.model_json import camera_to_dict
    from .studio import read_studio_model

    folder = Path(capture_path)
    _, settings, _, rig = read_studio_model(folder)
    parsed = parse_board(board)
    lenses: dict[str, tuple] = {}  # the lens's parameters as JSON text -> (name, camera, camera names)
    for index, name in enumerate(rig.names):
        camera = camera_at(rig.intrinsics, index)
        key = json.dumps(camera_to_dict(camera), sort_keys=True)
        if key not in lenses:
            lenses[key] = (f"lens_{len(lenses)}", camera, [])
        lenses[key][2].append(name)
    out = folder / "calibration"
    out.mkdir(exist_ok=True)
    fps = 30.0
    for lens_name, camera, _ in lenses.values():
        if progress is not None:
            progress(lens_name)
        write_board_video(out / f"{lens_name}.mp4", camera, parsed, views=views, frames_per_view=frames_per_view,
                          fps=fps, seed=settings.seed if seed is None else seed, distance_m=(0.3, 0.7))
    table = {name: cameras for name, _, cameras in lenses.values()}
    write_json_atomic(out / "lenses.json", {"board": board, "fps": fps, "lenses": table})
    return table
