"""benchmarks/suite.py (issue 42): the grid, the realistic config a user would write, and the time offsets compared
with the truth in one unit."""

import json

import numpy as np
import pytest

from benchmarks import suite
from bcmocap.pipeline.config import load_config


def test_the_grid_covers_every_motion_and_room_and_names_are_unique():
    full = suite.planned_runs(False, 3)
    realistic = [r for r in full if r.condition == "realistic"]
    clean = [r for r in full if r.condition == "clean"]
    assert len(realistic) == 20 and len(clean) == 10 and len({r.name for r in full}) == 30
    assert {r.motion for r in realistic} == set(suite.MOTIONS) and {r.room for r in realistic} == set(suite.ROOMS)
    assert [r.name for r in suite.planned_runs(True, 3)] == ["clean-walk-textured-s0", "realistic-walk-textured-s0"]


def test_the_realistic_config_is_told_only_what_a_user_knows():
    config = load_config(suite.CONFIGS["realistic"])
    f, s = config.frontend, config.solver
    assert f.rolling_shutter_readout == pytest.approx(0.0148)  # a data sheet's, not the capture's
    assert f.gyro_timing == "frames" and f.estimate_readout  # timing and readout found in the frames
    assert s.rolling_shutter_readout == 0 and s.estimate_time_offsets and s.self_calibration
    assert tuple(s.mount_compliance) == (0.003, 2.0)  # the documented default, not the rendered wobble


def test_time_offsets_are_compared_in_video_frames_relative_to_their_mean(tmp_path):
    true = np.array([0.1, -0.3, 0.2])  # video frames after the run's frame times
    clocks = {"offsets": [10, 20, 30], "first_clap_true": (np.array([10, 20, 30]) - true).tolist(), "fps": 60.0}
    run = tmp_path / "run"
    (run / "frontend" / "capture").mkdir(parents=True)
    assert suite.time_offset_errors(tmp_path / "nothing", clocks) is None
    gyro_ms = (true + 0.5) / 60.0 * 1e3 + 25.0  # a common IMU clock offset drops out
    gyro_ms[1] += 0.6  # 0.036 frames off
    (run / "frontend" / "capture" / "registration.json").write_text(json.dumps(
        {"stride": 2, "gyro_timing": {"time_shift_ms": gyro_ms.tolist(), "readout_ms": 13.0}}))
    (run / "solve").mkdir()
    np.savez(run / "solve" / "motion.npz", **{"static:time_offset": ((true + 0.2) / 2)[:, None]})  # solver frames
    found = suite.time_offset_errors(run, clocks)
    assert found["solver"]["max_frames"] == pytest.approx(0.0, abs=1e-12)
    assert found["gyro"]["max_frames"] == pytest.approx(0.6 * 60 / 1e3 * 2 / 3) and found["gyro"]["readout_ms"] == 13.0


def test_lens_error_separates_what_a_turn_of_the_camera_undoes():
    from bcmocap.cameras import FOVCamera

    truth = FOVCamera(width=640, height=360, focal=[250.0, 250.0], principal_point=[319.5, 179.5], omega=0.9)
    same = suite._lens_error(truth, truth)
    assert same["covered_max_px"] < 1e-9 and same["covered_max_after_rotation_px"] < 1e-9
    shifted = suite._lens_error(FOVCamera(width=640, height=360, focal=[250.0, 250.0],
                                          principal_point=[319.5, 180.0], omega=0.9), truth)
    assert shifted["covered_max_px"] == pytest.approx(0.5, abs=1e-6)  # half a pixel everywhere
    assert shifted["covered_rms_after_rotation_px"] < 0.25 * shifted["covered_rms_px"]  # mostly a turn
    assert 0.05 < shifted["rotation_deg"] < 0.2
    longer = suite._lens_error(FOVCamera(width=640, height=360, focal=[251.0, 251.0],
                                         principal_point=[319.5, 179.5], omega=0.9), truth)
    assert longer["covered_max_after_rotation_px"] > 0.99 * longer["covered_max_px"]  # a focal error is not a turn


def test_the_sparse_room_is_photographed_with_more_overlap_and_every_subject_turns_the_ankles_last():
    import argparse

    args = argparse.Namespace(seconds=2.0, rom_seconds=6.0, rom_tempo=0.5, rom_protocol="feet_after")
    sparse = suite.capture_settings(suite.Run("realistic", "run", "sparse", 2), args)
    textured = suite.capture_settings(suite.Run("clean", "run", "textured", 2), args)
    assert sparse.reference_photos == 48 and textured.reference_photos == 24
    assert sparse.room == "sparse" and sparse.clock_ppm > 0 and textured.clock_ppm == 0  # the presets themselves
    assert sparse.rom_protocol == textured.rom_protocol == "feet_after"  # both conditions, one protocol



def test_captures_of_one_condition_and_seed_share_one_calibration_and_other_seeds_do_not():
    # The suite calibrates each lens set once (benchmarks/suite.py, lens_key): that is exact only because the studio
    # draws a capture's lens units from its seed and image size, whatever its room and motion.
    import argparse

    from bcmocap.cameras import FOVCamera, stack_cameras
    from bcmocap.kinematics.rig import Rig
    from bcmocap.sim.studio import _lens_units

    args = argparse.Namespace(seconds=2.0, rom_seconds=6.0, rom_tempo=0.5, rom_protocol="feet_after")
    lens = FOVCamera(width=640, height=360, focal=[250.0, 250.0], principal_point=[319.5, 179.5], omega=0.9)
    base = Rig(["a", "b", "c"], [0, 1, 2], np.tile([1.0, 0, 0, 0, 0, 0, 0], (3, 1)), stack_cameras([lens] * 3))

    def key(run, model=None):
        settings = suite.capture_settings(run, args)
        units, _ = _lens_units(settings, base)
        return suite.lens_key(settings, units, model or suite.LENS_MODELS[run.condition], 64)

    walk, lenses = key(suite.Run("realistic", "walk", "textured", 1))
    assert len(lenses) == 3 and sorted(sum(lenses.values(), [])) == ["a", "b", "c"]  # a unit per camera
    assert key(suite.Run("realistic", "hop", "sparse", 1))[0] == walk
    assert key(suite.Run("realistic", "walk", "textured", 2))[0] != walk
    assert key(suite.Run("realistic", "walk", "textured", 1), model="fov")[0] != walk
