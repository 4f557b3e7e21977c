"""bcmocap calibrate: board parsing and detection, view selection, the FOV / equidistant / Kannala–Brandt fits on
real fisheye images and on simulated views of a known lens, the files it writes, and its one-line errors."""

import dataclasses
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from bcmocap.calibrate import Board, BoardViews, calibrate, detect_views, parse_board, select_views
from bcmocap.calibrate.compare import camera_difference
from bcmocap.calibrate.fit import params_of
from bcmocap.cameras import FOVCamera
from bcmocap.cli import main
from bcmocap.frontend.capture import read_camera_json
from bcmocap.io.opencv_calibration import read_opencv_fisheye_calibration
from bcmocap.sim.board_views import simulate_board_views
from bcmocap.sim.rig import fov_camera_for

DATA = Path(__file__).parent / "data" / "fisheye"
CIRCLES = "circles:4x11:0.02:asymmetric"


@pytest.fixture(scope="module")
def real_folder(tmp_path_factory) -> Path:
    """Four real 640×480 images of an asymmetric circle grid through a 120° fisheye (MIT, see tests/data/fisheye)."""
    folder = tmp_path_factory.mktemp("jevois")
    for f in sorted(DATA.glob("jevois120_circlegrid_*.jpg")):
        shutil.copy(f, folder / f.name)
    return folder


@pytest.fixture(scope="module")
def real_views(real_folder) -> BoardViews:
    return detect_views(real_folder, parse_board(CIRCLES))


def _synthetic(camera, count, seed=0, noise=0.1, board=None):
    board = board or Board("chessboard", 9, 6, 0.03)
    pixels, seen, _ = simulate_board_views(camera, board.points, count, np.random.default_rng(seed), noise_px=noise)
    return BoardViews(board, pixels, seen, tuple(f"view {i}" for i in range(count)), camera.width, camera.height,
                      count, count)


def test_parse_board_forms_and_errors():
    b = parse_board("chessboard:9x6:0.025")
    assert (b.kind, b.cols, b.rows, b.spacing) == ("chessboard", 9, 6, 0.025)
    assert b.points.shape == (54, 3) and np.allclose(b.points[1], [0.025, 0, 0]) and np.allclose(b.points[9], [0, 0.025, 0])
    a = parse_board(CIRCLES)
    assert a.asymmetric and np.allclose(a.points[4], [0.02, 0.02, 0.0])  # the second row is staggered
    c = parse_board("charuco:10x7:0.03:0.022:DICT_4X4_50")
    assert c.points.shape == (9 * 6, 3)
    for bad in ("chessboard:9x6", "square:9x6:0.02", "chessboard:9by6:0.02", "circles:4x11:0.02:oval",
                "chessboard:9x6:-1", "charuco:10x7:0.03:0.05", "charuco:10x7:0.03:0.02:DICT_NOPE", "chessboard:2x6:0.02"):
        with pytest.raises(ValueError):
            parse_board(bad)


@pytest.mark.slow
def test_real_circle_grid_detected_and_calibrated(real_views):
    """FOV (our LM) and Kannala–Brandt (cv2.fisheye) on 4 real images: every board found, sub-pixel RMS, and a
    lens close to the set's own calibration near the centre of the image."""
    assert real_views.num_views == 4 and (real_views.width, real_views.height) == (640, 480)
    assert real_views.seen.all()
    reference = read_opencv_fisheye_calibration(DATA / "jevois120_circlegrid_calibration.yml", (640, 480))
    fov = calibrate(real_views, "fov")
    assert fov.method.startswith("bcmocap") and fov.rms_px < 1.0, fov.rms_px
    fx, fy, cx, cy, omega = params_of("fov", fov.camera)
    assert abs(cx - 307.4) < 15 and abs(cy - 237.0) < 15 and 0.9 < omega < 1.3 and abs(fx - fy) < 10
    assert np.all(np.isfinite(fov.std)) and fov.std[0] < 10
    kb = calibrate(real_views, "opencv_fisheye")
    assert kb.method == "cv2.fisheye.calibrate" and kb.rms_px < 1.0
    # Where the board was seen (the centre of the image), both agree with the reference (10 images) to within
    # what 4 views determine (principal point ± 4-6 px, one standard deviation).
    centre = np.zeros((480, 640), bool)
    centre[180:300, 240:400] = True
    assert camera_difference(fov.camera, reference, mask=centre).max_px < 10.0
    assert camera_difference(kb.camera, reference, mask=centre).max_px < 10.0


@pytest.mark.slow
def test_recovers_a_simulated_fov_lens():
    """The studio's 170° FOV lens (640×360) seen on 25 simulated board views with 0.1 px noise: recovered to far
    better than 0.3 px over every pixel the lens can invert."""
    truth = fov_camera_for(640, 360)
    truth = FOVCamera(640, 360, focal=np.asarray(truth.focal) * [1.0, 1.01], principal_point=[322.0, 177.5],
                      omega=truth.omega)
    views = _synthetic(truth, 25)
    fitted = calibrate(views, "fov")
    assert fitted.rms_px < 0.2
    diff = camera_difference(fitted.camera, truth)
    assert diff.max_px < 0.3 and diff.compared > 0.9, (diff.max_px, diff.compared)
    assert np.allclose(params_of("fov", fitted.camera), params_of("fov", truth), rtol=2e-3, atol=0.2)


@pytest.mark.slow  # two fits of new shapes to compile (12 and 11 views)
def test_a_view_without_a_board_pose_is_left_out_not_fatal():
    """A view whose few points allow no pose (here 3 of them) used to fail the whole calibration."""
    truth = fov_camera_for(640, 360)
    views = _synthetic(truth, 12)
    seen = views.seen.copy()
    seen[4, np.flatnonzero(seen[4])[3:]] = False
    fitted = calibrate(dataclasses.replace(views, seen=seen), "fov")
    assert "view 4" in fitted.rejected and fitted.views.num_views == 11
    assert camera_difference(fitted.camera, truth).max_px < 1.0  # 11 views: a fit, if not the best one


@pytest.mark.slow
def test_equidistant_model_has_no_distortion(real_views):
    eq = calibrate(real_views, "equidistant")
    assert np.allclose(np.asarray(eq.camera.distortion), 0.0) and eq.rms_px < 3.0


def test_select_views_spreads_over_the_sensor():
    """Twenty copies of one central view and five others: the selection keeps the five and one of the copies."""
    camera = fov_camera_for(640, 360)
    views = _synthetic(camera, 6, seed=3)
    dup = np.concatenate([np.repeat(views.pixels[:1], 20, axis=0), views.pixels[1:]])
    seen = np.concatenate([np.repeat(views.seen[:1], 20, axis=0), views.seen[1:]])
    many = BoardViews(views.board, dup, seen, tuple(map(str, range(25))), 640, 360, 25, 25)
    chosen = select_views(many, 6)
    assert set(range(20, 25)) <= set(chosen.tolist()) and len(chosen) == 6


@pytest.mark.slow
def test_too_few_and_degenerate_views():
    camera = fov_camera_for(640, 360)
    views = _synthetic(camera, 4)
    with pytest.raises(ValueError, match="too few views"):
        calibrate(views.subset([0, 1]), "fov")
    # A small board far away, seen three times in one pose: the focal length trades with the distance.
    board = Board("chessboard", 9, 6, 0.03)
    pixels, seen, _ = simulate_board_views(camera, board.points, 1, np.random.default_rng(2), noise_px=0.0,
                                           distance_m=(4.0, 4.0), max_tilt_deg=0.0)
    noisy = np.repeat(pixels, 3, axis=0) + np.random.default_rng(1).normal(scale=0.05, size=(3, *pixels.shape[1:]))
    same = BoardViews(board, noisy, np.repeat(seen, 3, axis=0), ("a", "b", "c"), 640, 360, 3, 3)
    with pytest.raises(ValueError, match="degenerate views"):
        calibrate(same, "fov")


@pytest.mark.slow  # ~10 s: the heavy tier
def test_cli_writes_files_the_project_reads(real_folder, tmp_path, capsys):
    out = tmp_path / "cam" / "jevois.yml"
    assert main(["calibrate", str(real_folder), "--board", CIRCLES, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "RMS reprojection error" in printed and "per view" in printed
    kb = read_opencv_fisheye_calibration(out)  # the cv2.fisheye file (Kannala–Brandt fit of the FOV lens)
    lens = read_camera_json(out.with_suffix(".json"))  # the exact lens, as a capture's intrinsics/<camera>.json
    assert isinstance(lens, FOVCamera) and (lens.width, lens.height) == (640, 480)
    record = json.loads(out.with_suffix(".json").read_text())["calibration"]
    assert record["model"] == "fov" and len(record["views_used"]) == 4 and record["rms_px"] < 1.0
    assert record["opencv_fisheye_fit_max_error_px"] < 0.5
    assert camera_difference(kb, lens).max_px < 0.5
    picture = cv2.imread(str(tmp_path / "cam" / "jevois.coverage.png"))
    assert picture is not None and picture.shape[1] == 640


def test_cli_one_line_errors(real_folder, tmp_path, capsys):
    def error(*argv):
        assert main(["calibrate", *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        return err[-1]

    assert "no board found" in error(str(real_folder), "--board", "chessboard:9x6:0.025", "--out", str(tmp_path / "a.yml"))
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(next(real_folder.glob("*.jpg")), one / "x.jpg")
    assert "too few views" in error(str(one), "--board", CIRCLES, "--out", str(tmp_path / "b.yml"))
    assert "is not chessboard" in error(str(one), "--board", "hexagons:3x3:1", "--out", str(tmp_path / "c.yml"))
    assert "expected a .yml" in error(str(one), "--board", CIRCLES, "--out", str(tmp_path / "c.txt"))
    assert "no such file" in error(str(tmp_path / "missing"), "--board", CIRCLES, "--out", str(tmp_path / "d.yml"))
    assert not list(tmp_path.glob("*.yml"))


def test_image_folder_ignores_files_outside_it(tmp_path, real_folder):
    """A symlink in the image folder that leads outside it is not read."""
    inner = tmp_path / "images"
    inner.mkdir()
    outside = tmp_path / "elsewhere.jpg"
    shutil.copy(next(real_folder.glob("*.jpg")), outside)
    (inner / "link.jpg").symlink_to(outside)
    with pytest.raises(ValueError, match="no images"):
        detect_views(inner, parse_board(CIRCLES))


def test_video_source_and_charuco(tmp_path):
    """A ChArUco board warped into the frames of a short video is found in them, partial views included."""
    board = parse_board("charuco:7x5:0.04:0.03:DICT_4X4_50")
    image = board.charuco().generateImage((700, 500), marginSize=20)
    path = tmp_path / "board.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (640, 480), False)
    rng = np.random.default_rng(0)
    src = np.float32([[0, 0], [699, 0], [699, 499], [0, 499]])
    for _ in range(12):
        corners = np.float32([[60, 50], [580, 40], [600, 430], [40, 440]]) + rng.uniform(-40, 40, (4, 2)).astype(np.float32)
        corners += rng.uniform(-150, 150, 2).astype(np.float32)  # part of the board may leave the frame
        frame = cv2.warpPerspective(image, cv2.getPerspectiveTransform(src, corners), (640, 480), borderValue=255)
        writer.write(frame)
    writer.release()
    views = detect_views(path, board)
    assert views.examined == 12 and views.found >= 8
    assert views.names[0].startswith("frame ")
    assert (~views.seen).any()  # some partial views
    assert views.seen.sum(axis=1).min() >= 6


def test_a_board_seen_as_one_row_of_corners_gives_no_pose_not_nan():
    """Five corners of one row (a board at the frame's edge in a rendered lens unit's board video): IPPE reports a
    pose of NaNs as found; it is no pose, so the view is left out instead of the fit diverging."""
    import math

    from bcmocap.calibrate.fit import _equidistant_rays, _pose_from_rays

    points = np.array([[0.06, 0.06, 0.0], [0.12, 0.06, 0.0], [0.18, 0.06, 0.0], [0.24, 0.06, 0.0], [0.30, 0.06, 0.0]])
    pixels = np.array([[120.66281891, 40.16259003], [98.64673615, 46.35504913], [75.45358276, 54.3748436],
                       [52.04242706, 64.29270172], [28.15530396, 76.20808411]])
    focal = 0.5 * math.hypot(640, 360) / math.radians(95.0)
    assert _pose_from_rays(points, _equidistant_rays(pixels, focal, np.array([319.5, 179.5]))) is None


@pytest.mark.slow  # two fits to compile (Kannala-Brandt, then thin prism from it)
def test_thin_prism_model_takes_up_a_units_decentering_and_tilt(tmp_path):
    """A manufactured lens unit (decentering, thin prism, a sensor tilted by ~0.25 deg) on 60 simulated board views
    with 0.1 px noise: the thin-prism fit, started from the Kannala-Brandt one, comes within 0.3 px of the unit within
    80 deg of the axis after the turn a camera's mount takes up (0.25 px); the Kannala-Brandt fit stays several
    times farther (1.5 px)."""
    from bcmocap.calibrate.compare import turned_difference
    from bcmocap.cameras import ThinPrismFisheyeCamera, TiltedThinPrismFisheyeCamera
    from bcmocap.sim.lens_units import lens_design

    design = lens_design(640, 360)
    unit = TiltedThinPrismFisheyeCamera(640, 360, focal=np.asarray(design.focal) * 1.003, principal_point=[321.7, 178.9],
                                        distortion=design.distortion, tangential=[3e-4, -2e-4], thin_prism=[1e-4, 5e-5],
                                        tilt=np.radians([0.2, -0.15]))
    views = _synthetic(unit, 60, seed=3)
    prism = calibrate(views, "thin_prism_fisheye")
    kannala_brandt = calibrate(views, "opencv_fisheye")
    assert isinstance(prism.camera, ThinPrismFisheyeCamera) and prism.method.startswith("bcmocap Levenberg-Marquardt")
    assert prism.rms_px < 0.15 and kannala_brandt.rms_px > prism.rms_px  # 0.1 px per axis: 0.14 px per point
    np.testing.assert_allclose(params_of("thin_prism_fisheye", prism.camera)[:4], [*unit.focal, *unit.principal_point],
                               atol=1.5)
    near, _ = turned_difference(prism.camera, unit, max_angle_deg=80.0)
    far, _ = turned_difference(kannala_brandt.camera, unit, max_angle_deg=80.0)
    assert near.max_px < 0.3 and far.max_px > 3 * near.max_px, (near.max_px, far.max_px)
    # written as a capture's intrinsics/<camera>.json and read back by the frontend: the same lens
    from bcmocap.calibrate.report import write_calibration

    write_calibration(tmp_path / "chest.yml", prism)
    lens = read_camera_json(tmp_path / "chest.json")
    assert isinstance(lens, ThinPrismFisheyeCamera)
    assert camera_difference(lens, prism.camera).max_px < 1e-9


def test_views_a_refit_puts_off_are_dropped_in_further_rounds(monkeypatch):
    """On a studio board video the refit after dropping one bad view put another view's planar pose on its wrong
    side (674 px off) and left the intrinsics undetermined; each refit's bad views are dropped in turn, for at most
    REJECT_ROUNDS rounds. The fits are stood in for (each round's residuals given) to pin the rounds' logic."""
    from bcmocap.calibrate import fit as fit_module

    truth = fov_camera_for(640, 360)
    views = _synthetic(truth, 8)
    params = fit_module.params_of("fov", truth)
    fits = []

    def fake_fit(subset, model, max_steps):
        residuals = np.full(subset.pixels.shape, 0.1)
        off = {0: "view 2", 1: "view 5"}.get(len(fits))  # the first fit's bad view, then the refit's
        if off in subset.names:
            residuals[subset.names.index(off)] = 50.0
        fits.append(subset.names)
        eye = np.broadcast_to(np.eye(3), (subset.num_views, 3, 3))
        return (subset, params, eye, np.zeros((subset.num_views, 3)), residuals, np.full(5, 0.01), 3, "stand-in")

    monkeypatch.setattr(fit_module, "_fit", fake_fit)
    fitted = calibrate(views, "fov")
    assert fitted.rejected == ("view 2", "view 5") and len(fits) == 3
    assert fitted.views.names == tuple(f"view {i}" for i in range(8) if i not in (2, 5))
    fits.clear()
    monkeypatch.setattr(fit_module, "REJECT_ROUNDS", 1)
    assert calibrate(views, "fov").rejected == ("view 2",)  # one round: the refit's bad view stays
