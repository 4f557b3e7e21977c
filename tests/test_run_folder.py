"""The run folder's owner (bcmocap.io.run_folder): its log, its readers and their one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bcmocap.io.run_folder import (MODEL_FILES, RUN_FORMAT, STAGE_OUTPUTS, STAGES, RunLog, load_model, load_motion,
                                   load_solved_variables, read_json, read_run_log, save_motion, solved_variables)
from bcmocap.kinematics.skeleton import Motion


def test_every_stage_has_its_outputs_listed():
    assert set(STAGE_OUTPUTS) == set(STAGES)
    assert all(STAGE_OUTPUTS[s] for s in STAGES)


def test_the_run_log_records_forgets_and_reads_back(tmp_path):
    capture = tmp_path / "capture"
    capture.mkdir()
    (tmp_path / "run").mkdir()
    log = RunLog(tmp_path / "run", capture)
    for stage in STAGES[:4]:
        log.record(stage, f"fp-{stage}", 1.23456, frames=7)
    again = RunLog(tmp_path / "run", capture)
    assert again.finished("skeleton", "fp-skeleton") and not again.finished("skeleton", "other")
    assert again.data["stages"]["world"]["seconds"] == 1.235 and again.data["stages"]["world"]["frames"] == 7
    again.forget_from("skeleton")
    assert list(RunLog(tmp_path / "run", capture).data["stages"]) == ["frontend", "world"]
    assert read_run_log(tmp_path / "run")["capture"] == str(capture.resolve())


def test_a_run_of_another_capture_is_refused(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    RunLog(tmp_path, tmp_path / "a").record("frontend", "x", 1.0)
    with pytest.raises(ValueError, match="holds a run of another capture"):
        RunLog(tmp_path, tmp_path / "b")


@pytest.mark.parametrize("content, message", [
    (None, "not a bcmocap run folder"),
    ("{", "run.json: cannot read"),
    (json.dumps({"format": "something else", "capture": "/x"}), "run.json: not a bcmocap run log"),
    (json.dumps({"format": RUN_FORMAT, "capture": 3}), "run.json: not a bcmocap run log"),
    (json.dumps([1, 2]), "run.json: not a bcmocap run log"),
])
def test_a_folder_that_is_no_run_gets_one_line(tmp_path, content, message):
    if content is not None:
        (tmp_path / "run.json").write_text(content)
    with pytest.raises(ValueError, match=message) as info:
        read_run_log(tmp_path)
    assert "\n" not in str(info.value)


def test_read_json_names_the_file(tmp_path):
    with pytest.raises(ValueError, match=r"missing\.json: cannot read"):
        read_json(tmp_path / "missing.json")


def test_a_motion_and_its_variables_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    q = rng.normal(size=(5, 3, 4))
    motion = Motion(rng.normal(size=(5, 3)), q / np.linalg.norm(q, axis=-1, keepdims=True))

    class Solution:
        statics = {"readout": np.array([0.25])}
        frame_variables = {"bias": np.arange(10.0).reshape(5, 2)}

    save_motion(tmp_path / "motion.npz", motion, **solved_variables(Solution()))
    back = load_motion(tmp_path / "motion.npz")
    np.testing.assert_array_equal(np.asarray(back.root_position), np.asarray(motion.root_position))
    np.testing.assert_array_equal(np.asarray(back.rotations), np.asarray(motion.rotations))
    statics, frames = load_solved_variables(tmp_path / "motion.npz")
    np.testing.assert_array_equal(statics["readout"], [0.25])
    np.testing.assert_array_equal(frames["bias"], Solution.frame_variables["bias"])


def test_a_motion_that_is_not_one_names_the_file(tmp_path):
    np.savez(tmp_path / "other.npz", something=np.zeros(3))
    with pytest.raises(ValueError, match=r"other\.npz: not a saved motion"):
        load_motion(tmp_path / "other.npz")


def test_the_solved_model_falls_back_to_the_estimate(tmp_path):
    from bcmocap.io.model_json import rig_to_dict, skeleton_to_dict
    from bcmocap.sim.motions import load_body_motion
    from bcmocap.sim.rig import standard_rig

    skeleton, _ = load_body_motion("walk", fps=60.0, seconds=0.1)
    rig = standard_rig(skeleton)
    (tmp_path / "model").mkdir()
    for name, content in zip(MODEL_FILES, (skeleton_to_dict(skeleton), rig_to_dict(rig, skeleton))):
        (tmp_path / "model" / name).write_text(json.dumps(content))
    for stage in ("model", "solve"):
        got_skeleton, got_rig = load_model(tmp_path, stage)
        assert got_skeleton.names == skeleton.names and got_rig.names == rig.names
