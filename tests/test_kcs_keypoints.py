"""Detector keypoints as ``bcmocap kcs`` input (bcmocap.kcs.keypoints): files in each tool's documented format."""

import json

import numpy as np
import pytest

from bcmocap.kcs import CMU_JOINTS
from bcmocap.kcs.keypoints import KEYPOINT_NAMES, read_keypoints

FRAMES = 6
WIDTH, HEIGHT = 640, 480


@pytest.fixture(scope="module")
def scene():
    """Pixel positions of every keypoint name any format uses, for a few frames (a person-like layout that moves),
    and of the CMU joints they map to."""
    rng = np.random.default_rng(2)
    names = sorted({n for names in KEYPOINT_NAMES.values() for n in names})
    base = {n: rng.uniform([100, 60], [540, 420]) for n in names}
    pixels = {n: base[n] + np.arange(FRAMES)[:, None] * [3.0, -2.0] for n in names}
    return pixels


def _coco_results(scene, path, extra_person=False, low=()):
    rows = []
    for f in range(FRAMES):
        kp = []
        for name in KEYPOINT_NAMES["coco17"]:
            x, y = scene[name][f]
            kp += [float(x), float(y), 0.1 if name in low else 0.9]
        rows.append({"image_id": 10 + f, "category_id": 1, "keypoints": kp, "score": 0.95})
        if extra_person:  # a second, less sure person elsewhere in the frame
            rows.append({"image_id": 10 + f, "category_id": 1, "keypoints": [v + 50 for v in kp], "score": 0.4})
    path.write_text(json.dumps(rows))
    return path


def test_coco_results_map_onto_the_cmu_joints_with_midpoints_and_missing_joints(scene, tmp_path):
    path = _coco_results(scene, tmp_path / "coco.json", extra_person=True, low=("left_knee",))
    joints = read_keypoints(path, "coco17", CMU_JOINTS)
    assert joints.shape == (FRAMES, len(CMU_JOINTS), 2)
    rows = json.loads(path.read_text())
    path.with_name("gap.json").write_text(json.dumps([r for r in rows if r["image_id"] != 12]))  # nobody in frame 2
    gap = read_keypoints(path.with_name("gap.json"), "coco17", CMU_JOINTS)
    assert gap.shape == joints.shape and np.isnan(gap[2]).all() and np.array_equal(gap[3], joints[3], equal_nan=True)
    at = {n: joints[:, k] for k, n in enumerate(CMU_JOINTS)}
    np.testing.assert_allclose(at["rfemur"], scene["right_hip"])  # the surer person of each frame
    np.testing.assert_allclose(at["root"], 0.5 * (scene["left_hip"] + scene["right_hip"]))
    np.testing.assert_allclose(at["head"], 0.5 * (scene["left_ear"] + scene["right_ear"]))
    np.testing.assert_allclose(at["lowerneck"], 0.5 * (scene["left_shoulder"] + scene["right_shoulder"]))
    for missing in ("thorax", "head_end", "ltoes", "rtoes", "ltibia"):  # not given, or below the confidence
        assert np.isnan(at[missing]).all(), missing
    assert not np.isnan(read_keypoints(path, "coco17", CMU_JOINTS, min_confidence=0.05)[:, CMU_JOINTS.index("ltibia")]).any()


def test_a_coco_dataset_file_orders_frames_by_file_name(scene, tmp_path):
    names = KEYPOINT_NAMES["coco17"]
    images = [{"id": 100 - f, "file_name": f"frame_{f:04d}.png"} for f in range(FRAMES)]
    annotations = [{"image_id": 100 - f, "keypoints": [v for n in names for v in (*scene[n][f], 2)]}
                   for f in reversed(range(FRAMES)) if f != 1]  # nobody annotated in frame 1
    path = tmp_path / "dataset.json"
    path.write_text(json.dumps({"images": images, "annotations": annotations, "categories": [{"id": 1}]}))
    joints = read_keypoints(path, "coco17", CMU_JOINTS)
    keep = [0, 2, 3, 4, 5]
    assert len(joints) == FRAMES and np.isnan(joints[1]).all()
    np.testing.assert_allclose(joints[keep, CMU_JOINTS.index("lwrist")], scene["left_wrist"][keep])


def test_an_openpose_folder_maps_neck_midhip_and_big_toes(scene, tmp_path):
    folder = tmp_path / "openpose"
    folder.mkdir()
    aliases = {"Nose": "nose", "Neck": "Neck", "MidHip": "MidHip", "REye": "right_eye", "LEye": "left_eye",
               "REar": "right_ear", "LEar": "left_ear", "LBigToe": "left_foot_index", "RBigToe": "right_foot_index",
               "LSmallToe": "not found", "RSmallToe": "not found", "LHeel": "left_heel", "RHeel": "right_heel"}
    for side, s in (("L", "left"), ("R", "right")):
        for part in ("Shoulder", "Elbow", "Wrist", "Hip", "Knee", "Ankle"):
            aliases[side + part] = f"{s}_{part.lower()}"
    for f in range(FRAMES):
        person = []
        for name in KEYPOINT_NAMES["body25"]:
            source = aliases[name]
            x, y = scene[source][f] if source in scene else (0.0, 0.0)
            person += [float(x), float(y), 0.0 if source not in scene else 0.8]
        people = [] if f == 2 else [{"person_id": [-1], "pose_keypoints_2d": person}]  # nobody found in frame 2
        (folder / f"video_{f:012d}_keypoints.json").write_text(json.dumps({"version": 1.3, "people": people}))
    joints = read_keypoints(folder, "body25", CMU_JOINTS)
    at = {n: joints[:, k] for k, n in enumerate(CMU_JOINTS)}
    assert np.isnan(joints[2]).all()
    keep = [0, 1, 3, 4, 5]
    np.testing.assert_allclose(at["ltoes"][keep], scene["left_foot_index"][keep])
    np.testing.assert_allclose(at["root"][keep], scene["MidHip"][keep])  # BODY-25's own pelvis and neck
    np.testing.assert_allclose(at["lowerneck"][keep], scene["Neck"][keep])
    np.testing.assert_allclose(at["head"][keep], 0.5 * (scene["left_ear"] + scene["right_ear"])[keep])


def test_mediapipe_landmarks_are_scaled_to_pixels(scene, tmp_path):
    frames = []
    for f in range(FRAMES):
        marks = [{"x": scene[n][f][0] / WIDTH, "y": scene[n][f][1] / HEIGHT, "z": 0.1, "visibility": 0.9}
                 for n in KEYPOINT_NAMES["mediapipe33"]]
        frames.append(None if f == 4 else {"landmark": marks})
    path = tmp_path / "mediapipe.json"
    path.write_text(json.dumps({"image_width": WIDTH, "image_height": HEIGHT, "frames": frames}))
    joints = read_keypoints(path, "mediapipe33", CMU_JOINTS)
    np.testing.assert_allclose(joints[[0, 1, 2, 3, 5], CMU_JOINTS.index("rtoes")], scene["right_foot_index"][[0, 1, 2, 3, 5]])
    assert np.isnan(joints[4]).all()


@pytest.mark.parametrize("content, fmt, culprit", [
    ("not json", "coco17", "cannot read as JSON"),
    ('[{"image_id": 1, "keypoints": [1, 2, 3]}]', "coco17", "entry 0: expected 51 numbers"),
    ('[{"image_id": [1], "keypoints": []}]', "coco17", "entry 0: needs an 'image_id'"),
    ('{"frames": []}', "mediapipe33", "'image_width' must be a positive number"),
    ('{"image_width": 640, "image_height": 480, "frames": [{"landmark": []}]}', "mediapipe33", "frames[0] must be null"),
])
def test_bad_keypoint_files_are_named(tmp_path, content, fmt, culprit):
    path = tmp_path / "bad.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=r"bad\.json: ") as info:
        read_keypoints(path, fmt, CMU_JOINTS)
    assert culprit in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(ValueError, match="no \\*_keypoints.json files"):
        read_keypoints(tmp_path, "body25", CMU_JOINTS)


@pytest.mark.slow  # ~10 s: the heavy tier
def test_kcs_reconstructs_a_walk_from_coco_keypoints(tmp_path, capsys):
    """The bundled CMU walk seen by a static camera, given as COCO-17 detections (so no thorax, top of the head
    or toes): ``bcmocap kcs --keypoints coco17`` reconstructs the joints COCO gives."""
    from bcmocap.cli import main
    from bcmocap.kcs import aligned_joint_errors
    from bcmocap.kcs.keypoints import cmu_prior

    chain, rest = cmu_prior()
    from importlib import resources

    from bcmocap.io import read_amc, read_asf
    from bcmocap.kinematics.fk import joint_positions

    base = resources.files("bcmocap") / "data" / "cmu"
    with resources.as_file(base / "35.asf") as asf_path, resources.as_file(base / "35_01.amc") as amc_path:
        asf = read_asf(asf_path)
        truth_all = np.asarray(joint_positions(asf.skeleton, read_amc(amc_path, asf)))
    names = list(asf.skeleton.names)
    frames = slice(0, 240, 4)  # 2 s at 30 Hz
    truth = truth_all[frames][:, [names.index(n) for n in CMU_JOINTS]]
    ears = truth_all[frames][:, names.index("head")] + [0.0, 0.0, 0.08]  # both ears at the head's centre
    camera = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # looking along +y, z up
    def pixels(points):
        p = points @ camera.T + [0.0, 0.0, 6.0]
        return 300.0 * p[..., :2] / p[..., 2:] + [320.0, 240.0]
    at = {n: pixels(truth[:, k]) for k, n in enumerate(CMU_JOINTS)}
    coco = {"left_hip": "lfemur", "right_hip": "rfemur", "left_knee": "ltibia", "right_knee": "rtibia",
            "left_ankle": "lfoot", "right_ankle": "rfoot", "left_shoulder": "lhumerus", "right_shoulder": "rhumerus",
            "left_elbow": "lradius", "right_elbow": "rradius", "left_wrist": "lwrist", "right_wrist": "rwrist"}
    rows = []
    for f in range(len(truth)):
        kp = []
        for name in KEYPOINT_NAMES["coco17"]:
            if name in coco:
                x, y = at[coco[name]][f]
            elif name.endswith("ear"):
                x, y = pixels(ears[f])
            else:
                x, y = pixels(ears[f] + [0.0, -0.1, -0.03])  # the face
            kp += [float(x), float(y), 0.9]
        rows.append({"image_id": f, "category_id": 1, "keypoints": kp, "score": 0.9})
    path = tmp_path / "walk_coco.json"
    path.write_text(json.dumps(rows))
    out = tmp_path / "out"
    assert main(["kcs", str(path), "--keypoints", "coco17", "--out", str(out), "--fps", "30"]) == 0
    result = np.load(out / "result.npz")
    given = [CMU_JOINTS.index(n) for n in coco.values()]
    errors = aligned_joint_errors(result["joints"][:, given], truth[:, given])
    # 72 mm here (without a thorax, top of the head or toes, and with the ears for the head); a wrong mapping (sides
    # swapped, a knee for a hip) is far worse. The accuracy against noise is benchmarks/kcs_table.py's.
    assert np.mean(errors) < 0.08, np.mean(errors)
