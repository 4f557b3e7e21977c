"""Monocular motion capture in the kinematic chain space (bcmocap.kcs).

KCS matrices against their definition, SVT against an SVD reference, cameras against scipy, the sign DP
against brute force, recovery of a simulated quadruped (a non-human chain), masking, batching, errors.
Problem sizes are shared so the solver compiles only a few times.
"""

from __future__ import annotations

import itertools
from importlib.resources import files

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from bcmocap.geometry import euler_to_matrix, quat_from_matrix
from bcmocap.io import load_cmu
from bcmocap.kcs import (
    CMU_JOINTS,
    KCSOptions,
    KinematicChainSpace,
    WeakPerspectiveCameras,
    aligned_joint_errors,
    fit_cameras,
    initial_cameras,
    joint_errors,
    mean_pose,
    motion_from_joints,
    reconstruct,
    singular_value_threshold,
)
from bcmocap.kcs.solve import _smooth_in_time, _viterbi_signs
from bcmocap.kinematics import Motion, Skeleton, joint_positions

# ---- a quadruped (non-human chain): trunk, neck, head, tail, four two-bone legs --------------------------
NAMES = ("root", "chest", "neck", "head", "nose", "tail", "lhip", "lknee", "lhoof", "rhip", "rknee", "rhoof",
         "lsho", "lelb", "lfhoof", "rsho", "relb", "rfhoof")
PARENTS = (-1, 0, 1, 2, 3, 0, 0, 6, 7, 0, 9, 10, 1, 12, 13, 1, 15, 16)
OFFSETS = np.array([
    [0, 0, 0], [0.6, 0, 0.05], [0.2, 0, 0.2], [0.15, 0, 0.05], [0.15, 0, -0.05], [-0.3, 0, 0.05],
    [0, 0.15, 0], [0.05, 0, -0.3], [-0.05, 0, -0.3], [0, -0.15, 0], [0.05, 0, -0.3], [-0.05, 0, -0.3],
    [0, 0.15, -0.05], [0, 0, -0.3], [0, 0, -0.3], [0, -0.15, -0.05], [0, 0, -0.3], [0, 0, -0.3],
])
FRAMES = 40
PX_PER_M = 200.0


def quadruped(num_frames: int = FRAMES, fps: float = 30.0, seed: int = 0, front_in_phase: bool = False):
    """``(skeleton, joints (F, J, 3), rest joints (J, 3))`` of a trotting quadruped (m, Z up).

    ``front_in_phase`` moves both front legs together (a bar between the front hooves stays rigid).
    """
    skeleton = Skeleton(NAMES, PARENTS, OFFSETS)
    rng = np.random.default_rng(seed)
    t = np.arange(num_frames) / fps
    phase = 2 * np.pi * 1.2 * t + rng.uniform(0, 2 * np.pi)
    angles = np.zeros((num_frames, len(NAMES), 3))
    legs = {"lhip": 0.0, "rhip": np.pi, "lsho": np.pi, "rsho": np.pi if front_in_phase else 0.0}
    for name, offset in legs.items():
        j = NAMES.index(name)
        angles[:, j, 1] = np.deg2rad(25) * np.sin(phase + offset)
        bend = np.deg2rad(20) * (1 + np.sin(phase + offset + 0.8))
        angles[:, j + 1, 1] = -bend if name.endswith("hip") else bend
    angles[:, NAMES.index("neck"), 1] = np.deg2rad(10) * np.sin(phase)
    angles[:, NAMES.index("tail"), 2] = np.deg2rad(20) * np.sin(0.5 * phase)
    angles[:, 0, 2] = np.deg2rad(8) * np.sin(0.3 * phase)
    motion = Motion(np.stack([1.5 * t, 0 * t, 0.6 + 0 * t], -1), quat_from_matrix(euler_to_matrix(angles, "XYZ")))
    return skeleton, np.asarray(joint_positions(skeleton, motion)), np.asarray(joint_positions(skeleton, skeleton.rest_motion()))


def camera_rotations(num_frames: int, rng: np.random.Generator) -> np.ndarray:
    """``(F, 3, 3)`` camera_from_world of a near-static camera looking slightly down (drifts ≤ 5°)."""
    az = rng.uniform(0, 2 * np.pi) + np.deg2rad(rng.uniform(-5, 5)) * np.linspace(0, 1, num_frames)
    el = np.deg2rad(rng.uniform(5, 30)) * np.ones(num_frames)
    forward = np.stack([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), -np.sin(el)], -1)
    right = np.stack([-np.sin(az), np.cos(az), 0 * az], -1)
    return np.stack([right, np.cross(forward, right), forward], -2)


def images(joints: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    centred = joints - joints.mean(axis=-2, keepdims=True)
    return PX_PER_M * np.einsum("...fij,fkj->...fki", rotations[..., :2, :], centred) + 320.0


@pytest.fixture(scope="module")
def scene():
    skeleton, joints, rest = quadruped()
    rng = np.random.default_rng(7)
    rotations = np.stack([camera_rotations(FRAMES, rng) for _ in range(2)])
    chain = KinematicChainSpace.from_skeleton(skeleton)
    return chain, joints, rest, rotations, images(joints, rotations)


@pytest.fixture(scope="module")
def solved(scene):
    chain, joints, rest, rotations, uv = scene
    return reconstruct(chain, uv, rest)


# ---- the kinematic chain space ---------------------------------------------------------------------------


def test_c_and_d_match_their_definition(skeleton, rng):
    chain = KinematicChainSpace.from_skeleton(skeleton)
    x = rng.normal(size=(5, chain.num_joints, 3))
    bones = chain.bones(x)
    for k, (a, b) in enumerate(chain.links):
        np.testing.assert_allclose(bones[:, k], x[:, b] - x[:, a], atol=1e-12)
    np.testing.assert_allclose(chain.C.sum(axis=0), 0.0)  # bones carry no translation
    np.testing.assert_allclose(chain.joints(bones), x - x[:, [chain.root]], atol=1e-12)  # X = B D, root at 0
    j = chain.num_joints
    np.testing.assert_allclose(chain.C @ chain.D, np.eye(j) - np.outer(np.eye(j)[chain.root], np.ones(j)), atol=1e-12)
    np.testing.assert_allclose(chain.D_least_squares, chain.D, atol=1e-12)


def test_extra_links_are_extra_columns_and_loops_close(skeleton, rng):
    chain = KinematicChainSpace.from_skeleton(skeleton, extra_links=[("head", "foot")])
    assert chain.num_bones == skeleton.num_segments and chain.bone_names[-1] == "head->foot"
    assert np.all(chain.D[-1] == 0)
    x = rng.normal(size=(3, chain.num_joints, 3))
    bones = chain.bones(x)
    np.testing.assert_allclose(bones[:, -1], x[:, skeleton.index("foot")] - x[:, skeleton.index("head")])
    np.testing.assert_allclose(chain.joints(bones), x - x[:, [0]], atol=1e-12)  # least squares, consistent bones
    bad = bones.copy()
    bad[:, -1] += 0.3  # a link that does not close: the least-squares D spreads the mismatch
    assert not np.allclose(chain.joints(bad), chain.joints(bad, least_squares=False))


def test_from_skeleton_keeps_nearest_ancestors_on_the_cmu_skeleton():
    cmu = files("bcmocap") / "data" / "cmu"
    skeleton, motion = load_cmu(cmu / "35.asf", cmu / "35_01.amc")
    chain = KinematicChainSpace.from_skeleton(skeleton, CMU_JOINTS)
    parent = {n: chain.names[p] if p >= 0 else None for n, p in zip(chain.names, chain.parents)}
    assert parent["lfemur"] == "root" and parent["thorax"] == "root" and parent["lhumerus"] == "thorax"
    assert parent["head_end"] == "head" and parent["lwrist"] == "lradius" and parent["root"] is None
    x = np.asarray(joint_positions(skeleton, motion[:3]))[:, [skeleton.index(n) for n in CMU_JOINTS]]
    lengths = np.linalg.norm(chain.bones(x), axis=-1)
    assert np.all(lengths > 0.05) and np.ptp(lengths, axis=0).max() < 1e-4  # nearly rigid, none degenerate


@pytest.mark.parametrize(
    "names, parents, links, match",
    [
        (["a", "b", "c"], [-1, 2, 1], (), "cycle: b -> c -> b"),
        (["a", "b", "c"], [1, 2, 0], (), "exactly one root"),
        (["a", "b"], [-1, -1], (), "exactly one root"),
        (["a", "b", "c"], [-1, "a", "zz"], (), "unknown joint 'zz'"),
        (["a", "b", "a"], [-1, 0, 1], (), "duplicate joint names"),
        (["a", "b", "c"], [-1, 0, 1], [("b", "a")], "duplicates a tree bone"),
        (["a", "b", "c"], [-1, 0, 1], [("a", "c"), ("c", "a")], "given twice"),
        (["a", "b"], [-1, 0, 5], (), "2 names but 3 parents"),
    ],
)
def test_bad_topologies_are_refused(names, parents, links, match):
    with pytest.raises(ValueError, match=match):
        KinematicChainSpace.from_parents(names, parents, links)


def test_mean_pose_undoes_rotations_and_translations(rng):
    base = rng.normal(size=(7, 3))
    frames = []
    for _ in range(6):
        r = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
        frames.append(base @ r.T + rng.normal(size=3))
    mean = mean_pose(np.stack(frames))
    assert float(aligned_joint_errors(mean, base - base.mean(0))) < 1e-9


def test_mean_pose_with_a_chain_keeps_bone_lengths(scene):
    chain, joints, rest, rotations, uv = scene
    true = np.linalg.norm(chain.bones(joints[0]), axis=-1)
    plain = np.linalg.norm(chain.bones(mean_pose(joints)), axis=-1)
    kept = np.linalg.norm(chain.bones(mean_pose(joints, chain)), axis=-1)
    assert np.all(plain <= true + 1e-9) and (plain / true).min() < 0.9  # averaging shortens swinging bones
    np.testing.assert_allclose(kept, true, rtol=1e-9)
    with pytest.raises(ValueError, match="the chain has 18 joints, the frames 5"):
        mean_pose(joints[:, :5], chain)


# ---- proximal map, cameras, signs ------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(30, 6), (4, 9)])
def test_svt_equals_the_svd_proximal_map(shape, rng):
    m = rng.normal(size=shape)
    for t in (0.0, 0.7, 2.5, 100.0):
        u, s, vt = np.linalg.svd(m, full_matrices=False)
        reference = (u * np.maximum(s - t, 0)) @ vt
        np.testing.assert_allclose(singular_value_threshold(jnp.asarray(m), t), reference, atol=1e-10)
    # and it is the minimiser of ½‖X − M‖² + t‖X‖_*
    t = 0.7
    x = np.asarray(singular_value_threshold(jnp.asarray(m), t))

    def objective(z):
        return 0.5 * np.sum((z - m) ** 2) + t * np.linalg.svd(z, compute_uv=False).sum()

    for _ in range(20):
        assert objective(x) <= objective(x + 1e-3 * rng.normal(size=shape)) + 1e-12


def random_cameras(rng, frames):
    rot = Rotation.random(frames, random_state=rng.integers(1 << 30)).as_matrix()
    return rot, rng.uniform(100, 300, frames)


def test_cameras_are_weak_perspective_and_recover_exact_data(rng):
    bones = rng.normal(size=(3, 12))
    rot, scale = random_cameras(rng, 8)
    y = scale[:, None, None] * rot[:, :2] @ bones
    w = jnp.ones((8, 12))
    cams = initial_cameras(jnp.asarray(y), w, jnp.asarray(bones))
    p = np.asarray(cams.matrices())
    np.testing.assert_allclose(np.sum(p[:, 0] ** 2, -1) - np.sum(p[:, 1] ** 2, -1), 0, atol=1e-8)  # Eq. 24
    np.testing.assert_allclose(np.sum(p[:, 0] * p[:, 1], -1), 0, atol=1e-8)  # Eq. 25
    np.testing.assert_allclose(p, scale[:, None, None] * rot[:, :2], atol=1e-6)
    np.testing.assert_allclose(np.asarray(cams.rotation) @ np.swapaxes(np.asarray(cams.rotation), 1, 2), np.broadcast_to(np.eye(3), (8, 3, 3)), atol=1e-12)


def test_camera_fit_matches_scipy_on_noisy_data(rng):
    bones = rng.normal(size=(3, 10))
    rot, scale = random_cameras(rng, 3)
    y = scale[:, None, None] * rot[:, :2] @ bones + rng.normal(scale=5.0, size=(3, 2, 10))
    w = np.ones((3, 10))
    w[0, :3] = 0.0  # masked bones must not count
    cams = initial_cameras(jnp.asarray(y), jnp.asarray(w), jnp.asarray(bones), iterations=200)
    for k in range(3):
        def cost(v, k=k):
            p = np.exp(v[3]) * Rotation.from_rotvec(v[:3]).as_matrix()[:2]
            return np.sum(w[k] * (y[k] - p @ bones) ** 2)

        best = min(
            minimize(cost, np.r_[Rotation.random(random_state=s).as_rotvec(), np.log(200.0)], method="BFGS").fun
            for s in range(8)
        )
        ours = cost(np.r_[Rotation.from_matrix(np.asarray(cams.rotation[k])).as_rotvec(), np.log(float(cams.scale[k]))])
        assert ours <= best * (1 + 1e-6) + 1e-9


def test_camera_refinement_never_increases_the_error(rng):
    bones = rng.normal(size=(5, 3, 9))
    rot, scale = random_cameras(rng, 5)
    y = jnp.asarray(scale[:, None, None] * rot[:, :2] @ bones + rng.normal(size=(5, 2, 9)))
    w = jnp.ones((5, 9))
    cams = WeakPerspectiveCameras(jnp.asarray(Rotation.random(5, random_state=3).as_matrix()), jnp.full(5, 150.0))
    previous = None
    for _ in range(6):
        res = np.sum((np.asarray(y) - np.asarray(cams.matrices() @ bones)) ** 2, axis=(1, 2))
        if previous is not None:
            assert np.all(res <= previous + 1e-9)
        previous = res
        cams = fit_cameras(y, w, jnp.asarray(bones), cams, iterations=1)


def test_sign_dynamic_programming_matches_brute_force(rng):
    frames = 6
    u = rng.normal(size=(frames, 2))
    depth = np.abs(rng.normal(size=frames))
    cand = np.stack([np.c_[u, depth], np.c_[u, -depth]], 1)
    target = rng.normal(size=(frames, 3))
    mu = 0.8

    def cost(signs):
        b = cand[np.arange(frames), signs]
        return np.sum((b - target) ** 2) + mu * np.sum((b[:-2] - 2 * b[1:-1] + b[2:]) ** 2)

    best = min(itertools.product((0, 1), repeat=frames), key=lambda s: cost(np.array(s)))
    got = np.asarray(_viterbi_signs(jnp.asarray(cand), jnp.asarray(target), mu))
    assert cost(got) == pytest.approx(cost(np.array(best)), abs=1e-12)


def test_depth_smoothing_is_a_normalised_gaussian(rng):
    x = rng.normal(size=(30, 4))
    sigma = 2.0
    t = np.arange(30)
    weights = np.exp(-0.5 * ((t[:, None] - t[None, :]) / sigma) ** 2) * (np.abs(t[:, None] - t[None, :]) <= 6)
    reference = weights @ x / weights.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(_smooth_in_time(jnp.asarray(x), sigma), reference, atol=1e-12)
    np.testing.assert_allclose(_smooth_in_time(jnp.asarray(x), 0.0), x)


# ---- Algorithm 1 -----------------------------------------------------------------------------------------


@pytest.mark.slow
def test_quadruped_reconstructs(scene, solved):
    """A non-human chain (§4.3): far better than the rest pose it starts from, bone lengths recovered."""
    chain, joints, rest, rotations, uv = scene
    err = np.asarray(aligned_joint_errors(solved.joints, np.broadcast_to(joints, solved.joints.shape)))
    start = float(np.asarray(aligned_joint_errors(np.broadcast_to(rest, joints.shape), joints)).mean())
    assert err.mean() < 0.6 * start, (err.mean(), start)
    true_lengths = np.linalg.norm(chain.bones(joints[0]), axis=-1)
    assert np.median(np.abs(np.asarray(solved.bone_lengths) / true_lengths - 1)) < 0.05
    # the camera-frame reconstruction matches the image exactly in x, y up to the camera scale
    cam = np.asarray(solved.joints_camera)[..., :2] * np.asarray(solved.cameras.scale)[..., None, None]
    centred_uv = uv - uv.mean(axis=-2, keepdims=True)
    assert np.sqrt(np.mean((cam - cam.mean(-2, keepdims=True) - centred_uv) ** 2)) < 2.0  # px
    assert float(np.asarray(joint_errors(solved.joints_camera, np.einsum("pfij,fkj->pfki", rotations, joints))).mean()) < 0.08


def test_reprojection_record_and_convergence(solved):
    hist = np.asarray(solved.reprojection_px)
    it = np.asarray(solved.iterations)
    assert hist.shape == (2, 2 * KCSOptions().max_iterations + 1)
    for h, n in zip(hist, it):
        assert np.all(np.isfinite(h[: 2 * n + 1])) and np.all(np.isnan(h[2 * n + 1 :]))
        assert h[2 * n] < 0.2 * h[0]  # Fig. 5: the reprojection error falls from the B0 fit
        assert np.all(h[2::2][:n] <= h[1::2][:n] + 1e-9)  # a camera step never increases it
    assert np.all(np.asarray(solved.converged) | (it == KCSOptions().max_iterations))


def test_batched_equals_single(scene, solved):
    chain, joints, rest, rotations, uv = scene
    single = reconstruct(chain, uv[1], rest)
    np.testing.assert_allclose(np.asarray(single.joints), np.asarray(solved.joints[1]), atol=1e-8)
    assert single.joints.shape == (FRAMES, chain.num_joints, 3) and single.iterations.shape == ()


def test_eq21_as_printed_keeps_the_depths_of_b0(scene):
    """Without the constancy projection the minimum-nuclear-norm deviation has no depth in the camera frame."""
    chain, joints, rest, rotations, uv = scene
    options = KCSOptions(constant_bone_lengths=False, nuclear_weight=0.0, max_iterations=3)
    res = reconstruct(chain, uv[0], rest, options=options)
    b0 = chain.bones(rest)
    deviation = np.asarray(res.cameras.rotation) @ np.swapaxes(np.asarray(res.bones) - b0, -1, -2)
    assert np.abs(deviation[:, 2]).max() < 1e-9 < np.abs(deviation[:, :2]).max()


def test_missing_joints_are_masked(scene, solved):
    chain, joints, rest, rotations, uv = scene
    rng = np.random.default_rng(3)
    holes = uv[1].copy()
    holes[rng.random(holes.shape[:2]) < 0.1] = np.nan  # 10 % of the joints missing
    holes[5] = np.nan  # and a whole frame
    res = reconstruct(chain, holes, rest)
    start = float(np.asarray(aligned_joint_errors(np.broadcast_to(rest, joints.shape), joints)).mean())
    err = np.asarray(aligned_joint_errors(res.joints, joints))
    assert np.all(np.isfinite(np.asarray(res.joints)))
    assert err.mean() < 0.85 * start
    # the same holes given as a mask
    mask = np.isfinite(holes).all(-1)
    masked = reconstruct(chain, np.where(mask[..., None], uv[1], 1e6), rest, mask=mask)
    np.testing.assert_allclose(np.asarray(masked.joints), np.asarray(res.joints), atol=1e-8)


def test_bad_input_gives_clear_errors(scene):
    chain, joints, rest, rotations, uv = scene
    with pytest.raises(ValueError, match=r"joints_2d must have shape \(\.\.\., F, 18, 2\)"):
        reconstruct(chain, uv[0, :, :5], rest)
    with pytest.raises(ValueError, match=r"joints_2d must have shape"):
        reconstruct(chain, uv[0, ..., :1], rest)
    with pytest.raises(ValueError, match=r"mean_pose must have shape \(\.\.\., 18, 3\)"):
        reconstruct(chain, uv[0], rest[:, :2])
    with pytest.raises(ValueError, match="mean_pose holds NaN"):
        reconstruct(chain, uv[0], np.full_like(rest, np.nan))
    bad = uv[0].copy()
    bad[2, 3, 0] = np.inf
    with pytest.raises(ValueError, match=r"infinite value at index \(2, 3, 0\)"):
        reconstruct(chain, bad, rest)
    with pytest.raises(ValueError, match="no frame with at least 2 observed bones"):
        reconstruct(chain, np.full_like(uv[0], np.nan), rest)
    with pytest.raises(ValueError, match=r"mask must have shape \(40, 18\)"):
        reconstruct(chain, uv[0], rest, mask=np.ones((40, 17), bool))
    with pytest.raises(ValueError, match="shape_steps .* multiple of sign_every"):
        KCSOptions(shape_steps=7)


def test_motion_from_joints_reproduces_rigid_joints(scene):
    chain, joints, rest, rotations, uv = scene
    skeleton, motion = motion_from_joints(chain, joints, rest_joints=rest)
    fk = np.asarray(joint_positions(skeleton, motion))
    order = [skeleton.index(n) for n in chain.names]
    np.testing.assert_allclose(fk[:, order], joints, atol=1e-6)


def test_smoothing_in_time_is_a_renormalised_gaussian_and_handles_short_sequences():
    from bcmocap.kcs.solve import _smooth_in_time

    x = np.random.default_rng(0).normal(size=(50, 3))
    k = np.exp(-0.5 * (np.arange(-9, 10) / 3.0) ** 2)
    k /= k.sum()
    ones = np.convolve(np.ones(50), k, "same")
    expected = np.stack([np.convolve(x[:, j], k, "same") / ones for j in range(3)], 1)
    np.testing.assert_allclose(np.asarray(_smooth_in_time(jnp.asarray(x), 3.0)), expected, atol=1e-12)
    short = np.asarray(_smooth_in_time(jnp.asarray(x[:5]), 3.0))  # shorter than the 19-tap kernel
    assert short.shape == (5, 3) and np.allclose(_smooth_in_time(jnp.ones((5, 3)), 3.0), 1.0)


def test_padding_to_a_bucket_changes_no_result(scene):
    # 37 frames with holes, solved as they are and padded to 48: the same joints, cameras, lengths, history
    chain, joints, rest, rotations, uv = scene
    seq = uv[0, :37].copy()
    seq[5:9, 3] = np.nan
    padded, plain = reconstruct(chain, seq, rest), reconstruct(chain, seq, rest, pad=False)
    assert padded.joints.shape == plain.joints.shape == (37, chain.num_joints, 3)
    assert padded.cameras.rotation.shape == (37, 3, 3) and int(padded.iterations) == int(plain.iterations)
    for got, want in ((padded.joints, plain.joints), (padded.cameras.scale, plain.cameras.scale),
                      (padded.bone_lengths, plain.bone_lengths), (padded.reprojection_px, plain.reprojection_px)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-8, equal_nan=True)


def test_padded_lengths_are_few():
    from bcmocap.kcs.solve import padded_length

    lengths = [padded_length(f) for f in range(3, 2001)]
    assert all(f <= size <= max(16, 1.5 * f) for f, size in zip(range(3, 2001), lengths))
    assert sorted(set(lengths)) == [16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512, 768, 1024, 1536, 2048]


def test_a_pool_s_mean_pose_is_kept_in_a_file_keyed_by_the_pool(scene, tmp_path, monkeypatch):
    from bcmocap.kcs import prior
    from bcmocap.kcs.prior import pool_mean_pose

    chain, joints, rest, rotations, uv = scene
    pool = {"a": joints[:30], "b": joints[10:]}
    first = pool_mean_pose(pool, chain, max_frames=20, folder=tmp_path)
    sub = [x[np.linspace(0, len(x) - 1, 20).astype(int)] for x in pool.values()]
    np.testing.assert_allclose(first, mean_pose(sub, chain), atol=1e-12)
    files = list(tmp_path.glob("kcs-prior-*.npz"))
    assert len(files) == 1

    def fail(*args, **kwargs):
        raise AssertionError("computed again")

    monkeypatch.setattr(prior, "mean_pose", fail)
    np.testing.assert_array_equal(pool_mean_pose(pool, chain, max_frames=20, folder=tmp_path), first)  # read back
    with pytest.raises(AssertionError, match="computed again"):  # another pool: another key
        pool_mean_pose({"a": joints[:30], "b": joints[11:]}, chain, max_frames=20, folder=tmp_path)
    with pytest.raises(AssertionError, match="computed again"):  # other settings
        pool_mean_pose(pool, chain, max_frames=None, folder=tmp_path)
    monkeypatch.undo()
    files[0].write_bytes(b"damaged")
    np.testing.assert_allclose(pool_mean_pose(pool, chain, max_frames=20, folder=tmp_path), first, atol=1e-12)
    with pytest.raises(ValueError, match="no trial"):
        pool_mean_pose({}, chain)


@pytest.mark.slow  # two more compilations of the solver (8 s)
def test_keypoint_smoothing_averages_each_observed_bone_and_helps_on_jittery_input(scene):
    # 3 px of independent jitter per frame on the quadruped: smoothing the observed bones over time (σ 3 frames)
    # brings the 3-D error down; with it, padding still changes nothing
    chain, joints, rest, rotations, uv = scene
    noisy = uv[0] + np.random.default_rng(3).normal(scale=3.0, size=uv[0].shape)
    noisy[10:14, 2] = np.nan
    errors = {}
    for sigma in (0.0, 3.0):
        options = KCSOptions(keypoint_smoothing=sigma)
        result = reconstruct(chain, noisy, rest, options=options)
        errors[sigma] = float(np.asarray(aligned_joint_errors(result.joints, joints)).mean())
        if sigma:
            plain = reconstruct(chain, noisy, rest, options=options, pad=False)
            # to the rounding that 30 iterations on noisy input amplify (the programs differ in shape): 0.01 mm
            np.testing.assert_allclose(np.asarray(result.joints), np.asarray(plain.joints), atol=1e-5)
    assert errors[3.0] < 0.9 * errors[0.0], errors  # 50.5 -> 37.6 mm (42.0 -> 34.7 with the lengths' sum free)
    with pytest.raises(ValueError, match="keypoint_smoothing"):
        KCSOptions(keypoint_smoothing=-1.0)


def test_known_bone_lengths_are_held_and_carry_the_error_the_estimated_ones_leave(scene, solved):
    # the quadruped with its true bone lengths given (as if measured on the animal): the bones keep them (the relaxed
    # projection's mean over the sequence) and the 3-D error falls below that with estimated lengths (22.9 -> 16.5 mm)
    chain, joints, rest, rotations, uv = scene
    true_lengths = np.linalg.norm(chain.bones(joints[0]), axis=-1)
    known = reconstruct(chain, uv, rest, bone_lengths=true_lengths)
    errors = [float(np.asarray(aligned_joint_errors(r.joints, np.broadcast_to(joints, r.joints.shape))).mean())
              for r in (solved, known)]
    assert errors[1] < 0.85 * errors[0], errors
    np.testing.assert_allclose(np.asarray(known.bone_lengths), np.broadcast_to(true_lengths, (2, len(true_lengths))),
                               rtol=0.02)
    # one set of lengths per camera path, each held on its own path
    per_path = reconstruct(chain, uv, rest, bone_lengths=np.stack([true_lengths, 1.1 * true_lengths]))
    np.testing.assert_allclose(np.asarray(per_path.bone_lengths), np.stack([true_lengths, 1.1 * true_lengths]), rtol=0.02)
    for bad, match in ((true_lengths[:-1], r"bone_lengths must have shape \(\.\.\., %d\)" % len(true_lengths)),
                       (np.stack([true_lengths] * 3), "does not broadcast to the batch shape"),
                       (-true_lengths, "positive and finite"),
                       (np.where(np.arange(len(true_lengths)) == 0, np.nan, true_lengths), "positive and finite")):
        with pytest.raises(ValueError, match=match):
            reconstruct(chain, uv, rest, bone_lengths=bad)
    with pytest.raises(ValueError, match="constant_bone_lengths=True"):
        reconstruct(chain, uv, rest, options=KCSOptions(constant_bone_lengths=False), bone_lengths=true_lengths)


def test_prior_scale_holds_the_lengths_sum_to_the_initial_configurations(scene, solved):
    # weak perspective does not observe the scale: with prior_scale the bones' lengths sum to the mean pose's (here
    # the quadruped's rest pose, its true lengths), where left free they drift with the cameras' scales
    chain, joints, rest, rotations, uv = scene
    prior_sum = np.linalg.norm(chain.bones(rest), axis=-1).sum()
    free = reconstruct(chain, uv, rest, options=KCSOptions(prior_scale=False))
    held = solved  # the default
    drift = [abs(float(np.asarray(r.bone_lengths).sum(-1).mean()) / prior_sum - 1.0) for r in (free, held)]
    assert drift[1] < 2e-3 and drift[1] < drift[0], drift
    # (not a gain everywhere: here the 3-D error goes from 21.6 to 22.9 mm, where subject 35's walks gain 2.2 mm on
    # average, every one of the 23)
    errors = [float(np.asarray(aligned_joint_errors(r.joints, np.broadcast_to(joints, r.joints.shape))).mean())
              for r in (free, held)]
    assert errors[1] < 1.1 * errors[0], errors
