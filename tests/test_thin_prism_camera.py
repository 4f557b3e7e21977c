"""Tests for bcmocap.cameras.ThinPrismFisheyeCamera (COLMAP's THIN_PRISM_FISHEYE): pycolmap as the reference,
round trips over the image, derivatives against finite differences, the exact Kannala-Brandt limit, batching,
clamping, errors, and its JSON and COLMAP descriptions."""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from bcmocap.cameras import OpenCVFisheyeCamera, ThinPrismFisheyeCamera, camera_at, stack_cameras
from bcmocap.io.colmap import from_pycolmap, to_pycolmap
from bcmocap.io.model_json import camera_from_dict, camera_to_dict

W, H = 640, 360
# About the studio's lens design (the Kannala-Brandt fit of the 170 deg FOV lens): image corners ~102 deg off-axis.
K = (-0.2544, 0.1091, -0.0270, 0.0028)


def unit(p=(3e-4, -2e-4), s=(2e-4, 1e-4), k=K, f=(289.3, 289.9), c=(321.2, 178.4)) -> ThinPrismFisheyeCamera:
    return ThinPrismFisheyeCamera(W, H, focal=f, principal_point=c, distortion=k, tangential=p, thin_prism=s)


def rays(theta, phi):
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def sample_rays(max_deg, n=400, seed=0):
    rng = np.random.default_rng(seed)
    theta = np.radians(rng.uniform(0.0, max_deg, n))
    theta[:2] = [0.0, np.radians(max_deg)]
    return rays(theta, rng.uniform(0, 2 * np.pi, n))


def image_grid(step=7):
    v, u = np.mgrid[-0.5 : H - 0.5 : step, -0.5 : W - 0.5 : step]
    corners = [[-0.5, -0.5], [W - 0.5, -0.5], [-0.5, H - 0.5], [W - 0.5, H - 0.5]]
    return np.concatenate([np.stack([u.ravel(), v.ravel()], axis=-1), corners])


@jax.jit
def _pixel_roundtrip(cam, uv):
    ray = cam.unproject(uv)
    return *cam.project(ray), ray


def test_matches_pycolmap():
    pycolmap = pytest.importorskip("pycolmap")
    cam = unit()
    pc = to_pycolmap(cam)
    assert pc.model.name == "THIN_PRISM_FISHEYE"
    np.testing.assert_allclose(pc.params, [289.3, 289.9, 321.7, 178.9, K[0], K[1], 3e-4, -2e-4, K[2], K[3], 2e-4, 1e-4])
    pts = sample_rays(85.0) * np.random.default_rng(1).uniform(0.5, 5.0, (400, 1))  # COLMAP: in front only
    uv, valid = cam.project(pts)
    assert bool(valid.all())
    np.testing.assert_allclose(uv, pc.img_from_cam(pts) - 0.5, atol=1e-9, rtol=0)
    xy = pc.cam_from_img(np.asarray(uv) + 0.5)
    np.testing.assert_allclose(xy, pts[:, :2] / pts[:, 2:], atol=1e-8, rtol=1e-8)
    back = from_pycolmap(pycolmap.Camera(model="THIN_PRISM_FISHEYE", width=W, height=H, params=pc.params))
    assert isinstance(back, ThinPrismFisheyeCamera)
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(cam)):
        np.testing.assert_allclose(a, b, rtol=1e-15, atol=1e-12)


def test_pixel_roundtrip_over_the_image():
    # Every pixel of the image (corners ~102 deg off-axis, beyond 90) and the pixel edges.
    cam = unit()
    uv = image_grid()
    back, valid, ray = _pixel_roundtrip(cam, jnp.asarray(uv))
    theta = np.arccos(np.asarray(ray)[:, 2])
    assert bool(valid.all()) and theta.max() > np.radians(100) and theta.max() < float(cam.max_angle)
    np.testing.assert_allclose(back, uv, atol=1e-9, rtol=0)


def test_ray_roundtrip_inside_max_angle():
    cam = unit(p=(1e-3, 8e-4), s=(-6e-4, 5e-4))  # larger terms than any manufactured unit
    points = sample_rays(175.0) * np.random.default_rng(2).uniform(0.1, 20.0, (400, 1))
    uv, valid = cam.project(points)
    assert bool(valid.all())
    back = cam.unproject(uv)
    np.testing.assert_allclose(back, points / np.linalg.norm(points, axis=-1, keepdims=True), atol=1e-9, rtol=0)


@pytest.mark.parametrize("k", [K, (0.02, -0.004, 0.0006, -4e-5), (-0.3, 0.05, -0.02, 0.0)])
def test_without_decentering_it_is_the_kannala_brandt_camera(k):
    kb = OpenCVFisheyeCamera(W, H, focal=(215.0, 214.0), principal_point=(320.3, 179.4), distortion=k)
    tp = ThinPrismFisheyeCamera(W, H, focal=(215.0, 214.0), principal_point=(320.3, 179.4), distortion=k,
                                tangential=(0.0, 0.0), thin_prism=(0.0, 0.0))
    assert float(tp.max_angle) == float(kb.max_angle)
    # Up to a degree inside a fold of theta_d (k2's at 64 deg), where theta is known only to sqrt(rounding).
    limit = min(float(kb.max_angle) - np.radians(1.0), np.radians(178.0))
    points = sample_rays(np.degrees(limit)) * 2.5
    (uv_tp, ok_tp), (uv_kb, ok_kb) = tp.project(points), kb.project(points)
    np.testing.assert_allclose(uv_tp, uv_kb, rtol=1e-13, atol=1e-12)  # the same formula, compiled apart
    np.testing.assert_array_equal(ok_tp, ok_kb)
    np.testing.assert_allclose(tp.unproject(uv_kb), kb.unproject(uv_kb), atol=1e-12, rtol=0)
    far = np.array([[5000.0, 0.0], [320.3, -4000.0]])  # beyond the image of max_angle: clamped alike
    np.testing.assert_allclose(tp.unproject(far), kb.unproject(far), atol=1e-9, rtol=0)


def test_max_angle_shrinks_only_when_the_terms_could_fold_the_image():
    folding = (0.02, -0.02, 0.0, 0.0)  # d theta_d / d theta = 0 at 106.8 deg

    def lens(p, s):
        return ThinPrismFisheyeCamera(W, H, focal=(200.0, 200.0), principal_point=(320, 180), distortion=folding,
                                      tangential=p, thin_prism=s)

    kb_limit = float(OpenCVFisheyeCamera(W, H, focal=(200.0, 200.0), principal_point=(320, 180),
                                         distortion=folding).max_angle)
    small, large = lens((1e-4, 1e-4), (1e-4, 0.0)), lens((0.01, 0.0), (0.0, 0.005))
    assert np.degrees(kb_limit) == pytest.approx(106.83, abs=0.01)
    assert kb_limit - np.radians(0.5) < float(small.max_angle) < kb_limit  # the manufactured units' order: ~0.2 deg
    assert np.radians(95) < float(large.max_angle) < float(small.max_angle)
    # Inside its max angle even the strongly decentred lens is one-to-one: rays come back from their pixels.
    points = sample_rays(np.degrees(float(large.max_angle)) - 1e-6, seed=3)
    uv, valid = large.project(points)
    assert bool(valid.all())
    np.testing.assert_allclose(large.unproject(uv), points, atol=1e-9, rtol=0)


def test_far_pixels_are_clamped_to_max_angle_with_finite_gradients():
    cam = unit(k=(0.02, -0.02, 0.0, 0.0))
    far = jnp.array([[3000.0, 180.0], [320.0, -2500.0], [-900.0, 900.0]])
    ray = np.asarray(cam.unproject(far))
    np.testing.assert_allclose(np.arccos(ray[:, 2]), float(cam.max_angle), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(ray, axis=-1), 1.0, atol=1e-12)
    grads = jax.jacfwd(lambda c, u: c.unproject(u), argnums=(0, 1))(cam, far)
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))


def _fd_jacobian(f, x, h):
    x = np.asarray(x, np.float64)
    cols = []
    for i in range(x.size):
        d = np.zeros_like(x)
        d.flat[i] = h
        cols.append((np.asarray(f(x + d)) - np.asarray(f(x - d))).ravel() / (2 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("point", [(0.0, 0.0, 1.0), (0.3, -0.2, 1.0), (0.9, 0.5, -0.2), (-0.1, 0.4, -0.8)])
def test_project_jacobians_vs_finite_differences(point):
    cam = unit()
    p = np.asarray(point)
    j_cam, j_point = jax.jacfwd(lambda c, x: c.project(x)[0], argnums=(0, 1))(cam, jnp.asarray(p))
    np.testing.assert_allclose(j_point, _fd_jacobian(lambda x: cam.project(x)[0], p, 1e-6), rtol=1e-6, atol=1e-6)
    flat, unravel = ravel_pytree(cam)
    analytic = np.concatenate([np.asarray(leaf).reshape(2, -1) for leaf in jax.tree.leaves(j_cam)], axis=1)
    np.testing.assert_allclose(analytic, _fd_jacobian(lambda x: unravel(x).project(p)[0], flat, 1e-7),
                               rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("uv", [(321.2, 178.4), (471.2, 88.4), (0.0, 359.0)])
def test_unproject_jacobians_vs_finite_differences(uv):
    cam = unit()
    uv = np.asarray(uv)
    j_cam, j_pixel = jax.jacfwd(lambda c, x: c.unproject(x), argnums=(0, 1))(cam, jnp.asarray(uv))
    np.testing.assert_allclose(j_pixel, _fd_jacobian(cam.unproject, uv, 1e-4), rtol=1e-6, atol=1e-9)
    flat, unravel = ravel_pytree(cam)
    analytic = np.concatenate([np.asarray(leaf).reshape(3, -1) for leaf in jax.tree.leaves(j_cam)], axis=1)
    np.testing.assert_allclose(analytic, _fd_jacobian(lambda x: unravel(x).unproject(uv), flat, 1e-7),
                               rtol=1e-5, atol=1e-7)


def test_batched_cameras_under_vmap_and_jit():
    cams = [unit(), unit(p=(-1e-4, 2e-4), s=(0.0, -3e-4), c=(318.0, 181.0)), unit(k=(0.02, -0.02, 0.0, 0.0))]
    batch = stack_cameras(cams)
    assert batch.batch_shape == (3,) and batch.max_angle.shape == (3,)
    uv = jnp.asarray(image_grid(41))
    rays = jax.jit(jax.vmap(lambda c: c.unproject(uv)))(batch)
    for i, cam in enumerate(cams):
        np.testing.assert_allclose(rays[i], cam.unproject(uv), atol=1e-15)
        assert float(camera_at(batch, i).max_angle) == float(cam.max_angle)


def test_json_roundtrip_in_colmap_order():
    cam = unit()
    data = camera_to_dict(cam)
    assert data["model"] == "THIN_PRISM_FISHEYE"
    assert data["params"] == [289.3, 289.9, 321.2, 178.4, K[0], K[1], 3e-4, -2e-4, K[2], K[3], 2e-4, 1e-4]
    back = camera_from_dict(data, "lens.json")
    assert isinstance(back, ThinPrismFisheyeCamera)
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(cam)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="lens.json: unsupported camera model 'THIN_PRISM_FISHEYE' with 8 params"):
        camera_from_dict({**data, "params": data["params"][:8]}, "lens.json")


@pytest.mark.parametrize("field, value, match", [
    ("tangential", (1e-4,), r"ThinPrismFisheyeCamera.tangential must have shape \(\.\.\., 2\) \(p1, p2\)"),
    ("thin_prism", (0.0, 0.0, 0.0), r"ThinPrismFisheyeCamera.thin_prism must have shape \(\.\.\., 2\)"),
    ("distortion", (0.1, 0.0, 0.0), r"ThinPrismFisheyeCamera.distortion must have shape \(\.\.\., 4\)"),
    ("thin_prism", (np.nan, 0.0), r"ThinPrismFisheyeCamera.thin_prism must be finite"),
    ("tangential", np.zeros((2, 2)), r"ThinPrismFisheyeCamera: array fields have different leading \(batch\) shapes"),
])
def test_construction_errors_name_the_field(field, value, match):
    fields = {"focal": (289.3, 289.9), "principal_point": (321.2, 178.4), "distortion": K, "tangential": (0.0, 0.0),
              "thin_prism": (0.0, 0.0), field: value}
    with pytest.raises(ValueError, match=match) as err:
        ThinPrismFisheyeCamera(W, H, **fields)
    assert "\n" not in str(err.value)
