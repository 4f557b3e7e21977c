"""Camera models to and from ``pycolmap.Camera`` (FOV, OPENCV_FISHEYE, THIN_PRISM_FISHEYE, PINHOLE; SIMPLE_PINHOLE read).

COLMAP puts the centre of the top-left pixel at (0.5, 0.5), bcmocap (as OpenCV) at (0, 0): the principal
point shifts by 0.5 px. pycolmap is imported when a conversion runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..cameras import (
    CameraModel,
    FOVCamera,
    OpenCVFisheyeCamera,
    PinholeCamera,
    ThinPrismFisheyeCamera,
    single_camera_intrinsics,
)
from ..native_crashes import load_pycolmap

if TYPE_CHECKING:  # pragma: no cover
    import pycolmap

__all__ = ["from_pycolmap", "to_pycolmap"]


def to_pycolmap(camera: CameraModel) -> "pycolmap.Camera":
    """Convert a single camera to a ``pycolmap.Camera`` (FOV, OPENCV_FISHEYE, THIN_PRISM_FISHEYE or PINHOLE).

    The principal point is shifted by +0.5 px into COLMAP's pixel convention.
    """
    pycolmap = load_pycolmap()

    (fx, fy), principal_point = single_camera_intrinsics(camera, "to_pycolmap")
    cx, cy = principal_point + 0.5
    if isinstance(camera, FOVCamera):
        model, params = "FOV", [fx, fy, cx, cy, float(camera.omega)]
    elif isinstance(camera, OpenCVFisheyeCamera):
        model, params = "OPENCV_FISHEYE", [fx, fy, cx, cy, *np.asarray(camera.distortion).tolist()]
    elif isinstance(camera, ThinPrismFisheyeCamera):
        (k1, k2, k3, k4), (p1, p2), (sx1, sy1) = (np.asarray(x, np.float64).tolist() for x in
                                                  (camera.distortion, camera.tangential, camera.thin_prism))
        model, params = "THIN_PRISM_FISHEYE", [fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1]
    elif isinstance(camera, PinholeCamera):
        model, params = "PINHOLE", [fx, fy, cx, cy]
    else:
        raise ValueError(f"to_pycolmap: unsupported camera class {type(camera).__name__}")
    return pycolmap.Camera(
        model=model, width=camera.width, height=camera.height, params=[float(x) for x in params]
    )


def from_pycolmap(cam: "pycolmap.Camera") -> CameraModel:
    """Convert a ``pycolmap.Camera`` (FOV, OPENCV_FISHEYE, THIN_PRISM_FISHEYE, PINHOLE, SIMPLE_PINHOLE) to a model.

    The principal point is shifted by -0.5 px into OpenCV's pixel convention.

    Raises:
        ValueError: For any other COLMAP camera model (the message names it).
    """
    name = cam.model.name
    prm = np.asarray(cam.params, dtype=np.float64)
    size = {"width": int(cam.width), "height": int(cam.height)}
    if name == "SIMPLE_PINHOLE":
        return PinholeCamera(**size, focal=[prm[0], prm[0]], principal_point=prm[1:3] - 0.5)
    if name == "PINHOLE":
        return PinholeCamera(**size, focal=prm[0:2], principal_point=prm[2:4] - 0.5)
    if name == "FOV":
        return FOVCamera(**size, focal=prm[0:2], principal_point=prm[2:4] - 0.5, omega=prm[4])
    if name == "OPENCV_FISHEYE":
        return OpenCVFisheyeCamera(
            **size, focal=prm[0:2], principal_point=prm[2:4] - 0.5, distortion=prm[4:8]
        )
    if name == "THIN_PRISM_FISHEYE":
        return ThinPrismFisheyeCamera(
            **size, focal=prm[0:2], principal_point=prm[2:4] - 0.5, distortion=prm[[4, 5, 8, 9]],
            tangential=prm[6:8], thin_prism=prm[10:12],
        )
    raise ValueError(
        f"from_pycolmap: unsupported COLMAP camera model {name!r} "
        "(supported: FOV, OPENCV_FISHEYE, THIN_PRISM_FISHEYE, PINHOLE, SIMPLE_PINHOLE)"
    )
