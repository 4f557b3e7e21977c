"""Tests for bcmocap.cameras.TiltedThinPrismFisheyeCamera (the studio's lens units: a thin-prism fisheye in front of
a tilted sensor): OpenCV's tilted sensor model as the reference, round trips, the untilted limit, derivatives
against finite differences, batching, its JSON description, and errors."""

import jax

jax.config.update("jax_enable_x64", True)

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from bcmocap.cameras import ThinPrismFisheyeCamera, TiltedThinPrismFisheyeCamera, stack_cameras
from bcmocap.io.colmap import to_pycolmap
from bcmocap.io.model_json import camera_from_dict, camera_to_dict

W, H = 640, 360
K = (-0.2544, 0.1091, -0.0270, 0.0028)  # about the studio's lens design
TILT = (np.radians(0.25), np.radians(-0.15))


def unit(tilt=TILT) -> TiltedThinPrismFisheyeCamera:
    return TiltedThinPrismFisheyeCamera(W, H, focal=(289.3, 289.9), principal_point=(321.2, 178.4), distortion=K,
                                        tangential=(3e-4, -2e-4), thin_prism=(2e-4, 1e-4), tilt=tilt)


def sample_rays(max_deg, n=300, seed=0):
    rng = np.random.default_rng(seed)
    theta, phi = np.radians(rng.uniform(0.0, max_deg, n)), rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def test_the_tilt_is_opencvs_tilted_sensor_model():
    """The tilt acts on the lens's own normalised image point: the pixel is cv2.projectPoints' of that point taken
    as a pinhole's, with only tau_x, tau_y among the 14 distortion coefficients."""
    camera = unit()
    rays = sample_rays(60.0)
    lens_point = np.asarray(camera.lens._project_normalized(jnp.asarray(rays)))
    ours = np.asarray(camera.project(rays)[0])
    # OpenCV: a pinhole whose normalised point is the lens's, tilted by (tau_x, tau_y)
    points = np.concatenate([lens_point, np.ones((len(rays), 1))], axis=1)
    matrix = np.array([[289.3, 0.0, 321.2], [0.0, 289.9, 178.4], [0.0, 0.0, 1.0]])
    coefficients = np.zeros(14)
    coefficients[12:] = TILT
    reference, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), matrix, coefficients)
    np.testing.assert_allclose(ours, reference.reshape(-1, 2), atol=1e-9)
    # the tilt moves the image by a fraction of a pixel to a few pixels
    untilted = np.asarray(camera.lens.project(rays)[0])
    assert 0.3 < np.abs(ours - untilted).max() < 5.0


def test_untilted_it_is_the_thin_prism_camera_and_rays_round_trip():
    flat = unit(tilt=(0.0, 0.0))
    rays = sample_rays(100.0)
    np.testing.assert_allclose(np.asarray(flat.project(rays)[0]), np.asarray(flat.lens.project(rays)[0]), atol=1e-12)
    assert isinstance(flat.lens, ThinPrismFisheyeCamera)
    camera = unit()
    pixels, valid = camera.project(rays)
    assert np.asarray(valid).all()
    np.testing.assert_allclose(np.asarray(camera.unproject(pixels)), rays, atol=1e-10)
    assert float(camera.max_angle) == float(flat.lens.max_angle)


def test_project_and_unproject_jacobians_vs_finite_differences():
    camera = unit()
    point = jnp.array([0.4, -0.3, 0.5])
    pixel = jnp.array([500.0, 60.0])

    def project(c, p):
        return c.project(p)[0]

    for f, x in ((project, point), (lambda c, u: c.unproject(u), pixel)):
        by_x = jax.jacfwd(lambda v: f(camera, v))(x)
        by_tilt = jax.jacfwd(lambda t: f(TiltedThinPrismFisheyeCamera(
            W, H, focal=camera.focal, principal_point=camera.principal_point, distortion=camera.distortion,
            tangential=camera.tangential, thin_prism=camera.thin_prism, tilt=t), x))(camera.tilt)
        for jac, at, step in ((by_x, x, 1e-6), (by_tilt, camera.tilt, 1e-7)):
            numeric = []
            for i in range(len(at)):
                e = jnp.zeros(len(at)).at[i].set(step)
                if at is x:
                    plus, minus = f(camera, x + e), f(camera, x - e)
                else:
                    moved = [TiltedThinPrismFisheyeCamera(W, H, focal=camera.focal, principal_point=camera.principal_point,
                                                          distortion=camera.distortion, tangential=camera.tangential,
                                                          thin_prism=camera.thin_prism, tilt=camera.tilt + sign * e)
                             for sign in (1, -1)]
                    plus, minus = f(moved[0], x), f(moved[1], x)
                numeric.append((np.asarray(plus) - np.asarray(minus)) / (2 * step))
            np.testing.assert_allclose(np.asarray(jac), np.stack(numeric, axis=-1), rtol=1e-5, atol=1e-6)


def test_batched_under_vmap_and_json_roundtrip():
    cameras = [unit(), unit(tilt=(0.001, 0.002))]
    batch = stack_cameras(cameras)
    rays = sample_rays(80.0, n=20)
    by_vmap = jax.vmap(lambda c: c.project(rays)[0])(batch)
    for i, c in enumerate(cameras):
        np.testing.assert_allclose(np.asarray(by_vmap[i]), np.asarray(c.project(rays)[0]), atol=1e-12)
    data = camera_to_dict(cameras[0])
    assert data["model"] == "THIN_PRISM_FISHEYE_TILTED" and len(data["params"]) == 14
    np.testing.assert_allclose(data["params"][12:], TILT)
    back = camera_from_dict(data, "rig.json")
    assert isinstance(back, TiltedThinPrismFisheyeCamera)
    np.testing.assert_array_equal(np.asarray(back.project(rays)[0]), np.asarray(cameras[0].project(rays)[0]))
    with pytest.raises(ValueError, match="rig.json: unsupported camera model 'THIN_PRISM_FISHEYE_TILTED' with 12"):
        camera_from_dict({**data, "params": data["params"][:12]}, "rig.json")
    with pytest.raises(ValueError, match="to_pycolmap: unsupported camera class TiltedThinPrismFisheyeCamera"):
        to_pycolmap(cameras[0])  # not a COLMAP model: never written as the untilted one


@pytest.mark.parametrize("field, value, match", [
    ("tilt", (0.0, np.nan), "TiltedThinPrismFisheyeCamera.tilt must be finite"),
    ("tilt", (0.0, 0.0, 0.0), r"TiltedThinPrismFisheyeCamera.tilt must have shape \(\.\.\., 2\)"),
    ("distortion", (0.1, 0.0), r"TiltedThinPrismFisheyeCamera.distortion must have shape \(\.\.\., 4\)"),
])
def test_construction_errors_name_the_field(field, value, match):
    kwargs = dict(focal=(289.3, 289.9), principal_point=(321.2, 178.4), distortion=K, tangential=(0.0, 0.0),
                  thin_prism=(0.0, 0.0), tilt=(0.0, 0.0))
    kwargs[field] = value
    with pytest.raises(ValueError, match=match):
        TiltedThinPrismFisheyeCamera(W, H, **kwargs)
