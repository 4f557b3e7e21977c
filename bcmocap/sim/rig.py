"""The paper-like rig: 18 outward-looking 170° FOV fisheye cameras on the camera skeleton.

Three cameras on the waist, two on the torso, one on the head and one on each upper arm, forearm,
hand, thigh, shin and foot (§3, Fig. 2). Each camera sits a few centimetres off its segment's surface
and looks outward; limb cameras look sideways, away from the body, as the paper places them to limit
self-occlusion.
"""

from __future__ import annotations

import numpy as np

from ..cameras import FOVCamera
from ..geometry import SE3, SO3
from ..kinematics.fk import forward_kinematics
from ..kinematics.rig import Rig
from ..kinematics.skeleton import Skeleton


def fov_camera_for(width: int, height: int, fov_deg: float = 170.0, omega: float = 1.2) -> FOVCamera:
    """A square-pixel FOV-model camera whose horizontal field of view is ``fov_deg``."""
    half = np.deg2rad(fov_deg) / 2.0
    r_norm = np.arctan(2.0 * np.tan(half) * np.tan(omega / 2.0)) / omega
    focal = (width / 2.0) / r_norm
    return FOVCamera(
        focal=np.array([focal, focal]),
        principal_point=np.array([(width - 1) / 2.0, (height - 1) / 2.0]),
        omega=np.asarray(omega),
        width=width,
        height=height,
    )


def _look_rotation(view: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``segment_from_camera`` rotation whose camera z looks along ``view`` with image y down along −up."""
    z = view / np.linalg.norm(view)
    y = -(up - np.dot(up, z) * z)
    if np.linalg.norm(y) < 1e-6:
        y = np.cross(z, np.array([1.0, 0.0, 0.0]))
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=1)


def body_axes(skeleton: Skeleton) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit (forward, left, up) directions of the body at rest, from the hips (world is Z up)."""
    rest = np.asarray(forward_kinematics(skeleton, skeleton.rest_motion()).translation())
    up = np.array([0.0, 0.0, 1.0])
    left = rest[skeleton.index("left_thigh")] - rest[skeleton.index("right_thigh")]
    left = left - np.dot(left, up) * up
    left /= np.linalg.norm(left)
    forward = np.cross(left, up)
    return forward, left, up


def standard_rig(skeleton: Skeleton, width: int = 640, height: int = 360, fov_deg: float = 170.0) -> Rig:
    """The 18-camera rig of the standard synthetic capture, for a skeleton from :mod:`bcmocap.sim.motions`.

    Args:
        skeleton: a camera skeleton with the segment names of :data:`BODY_SEGMENTS`.
        width, height: image size (px).
        fov_deg: horizontal field of view of the FOV-model lenses.
    """
    rest = np.asarray(forward_kinematics(skeleton, skeleton.rest_motion()).translation())
    forward, left, up = body_axes(skeleton)
    camera = fov_camera_for(width, height, fov_deg)

    def child_offset(segment: str) -> np.ndarray:
        j = skeleton.index(segment)
        kids = skeleton.children(j)
        return np.asarray(skeleton.offsets[kids[0]]) if kids else np.zeros(3)

    mounts = []

    def add(name, segment, position, view, cam_up=up):
        rot = _look_rotation(np.asarray(view, float), np.asarray(cam_up, float))
        pose = SE3.from_rotation_and_translation(SO3.from_matrix(rot), np.asarray(position, float))
        mounts.append((name, segment, np.asarray(pose.wxyz_xyz), camera))

    tilt = -0.35 * up  # waist and limb cameras look slightly downward
    add("waist_front", "pelvis", 0.16 * forward + 0.05 * up, forward + tilt)
    add("waist_left", "pelvis", 0.18 * left + 0.05 * up, left + tilt)
    add("waist_right", "pelvis", -0.18 * left + 0.05 * up, -left + tilt)
    torso_height = child_offset("torso")
    add("chest", "torso", 0.75 * torso_height + 0.14 * forward, forward + 0.2 * up)
    add("back", "torso", 0.75 * torso_height - 0.14 * forward, -forward + 0.2 * up)
    add("head", "head", 0.15 * up + 0.1 * forward, forward + 0.3 * up)
    for side, sign in (("left", 1.0), ("right", -1.0)):
        lateral = sign * left
        # The rest pose is a T-pose: an arm's outer side is "up" at rest and faces sideways once the
        # arm hangs; leg cameras sit on the outer side of the leg (§6).
        for seg, radius, outward, view in (
            (f"{side}_upper_arm", 0.07, up, up + 0.3 * forward),
            (f"{side}_forearm", 0.06, up, up + 0.3 * forward),
            (f"{side}_thigh", 0.10, lateral, lateral + 0.2 * forward),
            (f"{side}_shin", 0.07, lateral, lateral + 0.2 * forward),
        ):
            add(f"{seg}", seg, 0.5 * child_offset(seg) + radius * outward, view, cam_up=forward)
        hand_dir = np.asarray(skeleton.offsets[skeleton.index(f"{side}_hand")])
        hand_dir = hand_dir / max(np.linalg.norm(hand_dir), 1e-9)
        add(f"{side}_hand", f"{side}_hand", 0.08 * hand_dir + 0.05 * up, up + 0.5 * forward, cam_up=forward)
        add(f"{side}_foot", f"{side}_foot", 0.1 * forward + 0.05 * up, forward + 0.1 * up)
    return Rig.from_mounts(skeleton, mounts)
