"""OpenCV ``cv2.fisheye`` calibration files (``cv2.FileStorage`` YAML/XML/JSON) to and from
:class:`~bcmocap.cameras.OpenCVFisheyeCamera`. cv2 is imported when a file is read or written.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..cameras import CameraModel, OpenCVFisheyeCamera, single_camera_intrinsics

__all__ = ["fit_opencv_fisheye", "read_opencv_fisheye_calibration", "write_opencv_fisheye_calibration",
           "write_opencv_storage"]

_K_NAMES = ("camera_matrix", "K")
_D_NAMES = ("dist_coeff", "distortion_coefficients", "D")


def _read_node(fs: Any, names: Sequence[str]) -> tuple[str, Any] | None:
    for name in names:
        node = fs.getNode(name)
        if not node.empty():
            return name, node
    return None


def read_opencv_fisheye_calibration(
    path: str | os.PathLike, image_size: tuple[int, int] | None = None
) -> OpenCVFisheyeCamera:
    """Read a ``cv2.fisheye`` calibration written with ``cv2.FileStorage``.

    Reads ``camera_matrix`` (3x3 K; also ``K``), ``dist_coeff`` (4 coefficients; also
    ``distortion_coefficients`` or ``D``) and, if present, ``image_width``/``image_height``.

    Args:
        path: The .yml/.yaml/.xml/.json file.
        image_size: ``(width, height)`` in pixels, used when the file does not store the size.

    Raises:
        ValueError: Naming the file and the missing or malformed field.
    """
    import cv2

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"{path}: calibration file does not exist")
    try:
        # A truncated file makes the constructor fail inside OpenCV's parser (cv2.error, or a SystemError from
        # the binding), and a structurally broken one can fail later, at the first node read.
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:
        raise ValueError(f"{path}: cannot parse as an OpenCV FileStorage file ({' '.join(str(e).split())})") from None
    if not fs.isOpened():
        raise ValueError(f"{path}: cannot open as an OpenCV FileStorage file")
    try:
        return _fisheye_from_storage(path, fs, image_size)
    except (cv2.error, SystemError) as e:
        raise ValueError(f"{path}: malformed OpenCV FileStorage file ({' '.join(str(e).split())})") from None
    finally:
        fs.release()


def _fisheye_from_storage(path: str, fs: Any, image_size: tuple[int, int] | None) -> OpenCVFisheyeCamera:
    """The camera in an open ``cv2.FileStorage`` (see :func:`read_opencv_fisheye_calibration`)."""
    found = _read_node(fs, _K_NAMES)
    if found is None:
        raise ValueError(f"{path}: missing field 'camera_matrix' (3x3 camera matrix K)")
    k_name, node = found
    K = node.mat()
    if K is None or np.shape(K) != (3, 3):
        raise ValueError(f"{path}: field '{k_name}' must be a 3x3 matrix; got shape {np.shape(K)}")
    found = _read_node(fs, _D_NAMES)
    if found is None:
        raise ValueError(f"{path}: missing field 'dist_coeff' (4 fisheye coefficients k1..k4)")
    d_name, node = found
    D = node.mat()
    if D is None or np.size(D) != 4:
        raise ValueError(
            f"{path}: field '{d_name}' must hold 4 coefficients; got shape {np.shape(D)}"
        )
    w_node, h_node = fs.getNode("image_width"), fs.getNode("image_height")
    if not w_node.empty() and not h_node.empty():
        width, height = int(w_node.real()), int(h_node.real())
    elif image_size is not None:
        width, height = (int(s) for s in image_size)
    else:
        missing = "image_width" if w_node.empty() else "image_height"
        raise ValueError(f"{path}: missing field '{missing}'; pass image_size=(width, height)")
    K = np.asarray(K, dtype=np.float64)
    if abs(K[0, 1]) > 1e-12 * abs(K[0, 0]) or not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise ValueError(
            f"{path}: field '{k_name}' must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] "
            f"(no skew); got {K.tolist()}"
        )
    try:
        return OpenCVFisheyeCamera(
            width=width,
            height=height,
            focal=[K[0, 0], K[1, 1]],
            principal_point=[K[0, 2], K[1, 2]],
            distortion=np.asarray(D, dtype=np.float64).reshape(4),
        )
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def write_opencv_fisheye_calibration(path: str | os.PathLike, camera: OpenCVFisheyeCamera) -> None:
    """Write a single camera as ``image_width``, ``image_height``, ``camera_matrix``, ``dist_coeff``.

    The format (chosen by the extension, e.g. .yml) is readable by ``cv2.FileStorage`` and by
    :func:`read_opencv_fisheye_calibration`.
    """
    import cv2

    if not isinstance(camera, OpenCVFisheyeCamera):
        raise ValueError(
            f"write_opencv_fisheye_calibration: expected an OpenCVFisheyeCamera, got {type(camera).__name__}"
        )
    (fx, fy), (cx, cy) = single_camera_intrinsics(camera, "write_opencv_fisheye_calibration")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    D = np.asarray(camera.distortion, dtype=np.float64).reshape(4, 1)
    write_opencv_storage(path, {"image_width": int(camera.width), "image_height": int(camera.height),
                                "camera_matrix": K, "dist_coeff": D})


def write_opencv_storage(path: str | os.PathLike, fields: dict) -> None:
    """``fields`` (name → int, float or array) as a ``cv2.FileStorage`` file whose format its suffix picks
    (.yml/.yaml/.xml/.json). Composed in memory and written by Python: OpenCV's own file writer ignores write
    errors (on a full disk it leaves an empty file and reports nothing)."""
    import cv2

    path = os.fspath(path)
    suffix = os.path.splitext(path)[1] or ".yml"
    fs = cv2.FileStorage(f"storage{suffix}", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    if not fs.isOpened():
        raise ValueError(f"{path}: OpenCV cannot write a FileStorage file with the suffix {suffix!r}")
    for name, value in fields.items():
        fs.write(name, value)
    text = fs.releaseAndGetString()
    with open(path, "w", encoding="utf-8") as out:
        out.write(text)


def fit_opencv_fisheye(camera: CameraModel) -> tuple[OpenCVFisheyeCamera, float]:
    """The Kannala-Brandt (``cv2.fisheye``) model closest to a camera over its image.

    Fits ``r = f' theta (1 + k1 theta^2 + ... + k4 theta^8)`` to the camera's own image radius over the
    angles its pixels see (reweighted linear least squares towards the smallest largest error), keeping
    the principal point.

    Returns:
        ``(camera, max_error_px)``: the fitted model and its largest reprojection difference (px) over a
        grid of the image.
    """
    if isinstance(camera, OpenCVFisheyeCamera):
        return camera, 0.0
    h, w = camera.height, camera.width
    v, u = np.mgrid[0 : h : max(h // 48, 1), 0 : w : max(w // 64, 1)].astype(np.float64)
    uv = np.stack([u.ravel(), v.ravel()], axis=-1)
    uv = np.concatenate([uv, [[0.0, 0.0], [w - 1.0, h - 1.0], [0.0, h - 1.0], [w - 1.0, 0.0]]])
    rays = np.asarray(camera.unproject(uv))
    theta = np.arccos(np.clip(rays[:, 2], -1.0, 1.0))
    m = (uv - np.asarray(camera.principal_point)) / np.asarray(camera.focal)
    radius = np.linalg.norm(m, axis=1)
    basis = np.stack([theta ** (2 * i + 1) for i in range(5)], axis=1)
    # Lawson's reweighting turns least squares into (nearly) the minimax fit: 0.95 -> 0.17 px at 170°.
    weight = np.ones_like(radius)
    for _ in range(20):
        coef, *_ = np.linalg.lstsq(basis * weight[:, None], radius * weight, rcond=None)
        err = np.abs(basis @ coef - radius)
        weight = weight * np.sqrt(err / max(err.max(), 1e-15) + 1e-3)
        weight /= weight.mean()
    fitted = OpenCVFisheyeCamera(
        width=w, height=h, focal=np.asarray(camera.focal) * coef[0], principal_point=np.asarray(camera.principal_point),
        distortion=coef[1:] / coef[0],
    )
    back, ok = fitted.project(rays)
    err = np.linalg.norm(np.asarray(back) - uv, axis=1)
    return fitted, float(np.max(np.where(np.asarray(ok), err, np.inf)))
