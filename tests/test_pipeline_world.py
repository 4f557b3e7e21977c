"""bcmocap.pipeline.world and .config: similarities, moving a model between worlds, the run's settings."""

import numpy as np
import pytest
from conftest import make_rig, make_skeleton, one_line_error, random_quaternions

from bcmocap.cli import main
from bcmocap.geometry import SO3
from bcmocap.kinematics import Motion
from bcmocap.kinematics.fk import joint_positions
from bcmocap.kinematics.rig import camera_poses
from bcmocap.pipeline.config import RunConfig, load_config
from bcmocap.pipeline.run import STAGES, fingerprints
from bcmocap.pipeline.world import Similarity, scale_from_measurements, transform_model, upright_frame


def _similarity(seed=0) -> Similarity:
    rng = np.random.default_rng(seed)
    rot = np.asarray(SO3.exp(rng.normal(size=3)).as_matrix())
    return Similarity(float(rng.uniform(0.3, 3.0)), rot, rng.normal(size=3))


def _motion(skeleton, frames=4, seed=1) -> Motion:
    rng = np.random.default_rng(seed)
    rot = np.asarray(skeleton.project_rotations(random_quaternions(rng, (frames, skeleton.num_segments), 0.6)))
    return Motion(rng.normal(size=(frames, 3)), rot)


def test_similarity_maps_poses_points_and_composes():
    a, b = _similarity(0), _similarity(1)
    x = np.random.default_rng(2).normal(size=(5, 3))
    np.testing.assert_allclose(a.then(b).points(x), b.points(a.points(x)), atol=1e-12)
    np.testing.assert_allclose(a.inverse().points(a.points(x)), x, atol=1e-12)
    poses = np.concatenate([random_quaternions(np.random.default_rng(3), (5,)), x], axis=1)
    poses[2] = np.nan
    moved = a.poses(poses)
    assert np.isnan(moved[2]).all()
    np.testing.assert_allclose(moved[[0, 1, 3, 4], 4:], a.points(x[[0, 1, 3, 4]]), atol=1e-12)
    back = a.inverse().poses(moved)
    same_rotation = np.abs(np.sum(back[:, :4] * poses[:, :4], axis=1))
    np.testing.assert_allclose(same_rotation[[0, 1, 3, 4]], 1.0, atol=1e-10)
    assert Similarity.from_dict(a.to_dict()).to_dict() == a.to_dict()
    with pytest.raises(ValueError, match="similarity.json"):
        Similarity.from_dict({"scale": 1.0}, "similarity.json")


def test_transform_model_moves_joints_and_cameras_by_the_similarity_and_keeps_joint_angles():
    skeleton = make_skeleton()
    rig = make_rig(skeleton)
    motion = _motion(skeleton)
    sim = _similarity(4)
    sk2, rig2, m2 = transform_model(skeleton, rig, motion, sim)
    np.testing.assert_allclose(np.asarray(joint_positions(sk2, m2)), sim.points(np.asarray(joint_positions(skeleton, motion))), atol=1e-10)
    cams, cams2 = np.asarray(camera_poses(skeleton, rig, motion).wxyz_xyz), np.asarray(camera_poses(sk2, rig2, m2).wxyz_xyz)
    np.testing.assert_allclose(cams2[..., 4:], sim.points(cams[..., 4:]), atol=1e-10)
    expected = sim.poses(cams.reshape(-1, 7)).reshape(cams.shape)
    np.testing.assert_allclose(np.abs(np.sum(cams2[..., :4] * expected[..., :4], axis=-1)), 1.0, atol=1e-10)
    angle = lambda q: 2 * np.arccos(np.clip(np.abs(np.asarray(q)[..., 0]), 0, 1))
    np.testing.assert_allclose(angle(m2.rotations[:, 1:]), angle(motion.rotations[:, 1:]), atol=1e-7)
    # the rest pose stays the rest pose: segment frames parallel to the new world
    rest2 = np.asarray(joint_positions(sk2, sk2.rest_motion()))
    rest = np.asarray(joint_positions(skeleton, skeleton.rest_motion()))
    np.testing.assert_allclose(rest2, sim.scale * rest @ sim.rotation.T, atol=1e-10)


def test_scale_from_measurements_and_its_errors():
    skeleton = make_skeleton()
    rest = np.asarray(joint_positions(skeleton, skeleton.rest_motion()))
    d = float(np.linalg.norm(rest[3] - rest[5]))
    assert scale_from_measurements(skeleton, [{"from": "thigh", "to": "foot", "metres": 2 * d}]) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="unknown segment 'knee'"):
        scale_from_measurements(skeleton, [{"from": "knee", "to": "foot", "metres": 0.4}])
    with pytest.raises(ValueError, match="no measurement"):
        scale_from_measurements(skeleton, [])
    with pytest.raises(ValueError, match=r"\[0\]"):
        scale_from_measurements(skeleton, [{"from": "thigh"}])


def test_upright_frame_points_feet_to_head_along_z_and_puts_the_ankles_on_the_floor():
    skeleton = make_skeleton()
    tilt = SO3.exp(np.array([0.7, -0.3, 0.2]))
    rotations = np.tile(np.array([1.0, 0, 0, 0]), (3, 6, 1))
    rotations[:, 0] = np.asarray(tilt.wxyz)
    rest = Motion(np.array([[1.0, 2.0, 3.0]] * 3), rotations)
    sim = upright_frame(skeleton, rest, ["foot"], "head", 2.0)
    joints = sim.points(np.asarray(joint_positions(skeleton, rest)))
    up = joints[0, 2] - joints[0, 5]
    assert np.linalg.norm(up[:2]) < 1e-9 and up[2] > 0
    assert abs(joints[0, 5, 2]) < 1e-9 and np.linalg.norm(joints[0, 0, :2]) < 1e-9
    with pytest.raises(ValueError, match="unknown segment 'toe'"):
        upright_frame(skeleton, rest, ["toe"], "head", 1.0)


def test_config_file_flags_and_errors(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text('[solver]\nwindow = 30\nloss = "huber"\n[frontend]\nstride = 1\n')
    config = load_config(path)
    assert config.solver.window == 30 and config.solver.loss == "huber" and config.frontend.stride == 1
    assert config.with_overrides({"solver.overlap": 5}).solver.overlap == 5
    assert RunConfig.from_dict(config.to_dict()) == config
    bad = tmp_path / "bad.toml"
    bad.write_text("[solver]\nwindoww = 3\n")
    with pytest.raises(ValueError, match=r"bad.toml: solver.windoww is not a setting"):
        load_config(bad)
    bad.write_text("[solverr]\n")
    with pytest.raises(ValueError, match=r"unknown section \[solverr\]"):
        load_config(bad)
    bad.write_text('[solver]\nloss = "l1"\n')
    with pytest.raises(ValueError, match="solver.loss"):
        load_config(bad)
    with pytest.raises(ValueError, match="cannot read"):
        load_config(tmp_path / "missing.toml")
    with pytest.raises(ValueError, match="unknown setting"):
        config.with_overrides({"solver.nope": 1})


def test_run_refuses_a_user_term_it_cannot_import_before_reading_the_capture(tmp_path, capsys):
    path = tmp_path / "run.toml"
    path.write_text('[[solver.user_terms]]\nfactory = "no_such_module_xyz:f"\n')
    out = tmp_path / "out"
    assert main(["run", str(tmp_path / "no capture here"), "--out", str(out), "--config", str(path)]) == 2
    one_line_error(capsys, "run", "term factory 'no_such_module_xyz:f': cannot import 'no_such_module_xyz'", "PYTHONPATH")
    assert not out.exists()


@pytest.mark.parametrize("name, text, culprit", [
    ("run.toml", "[solver]\nloss_scale = inf\n", "solver.loss_scale must be finite, got inf"),
    ("run.toml", "[solver]\nroot_smoothness = inf\n", "solver.root_smoothness must be finite"),
    ("run.json", '{"solver": {"joint_smoothness": NaN}}', "solver.joint_smoothness must be finite"),
    ("run.toml", "[solver]\nwindow = 1000000000\n", "solver.window must be in [2, 100000]"),
    ("run.toml", "[frontend]\nmax_features = 10000000000\n", "frontend.max_features must be in [100, 1000000]"),
    ("run.toml", '[skeleton]\nrest_seconds = ["a"]\n', "skeleton.rest_seconds must be a list of numbers"),
    ("run.toml", "[skeleton]\nrest_seconds = [0.0, nan]\n", "skeleton.rest_seconds must be finite"),
    ("run.json", '{"skeleton": {"root_origin": [1]}}', "skeleton.root_origin must be a list of strings"),
    ("run.toml", '[frontend]\npoints = "some"\n', "frontend.points must be 'all' or 'reference', got 'some'"),
    ("run.toml", '[skeleton]\ndegenerate = "ignore"\n', "skeleton.degenerate must be 'raise', 'hinge' or 'mirror', got 'ignore'"),
    ("run.toml", '[skeleton]\nunregistered_ends = "drop"\n',
     "skeleton.unregistered_ends must be 'raise' or 'mirror', got 'drop'"),
    ("run.toml", "[solver]\nregistered_pose = [0.02, 0.0]\n",
     "solver.registered_pose must be [m, deg], both 0 or both > 0 (at most 1 m, 30 deg), got [0.02, 0.0]"),
    ("run.toml", "[solver]\nregistered_pose_below = 0\n", "solver.registered_pose_below must be an integer in [1, 100000]"),
    ("run.toml", '[skeleton]\ncentre_trials = ["capture"]\n',
     """skeleton.centre_trials must be ["rom"] or ["rom", "capture"], got ['capture']"""),
])
def test_run_refuses_non_finite_huge_or_mistyped_settings(tmp_path, capsys, name, text, culprit):
    path = tmp_path / name
    path.write_text(text)
    out = tmp_path / "out"
    assert main(["run", str(tmp_path), "--out", str(out), "--config", str(path)]) == 2
    one_line_error(capsys, "run", f"{path}: {culprit}")
    assert not out.exists()


def test_run_refuses_a_non_finite_flag(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(tmp_path), "--out", str(out), "--root-smoothness", "inf"]) == 2
    one_line_error(capsys, "run", "solver.root_smoothness must be finite")
    assert not out.exists()


def test_fingerprints_change_from_the_first_stage_a_setting_affects():
    base = fingerprints(RunConfig())
    solver = fingerprints(RunConfig().with_overrides({"solver.window": 30}))
    assert [base[s] == solver[s] for s in ("frontend", "world", "skeleton", "initial")] == [True] * 4
    assert base["solve"] != solver["solve"] and base["outputs"] != solver["outputs"]
    stride = fingerprints(RunConfig().with_overrides({"frontend.stride": 3}))
    assert all(base[s] != stride[s] for s in base)
    rom_only = fingerprints(RunConfig().with_overrides({"skeleton.centre_trials": ["rom"]}))
    assert base["frontend"] == rom_only["frontend"] and all(base[s] != rom_only[s] for s in STAGES[1:])
    # the world stage re-fits the registered poses under the solver's camera model: set, it redoes the world
    for camera_model in ({"solver.rolling_shutter_readout": 0.015}, {"solver.self_calibration": True}):
        changed = fingerprints(RunConfig().with_overrides(camera_model))
        assert base["frontend"] == changed["frontend"] and all(base[s] != changed[s] for s in STAGES[1:])


def test_a_readout_longer_than_two_processed_frames_names_the_setting():
    import types

    from bcmocap.pipeline.run import readouts_in_frames

    stores = [types.SimpleNamespace(fps=20.0), types.SimpleNamespace(fps=30.0)]
    assert readouts_in_frames(0.015, stores) == pytest.approx([0.3, 0.45])
    with pytest.raises(ValueError, match=r"solver.rolling_shutter_readout = 0.08 s spans 2.4 frame periods of the 30 fps"):
        readouts_in_frames(0.08, stores)


def test_a_range_of_motion_trial_with_nothing_registered_is_one_line_not_a_division_by_zero(tmp_path, monkeypatch):
    """A room whose repeated pattern matched nothing of the reference (the suite's realistic scoop in the repeated
    room): the world stage names what happened instead of dividing by a zero span."""
    from bcmocap.pipeline import run

    monkeypatch.setattr(run, "_refine_registered_poses", lambda ctx: None)
    monkeypatch.setattr(run, "_rom_inputs", lambda ctx: (np.zeros((5, 3, 7)), np.zeros((5, 3), bool), np.ones(5, bool)))
    ctx = run.RunContext(capture=None, config=RunConfig(), out=tmp_path, log=print)
    with pytest.raises(ValueError, match=r"registered no camera-frame of the range-of-motion trial \(see .*rom"):
        run._stage_world(ctx)


def test_the_skeleton_stage_logs_what_the_estimate_warns(monkeypatch):
    # A warning of the range-of-motion estimate (an end mirrored from its other side, a ball joint held on an axis)
    # is what the skeleton stage assumed: it goes to the run's log, with the settings passed through.
    import types
    import warnings

    import bcmocap.kinematics.rom as rom
    from bcmocap.pipeline import run

    seen = {}

    def estimate(*args, options, **kwargs):
        seen["options"] = options
        warnings.warn("joint 'left_foot': its centre is 'right_foot''s mirrored", stacklevel=2)
        return "estimate"

    monkeypatch.setattr(rom, "skeleton_from_range_of_motion", estimate)
    for name in ("_topology", "_stacked_intrinsics"):
        monkeypatch.setattr(run, name, lambda *a, **k: None)
    monkeypatch.setattr(run, "_more_trials", lambda *a, **k: [])
    monkeypatch.setattr(run, "_gyro_rest_orientations", lambda *a, **k: None)
    monkeypatch.setattr(run, "_sibling_rotations_from_gyros", lambda *a, **k: {})
    config = RunConfig().with_overrides({"skeleton.unregistered_ends": "raise"})
    logged = []
    ctx = types.SimpleNamespace(capture=types.SimpleNamespace(cameras=[]), config=config, log=logged.append)
    assert run._estimate_skeleton(ctx, Similarity.identity(), None, None, None) == "estimate"
    assert logged == ["skeleton: joint 'left_foot': its centre is 'right_foot''s mirrored"]
    assert seen["options"].unregistered_ends == "raise"
