"""Tests for the textured scene and the ray-cast renderer (bcmocap.sim.scene, bcmocap.sim.render).

Tiny images, one shared scene per kind: each distinct image size compiles the renderer once.
"""

import dataclasses
import hashlib

import cv2
import jax
import numpy as np
import pytest

from bcmocap.cameras import FOVCamera, OpenCVFisheyeCamera, PinholeCamera
from bcmocap.sim.render import Renderer, RenderOptions, camera_rays, interpolate_poses
from bcmocap.sim.rig import fov_camera_for
from bcmocap.sim.scene import (
    BLANK,
    NOISE,
    ROOM_STYLES,
    TILED,
    TexturedScene,
    TextureParams,
    finished_texture,
    make_room,
    make_textured_scene,
    surface_texture,
)

W, H = 96, 72
# A big empty room with a texture down to 6 cm: a pixel's colour is the texture at its ray's floor hit,
# filtered for the pixel's footprint there.
ROOM = TexturedScene(
    lower=np.array([-30.0, -30.0, 0.0]),
    upper=np.array([30.0, 30.0, 10.0]),
    boxes=np.zeros((0, 2, 3)),
    pillars=np.zeros((0, 3)),
    colors=np.tile([0.9, 0.8, 0.7], (6, 1)),
    texture=TextureParams(octaves=6, seed=3),
)
NO_NOISE = RenderOptions(noise_dn=0.0)
HEIGHT_M = 1.0
# Looking straight down: camera z = world -z, camera x = world x, camera y = world -y.
DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
ORIGIN = np.array([0.3, -0.2, HEIGHT_M])

CAMERAS = {
    "fov": fov_camera_for(W, H, fov_deg=150.0),
    "opencv_fisheye": OpenCVFisheyeCamera(W, H, focal=(30.0, 31.0), principal_point=(47.2, 35.6),
                                          distortion=(0.05, -0.01, 0.002, -0.0005)),
    "pinhole": PinholeCamera(W, H, focal=(50.0, 50.0), principal_point=(47.5, 35.5)),
}


def render_one(renderer, rotation, origin, capsules=None, radii=None, colors=None):
    caps = None if capsules is None else np.asarray(capsules)[None, None]
    return renderer.render(rotation[None, None, None], origin[None, None, None], caps, radii, colors)[0]


def expected_floor_colour(scene, points, footprint, options):
    """The renderer's shading of floor points seen from above (normal +z), in 8-bit levels."""
    grey = np.asarray(surface_texture(points[:, 0], points[:, 1], np.zeros(len(points), np.int32), footprint, scene.texture))
    light = np.asarray(options.light) / np.linalg.norm(options.light)
    lit = options.ambient + (1 - options.ambient) * max(light[2], 0.0)
    return scene.colors[0] * ((0.15 + 0.85 * grey) * lit)[:, None] * 255.0


@pytest.mark.slow
@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_floor_texel_lands_where_project_puts_it(model):
    camera = CAMERAS[model]
    renderer = Renderer(ROOM, camera, NO_NOISE)
    image = render_one(renderer, DOWN, ORIGIN).astype(float)
    rng = np.random.default_rng(0)
    # Floor points in view (within 55° of the nadir), chosen so that they project to pixel centres.
    pix = np.stack([rng.integers(4, W - 4, 300), rng.integers(4, H - 4, 300)], axis=1).astype(float)
    rays = np.asarray(camera.unproject(pix))
    keep = rays[:, 2] > np.cos(np.radians(55))
    pix, rays = pix[keep][:60], rays[keep][:60]
    world = ORIGIN + (HEIGHT_M / rays[:, 2])[:, None] * (rays @ DOWN.T)  # floor hit of each pixel's ray
    assert np.allclose(world[:, 2], 0.0, atol=1e-9)
    back, ok = camera.project((world - ORIGIN) @ DOWN)  # world -> camera frame -> pixel
    assert np.all(np.asarray(ok))
    np.testing.assert_allclose(np.asarray(back), pix, atol=1e-6)
    # Footprint: distance times the pixel's angular size, stretched by the incidence (render.py's rule).
    iv, iu = pix[:, 1].astype(int), pix[:, 0].astype(int)
    distance = HEIGHT_M / rays[:, 2]
    footprint = distance * renderer.rays.pixel_angle[iv, iu] / np.sqrt(rays[:, 2])
    want = expected_floor_colour(ROOM, world, footprint, NO_NOISE)
    got = image[iv, iu]
    np.testing.assert_allclose(got, want, atol=1.5)  # float32 rendering, 8-bit rounding
    # The test can tell a one-pixel shift: the texture changes that much between neighbours.
    shifted = image[iv, iu + 1]
    assert np.abs(shifted - want).mean() > 4 * np.abs(got - want).mean() + 2


def test_depth_of_the_floor_and_of_a_wall():
    camera = CAMERAS["fov"]
    renderer = Renderer(ROOM, camera, NO_NOISE)
    depth, body = renderer.depth(DOWN, ORIGIN)
    rays = camera_rays(camera).directions[0]  # (3, H, W)
    floor = HEIGHT_M / np.maximum(rays[2], 1e-9)
    down = rays[2] > 0.2  # pixels whose ray reaches the floor before a wall
    np.testing.assert_allclose(depth[down], floor[down], rtol=1e-4)
    assert not body.any()
    # Looking horizontally along +x: the wall at x = 30 m.
    along_x = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    depth, _ = renderer.depth(along_x, np.array([0.0, 0.0, 5.0]))
    assert depth[H // 2, W // 2] == pytest.approx(30.0 / rays[2, H // 2, W // 2], rel=1e-4)


def _ray_segment_distance(rays, a, b):
    """Distance between rays from the origin (N, 3 unit) and the segment [a, b] (numpy, by dense sampling)."""
    s = np.linspace(0.0, 1.0, 2001)
    pts = a + s[:, None] * (b - a)  # (S, 3)
    along = np.clip(rays @ pts.T, 0.0, None)  # (N, S)
    closest = along[..., None] * rays[:, None, :]
    return np.linalg.norm(closest - pts[None], axis=-1).min(axis=1)


@pytest.mark.slow
def test_a_capsule_in_front_of_the_camera_masks_its_pixels():
    camera = CAMERAS["fov"]
    renderer = Renderer(ROOM, camera, NO_NOISE)
    a, b, radius = np.array([-0.25, 0.1, 0.5]), np.array([0.3, -0.15, 0.6]), 0.08  # camera frame, metres
    capsule = np.stack([a, b]) @ DOWN.T + ORIGIN  # world
    depth, body = renderer.depth(DOWN, ORIGIN, capsule[None], np.array([radius]))
    rays = camera_rays(camera).directions[0].reshape(3, -1).T
    dist = _ray_segment_distance(rays, a, b).reshape(H, W)
    inside, outside = dist < radius - 2e-3, dist > radius + 2e-3
    assert inside.sum() > 100
    assert body[inside].all() and not body[outside].any()
    # The image shows the body's colour there, and the floor elsewhere.
    colour = np.array([[0.2, 0.4, 0.9]])
    image = render_one(renderer, DOWN, ORIGIN, capsule[None], np.array([radius]), colour).astype(float)
    hue = image / np.maximum(image.sum(axis=-1, keepdims=True), 1)
    np.testing.assert_allclose(hue[inside], np.broadcast_to(colour / colour.sum(), hue[inside].shape), atol=0.02)
    # Depth of the capsule's nearest point is its distance minus the radius along the central ray.
    u, v = np.unravel_index(np.argmin(np.where(inside, depth, np.inf)), depth.shape)
    assert depth[u, v] >= np.linalg.norm(a + 0.5 * (b - a)) - 0.3
    # A camera inside a capsule (its own mount) sees through it.
    _, body = renderer.depth(DOWN, ORIGIN, np.stack([ORIGIN - [0, 0, 0.05], ORIGIN + [0, 0, 0.05]])[None], np.array([0.1]))
    assert not body.any()


def test_rendering_is_deterministic_and_noise_follows_the_key():
    renderer = Renderer(ROOM, CAMERAS["fov"], RenderOptions(noise_dn=2.0))
    rot = np.broadcast_to(DOWN, (2, 1, 1, 3, 3))
    org = np.broadcast_to(ORIGIN, (2, 1, 1, 3))
    first = renderer.render(rot, org, keys=np.array([7, 8]))
    again = Renderer(ROOM, CAMERAS["fov"], RenderOptions(noise_dn=2.0)).render(rot, org, keys=np.array([7, 8]))
    assert first.tobytes() == again.tobytes()
    diff = first[0].astype(int) - first[1].astype(int)  # same pose, other noise
    assert 0 < np.abs(diff).mean() < 4 and np.abs(diff).max() <= 12


def _yawed(yaw):
    """world_from_camera (wxyz, xyz) looking down from ORIGIN, turned by ``yaw`` about the vertical."""
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ DOWN
    q = cv2.Rodrigues(rotation)[0].ravel()
    angle = np.linalg.norm(q)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * q / angle, ORIGIN])


def test_motion_blur_and_rolling_shutter_change_only_moving_views():
    camera = CAMERAS["fov"]
    still = np.stack([_yawed(0.3)] * 3)
    moving = np.stack([_yawed(0.3 + 0.5 * k) for k in range(3)])  # a fast turn: 30 rad/s at 60 fps
    plain = Renderer(ROOM, camera, NO_NOISE)
    for opts in (dataclasses.replace(NO_NOISE, motion_blur=True, blur_samples=2),
                 dataclasses.replace(NO_NOISE, rolling_shutter=True)):
        effect = Renderer(ROOM, camera, opts)
        for poses, changed in ((still, False), (moving, True)):
            image = effect.render(*effect.poses_at(poses, np.array([1])))[0].astype(int)
            reference = plain.render(*plain.poses_at(poses, np.array([1])))[0].astype(int)
            if changed:
                assert np.abs(image - reference).mean() > 3, opts
            else:
                assert np.abs(image - reference).max() <= 1


def test_motion_blur_is_the_mean_of_its_sub_exposures():
    # Blur of a fast turn past a moving body capsule, with a rolling shutter and two rays per pixel: the image is
    # the mean of the sub-exposures rendered one by one (each rounded to 8 bits: within a level).
    camera = CAMERAS["fov"]
    poses = np.stack([_yawed(0.3 + 0.5 * k) for k in range(3)])
    poses[:, 4:] += np.array([[0.0, 0.0, 0.0], [0.2, 0.1, 0.0], [0.4, 0.2, 0.0]])
    capsule = np.stack([[-0.25, 0.1, 0.5], [0.3, -0.15, 0.6]]) @ DOWN.T + ORIGIN
    ends = np.stack([capsule + [0.1 * k, 0.0, 0.0] for k in range(3)])[:, None]  # (T, 1, 2, 3)
    radii, colour = np.array([0.08]), np.array([[0.2, 0.4, 0.9]])
    base = dataclasses.replace(NO_NOISE, rolling_shutter=True, samples_per_pixel=2)
    blur = Renderer(ROOM, camera, dataclasses.replace(base, motion_blur=True, blur_samples=3, exposure_frames=1.0))
    frames = np.array([1])
    rot, org = blur.poses_at(poses, frames)
    caps = blur.capsules_at(ends, frames)
    image = blur.render(rot, org, caps, radii, colour)[0].astype(int)
    single = Renderer(ROOM, camera, base)
    subs = np.stack([single.render(rot[:, s: s + 1], org[:, s: s + 1], caps[:, s: s + 1], radii, colour)[0]
                     for s in range(3)]).astype(float)
    diff = np.abs(image - subs.mean(axis=0))
    assert diff.max() <= 1.0 and diff.mean() < 0.35
    assert min(np.abs(image - sub).mean() for sub in subs) > 3  # a moving view: not one of its sub-exposures
    # The same sub-exposure twice is the single exposure (sums of equal values are exact; within a level).
    twice = Renderer(ROOM, camera, dataclasses.replace(base, motion_blur=True, blur_samples=2))
    same = twice.render(np.repeat(rot[:, 1:2], 2, 1), np.repeat(org[:, 1:2], 2, 1), np.repeat(caps[:, 1:2], 2, 1),
                        radii, colour)[0].astype(int)
    assert np.abs(same - subs[1]).max() <= 1 and (same != subs[1]).mean() < 1e-3


def test_interpolate_poses_holds_ends_and_slerps():
    poses = np.array([[1.0, 0, 0, 0, 0, 0, 0], [np.cos(0.5), 0, 0, np.sin(0.5), 2.0, 0, 0]])
    rot, x = interpolate_poses(poses, np.array([-1.0, 0.5, 3.0]))
    np.testing.assert_allclose(x[:, 0], [0.0, 1.0, 2.0])
    np.testing.assert_allclose(rot[1], cv2.Rodrigues(np.array([0.0, 0.0, 0.5]))[0], atol=1e-12)
    np.testing.assert_allclose(rot[0], np.eye(3), atol=1e-12)


@pytest.mark.slow
def test_sift_keeps_many_inliers_between_consecutive_frames():
    # A camera carried at walking speed (1.4 m/s, turning 20°/s) past the clutter, 320x180, 170° FOV.
    scene = make_textured_scene(np.array([[0.0, 0.0], [3.0, 0.0]]), seed=1)
    camera = fov_camera_for(320, 180)
    renderer = Renderer(scene, camera)
    frames = []
    for k in range(2):
        yaw = np.radians(20.0) * k / 60
        forward = np.array([np.cos(yaw), np.sin(yaw), -0.3])
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        rot = np.stack([right, np.cross(forward, right), forward], axis=1)
        frames.append(render_one(renderer, rot, np.array([1.4 * k / 60, 0.0, 1.0])))
    sift = cv2.SIFT_create()
    (ka, da), (kb, db) = (sift.detectAndCompute(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), None) for f in frames)
    matches = [m for m, n in cv2.BFMatcher().knnMatch(da, db, k=2) if m.distance < 0.8 * n.distance]
    ra = np.asarray(camera.unproject(np.float64([ka[m.queryIdx].pt for m in matches])))
    rb = np.asarray(camera.unproject(np.float64([kb[m.trainIdx].pt for m in matches])))
    ok = (ra[:, 2] > 0.2) & (rb[:, 2] > 0.2)
    _, mask = cv2.findEssentialMat(ra[ok, :2] / ra[ok, 2:], rb[ok, :2] / rb[ok, 2:], np.eye(3), method=cv2.RANSAC,
                                   prob=0.999, threshold=1.0 / float(camera.focal[0]))
    assert int(mask.sum()) >= 150, f"{int(mask.sum())} inliers of {len(matches)} matches"


def test_scene_validation_and_round_trip():
    scene = make_textured_scene(np.array([[0.0, 0.0], [4.0, 1.0]]), seed=2)
    again = TexturedScene.from_dict(scene.to_dict())
    for field in ("lower", "upper", "boxes", "pillars", "colors"):
        np.testing.assert_array_equal(getattr(again, field), getattr(scene, field))
    assert again.texture == scene.texture
    points, materials = scene.sample_points(density_per_m2=1.0, seed=0)
    assert not scene.inside_clutter(points).any() and materials.max() < scene.num_materials
    with pytest.raises(ValueError, match="colors must have shape"):
        dataclasses.replace(scene, colors=scene.colors[:3])
    with pytest.raises(ValueError, match="missing field"):
        TexturedScene.from_dict({"lower": [0, 0, 0]}, "scene.json")
    with pytest.raises(ValueError, match="samples_per_pixel"):
        RenderOptions(samples_per_pixel=3)
    with pytest.raises(ValueError, match="single camera"):
        camera_rays(FOVCamera(8, 8, focal=[[5.0, 5.0]] * 2, principal_point=[[3.5, 3.5]] * 2, omega=[1.0, 1.0]))


# ---------------------------------------------------------------------------------------------
# The studio's rooms (make_room).

PATH = np.array([[0.0, 0.0], [4.0, 1.0]])  # heads for the x+ wall


def look_along(forward):
    """world_from_camera rotation of a camera looking along ``forward`` (world), image x to its right, y down."""
    forward = np.asarray(forward, float) / np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(forward, right), forward], axis=1)


def test_default_room_renders_the_bytes_it_did_before_rooms():
    # Pinned from the code before finishes existed (JAX 0.10.2, x86-64 CPU, float64 on as conftest.py sets it): the
    # default room keeps the plain texture's code. Regenerate only when JAX/XLA itself changes its float32 code.
    scene = make_textured_scene(np.array([[0.0, 0.0], [3.0, 0.0]]), seed=1)
    assert make_room("textured", np.array([[0.0, 0.0], [3.0, 0.0]]), seed=1).to_dict() == scene.to_dict()
    assert not scene.has_finishes and "finish_kinds" not in scene.to_dict()
    image = render_one(Renderer(scene, CAMERAS["fov"]), look_along([1.0, 0.1, -0.3]), np.array([0.5, 0.0, 1.0]),
                       np.array([[[1.5, -0.2, 0.5], [1.5, 0.2, 1.2]]]), np.array([0.1]), np.array([[0.3, 0.4, 0.6]]))
    assert hashlib.sha256(image.tobytes()).hexdigest() == \
        "fb79c7b32075e2c6670ebc94a580d60ead9fa421e84a484a5e0338d440453a7e"
    u, v = np.meshgrid(np.linspace(-5.0, 5.0, 64), np.linspace(0.0, 4.0, 32))
    grey = np.asarray(surface_texture(u, v, (np.arange(u.size) % 24).reshape(u.shape), np.full(u.shape, 0.004),
                                      scene.texture))
    assert hashlib.sha256(grey.tobytes()).hexdigest() == \
        "378fb131972e0548863636f93231001a1f9f297a51590d767532d61043077767"


def test_rooms_are_deterministic_per_seed_and_round_trip():
    for style in ROOM_STYLES:
        scene = make_room(style, PATH, seed=4)
        assert scene.to_json() == make_room(style, PATH, seed=4).to_json()
        assert scene.to_json() != make_room(style, PATH, seed=5).to_json()
        again = TexturedScene.from_dict(scene.to_dict())
        assert again.to_json() == scene.to_json() and again.has_finishes == (style != "textured")
    textured, sparse, repeated = (make_room(style, PATH, seed=4) for style in ("textured", "sparse", "repeated"))
    assert len(sparse.boxes) + len(sparse.pillars) < len(textured.boxes) + len(textured.pillars)
    assert sparse.finish_kinds[3] == BLANK and np.all(sparse.finish_gains[1:6] < 0.5)  # x+: the wall ahead
    assert sparse.finish_gains[0] > 0.5 and sparse.texture == textured.texture  # a concrete floor; the fine octaves
    np.testing.assert_array_equal(repeated.boxes, textured.boxes)  # the same clutter, periodic surfaces
    # Floor and ceiling tiles, bricks ahead (x+), windows behind (x-); the side walls and the clutter as usual.
    assert set(np.flatnonzero(repeated.finish_kinds == TILED)) == {0, 1, 2, 3} and repeated.tiles[3, 2] == 0.5
    assert repeated.tiles[0, 4] == 8 and np.all(repeated.tiles[1:4, 4] == 1)  # floor tiles of 8 faces
    # A scene file written before tiles had faces reads with one face per material.
    old = dict(repeated.to_dict(), tiles=np.asarray(repeated.tiles)[:, :4].tolist())
    np.testing.assert_array_equal(TexturedScene.from_dict(old).tiles[:, 4], 1.0)
    with pytest.raises(ValueError, match="whole number of faces"):
        dataclasses.replace(repeated, tiles=np.column_stack([repeated.tiles[:, :4], np.full(repeated.num_materials, 0.5)]))
    assert np.all(repeated.finish_kinds[4:] == NOISE)
    with pytest.raises(ValueError, match="given together"):
        dataclasses.replace(textured, finish_kinds=np.zeros(textured.num_materials, int))
    with pytest.raises(ValueError, match="finish_kinds must be"):
        dataclasses.replace(sparse, finish_kinds=np.full(sparse.num_materials, 7))
    with pytest.raises(ValueError, match="style must be one of"):
        make_room("cave", PATH)


@pytest.mark.slow  # ~10 s: the heavy tier
def test_repeated_room_repeats_its_tiles():
    scene = make_room("repeated", PATH, seed=2)
    tiled = np.flatnonzero(scene.finish_kinds == TILED)
    assert {0, 1} <= set(tiled.tolist()) and len(tiled) == 4  # floor, ceiling and two walls
    assert len({tuple(scene.tiles[m, :2]) for m in tiled}) == 4  # four sizes: no lattice shared by two surfaces
    rng = np.random.default_rng(0)
    u = rng.uniform(-16, 16, 400)
    v = rng.uniform(0, 4, 400)
    texture = jax.jit(finished_texture, static_argnums=4)  # one compilation rather than op by op
    for m in tiled:
        width, height, shift, _, faces = scene.tiles[m]

        def grey(du, dv, m=m, u=u, v=v):
            return np.asarray(texture(u + du, v + dv, m, np.full(u.shape, 0.003), scene.texture, TILED,
                                      scene.finish_gains[m], tuple(scene.tiles[m])))

        base = grey(0.0, 0.0)
        assert base.std() > 0.05 and np.abs(grey(0.5 * width, 0.0) - base).mean() > 0.03
        edge = np.asarray(texture(np.full(3, 0.3 * width), np.array([0.0, height, 2 * height]), m, np.full(3, 1e-3),
                                  scene.texture, TILED, 1.0, tuple(scene.tiles[m])))
        np.testing.assert_allclose(edge, 0.2, atol=1e-6)  # on a joint: the joints' grey
        if faces == 1:  # every tile alike: a tile over is the same grey (to float32's rounding of u + width)
            np.testing.assert_allclose(grey(width, 0.0), base, atol=2e-3)
            np.testing.assert_allclose(grey(-3 * width, (2.0 if shift else 1.0) * height), base, atol=2e-3)
            continue
        # Tiles of a few faces: the same point of 60 x 40 tiles shows exactly `faces` patterns, each many times.
        inside = np.stack(np.meshgrid(np.linspace(0.1, 0.9, 5) * width, np.linspace(0.1, 0.9, 5) * height), -1)
        corners = np.stack(np.meshgrid(np.arange(60) * width, np.arange(40) * height), -1).reshape(-1, 1, 2)
        points = (corners + inside.reshape(1, -1, 2)).reshape(-1, 2)
        patterns = np.asarray(texture(points[:, 0], points[:, 1], m, np.full(len(points), 0.003), scene.texture,
                                      TILED, scene.finish_gains[m], tuple(scene.tiles[m]))).reshape(len(corners), -1)
        same = np.abs(patterns[:, None] - patterns[None]).max(-1) < 2e-3  # alike to float32's rounding of u
        groups = {int(np.argmax(row)) for row in same}  # each tile's first alike tile names its face
        counts = same[sorted(groups)].sum(1)
        assert len(groups) == faces and counts.min() > 0.5 * len(corners) / faces


def test_sparse_room_has_a_blank_wall():
    scene = make_room("sparse", PATH, seed=2)
    camera = CAMERAS["pinhole"]
    renderer = Renderer(scene, camera, NO_NOISE)
    rotation = look_along([1.0, 0.0, 0.15])
    origin = np.array([scene.upper[0] - 4.0, 0.5 * (scene.lower[1] + scene.upper[1]), 1.5])
    image = render_one(renderer, rotation, origin).astype(int)
    depth, _ = renderer.depth(rotation, origin)
    rays = np.einsum("ij,jhw->ihw", rotation, camera_rays(camera).directions[0])
    to_wall = (scene.upper[0] - origin[0]) / np.maximum(rays[0], 1e-9)  # distance to the x+ wall's plane
    wall = np.abs(depth - to_wall) < 1e-3 * to_wall
    assert wall.mean() > 0.4
    assert np.ptp(image[wall], axis=0).max() == 0  # uniform: nothing to track
    assert image[~wall].std(axis=0).min() > 2  # the rest (floor, ceiling, walls, boxes) is not
