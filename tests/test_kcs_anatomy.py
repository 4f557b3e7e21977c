"""Anatomical limb-sign choice of the KCS solver (bcmocap.kcs.anatomy, bcmocap.kcs.solve.limb_signs).

The state DP against brute force, the CMU anatomy, recovery of flipped limb signs on a true walking clip,
and the whole solver with and without the anatomy on a short CMU clip.
"""

from __future__ import annotations

import itertools
from importlib.resources import files

import jax.numpy as jnp
import numpy as np
import pytest

from bcmocap.io import load_cmu
from bcmocap.kcs import CMU_JOINTS, KCSOptions, KinematicChainSpace, aligned_joint_errors, mean_pose, reconstruct
from bcmocap.kcs.anatomy import human_anatomy
from bcmocap.kcs.solve import _viterbi_states, limb_signs
from bcmocap.kinematics import Skeleton, joint_positions


pytestmark = pytest.mark.slow  # the KCS solver on CMU walks


@pytest.fixture(scope="module")
def cmu():
    """``(chain, joints (F, J, 3))`` of the bundled CMU 35_01 walk, every other frame (60 Hz)."""
    data = files("bcmocap") / "data" / "cmu"
    skeleton, motion = load_cmu(data / "35.asf", data / "35_01.amc")
    chain = KinematicChainSpace.from_skeleton(skeleton, CMU_JOINTS)
    x = np.asarray(joint_positions(skeleton, motion))[::2, [skeleton.index(n) for n in CMU_JOINTS]]
    return chain, x


def view(azimuth_deg, elevation_deg=15.0):
    """``(3, 3)`` camera_from_world (rows: image x, image y, depth) of a static camera; data are Z up."""
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    forward = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), -np.sin(el)])
    right = np.array([-np.sin(az), np.cos(az), 0.0])
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


def test_state_dynamic_programming_matches_brute_force(rng):
    frames, states, n = 5, 3, 2
    unary = rng.uniform(size=(frames, states))
    points = rng.normal(size=(frames, states, n, 3))
    mu = 0.3

    def cost(seq):
        p = points[np.arange(frames), seq]
        return unary[np.arange(frames), seq].sum() + mu * np.sum((p[:-2] - 2 * p[1:-1] + p[2:]) ** 2)

    best = min(itertools.product(range(states), repeat=frames), key=lambda s: cost(np.array(s)))
    got = np.asarray(_viterbi_states(jnp.asarray(unary), jnp.asarray(points), mu))
    assert cost(got) == pytest.approx(cost(np.array(best)), abs=1e-12)


def test_human_anatomy_on_cmu_and_none_elsewhere(cmu):
    chain, _ = cmu
    anatomy = human_anatomy(chain)
    names = [[chain.bone_names[k] for k in limb] for limb in anatomy.limbs]
    assert names == [
        ["lfemur->ltibia", "ltibia->lfoot", "lfoot->ltoes"],
        ["rfemur->rtibia", "rtibia->rfoot", "rfoot->rtoes"],
        ["lhumerus->lradius", "lradius->lwrist"],
        ["rhumerus->rradius", "rradius->rwrist"],
        ["root->lfemur", "root->rfemur", "root->thorax"],
        ["thorax->lhumerus", "thorax->rhumerus", "thorax->lowerneck"],
    ]
    assert anatomy.rigid == ((4, 0, 1), (4, 0, 2), (4, 1, 2), (5, 0, 1), (5, 0, 2), (5, 1, 2))
    assert [(h.limb, h.parent, h.child, h.sign, h.planar) for h in anatomy.hinges] == [
        (0, 0, 1, 1.0, True), (0, 1, 2, -1.0, True), (1, 0, 1, 1.0, True), (1, 1, 2, -1.0, True),
        (2, 0, 1, -1.0, False), (3, 0, 1, -1.0, False),
    ]
    quadruped = KinematicChainSpace(("root", "a", "b"), (-1, 0, 1))
    assert human_anatomy(quadruped) is None
    skeleton = Skeleton(("root", "lfemur", "ltibia"), (-1, 0, 1), np.zeros((3, 3)))
    assert human_anatomy(KinematicChainSpace.from_skeleton(skeleton)) is None


@pytest.mark.parametrize("azimuth", [0.0, 40.0, 120.0, 230.0])
def test_limb_signs_undo_flipped_stretches_of_a_true_walk(cmu, azimuth, rng):
    """True bones with the depths of two bones of every limb flipped over stretches of frames."""
    chain, x = cmu
    x = x[:90]
    truth = np.einsum("ij,fbj->fbi", view(azimuth), chain.bones(x))  # (F, b, 3) camera frame
    anatomy = human_anatomy(chain)
    flipped = truth.copy()
    for limb in anatomy.limbs:
        for bone in limb[:2]:
            start = rng.integers(0, 60)
            flipped[start : start + 25, bone, 2] *= -1
    got = np.asarray(limb_signs(jnp.asarray(flipped), anatomy, rest_bones=jnp.asarray(chain.bones(x[0]))))
    limb_bones = [b for limb in anatomy.limbs for b in limb]
    others = [b for b in range(chain.num_bones) if b not in limb_bones]
    np.testing.assert_array_equal(got[:, others], flipped[:, others])
    np.testing.assert_allclose(np.abs(got), np.abs(flipped))
    # the depth of a bone nearly in the image plane is immaterial; most flipped deep ones are restored
    # (a thigh or upper arm seen nearly edge-on to the lateral axis can stay ambiguous)
    deep = np.abs(truth[:, limb_bones, 2]) > 0.03
    before = (np.sign(flipped[:, limb_bones, 2]) != np.sign(truth[:, limb_bones, 2])) & deep
    after = (np.sign(got[:, limb_bones, 2]) != np.sign(truth[:, limb_bones, 2])) & deep
    assert after.sum() < 0.35 * before.sum() and after.mean() < 0.08, (after.mean(), before.mean())


def test_anatomy_improves_the_solver_on_a_cmu_walk(cmu):
    """Three static views; the prior is the walk's mean pose made 5 % too large (as from another subject)."""
    chain, x = cmu
    prior = 1.05 * mean_pose(x[::2], chain)
    x = x[:80]
    rotation = np.stack([view(a) for a in (35.0, 150.0, 250.0)])
    centred = x - x.mean(axis=1, keepdims=True)
    uv = 200.0 * np.einsum("pij,fkj->pfki", rotation[:, :2], centred) + 320.0
    errors = {}
    for anatomy in (False, True):
        result = reconstruct(chain, uv, prior, options=KCSOptions(max_iterations=8, anatomy=anatomy))
        errors[anatomy] = np.asarray(aligned_joint_errors(result.joints, np.broadcast_to(x, result.joints.shape))).mean(1)
    assert errors[True].mean() < errors[False].mean() - 0.002, errors
    assert np.all(errors[True] < errors[False] + 0.002), errors


def test_options_check_the_new_weights():
    for name in ("hinge_weight", "rigid_weight", "limb_smoothness", "limb_agreement"):
        with pytest.raises(ValueError, match="non-negative"):
            KCSOptions(**{name: -1.0})


def test_padding_changes_no_result_with_anatomy_and_depth_smoothing(cmu):
    """The human chain's limb signs, per-bone signs and depth smoothing over 50 frames padded to 64."""
    chain, x = cmu
    prior = mean_pose(x[::2], chain)
    x = x[:50]
    centred = x - x.mean(axis=1, keepdims=True)
    uv = 200.0 * np.einsum("ij,fkj->fki", view(35.0)[:2], centred) + 320.0
    options = KCSOptions(max_iterations=4, depth_smoothing=1.5)
    padded, plain = (reconstruct(chain, uv, prior, options=options, pad=pad) for pad in (True, False))
    np.testing.assert_allclose(np.asarray(padded.joints), np.asarray(plain.joints), atol=1e-8)
    np.testing.assert_allclose(np.asarray(padded.bone_lengths), np.asarray(plain.bone_lengths), atol=1e-10)
