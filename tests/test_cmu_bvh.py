"""benchmarks/_cmu_bvh.py (issue 47): subject 35's walks from the cgspeed BVH conversion give the joints their AMC
files would, the thorax the conversion drops put back."""

from pathlib import Path

import numpy as np
import pytest

from benchmarks import _cmu_bvh
from bcmocap.io import read_asf
from bcmocap.kcs import CMU_JOINTS

ROOT = Path(__file__).resolve().parents[1]
ASF = ROOT / "bcmocap" / "data" / "cmu" / "35.asf"
DATA = ROOT / "benchmarks" / "data" / "cmu_bvh"
WALK = DATA / "35_30.bvh"


@pytest.mark.parametrize("asf_path, bvh_path", [(ASF, WALK), (DATA / "13.asf", DATA / "13_11.bvh")],
                         ids=["35_30 walk", "13_11 jump"])
def test_the_converted_trial_keeps_every_bone_of_the_asf_in_every_frame(asf_path, bvh_path):
    """Every bone but the hands' has its ASF length in each frame (the file's 5 decimals: 0.1 mm), the neck and
    shoulders included once the thorax is back; without it they are about 0.1 m short."""
    asf = read_asf(asf_path)
    bvh = _cmu_bvh.cgspeed_skeleton(bvh_path, asf)
    from bcmocap.kinematics import joint_positions

    x = np.asarray(joint_positions(bvh.skeleton, bvh.motion))[1:]  # (F, J, 3), the T-pose left out
    names, parents = asf.skeleton.names, np.asarray(asf.skeleton.parents)
    rest = _cmu_bvh.rest_positions(asf.skeleton)
    hands = {"lhand", "lfingers", "lfingers_end", "lthumb", "lthumb_end",
             "rhand", "rfingers", "rfingers_end", "rthumb", "rthumb_end"}
    for j in range(1, len(names)):
        if names[j] in hands:
            continue
        length = np.linalg.norm(x[:, j] - x[:, parents[j]], axis=-1)
        np.testing.assert_allclose(length, np.linalg.norm(rest[j] - rest[parents[j]]), atol=1e-4, err_msg=names[j])
    plain = _cmu_bvh.read_bvh(bvh_path, length_unit_m=_cmu_bvh.CGSPEED_LENGTH_UNIT_M)
    neck = names.index("lowerneck")
    assert np.linalg.norm(np.asarray(plain.skeleton.offsets)[neck]) == 0.0
    assert 0.08 < np.linalg.norm(rest[neck] - rest[names.index("thorax")]) < 0.15


def test_the_trial_is_the_chain_s_joints_without_the_t_pose():
    asf = read_asf(ASF)
    joints = _cmu_bvh.read_cgspeed_trial(WALK, asf)
    assert joints.shape == (412, len(CMU_JOINTS), 3)  # 413 frames in the file, the first the conversion's T-pose
    assert 0.9 < np.median(joints[:, 0, 2]) < 1.1  # the root about a metre up (Z up, metres)
    walked = np.linalg.norm(joints[-1, 0, :2] - joints[0, 0, :2])
    assert walked > 1.0  # a walk


def test_a_file_of_another_skeleton_is_one_line(tmp_path):
    other = tmp_path / "two_links.bvh"
    other.write_text("HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 6 Xposition Yposition Zposition Zrotation "
                     "Yrotation Xrotation\n  JOINT Leg\n  {\n    OFFSET 0 -1 0\n    CHANNELS 3 Zrotation Yrotation Xrotation\n"
                     "    End Site\n    {\n      OFFSET 0 -1 0\n    }\n  }\n}\nMOTION\nFrames: 1\nFrame Time: 0.01\n"
                     "0 0 0 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match=r"two_links\.bvh: its 3 joints are not the 38 bones of the ASF file"):
        _cmu_bvh.cgspeed_skeleton(other, read_asf(ASF))
