"""Tests for the reference reconstruction (bcmocap.frontend.reference) on 4 real SceauxCastle photos
(640 px wide copies; terms in tests/data/sceaux/README.md)."""

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from bcmocap.cameras import PinholeCamera
from bcmocap.frontend.reference import (
    build_reference,
    extract_sift,
    load_reference,
    match_descriptors,
    save_reference,
    verify_distinctive,
    verify_matches,
)

SCEAUX = Path(__file__).parent / "data" / "sceaux"
NAMES = ["100_7100.jpg", "100_7101.jpg", "100_7102.jpg", "100_7103.jpg"]
SCALE = 640 / 2832  # K.txt is for the 2832x2128 originals


def test_sift_flann_ratio_and_fundamental_ransac():
    a, b = (cv2.imread(str(SCEAUX / n), cv2.IMREAD_GRAYSCALE) for n in NAMES[:2])
    (ka, da), (kb, db) = extract_sift(a, max_features=1500), extract_sift(b, max_features=1500)
    assert ka.shape[1] == 4 and da.dtype == np.uint8 and da.shape == (len(ka), 128) and len(ka) > 1000
    matches = match_descriptors(da, db)
    assert matches.dtype == np.uint32 and 100 < len(matches) < len(ka)
    assert len(set(matches[:, 1].tolist())) == len(matches)  # mutual: one-to-one
    inliers = verify_matches(ka, kb, matches)
    assert 0.5 * len(matches) < len(inliers) <= len(matches)
    # A shuffled pairing has no epipolar geometry: only what a random F explains by chance survives.
    shuffled = np.stack([matches[:, 0], np.random.default_rng(0).permutation(matches[:, 1])], axis=1)
    assert len(verify_matches(ka, kb, shuffled)) < 0.1 * len(inliers)
    assert len(verify_matches(ka, kb, shuffled, min_inliers=len(inliers) // 2)) == 0


def _epipolar_px(keypoints_a, keypoints_b, matches, rotation, shift, focal, centre):
    """Distance (px) of each match's point in b from the epipolar line of its point in a (x_b = R x_a + t)."""
    essential = np.array([[0, -shift[2], shift[1]], [shift[2], 0, -shift[0]], [-shift[1], shift[0], 0]]) @ rotation
    k = np.array([[focal, 0, centre[0]], [0, focal, centre[1]], [0, 0, 1.0]])
    fundamental = np.linalg.inv(k).T @ essential @ np.linalg.inv(k)
    pa = np.column_stack([keypoints_a[matches[:, 0], :2], np.ones(len(matches))])
    pb = np.column_stack([keypoints_b[matches[:, 1], :2], np.ones(len(matches))])
    lines = pa @ fundamental.T
    return np.abs(np.sum(lines * pb, 1)) / np.hypot(lines[:, 0], lines[:, 1])


def test_distinctive_matches_find_the_geometry_a_repeated_pattern_outvotes():
    # Photo b is 0.6 m right of photo a and turned 10 deg. 80 true matches over a scene in depth, 30 of them coarse
    # (keypoints 12 px across); 250 fine matches (3 px) of a repeated pattern, each tile matched to one a period
    # away, so that they fit the geometry of b shifted by 0.4 m more: the most inliers.
    rng = np.random.default_rng(0)
    focal, centre = 500.0, np.array([320.0, 240.0])
    rotation = np.array([[np.cos(0.17), 0, np.sin(0.17)], [0, 1, 0], [-np.sin(0.17), 0, np.cos(0.17)]])
    shift, alias_shift = np.array([-0.6, 0.0, 0.05]), np.array([-0.4, 0.05, 0.0])

    def view(points, t):
        seen = points @ rotation.T + t
        return focal * seen[:, :2] / seen[:, 2:] + centre

    true_points = rng.uniform([-1.5, -1.0, 3.0], [1.5, 1.0, 7.0], (80, 3))
    pattern = rng.uniform([-1.5, -1.0, 4.0], [1.5, 1.0, 4.5], (250, 3))  # a wall of tiles
    xy_a = np.concatenate([focal * true_points[:, :2] / true_points[:, 2:], focal * pattern[:, :2] / pattern[:, 2:]])
    xy_a += centre
    xy_b = np.concatenate([view(true_points, shift), view(pattern, shift + alias_shift)])
    xy_a += rng.normal(0, 0.3, xy_a.shape)
    xy_b += rng.normal(0, 0.3, xy_b.shape)
    sizes = np.r_[np.full(30, 12.0), np.full(50, 3.0), np.full(250, 3.0)]
    keypoints_a = np.column_stack([xy_a, sizes, np.zeros(330)]).astype(np.float32)
    keypoints_b = np.column_stack([xy_b, sizes, np.zeros(330)]).astype(np.float32)
    matches = np.stack([np.arange(330), np.arange(330)], axis=1).astype(np.uint32)
    every = verify_matches(keypoints_a, keypoints_b, matches)
    assert np.mean(every[:, 0] >= 80) > 0.7  # the pattern's geometry wins on every match

    kept = verify_distinctive(keypoints_a, keypoints_b, matches, min_size_px=8.0)
    assert np.sum(kept[:, 0] < 80) >= 75  # the true matches, the fine ones included
    assert np.mean(_epipolar_px(keypoints_a, keypoints_b, kept, rotation, shift, focal, centre) < 2.0) > 0.95
    # Too few coarse matches to agree on a geometry: no pair.
    assert len(verify_distinctive(keypoints_a, keypoints_b, matches[5:], min_size_px=8.0, min_distinctive=26)) == 0


def test_reference_model_on_real_photos(tmp_path):
    pycolmap.logging.minloglevel = 2
    camera = PinholeCamera(width=640, height=481, focal=[2905.88 * SCALE] * 2,
                           principal_point=[1416 * SCALE, 1064 * SCALE])
    model = build_reference(SCEAUX, NAMES, camera=camera, workdir=tmp_path, max_features=1500)
    assert model.registered == tuple(NAMES) and model.num_points3D > 300
    assert model.mean_reprojection_error_px < 1.0
    assert model.database_path.parent == tmp_path and model.database_path.is_file() and len(model.pair_inliers) == 6
    assert 1 <= model.mapping_attempts <= 3
    # Every pair is distinctive too, and their rotations agree: checked and kept. (With the five-point essential
    # matrix alone one of the 6 disagreed: the facade is nearly a plane, where its rotation can be the wrong one
    # of two.)
    assert model.distinctive_pairs == 6
    assert model.rotation_check == "agreed" and model.inconsistent_pairs == 0 and "rotations" in model.seconds
    # The reconstruction's camera is the one given (COLMAP convention: +0.5 px).
    params = np.asarray(model.reconstruction.cameras[1].params)
    assert params[2] == pytest.approx(1416 * SCALE + 0.5)
    # Saved and read back (to resume without rebuilding).
    save_reference(model, tmp_path)
    again = load_reference(tmp_path)
    assert again.registered == model.registered and again.num_points3D == model.num_points3D
    assert again.distinctive_pairs == 6
    assert again.reconstruction.num_points3D() == model.num_points3D and again.database_path == model.database_path
    assert again.pair_inliers == model.pair_inliers and again.mapping_attempts == model.mapping_attempts
    assert again.rotation_check == "agreed" and again.inconsistent_pairs == 0
    with pytest.raises(ValueError, match="reference.json: not a readable reference report"):
        load_reference(tmp_path / "model")


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="attempts must be >= 1, got 0"):
        build_reference(SCEAUX, NAMES, attempts=0)
    with pytest.raises(ValueError, match="photo folder does not exist"):
        build_reference(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="need at least 2 photos, found 0"):
        build_reference(tmp_path)
    with pytest.raises(ValueError, match=r"nope\.jpg: missing or not a readable image"):
        build_reference(SCEAUX, [NAMES[0], "nope.jpg"])


def test_a_camera_bcmocap_does_not_read_leaves_the_model_unchecked(tmp_path):
    pycolmap.logging.minloglevel = 2
    camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=640, height=481,
                             params=[2905.88 * SCALE, 1416 * SCALE + 0.5, 1064 * SCALE + 0.5, 0.0])
    model = build_reference(SCEAUX, NAMES[:3], camera=camera, workdir=tmp_path, max_features=1000)
    assert model.registered == tuple(NAMES[:3])
    assert model.rotation_check == "not checked" and model.inconsistent_pairs == 0 and model.mapping_attempts >= 1


def test_the_mapper_runs_on_one_thread_for_a_bitwise_reproducible_model(tmp_path, monkeypatch):
    # With its threads pycolmap's mapper gave the studio's 24 textured-room photos camera centres 2e-15 apart from
    # one build to the next (4 photos happen to come out equal either way, so this pins the setting instead).
    seen = []
    mapping = pycolmap.incremental_mapping

    def spy(*args, **kwargs):
        seen.append(kwargs["options"].num_threads)
        return mapping(*args, **kwargs)

    monkeypatch.setattr(pycolmap, "incremental_mapping", spy)
    pycolmap.logging.minloglevel = 2
    camera = PinholeCamera(width=640, height=481, focal=[2905.88 * SCALE] * 2,
                           principal_point=[1416 * SCALE, 1064 * SCALE])
    build_reference(SCEAUX, NAMES, camera=camera, workdir=tmp_path, max_features=1500)
    assert seen and set(seen) == {1}


def test_a_replacing_model_keeps_its_poses_and_takes_points_from_every_pair(tmp_path):
    # A model of the 4 photos from 3 of their 6 pairs (a chain), as the rotation check's model is from a subset,
    # triangulated again from the database of all 6: its photos stay where they were and it gains points.
    from bcmocap.frontend import reference

    pycolmap.logging.minloglevel = 2
    camera = PinholeCamera(width=640, height=481, focal=[2905.88 * SCALE] * 2,
                           principal_point=[1416 * SCALE, 1064 * SCALE])
    features = {n: extract_sift(cv2.imread(str(SCEAUX / n), cv2.IMREAD_GRAYSCALE), max_features=1500) for n in NAMES}
    verified, _ = reference._match_pairs(NAMES, features, ratio=0.8, threshold_px=1.5, min_inliers=15)
    assert len(verified) == 6
    mapping = dict(image_dir=SCEAUX, names=tuple(NAMES), camera=camera, features=features, threshold_px=1.5,
                   refine_intrinsics=True, random_seed=0, attempts=1, good_error_px=0.5, seconds={"mapping": 0.0})
    every, _ = reference._map(tmp_path / "every", verified, **mapping)
    chain = {pair: m for pair, m in verified.items() if NAMES.index(pair[1]) == NAMES.index(pair[0]) + 1}
    subset, _ = reference._map(tmp_path / "chain", chain, **mapping)
    before = reference._camera_centres(subset[1])
    points = subset[1].num_points3D()
    score, triangulated, pairs, database = reference._triangulated_from_every_pair(subset, every[3], SCEAUX,
                                                                                   tmp_path / "triangulated")
    assert database == every[3] and pairs is chain and score == subset[0]
    after = reference._camera_centres(triangulated)
    assert set(after) == set(before) == set(NAMES)
    assert max(np.linalg.norm(after[n] - before[n]) for n in NAMES) < 1e-9
    # 368 points from the chain, 481 with the other three pairs' matches (0.27 px)
    assert triangulated.num_points3D() > 1.2 * points and triangulated.compute_mean_reprojection_error() < 0.5
