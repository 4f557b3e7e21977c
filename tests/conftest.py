"""Shared small fixtures: a 6-segment skeleton with every joint type, a 6-camera FOV rig, motions, points.

Everything here is tiny on purpose (jit compiles dominate the test time) and deterministic.
"""

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np
import pytest

from bcmocap.cameras import FOVCamera
from bcmocap.geometry import SE3, SO3
from bcmocap.kinematics import Motion, Rig, Skeleton
import bcmocap.compilation_cache
from bcmocap.native_crashes import load_pycolmap

# pycolmap through bcmocap: its import's glog signal handler would hang a test process that faults in native code
# (CI's time then runs out) where the default ends it with faulthandler's report.
load_pycolmap()
# The test processes read JAX's persistent cache but never write it (commands run in them turn it on): in a worker
# that had compiled and freed many programs, serializing one threw a C++ exception whose unwinding faulted (CI hung
# on it under glog's handler). Commands run as subprocesses write it as usual.
bcmocap.compilation_cache.MIN_COMPILE_SECONDS = 1e9


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """After each test file, free JAX's compiled programs if the worker's memory mappings near the kernel's limit: a
    worker of the heavy tier compiles thousands of programs and would otherwise abort in XLA when mmap fails."""
    yield
    bcmocap.compilation_cache.release_compiled_programs()

SEGMENTS = ("pelvis", "torso", "head", "thigh", "shin", "foot")
PARENTS = (-1, 0, 1, 0, 3, 4)
TYPES = ("free", "ball", "ball", "ball", "hinge", "fixed")
OFFSETS = np.array(
    [[0.0, 0.0, 0.0], [0.0, 0.0, 0.25], [0.0, 0.02, 0.45], [0.1, 0.0, -0.08], [0.0, 0.01, -0.42], [0.0, 0.0, -0.4]]
)
# A knee axis that is neither unit length nor axis-aligned: the skeleton must normalise it.
KNEE_AXIS = np.array([2.0, 0.4, 0.0])
WIDTH, HEIGHT = 160, 120


def make_skeleton() -> Skeleton:
    axes = np.zeros((6, 3))
    axes[4] = KNEE_AXIS
    return Skeleton(SEGMENTS, PARENTS, OFFSETS, TYPES, axes)


def fov_camera(focal=70.0, omega=1.1) -> FOVCamera:
    return FOVCamera(
        WIDTH, HEIGHT, focal=(focal, focal + 0.5), principal_point=((WIDTH - 1) / 2, (HEIGHT - 1) / 2), omega=omega
    )


# (camera, segment, rotation vector of segment_from_camera, translation in the segment frame (m))
MOUNTS = (
    ("waist_front", "pelvis", (1.4, 0.1, 0.2), (0.15, 0.0, 0.05)),
    ("waist_back", "pelvis", (-1.3, 0.3, -0.1), (-0.15, 0.02, 0.05)),
    ("chest", "torso", (1.2, -0.4, 0.3), (0.12, 0.0, 0.2)),
    ("head", "head", (0.9, 0.5, -0.2), (0.1, 0.0, 0.12)),
    ("thigh", "thigh", (0.2, 1.5, 0.1), (0.1, 0.0, -0.2)),
    ("shin", "shin", (-0.3, 1.4, 0.4), (0.08, 0.0, -0.2)),
)


def make_rig(skeleton: Skeleton) -> Rig:
    mounts = []
    for k, (name, segment, rotvec, translation) in enumerate(MOUNTS):
        pose = SE3.from_rotation_and_translation(SO3.exp(np.asarray(rotvec, float)), np.asarray(translation, float))
        mounts.append((name, segment, pose, fov_camera(focal=65.0 + 3 * k, omega=1.0 + 0.05 * k)))
    return Rig.from_mounts(skeleton, mounts)


def random_quaternions(rng: np.random.Generator, shape, max_angle=np.pi) -> np.ndarray:
    """Unit quaternions ``(*shape, 4)`` of random axes and angles up to ``max_angle`` (either sign)."""
    axis = rng.normal(size=(*shape, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = rng.uniform(0.0, max_angle, size=shape)[..., None]
    q = np.concatenate([np.cos(angle / 2), np.sin(angle / 2) * axis], axis=-1)
    return q * rng.choice([-1.0, 1.0], size=(*shape, 1))


def random_motion(skeleton: Skeleton, num_frames: int | None, rng: np.random.Generator, max_angle=1.2) -> Motion:
    """A motion the skeleton can represent (hinges about their axis, fixed joints at identity)."""
    shape = () if num_frames is None else (num_frames,)
    q = random_quaternions(rng, (*shape, skeleton.num_segments), max_angle)
    rot = np.asarray(skeleton.project_rotations(q))
    return Motion(rng.normal(scale=0.5, size=(*shape, 3)) + np.array([0.0, 0.0, 1.0]), rot)


def scene_points(rng: np.random.Generator, n: int = 24) -> np.ndarray:
    """``(n, 3)`` points on a shell 3–6 m around the origin (visible from anywhere on the body)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * rng.uniform(3.0, 6.0, size=(n, 1)) + np.array([0.0, 0.0, 1.0])


def central_difference(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Jacobian ``(*f(x).shape, *x.shape)`` of a numpy-valued function by central differences."""
    x = np.asarray(x, dtype=np.float64)
    f0 = np.asarray(f(x))
    out = np.zeros((*f0.shape, x.size))
    for i in range(x.size):
        step = np.zeros(x.size)
        step[i] = eps
        step = step.reshape(x.shape)
        out[..., i] = (np.asarray(f(x + step)) - np.asarray(f(x - step))) / (2 * eps)
    return out.reshape(*f0.shape, *x.shape)


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product of wxyz quaternions (numpy, broadcasting)."""
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float))
    w1, v1, w2, v2 = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate([w1 * w2 - np.sum(v1 * v2, -1, keepdims=True), w1 * v2 + w2 * v1 + np.cross(v1, v2)], -1)


def quat_conjugate(q) -> np.ndarray:
    q = np.asarray(q, float)
    return np.concatenate([q[..., :1], -q[..., 1:]], -1)


def quat_distance(a, b) -> np.ndarray:
    """Angle (rad) between rotations given as quaternions, in numpy (independent of the package)."""
    a = np.asarray(a, float) / np.linalg.norm(a, axis=-1, keepdims=True)
    b = np.asarray(b, float) / np.linalg.norm(b, axis=-1, keepdims=True)
    rel = quat_multiply(quat_conjugate(a), b)
    return 2 * np.arctan2(np.linalg.norm(rel[..., 1:], axis=-1), np.abs(rel[..., 0]))


def quat_matrix(q) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of wxyz quaternions (numpy, textbook formula)."""
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rodrigues(rotvec) -> np.ndarray:
    """Rotation matrix of a rotation vector, ``I + sin θ K + (1 − cos θ) K²``."""
    rotvec = np.asarray(rotvec, float)
    theta = np.linalg.norm(rotvec)
    if theta == 0:
        return np.eye(3)
    kx, ky, kz = rotvec / theta
    k = np.array([[0, -kz, ky], [kz, 0, -kx], [-ky, kx, 0]])
    return np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * k @ k


def se3_matrix(wxyz_xyz) -> np.ndarray:
    """``(..., 4, 4)`` homogeneous matrices of SE3 parameters (wxyz_xyz)."""
    p = np.asarray(wxyz_xyz, float)
    out = np.zeros((*p.shape[:-1], 4, 4))
    out[..., :3, :3] = quat_matrix(p[..., :4])
    out[..., :3, 3] = p[..., 4:]
    out[..., 3, 3] = 1.0
    return out


def one_line_error(capsys, command: str, *culprits: str) -> str:
    """The command's stderr, checked to be one line ``bcmocap COMMAND: ...`` that names every culprit."""
    err = capsys.readouterr().err
    assert err.startswith(f"bcmocap {command}: ") and err.count("\n") == 1, err
    assert all(c in err for c in culprits), err
    return err


@pytest.fixture(scope="session")
def skeleton() -> Skeleton:
    return make_skeleton()


@pytest.fixture(scope="session")
def rig(skeleton) -> Rig:
    return make_rig(skeleton)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
