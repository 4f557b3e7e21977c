"""2-D keypoints from real detectors as ``bcmocap kcs`` input: COCO-17, OpenPose BODY-25 and MediaPipe Pose (33).

Each format's files are read as its tool documents them, one person per frame (the most confident where a frame
has several), and mapped onto the 19 joints of the CMU chain (:data:`~bcmocap.kcs.CMU_JOINTS`); a joint the
detector does not give, or gives below ``min_confidence``, is a missing measurement (NaN), never a zero.

**Files.**

- ``coco17``: a COCO keypoint JSON file, either detection results (a list of ``{"image_id", "category_id",
  "keypoints": [x, y, score] × 17, "score"}``; the integer ``image_id`` is the frame number, and every number from
  the smallest to the largest is a frame, with or without a detection) or a dataset file (``{"images": [{"id",
  "file_name"}], "annotations": [{"image_id", "keypoints": [x, y, v] × 17}]}``: one frame per image, in the order of
  the file names; a visibility ``v`` of 0 is missing, 1 (labelled, occluded) and 2 count as confidence 1).
- ``body25``: OpenPose's ``--write_json`` folder: one ``*_keypoints.json`` per frame, ``{"people": [{
  "pose_keypoints_2d": [x, y, c] × 25}]}``, frames in the order of the file names; a person not found in a frame
  (no ``people``) leaves every joint of that frame missing.
- ``mediapipe33``: a JSON file ``{"image_width", "image_height", "frames": [...]}`` whose frames are MediaPipe
  Pose's ``pose_landmarks`` as ``google.protobuf.json_format.MessageToDict`` writes them (``{"landmark": [{"x",
  "y", "z", "visibility"} × 33]}``, x and y normalised to the image) or ``null`` where no pose was found; the
  landmarks' ``visibility`` is the confidence.

**Mapping to the CMU chain** (the subject's left is ``l``):

=============  =================  ==================  =====================
CMU joint      COCO-17            BODY-25             MediaPipe 33
=============  =================  ==================  =====================
root           mid-hips           MidHip              mid-hips
l/rfemur       l/r hip            L/RHip              l/r hip
l/rtibia       l/r knee           L/RKnee             l/r knee
l/rfoot        l/r ankle          L/RAnkle            l/r ankle
l/rtoes        —                  L/RBigToe           l/r foot index
thorax         —                  —                   —
lowerneck      mid-shoulders      Neck                mid-shoulders
head           mid-ears           mid-ears            mid-ears
head_end       —                  —                   —
l/rhumerus     l/r shoulder       L/RShoulder         l/r shoulder
l/rradius      l/r elbow          L/RElbow            l/r elbow
l/rwrist       l/r wrist          L/RWrist            l/r wrist
=============  =================  ==================  =====================

A midpoint is missing unless both its points are seen. The joints no format gives (the thorax and the top of
the head; COCO's toes) are missing in every frame: the chain's bones still hold them, and the reconstruction
places them from the other joints and the prior's mean pose. The mid-ears stand for CMU's head joint (the base of
the skull), a few centimetres off it, and the mid-shoulders for its lower neck.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

__all__ = ["FORMATS", "KEYPOINT_NAMES", "cmu_prior", "keypoint_input", "read_keypoints"]

#: Each format's keypoints, in its own order.
KEYPOINT_NAMES = {
    "coco17": ("nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
               "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip", "left_knee",
               "right_knee", "left_ankle", "right_ankle"),
    "body25": ("Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "MidHip", "RHip",
               "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar", "LBigToe",
               "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel"),
    "mediapipe33": ("nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
                    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
                    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
                    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip", "right_hip",
                    "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel", "right_heel",
                    "left_foot_index", "right_foot_index"),
}
FORMATS = tuple(KEYPOINT_NAMES)

# CMU joint -> the format's keypoint, or a pair whose midpoint it is; absent: not given.
_COMMON = {"lfemur": "left_hip", "rfemur": "right_hip", "ltibia": "left_knee", "rtibia": "right_knee",
           "lfoot": "left_ankle", "rfoot": "right_ankle", "lhumerus": "left_shoulder", "rhumerus": "right_shoulder",
           "lradius": "left_elbow", "rradius": "right_elbow", "lwrist": "left_wrist", "rwrist": "right_wrist",
           "root": ("left_hip", "right_hip"), "lowerneck": ("left_shoulder", "right_shoulder"),
           "head": ("left_ear", "right_ear")}
_MAPPING = {
    "coco17": _COMMON,
    "mediapipe33": {**_COMMON, "ltoes": "left_foot_index", "rtoes": "right_foot_index"},
    "body25": {"lfemur": "LHip", "rfemur": "RHip", "ltibia": "LKnee", "rtibia": "RKnee", "lfoot": "LAnkle",
               "rfoot": "RAnkle", "ltoes": "LBigToe", "rtoes": "RBigToe", "lhumerus": "LShoulder",
               "rhumerus": "RShoulder", "lradius": "LElbow", "rradius": "RElbow", "lwrist": "LWrist",
               "rwrist": "RWrist", "root": "MidHip", "lowerneck": "Neck", "head": ("LEar", "REar")},
}


def _load_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read as JSON ({exc})") from None


def _triplets(values, count: int, where: str) -> np.ndarray:
    """``(count, 3)`` x, y, confidence from a flat list of ``3 * count`` numbers."""
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: keypoints must be numbers") from None
    if array.shape != (3 * count,):
        raise ValueError(f"{where}: expected {3 * count} numbers (x, y, confidence for {count} keypoints), got "
                         f"{array.size}")
    return array.reshape(count, 3)


def _read_coco(path: Path) -> np.ndarray:
    """``(F, 17, 3)``: one frame per image (a dataset file's images in the order of their file names; a results
    list's integer ``image_id`` from the smallest to the largest, so a frame with no detection stays a frame), the
    surest person of each, NaN where an image has none."""
    data = _load_json(path)
    if isinstance(data, dict) and isinstance(data.get("annotations"), list):
        images = [img for img in data.get("images") or [] if isinstance(img, dict) and "id" in img]
        ids = [img["id"] for img in sorted(images, key=lambda img: str(img.get("file_name", "")))]
        rows, visibility = data["annotations"], True
    elif isinstance(data, list):
        rows, visibility, ids = data, False, None
    else:
        raise ValueError(f"{path}: expected COCO keypoint results (a list) or a COCO file with a list of 'annotations'")
    best: dict = {}
    for k, row in enumerate(rows):
        where = f"{path}: entry {k}"
        if not isinstance(row, dict) or "keypoints" not in row or not isinstance(row.get("image_id"), (int, str)) \
                or isinstance(row.get("image_id"), bool):
            raise ValueError(f"{where}: needs an 'image_id' (a number or a name) and 'keypoints'")
        if row.get("category_id", 1) != 1:
            continue
        points = _triplets(row["keypoints"], 17, where)
        if visibility:
            points[:, 2] = (points[:, 2] > 0).astype(np.float64)
        try:
            score = float(row.get("score", np.nanmean(points[:, 2])))
        except (TypeError, ValueError):
            raise ValueError(f"{where}: 'score' must be a number") from None
        if row["image_id"] not in best or score > best[row["image_id"]][0]:
            best[row["image_id"]] = (score, points)
    if not best:
        raise ValueError(f"{path}: no person keypoints (category 1) in it")
    if ids is None:
        if not all(isinstance(i, int) for i in best):
            raise ValueError(f"{path}: detection results need integer image_id values (the frame numbers)")
        ids = list(range(min(best), max(best) + 1))
    else:
        unknown = sorted(map(str, set(best) - set(ids)))
        if unknown:
            raise ValueError(f"{path}: annotations of images not in 'images': {', '.join(unknown[:5])}")
    empty = np.full((17, 3), np.nan)
    return np.stack([best[i][1] if i in best else empty for i in ids])


def _read_openpose(path: Path) -> np.ndarray:
    if not path.is_dir():
        raise ValueError(f"{path}: body25 input is OpenPose's --write_json folder (*_keypoints.json per frame)")
    files = sorted(path.glob("*_keypoints.json"))
    if not files:
        raise ValueError(f"{path}: no *_keypoints.json files (OpenPose --write_json)")
    out = np.full((len(files), 25, 3), np.nan)
    for f, file in enumerate(files):
        data = _load_json(file)
        people = data.get("people") if isinstance(data, dict) else None
        if not isinstance(people, list):
            raise ValueError(f"{file}: expected {{'people': [...]}} (OpenPose keypoint JSON)")
        best = None
        for k, person in enumerate(people):
            if not isinstance(person, dict) or "pose_keypoints_2d" not in person:
                raise ValueError(f"{file}: people[{k}] has no 'pose_keypoints_2d'")
            if not person["pose_keypoints_2d"]:
                continue
            points = _triplets(person["pose_keypoints_2d"], 25, f"{file}: people[{k}].pose_keypoints_2d")
            if best is None or points[:, 2].mean() > best[:, 2].mean():
                best = points
        if best is not None:
            out[f] = best
    return out


def _read_mediapipe(path: Path) -> np.ndarray:
    data = _load_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise ValueError(f"{path}: expected {{'image_width', 'image_height', 'frames': [...]}} with MediaPipe "
                         "pose_landmarks per frame")
    size = []
    for field in ("image_width", "image_height"):
        value = data.get(field)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{path}: '{field}' must be a positive number of pixels, got {value!r}")
        size.append(float(value))
    out = np.full((len(data["frames"]), 33, 3), np.nan)
    for f, frame in enumerate(data["frames"]):
        if frame is None:
            continue
        marks = frame.get("landmark") if isinstance(frame, dict) else None
        if not isinstance(marks, list) or len(marks) != 33:
            raise ValueError(f"{path}: frames[{f}] must be null or {{'landmark': [33 landmarks]}}")
        for k, mark in enumerate(marks):
            try:  # MessageToDict leaves out fields at their default (0)
                out[f, k] = (float(mark.get("x", 0.0)) * size[0], float(mark.get("y", 0.0)) * size[1],
                             float(mark.get("visibility", 0.0)))
            except (AttributeError, TypeError, ValueError):
                raise ValueError(f"{path}: frames[{f}].landmark[{k}] must hold numbers x, y, visibility") from None
    if not len(out):
        raise ValueError(f"{path}: no frames")
    return out


_READERS = {"coco17": _read_coco, "body25": _read_openpose, "mediapipe33": _read_mediapipe}


def read_keypoints(path: str | Path, fmt: str, joints, *, min_confidence: float = 0.3) -> np.ndarray:
    """``(F, J, 2)`` pixels of ``joints`` (CMU joint names) from a detector's keypoint file(s); NaN where missing.

    Args:
        path: the file (``coco17``, ``mediapipe33``) or folder (``body25``) as the module docstring describes.
        fmt: one of :data:`FORMATS`.
        joints: CMU joint names (e.g. :data:`~bcmocap.kcs.CMU_JOINTS`) to map onto.
        min_confidence: a keypoint with a lower confidence is missing.

    Raises:
        ValueError: one line naming the file and what is wrong in it.
    """
    if fmt not in _READERS:
        raise ValueError(f"keypoint format {fmt!r}: expected one of {', '.join(FORMATS)}")
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such file or folder")
    raw = _READERS[fmt](path)  # (F, K, 3)
    index = {name: k for k, name in enumerate(KEYPOINT_NAMES[fmt])}
    seen = raw[..., 2] >= min_confidence
    points = np.where(seen[..., None], raw[..., :2], np.nan)
    out = np.full((len(raw), len(joints), 2), np.nan)
    for j, joint in enumerate(joints):
        source = _MAPPING[fmt].get(joint)
        if isinstance(source, str):
            out[:, j] = points[:, index[source]]
        elif source is not None:  # a midpoint: missing unless both are seen
            out[:, j] = 0.5 * (points[:, index[source[0]]] + points[:, index[source[1]]])
    return out


def cmu_prior():
    """The CMU chain (:data:`~bcmocap.kcs.CMU_JOINTS` of the bundled subject 35, ``bcmocap/data/cmu/35.asf``) and
    its mean pose over the bundled walk 35_01 (m; :func:`~bcmocap.kcs.mean_pose`), the initial configuration of a
    reconstruction from detector keypoints."""
    from importlib import resources

    from ..io import read_amc, read_asf
    from ..kinematics.fk import joint_positions
    from .chain_space import CMU_JOINTS, KinematicChainSpace, mean_pose

    base = resources.files("bcmocap") / "data" / "cmu"
    with resources.as_file(base / "35.asf") as asf_path, resources.as_file(base / "35_01.amc") as amc_path:
        asf = read_asf(asf_path)
        motion = read_amc(amc_path, asf)
    chain = KinematicChainSpace.from_skeleton(asf.skeleton, CMU_JOINTS)
    keep = [asf.skeleton.index(n) for n in CMU_JOINTS]
    joints = np.asarray(joint_positions(asf.skeleton, motion))[:, keep]
    return chain, mean_pose(joints, chain)


def keypoint_input(path: str | Path, fmt: str, *, min_confidence: float = 0.3, fps: float | None = None):
    """A :class:`~bcmocap.kcs.inputs.KCSInput` from a detector's keypoints: the CMU chain and mean pose of
    :func:`cmu_prior` and the keypoints of :func:`read_keypoints` on it."""
    from .chain_space import CMU_JOINTS
    from .inputs import KCSInput

    joints_2d = read_keypoints(path, fmt, CMU_JOINTS, min_confidence=min_confidence)
    if np.isnan(joints_2d).all():
        raise ValueError(f"{path}: no keypoint reaches the confidence {min_confidence:g} (--min-confidence)")
    chain, rest = cmu_prior()
    return KCSInput(chain=chain, joints_2d=joints_2d, rest=rest, fps=fps)
