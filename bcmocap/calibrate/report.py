"""What ``bcmocap calibrate`` writes: the lens files the project reads, a report, and a coverage picture.

For ``--out DIR/NAME.yml`` (or ``.json``):

* ``NAME.yml`` — ``cv2.fisheye`` calibration (``image_width``, ``image_height``, ``camera_matrix``,
  ``dist_coeff``) read by :func:`bcmocap.io.opencv_calibration.read_opencv_fisheye_calibration` and by
  OpenCV; exact for the Kannala–Brandt and equidistant models, the closest Kannala–Brandt fit of the lens
  for the FOV and thin-prism models (its largest difference over the image is in the report);
* ``NAME.json`` — the exact lens (``{"model", "width", "height", "params"}``, OpenCV pixel convention, as
  :func:`bcmocap.frontend.capture.read_camera_json` reads and a capture's ``intrinsics/<camera>.json``
  holds) with a ``"calibration"`` record: model, method, board, RMS and per-view errors (px), parameter
  standard deviations, views used and rejected;
* ``NAME.coverage.png`` — where on the sensor the board was seen: each view's outline, each point
  coloured by its reprojection error (green ≤ 0.5 px, yellow 1 px, red ≥ 2 px), and the sensor grid
  cells no view reached shaded.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..io.model_json import camera_to_dict
from ..io.opencv_calibration import fit_opencv_fisheye, write_opencv_fisheye_calibration
from .fit import Calibration

__all__ = ["calibration_record", "coverage_picture", "output_paths", "write_calibration"]


def output_paths(out: str | os.PathLike) -> tuple[Path, Path, Path]:
    """``(NAME.yml, NAME.json, NAME.coverage.png)`` for ``--out NAME.yml|.yaml|.json``."""
    out = Path(out)
    if out.suffix.lower() not in (".yml", ".yaml", ".json"):
        raise ValueError(f"--out {out}: expected a .yml, .yaml or .json file name")
    if out.is_dir():
        raise ValueError(f"--out {out} is a folder; give a file name such as {out / 'camera.yml'}")
    stem = out.with_suffix("")
    return stem.with_suffix(".yml" if out.suffix.lower() == ".json" else out.suffix), stem.with_suffix(".json"), \
        stem.with_name(stem.name + ".coverage.png")


def calibration_record(calibration: Calibration, seconds: float | None = None) -> dict:
    """The ``"calibration"`` record of ``NAME.json`` (plain JSON types)."""
    c = calibration
    views = c.views
    record = {
        "model": c.model,
        "method": c.method,
        "board": c.views.board.describe,
        "rms_px": c.rms_px,
        "max_px": float(c.errors.max()),
        "parameters": dict(zip(c.param_names, map(float, _params(c)))),
        "std": dict(zip(c.param_names, map(float, c.std))),
        "views_examined": views.examined,
        "views_with_board": views.found,
        "views_used": [{"name": n, "rms_px": float(e), "points": int(s)}
                       for n, e, s in zip(views.names, c.view_rms_px, views.seen.sum(axis=1))],
        "views_rejected": list(c.rejected),
        "solver_steps": c.steps,
        "rms_definition": "root mean square over points of the 2D reprojection error norm",
    }
    if seconds is not None:
        record["seconds"] = seconds
    return record


def _params(c: Calibration) -> np.ndarray:
    from .fit import params_of

    return params_of(c.model, c.camera)


def coverage_picture(calibration: Calibration, grid: tuple[int, int] = (8, 6)) -> np.ndarray:
    """``(H', W', 3)`` uint8 BGR picture of the sensor (at least 640 px wide) with what the board covered."""
    import cv2

    views = calibration.views
    scale = max(1.0, 640.0 / views.width)
    w, h = round(views.width * scale), round(views.height * scale)
    image = np.full((h, w, 3), 40, np.uint8)
    cols, rows = grid
    seen_px = views.pixels[views.seen]
    cu = np.clip((seen_px[:, 0] / views.width * cols).astype(int), 0, cols - 1)
    cv = np.clip((seen_px[:, 1] / views.height * rows).astype(int), 0, rows - 1)
    hit = np.zeros((rows, cols), bool)
    hit[cv, cu] = True
    for r in range(rows):
        for c in range(cols):
            p0 = (round(c * w / cols), round(r * h / rows))
            p1 = (round((c + 1) * w / cols) - 1, round((r + 1) * h / rows) - 1)
            cv2.rectangle(image, p0, p1, (70, 70, 70) if hit[r, c] else (40, 40, 110), -1 if not hit[r, c] else 1)
    for v in range(views.num_views):
        pts = views.pixels[v, views.seen[v]] * scale
        hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2)
        cv2.polylines(image, [np.round(hull).astype(np.int32)], True, (160, 160, 160), 1, cv2.LINE_AA)
    errors = calibration.errors[views.seen]
    for (x, y), e in zip(seen_px * scale, errors):
        t = float(np.clip((e - 0.5) / 1.5, 0.0, 1.0))  # 0.5 px green -> 2 px red
        colour = (0, round(255 * min(1.0, 2 - 2 * t)), round(255 * min(1.0, 2 * t)))
        cv2.circle(image, (round(x), round(y)), 2, colour, -1, cv2.LINE_AA)
    text = (f"{calibration.model}: {views.num_views} views, rms {calibration.rms_px:.3f} px, "
            f"{hit.mean() * 100:.0f}% of the {cols}x{rows} cells covered")
    cv2.putText(image, text, (8, h - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def write_calibration(out: str | os.PathLike, calibration: Calibration, seconds: float | None = None) -> list[Path]:
    """Write the three files of the module docstring (each atomically); returns their paths."""
    import cv2

    yml, lens, picture = output_paths(out)
    camera = calibration.camera
    fitted, fit_error = fit_opencv_fisheye(camera)
    with atomic_path(yml, suffix=yml.suffix) as tmp:  # OpenCV picks the format from the suffix
        write_opencv_fisheye_calibration(tmp, fitted)
    record = calibration_record(calibration, seconds)
    if calibration.model in ("fov", "thin_prism_fisheye"):
        record["opencv_fisheye_fit_max_error_px"] = fit_error
    with atomic_path(lens) as tmp:
        tmp.write_text(json.dumps({**camera_to_dict(camera), "calibration": record}, indent=1) + "\n")
    ok, png = cv2.imencode(".png", coverage_picture(calibration))
    if not ok:
        raise ValueError(f"{picture}: could not encode the coverage picture")
    with atomic_path(picture, suffix=".png") as tmp:
        tmp.write_bytes(png.tobytes())
    return [yml, lens, picture]
