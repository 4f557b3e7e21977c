"""Tests for bcmocap.cameras: round trips, references (cv2.fisheye, pycolmap), derivatives, masks."""

import jax

jax.config.update("jax_enable_x64", True)

import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.flatten_util import ravel_pytree

from bcmocap.cameras import (
    FISHEYE_ANGLE_LIMIT,
    CameraModel,
    FOVCamera,
    OpenCVFisheyeCamera,
    PinholeCamera,
    camera_at,
    stack_cameras,
)
from bcmocap.io.colmap import from_pycolmap, to_pycolmap
from bcmocap.io.opencv_calibration import read_opencv_fisheye_calibration, write_opencv_fisheye_calibration

DATA = Path(__file__).parent / "data" / "fisheye"
JEVOIS_YML = DATA / "jevois120_circlegrid_calibration.yml"
W, H = 640, 360


def fov_camera(omega=1.8, f=(230.0, 231.5), c=(319.2, 180.7)) -> FOVCamera:
    return FOVCamera(W, H, focal=f, principal_point=c, omega=omega)


def kb_camera(k=(0.02, -0.004, 0.0006, -4e-5), f=(215.0, 214.0), c=(320.3, 179.4)) -> OpenCVFisheyeCamera:
    # Roughly equidistant: 85 deg off-axis lands ~ 325 px from the centre, a 170 deg lens at 640x360.
    return OpenCVFisheyeCamera(W, H, focal=f, principal_point=c, distortion=k)


def jevois_camera() -> OpenCVFisheyeCamera:
    return read_opencv_fisheye_calibration(JEVOIS_YML, image_size=(640, 480))


def pinhole_camera() -> PinholeCamera:
    return PinholeCamera(W, H, focal=(300.0, 301.0), principal_point=(319.5, 179.5))


FISHEYES = {
    "fov_w1.0": lambda: fov_camera(1.0, f=(180.0, 180.0)),
    "fov_w1.8": fov_camera,
    "fov_w2.5": lambda: fov_camera(2.5, f=(500.0, 501.0)),
    "kb": kb_camera,
    "kb_jevois": jevois_camera,
}


def rays(theta, phi):
    theta, phi = np.asarray(theta), np.asarray(phi)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


N_RAYS = 500  # one size everywhere: each jitted helper then compiles once per camera class


def sample_rays(max_deg, seed=0, min_deg=0.0, n=N_RAYS):
    rng = np.random.default_rng(seed)
    theta = np.radians(rng.uniform(min_deg, max_deg, n))
    theta[:3] = np.radians([min_deg, max_deg, 0.5 * (min_deg + max_deg)])
    return rays(theta, rng.uniform(0, 2 * np.pi, n)), theta


@jax.jit
def _roundtrip(cam: CameraModel, points):
    uv, valid = cam.project(points)
    return uv, valid, cam.unproject(uv)


@jax.jit
def _pixel_roundtrip(cam: CameraModel, uv):
    ray = cam.unproject(uv)
    return *cam.project(ray), ray


# ----------------------------------------------------------------------------------------------
# 1. Round trips


@pytest.mark.parametrize("name", FISHEYES)
def test_unproject_project_roundtrip_170deg(name):
    cam = FISHEYES[name]()
    r, _ = sample_rays(85.0)
    depth = np.random.default_rng(1).uniform(0.1, 20.0, (len(r), 1))
    uv, valid, back = _roundtrip(cam, r * depth)
    assert bool(valid.all())
    np.testing.assert_allclose(back, r, atol=1e-9, rtol=0)


@pytest.mark.parametrize("omega", [1.0, 1.8, 2.5])
def test_fov_roundtrip_beyond_90deg(omega):
    cam = fov_camera(omega)
    r, _ = sample_rays(math.degrees(FISHEYE_ANGLE_LIMIT), seed=2, min_deg=85.0)
    uv, valid, back = _roundtrip(cam, 2.0 * r)
    assert bool(valid.all())
    np.testing.assert_allclose(back, r, atol=1e-9, rtol=0)
    # Image radius keeps growing with theta (no fold at 90 deg).
    theta = np.linspace(0.0, 3.0, N_RAYS)
    uv_line, _, _ = _roundtrip(cam, rays(theta, np.zeros_like(theta)))
    assert np.all(np.diff(np.asarray(uv_line[:, 0])) > 0)


def test_kb_roundtrip_beyond_90deg():
    cam = kb_camera()
    r, _ = sample_rays(150.0, seed=3, min_deg=85.0)
    uv, valid, back = _roundtrip(cam, r)
    assert bool(valid.all())
    np.testing.assert_allclose(back, r, atol=1e-9, rtol=0)


@pytest.mark.parametrize("name", [*FISHEYES, "pinhole"])
def test_project_unproject_pixels(name):
    cam = pinhole_camera() if name == "pinhole" else FISHEYES[name]()
    u, v = np.meshgrid(np.linspace(-0.5, cam.width - 0.5, 23), np.linspace(-0.5, cam.height - 0.5, 17))
    uv = np.stack([u.ravel(), v.ravel()], -1)
    uv2, valid, ray = _pixel_roundtrip(cam, uv)
    assert bool(valid.all())
    np.testing.assert_allclose(uv2, uv, atol=1e-8, rtol=0)
    np.testing.assert_allclose(np.linalg.norm(ray, axis=-1), 1.0, atol=1e-14)


@settings(max_examples=60, deadline=None, database=None)
@given(
    theta_deg=st.floats(0.0, 85.0),
    phi=st.floats(0.0, 2 * math.pi),
    depth=st.floats(1e-3, 1e3),
    omega=st.floats(0.0, 2.8),
    k1=st.floats(-0.05, 0.05),
)
def test_roundtrip_property(theta_deg, phi, depth, omega, k1):
    r = rays(math.radians(theta_deg), phi)
    for cam in (fov_camera(omega), kb_camera(k=(k1, 0.0, 0.0, 0.0))):
        _, valid, back = _roundtrip(cam, depth * r)
        assert bool(valid)
        np.testing.assert_allclose(back, r, atol=1e-9, rtol=0)


# ----------------------------------------------------------------------------------------------
# 2. References


@pytest.mark.parametrize("maker, max_deg", [(kb_camera, 80.0), (jevois_camera, 50.0)])
def test_kb_matches_cv2_fisheye(maker, max_deg):
    # The jevois polynomial sends 80 deg to ~5e4 px; its 640x480 image ends near 47 deg.
    cv2 = pytest.importorskip("cv2")
    cam = maker()
    r, _ = sample_rays(max_deg, seed=4)
    pts = r * np.random.default_rng(5).uniform(0.5, 5.0, (len(r), 1))
    (fx, fy), (cx, cy) = np.asarray(cam.focal), np.asarray(cam.principal_point)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    ref, _ = cv2.fisheye.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), K, np.asarray(cam.distortion))
    uv, valid, _ = _roundtrip(cam, pts)
    assert bool(valid.all())
    np.testing.assert_allclose(uv, ref[:, 0, :], atol=1e-6, rtol=1e-13)


@pytest.mark.parametrize(
    "maker", [fov_camera, lambda: fov_camera(2.5), kb_camera, jevois_camera, pinhole_camera]
)
def test_matches_pycolmap(maker):
    pytest.importorskip("pycolmap")
    cam = maker()
    pc = to_pycolmap(cam)
    max_deg = 60.0 if isinstance(cam, PinholeCamera) else 80.0
    r, _ = sample_rays(max_deg, seed=6)
    pts = r * np.random.default_rng(7).uniform(0.5, 5.0, (len(r), 1))
    uv, valid, ray = _roundtrip(cam, pts)
    assert bool(valid.all())
    ref = pc.img_from_cam(pts) - 0.5
    if isinstance(cam, FOVCamera):
        # COLMAP's FOV model swaps the closed form for a 2nd-order series when tan(theta) < 0.01,
        # off by up to ~1e-5 px there for large omega; check those points against the closed form.
        tan_theta = np.linalg.norm(pts[:, :2], axis=-1) / pts[:, 2]
        near = tan_theta < 0.01
        assert near.sum() >= 1
        a = 2 * np.tan(float(cam.omega) / 2)
        factor = np.arctan(a * tan_theta) / (np.maximum(tan_theta, 1e-300) * float(cam.omega))
        exact = np.asarray(cam.principal_point) + np.asarray(cam.focal) * pts[:, :2] / pts[:, 2:] * factor[:, None]
        exact[tan_theta == 0] = np.asarray(cam.principal_point)
        np.testing.assert_allclose(uv, exact, atol=1e-9, rtol=0)
        np.testing.assert_allclose(uv[near], ref[near], atol=3e-5, rtol=0)
        np.testing.assert_allclose(uv[~near], ref[~near], atol=1e-6, rtol=1e-13)
    else:
        np.testing.assert_allclose(uv, ref, atol=1e-6, rtol=1e-13)
    # cam_from_img returns normalised (x/z, y/z); compare on pixels inside the image.
    inside = np.asarray(cam.in_image(uv))
    xy = pc.cam_from_img(np.asarray(uv)[inside] + 0.5)
    ray = np.asarray(ray)[inside]
    np.testing.assert_allclose(ray[:, :2] / ray[:, 2:], xy, atol=1e-9, rtol=1e-9)
    np.testing.assert_allclose(xy, pts[inside, :2] / pts[inside, 2:], atol=1e-8, rtol=1e-8)


def test_pycolmap_roundtrip_and_models():
    pycolmap = pytest.importorskip("pycolmap")
    for cam in (fov_camera(), kb_camera(), pinhole_camera(), fov_camera(0.0)):
        pc = to_pycolmap(cam)
        back = from_pycolmap(pc)
        assert type(back) is type(cam) and (back.width, back.height) == (cam.width, cam.height)
        for a, b in zip(jax.tree.leaves(cam), jax.tree.leaves(back)):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    assert to_pycolmap(fov_camera()).model.name == "FOV"
    assert to_pycolmap(kb_camera()).model.name == "OPENCV_FISHEYE"
    np.testing.assert_allclose(to_pycolmap(pinhole_camera()).params, [300.0, 301.0, 320.0, 180.0])
    simple_pc = pycolmap.Camera(model="SIMPLE_PINHOLE", width=64, height=48, params=[50.0, 32.0, 24.0])
    simple = from_pycolmap(simple_pc)
    assert isinstance(simple, PinholeCamera)
    np.testing.assert_allclose(simple.focal, [50.0, 50.0])
    np.testing.assert_allclose(simple.principal_point, [31.5, 23.5])
    radial = pycolmap.Camera(model="SIMPLE_RADIAL", width=64, height=48, params=[50.0, 32.0, 24.0, 0.1])
    with pytest.raises(ValueError, match="SIMPLE_RADIAL"):
        from_pycolmap(radial)
    with pytest.raises(ValueError, match="single camera"):
        to_pycolmap(stack_cameras([fov_camera(), fov_camera()]))


# ----------------------------------------------------------------------------------------------
# 3. Derivatives against central finite differences


def _fd_jacobian(f, x, h):
    x = np.asarray(x, dtype=np.float64)
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e.flat[i] = h
        cols.append((np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * h))
    return np.stack(cols, axis=-1)


def _flat_jacobian(jac_tree, n_out):
    """Jacobian pytree (leaves (n_out, *leaf_shape)) -> (n_out, n_params) in ravel_pytree order."""
    return np.concatenate([np.asarray(x).reshape(n_out, -1) for x in jax.tree.leaves(jac_tree)], axis=1)


def _assert_jac_close(jac, fd, rtol=1e-6):
    scale = max(float(np.abs(fd).max()), 1e-300)
    np.testing.assert_allclose(jac, fd, atol=rtol * scale, rtol=0)


POINTS = {
    "axis": [0.0, 0.0, 2.0],
    "near_axis": [1e-9, -2e-9, 1.5],
    "generic": [0.4, -0.3, 1.1],
    "edge_85deg": rays(math.radians(85.0), 0.7) * 3.0,
    "behind_120deg": rays(math.radians(120.0), -2.0),
}

JAC_CAMERAS = {
    "fov": fov_camera,
    "fov_w2.5": lambda: fov_camera(2.5),
    "fov_small_w": lambda: fov_camera(0.004),
    "fov_tiny_w": lambda: fov_camera(1e-6),
    "fov_w0": lambda: fov_camera(0.0),
    "kb": kb_camera,
    "kb_jevois": jevois_camera,
    "pinhole": pinhole_camera,
}


@jax.jit
def _project_jacobians(cam, p):
    def f(cam, p):
        return cam.project(p)[0]

    return f(cam, p), jax.jacfwd(f, argnums=(0, 1))(cam, p), jax.jacrev(f, argnums=1)(cam, p)


@pytest.mark.parametrize("cam_name", JAC_CAMERAS)
@pytest.mark.parametrize("point", POINTS)
def test_project_jacobians_vs_finite_differences(cam_name, point):
    cam = JAC_CAMERAS[cam_name]()
    p = np.asarray(POINTS[point], dtype=np.float64)
    _, valid = cam.project(p)
    if not bool(valid):
        assert cam_name in ("pinhole", "fov_tiny_w", "fov_w0") and point == "behind_120deg"
        return
    _, (j_cam, j_point), j_point_rev = _project_jacobians(cam, p)
    np.testing.assert_allclose(j_point, j_point_rev, rtol=1e-12, atol=1e-12)

    # With respect to the point: smooth everywhere inside the valid domain, also on the axis.
    fd = _fd_jacobian(lambda x: cam.project(x)[0], p, h=1e-6)
    _assert_jac_close(j_point, fd)

    # With respect to all intrinsics (flattened leaves; static width/height stay put).
    flat, unravel = ravel_pytree(cam)
    fd = _fd_jacobian(lambda x: unravel(x).project(p)[0], flat, h=1e-6)
    _assert_jac_close(_flat_jacobian(j_cam, 2), fd)


@jax.jit
def _unproject_jacobians(cam, uv):
    """Ray, its Jacobians with respect to the camera (pytree) and the pixel."""
    return cam.unproject(uv), jax.jacfwd(lambda c, u: c.unproject(u), argnums=(0, 1))(cam, uv)


@pytest.mark.parametrize("cam_name", ["fov", "fov_small_w", "fov_w0", "kb", "pinhole"])
def test_unproject_jacobians_vs_finite_differences(cam_name):
    cam = JAC_CAMERAS[cam_name]()
    for uv in (np.asarray(cam.principal_point), np.asarray(cam.principal_point) + [150.0, -90.0]):
        _, (j_cam, j) = _unproject_jacobians(cam, jnp.asarray(uv))
        _assert_jac_close(j, _fd_jacobian(cam.unproject, uv, h=1e-4))
        flat, unravel = ravel_pytree(cam)
        fd = _fd_jacobian(lambda x: unravel(x).unproject(uv), flat, h=1e-6)
        _assert_jac_close(_flat_jacobian(j_cam, 3), fd)


# ----------------------------------------------------------------------------------------------
# 4. Invalid points, masks, jit and vmap


def _loss(cam, p):
    uv, valid = cam.project(p)
    return jnp.sum(jnp.where(valid[..., None], uv, 0.0) ** 2) + jnp.sum(uv)


@jax.jit
def _project_grad_jac(cam, p):
    """Projection, gradient of a loss of it (reverse mode) and Jacobian wrt the point (forward)."""
    grads = jax.grad(_loss, argnums=(0, 1))(cam, p)
    return cam.project(p), grads, jax.jacfwd(lambda q: cam.project(q)[0])(p)


@pytest.mark.parametrize(
    "cam_name, point, reason",
    [
        ("fov", [0.0, 0.0, 0.0], "origin"),
        ("fov", [0.0, 0.0, -1.0], "back pole"),
        ("fov", rays(math.radians(179.5), 0.3), "beyond max angle"),
        ("fov_w0", [0.3, 0.1, -1.0], "behind the pinhole limit"),
        ("kb", [0.0, 0.0, 0.0], "origin"),
        ("kb", [1e-12, 0.0, -1.0], "back pole"),
        ("pinhole", [0.3, 0.1, -1.0], "behind"),
        ("pinhole", [1.0, 0.0, 0.0], "z = 0"),
        ("pinhole", [0.0, 0.0, 0.0], "origin"),
        ("pinhole", [np.nan, 0.0, 1.0], "nan"),
        ("pinhole", [np.inf, 0.0, 1.0], "inf"),
    ],
)
def test_invalid_points_are_masked_finite(cam_name, point, reason):
    cam = JAC_CAMERAS[cam_name]()
    p = jnp.asarray(point, dtype=jnp.float64)
    (uv, valid), (g_cam, g_p), jac = _project_grad_jac(cam, p)
    assert not bool(valid), reason
    np.testing.assert_allclose(uv, cam.principal_point)
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(g_cam))
    assert np.all(np.isfinite(g_p)) and np.all(g_p == 0)
    assert np.all(np.isfinite(jac))


def test_kb_max_angle_at_fold():
    # theta_d = theta (1 - 0.3 theta^2) stops increasing at theta = 1 / sqrt(0.9).
    cam = kb_camera(k=(-0.3, 0.0, 0.0, 0.0))
    max_angle = float(cam.max_angle)
    np.testing.assert_allclose(max_angle, 1 / math.sqrt(0.9), rtol=1e-9)
    theta = np.linspace(0.0, 1.2, N_RAYS)
    _, valid, _ = _roundtrip(cam, rays(theta, 0.2))
    np.testing.assert_array_equal(valid, theta <= max_angle)
    # Pixels past the fold's image radius unproject to the boundary ray, with finite derivatives.
    far = np.asarray(cam.principal_point) + [1000.0, 0.0]
    ray, (j_cam, j_uv) = _unproject_jacobians(cam, jnp.asarray(far))
    np.testing.assert_allclose(math.acos(float(ray[2])), max_angle, atol=1e-9)
    assert np.all(np.isfinite(j_uv)) and all(np.all(np.isfinite(x)) for x in jax.tree.leaves(j_cam))
    assert float(kb_camera().max_angle) == pytest.approx(FISHEYE_ANGLE_LIMIT)
    assert float(pinhole_camera().max_angle) < math.pi / 2
    assert float(fov_camera(0.0).max_angle) < math.pi / 2 < float(fov_camera(0.5).max_angle)


def test_in_image():
    cam = fov_camera()
    uv = jnp.array([[-0.5, -0.5], [639.5, 359.5], [-0.51, 10.0], [10.0, 359.6], [320.0, 180.0]])
    np.testing.assert_array_equal(cam.in_image(uv), [True, True, False, False, True])


@jax.jit
def _batched_ops(batched, pts):
    def one(cam):
        uv, valid = cam.project(pts)
        return uv, valid, cam.unproject(uv), cam.max_angle

    grad = jax.grad(lambda c: jnp.sum(jax.vmap(_loss, in_axes=(0, None))(c, pts)))(batched)
    return jax.vmap(one)(batched), grad, camera_at(batched, 1).project(pts)[0]


@pytest.mark.parametrize(
    "makers", [(fov_camera, lambda: fov_camera(2.5), lambda: fov_camera(0.0)), (kb_camera, jevois_camera)]
)
def test_batched_cameras_vmap_jit(makers):
    cams = [m() for m in makers]
    if any(c.height != cams[0].height for c in cams):
        cams = [type(c)(W, H, c.focal, c.principal_point, c.distortion) for c in cams]
    batched = stack_cameras(cams)
    assert batched.focal.shape == (len(cams), 2) and batched.batch_shape == (len(cams),)
    pts = sample_rays(85.0, seed=8)[0]
    pts[-2:] = [[0.0, 0.0, 0.0], [0.0, 0.0, -1.0]]  # the camera centre, the back pole: invalid
    (uv_b, valid_b, rays_b, max_b), g, single_uv = _batched_ops(batched, pts)
    for i, cam in enumerate(cams):
        uv, valid, _ = _roundtrip(cam, pts)
        np.testing.assert_allclose(uv_b[i], uv, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(valid_b[i], valid)
        np.testing.assert_allclose(rays_b[i][:-2], pts[:-2], atol=1e-9)
        np.testing.assert_allclose(max_b[i], cam.max_angle)
        assert type(camera_at(batched, i)) is type(cam)
    np.testing.assert_allclose(single_uv, uv_b[1], rtol=0, atol=1e-12)
    assert np.all(np.isfinite(uv_b)) and not bool(valid_b[:, -2:].any())
    # Gradients with respect to the whole batch, invalid points included, are finite.
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(g))


def test_stack_cameras_errors():
    with pytest.raises(ValueError, match="FOVCamera.*PinholeCamera|PinholeCamera.*FOVCamera"):
        stack_cameras([fov_camera(), pinhole_camera()])
    other = FOVCamera(320, 240, focal=(1.0, 1.0), principal_point=(1.0, 1.0), omega=1.0)
    with pytest.raises(ValueError, match="image size 320x240"):
        stack_cameras([fov_camera(), other])
    with pytest.raises(ValueError, match="at least one"):
        stack_cameras([])


# ----------------------------------------------------------------------------------------------
# 5. OpenCV calibration files


def test_read_jevois_calibration():
    cam = jevois_camera()
    assert isinstance(cam, OpenCVFisheyeCamera) and (cam.width, cam.height) == (640, 480)
    np.testing.assert_allclose(cam.focal, [3.8875198441924482e02, 3.8805385348085332e02], rtol=1e-15)
    np.testing.assert_allclose(cam.principal_point, [3.0742201237082173e02, 2.3704844976450769e02], rtol=1e-15)
    np.testing.assert_allclose(
        cam.distortion,
        [-3.4284579156433487e-01, 1.6275344817769009e00, -5.8813928551680892e00, 8.7864713556487448e00],
        rtol=1e-15,
    )
    # The whole image of this 120 deg lens unprojects and reprojects.
    u, v = np.meshgrid(np.linspace(0, 639, 9), np.linspace(0, 479, 7))
    uv = np.stack([u.ravel(), v.ravel()], -1)
    back, valid, _ = _pixel_roundtrip(cam, uv)
    assert bool(valid.all())
    np.testing.assert_allclose(back, uv, atol=1e-8)


def test_calibration_without_size_needs_image_size():
    with pytest.raises(ValueError, match=r"jevois120_circlegrid_calibration\.yml.*image_width.*image_size"):
        read_opencv_fisheye_calibration(JEVOIS_YML)


def test_write_read_roundtrip(tmp_path):
    cam = kb_camera()
    for ext in ("yml", "xml"):
        path = tmp_path / f"calib.{ext}"
        write_opencv_fisheye_calibration(path, cam)
        back = read_opencv_fisheye_calibration(path)
        assert (back.width, back.height) == (cam.width, cam.height)
        for a, b in zip(jax.tree.leaves(cam), jax.tree.leaves(back)):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="OpenCVFisheyeCamera"):
        write_opencv_fisheye_calibration(tmp_path / "x.yml", fov_camera())


def test_calibration_file_errors(tmp_path):
    text = JEVOIS_YML.read_text()
    no_dist = tmp_path / "no_dist.yml"
    no_dist.write_text(text.split("dist_coeff")[0])
    with pytest.raises(ValueError, match=r"no_dist\.yml.*dist_coeff"):
        read_opencv_fisheye_calibration(no_dist, image_size=(640, 480))
    no_k = tmp_path / "no_k.yml"
    no_k.write_text("%YAML:1.0\n---\n" + "dist_coeff" + text.split("dist_coeff")[1])
    with pytest.raises(ValueError, match=r"no_k\.yml.*camera_matrix"):
        read_opencv_fisheye_calibration(no_k, image_size=(640, 480))
    with pytest.raises(ValueError, match=r"missing\.yml.*does not exist"):
        read_opencv_fisheye_calibration(tmp_path / "missing.yml", image_size=(640, 480))
    bad_d = tmp_path / "bad_d.yml"
    bad_d.write_text(text.replace("rows: 4", "rows: 2").replace(
        "-5.8813928551680892e+00, 8.7864713556487448e+00", ""
    ).replace("1.6275344817769009e+00,", "1.6275344817769009e+00"))
    with pytest.raises(ValueError, match=r"bad_d\.yml.*dist_coeff.*4 coefficients"):
        read_opencv_fisheye_calibration(bad_d, image_size=(640, 480))


# ----------------------------------------------------------------------------------------------
# 6. Construction errors


def _fov(**kw):
    args = {"width": W, "height": H, "focal": (1.0, 1.0), "principal_point": (1.0, 1.0), "omega": 1.0}
    return FOVCamera(**{**args, **kw})


def _kb(**kw):
    args = {"width": W, "height": H, "focal": (1.0, 1.0), "principal_point": (1.0, 1.0)}
    args["distortion"] = np.zeros(4)
    return OpenCVFisheyeCamera(**{**args, **kw})


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: _fov(focal=(1.0, 1.0, 1.0)), r"FOVCamera\.focal must have shape \(\.\.\., 2\).*got shape \(3,\)"),
        (lambda: _fov(principal_point=1.0), r"FOVCamera\.principal_point must have shape"),
        (lambda: _fov(omega=(1.0, 1.0)), r"FOVCamera.*batch.*omega \(2,\)"),
        (lambda: _fov(focal=(1.0, -1.0)), r"FOVCamera\.focal must be positive"),
        (lambda: _fov(principal_point=(np.nan, 1.0)), r"FOVCamera\.principal_point must be finite"),
        (lambda: _fov(omega=3.5), r"FOVCamera\.omega must be finite and in \[0, pi\)"),
        (lambda: _fov(omega=-0.1), r"FOVCamera\.omega"),
        (lambda: _fov(width=0), r"FOVCamera\.width must be a positive integer"),
        (lambda: _fov(height=360.5), r"FOVCamera\.height must be a positive integer"),
        (lambda: _kb(distortion=(0.1, 0.0, 0.0)), r"OpenCVFisheyeCamera\.distortion must have shape.*\(3,\)"),
        (lambda: _kb(distortion=(0.1, 0.0, np.inf, 0.0)), r"OpenCVFisheyeCamera\.distortion must be finite"),
        (lambda: _kb(focal=[[1.0, 1.0]]), r"OpenCVFisheyeCamera.*batch.*focal \(1, 2\)"),
        (lambda: PinholeCamera(W, H, focal=(0.0, 1.0), principal_point=(1.0, 1.0)), r"PinholeCamera\.focal"),
    ],
)
def test_construction_errors(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_method_shape_errors_and_traced_construction():
    cam = fov_camera()
    with pytest.raises(ValueError, match=r"points_cam.*\(\.\.\., 3\).*\(4, 2\)"):
        cam.project(jnp.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"pixels.*\(\.\.\., 2\)"):
        jax.jit(lambda uv: cam.unproject(uv))(jnp.zeros((3,)))

    # Constructing from traced values inside jit still checks shapes (values can't be checked).
    @jax.jit
    def make_and_project(f, w):
        cam = FOVCamera(W, H, focal=f, principal_point=(320.0, 180.0), omega=w)
        return cam.project(jnp.array([0.1, 0.2, 1.0]))

    uv, valid = make_and_project(jnp.array([200.0, 200.0]), 1.5)
    assert bool(valid) and np.all(np.isfinite(uv))
    with pytest.raises(ValueError, match=r"FOVCamera\.focal"):
        make_and_project(jnp.array([200.0, 200.0, 1.0]), 1.5)


def test_truncated_calibration_files_are_refused_naming_the_file(tmp_path):
    """Every prefix of a valid file (OpenCV's parser fails in several ways) is a ValueError naming it."""
    path = tmp_path / "calib.yml"
    write_opencv_fisheye_calibration(path, kb_camera())
    text = path.read_text()
    cut = tmp_path / "cut.yml"
    for n in range(0, len(text) - 1, 5):
        cut.write_text(text[:n])
        with pytest.raises(ValueError, match=r"cut\.yml: "):
            read_opencv_fisheye_calibration(cut)
