"""Skeletons, camera models and rigs as JSON-ready dicts (the layout of a capture's ground truth and of
``bcmocap run``'s ``model/``): one description shared by every writer and reader."""

from __future__ import annotations

import numpy as np

from ..cameras import (
    CameraModel,
    FOVCamera,
    OpenCVFisheyeCamera,
    PinholeCamera,
    ThinPrismFisheyeCamera,
    TiltedThinPrismFisheyeCamera,
    camera_at,
    stack_cameras,
)
from ..kinematics.rig import Rig
from ..kinematics.skeleton import JointType, Skeleton


def camera_to_dict(camera: CameraModel) -> dict:
    """``{"model": "FOV" | "OPENCV_FISHEYE" | "THIN_PRISM_FISHEYE" | "THIN_PRISM_FISHEYE_TILTED" | "PINHOLE", "width",
    "height", "params": [fx, fy, cx, cy, ...]}``; a thin-prism fisheye's params in COLMAP's order (fx, fy, cx, cy, k1,
    k2, p1, p2, k3, k4, sx1, sy1), the tilted one's followed by the sensor tilt (tau_x, tau_y, rad; not a COLMAP
    model: the studio's lens units, :class:`~bcmocap.cameras.TiltedThinPrismFisheyeCamera`)."""
    fx, fy = (float(x) for x in np.asarray(camera.focal))
    cx, cy = (float(x) for x in np.asarray(camera.principal_point))
    if isinstance(camera, FOVCamera):
        model, extra = "FOV", [float(camera.omega)]
    elif isinstance(camera, OpenCVFisheyeCamera):
        model, extra = "OPENCV_FISHEYE", [float(x) for x in np.asarray(camera.distortion)]
    elif isinstance(camera, (ThinPrismFisheyeCamera, TiltedThinPrismFisheyeCamera)):
        (k1, k2, k3, k4), (p1, p2), (sx1, sy1) = (np.asarray(x, np.float64).tolist() for x in
                                                  (camera.distortion, camera.tangential, camera.thin_prism))
        model, extra = "THIN_PRISM_FISHEYE", [k1, k2, p1, p2, k3, k4, sx1, sy1]
        if isinstance(camera, TiltedThinPrismFisheyeCamera):
            model, extra = "THIN_PRISM_FISHEYE_TILTED", [*extra, *np.asarray(camera.tilt, np.float64).tolist()]
    elif isinstance(camera, PinholeCamera):
        model, extra = "PINHOLE", []
    else:
        raise ValueError(f"cannot describe camera class {type(camera).__name__}")
    return {"model": model, "width": camera.width, "height": camera.height, "params": [fx, fy, cx, cy, *extra],
            "pixel_convention": "OpenCV: the centre of the top-left pixel is (0, 0)"}


def camera_from_dict(data: dict, where: str) -> CameraModel:
    """Inverse of :func:`camera_to_dict`; ValueError naming ``where`` on a bad description."""
    try:
        model, p = data["model"], [float(x) for x in data["params"]]
        size = {"width": int(data["width"]), "height": int(data["height"])}
        if model == "FOV" and len(p) == 5:
            return FOVCamera(**size, focal=p[0:2], principal_point=p[2:4], omega=p[4])
        if model == "OPENCV_FISHEYE" and len(p) == 8:
            return OpenCVFisheyeCamera(**size, focal=p[0:2], principal_point=p[2:4], distortion=p[4:8])
        if model == "THIN_PRISM_FISHEYE" and len(p) == 12:
            return ThinPrismFisheyeCamera(**size, focal=p[0:2], principal_point=p[2:4], distortion=[*p[4:6], *p[8:10]],
                                          tangential=p[6:8], thin_prism=p[10:12])
        if model == "THIN_PRISM_FISHEYE_TILTED" and len(p) == 14:
            return TiltedThinPrismFisheyeCamera(**size, focal=p[0:2], principal_point=p[2:4],
                                                distortion=[*p[4:6], *p[8:10]], tangential=p[6:8],
                                                thin_prism=p[10:12], tilt=p[12:14])
        if model == "PINHOLE" and len(p) == 4:
            return PinholeCamera(**size, focal=p[0:2], principal_point=p[2:4])
    except KeyError as err:
        raise ValueError(f"{where}: camera is missing field {err}") from None
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where}: malformed camera ({err})") from None
    raise ValueError(f"{where}: unsupported camera model {data.get('model')!r} with {len(data.get('params', []))} params")


def skeleton_to_dict(skeleton: Skeleton) -> dict:
    """``names``, ``parents``, ``offsets_m`` (J, 3), ``joint_types``, ``hinge_axes`` (J, 3)."""
    return {
        "names": list(skeleton.names),
        "parents": list(skeleton.parents),
        "offsets_m": np.asarray(skeleton.offsets).tolist(),
        "joint_types": [JointType(t).name.lower() for t in skeleton.joint_types],
        "hinge_axes": np.asarray(skeleton.hinge_axes).tolist(),
    }


def skeleton_from_dict(data: dict, where: str) -> Skeleton:
    """Inverse of :func:`skeleton_to_dict`; ValueError naming ``where`` and the field at fault."""
    try:
        return Skeleton(data["names"], data["parents"], data["offsets_m"], data["joint_types"], data["hinge_axes"])
    except KeyError as err:
        raise ValueError(f"{where}: missing field {err}") from None
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where}: {err}") from None


def rig_to_dict(rig: Rig, skeleton: Skeleton) -> dict:
    """``{"cameras": [{"name", "segment", "segment_from_camera" (wxyz_xyz, m), "intrinsics"}]}``."""
    return {"cameras": [
        {"name": n, "segment": skeleton.names[rig.segments[c]],
         "segment_from_camera": np.asarray(rig.segment_from_camera[c]).tolist(),
         "intrinsics": camera_to_dict(camera_at(rig.intrinsics, c))} for c, n in enumerate(rig.names)]}


def rig_from_dict(data: dict, skeleton: Skeleton, where: str) -> Rig:
    """Inverse of :func:`rig_to_dict`; ValueError naming ``where`` on a missing field or unknown segment."""
    try:
        cams = data["cameras"]
        return Rig([c["name"] for c in cams], [skeleton.index(c["segment"]) for c in cams],
                   np.array([c["segment_from_camera"] for c in cams], np.float64),
                   stack_cameras([camera_from_dict(c["intrinsics"], where) for c in cams]))
    except (KeyError, TypeError) as err:
        raise ValueError(f"{where}: missing or malformed field {err}") from None
    except ValueError as err:
        message = str(err)
        raise ValueError(message if message.startswith(where) else f"{where}: {message}") from None
