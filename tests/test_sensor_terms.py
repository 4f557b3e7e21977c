"""The wearable-sensor terms of examples/wearable_sensors (a user's terms outside bcmocap): with exact sensor
data from the studio they vanish at the true motion, and each pulls a perturbed motion back."""

import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from bcmocap.io.sensors import write_contacts, write_imu
from bcmocap.kinematics import Motion
from bcmocap.sim import standard_rig
from bcmocap.sim.sensors import simulate_contacts, simulate_imu
from bcmocap.sim.studio import _body_motion
from bcmocap.residuals import TermWindow
from bcmocap.solver.objective import UserTerms
from bcmocap.solver.window import make_window_problem, residuals, window_history

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "wearable_sensors"))
import sensor_terms  # noqa: E402

FPS, STRIDE, LEAD = 60.0, 2, 15
EXACT = dict(gyro_noise=0.0, gyro_bias=0.0, accel_noise=0.0, accel_bias=0.0)


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    """1.5 s of the walk, its exact sensor files in a trial folder, and the motion at the solver's frames
    (every STRIDE-th video frame from the first clap, the pose held before the trial starts)."""
    skeleton, motion = _body_motion("walk", FPS, 1.5)
    rig = standard_rig(skeleton, 64, 36)
    claps = np.array([-LEAD, motion.num_frames - 1 + LEAD])
    folder = tmp_path_factory.mktemp("trial")
    write_imu(folder / "imu.npz", simulate_imu(skeleton, rig, motion, FPS, claps, seed=1, **EXACT))
    write_contacts(folder / "contacts.npz", simulate_contacts(skeleton, motion, FPS, claps))
    frames = np.clip(claps[0] + STRIDE * np.arange((motion.num_frames + LEAD) // STRIDE), 0, motion.num_frames - 1)
    solver_motion = Motion(np.asarray(motion.root_position)[frames], np.asarray(motion.rotations)[frames])
    return skeleton, rig, folder, solver_motion


def _blocks(trial, factory, start, stop, **settings):
    skeleton, rig, folder, motion = trial
    window = TermWindow(start, stop, FPS / STRIDE, skeleton, rig, trial_folder=folder)
    terms = UserTerms(factory, settings, factory.__name__)(window)
    h = window_history(terms)
    before = np.maximum(np.arange(start - h, start), 0)
    index = np.concatenate([before, np.arange(start, stop)])
    reference = Motion(np.asarray(motion.root_position)[index], np.asarray(motion.rotations)[index])
    problem = make_window_problem(skeleton, rig, [t.window(0, stop - start) for t in terms], reference, min(start, h))
    return problem, terms


@pytest.mark.parametrize("factory, median, largest", [(sensor_terms.gyroscope, 1e-10, 1e-9),
                                                       (sensor_terms.accelerometer, 0.5, 10.0)])
def test_imu_terms_vanish_at_the_true_motion(trial, factory, median, largest):
    """The gyro's camera rotation changes (rad) and the accelerometer's IMU accelerations (m/s²) match the true
    motion's: the sensors, their mounts, their clock and the solver's frame times agree. The gyro is exact; the
    accelerometer's triangle-weighted average is a quadrature at 240 Hz of the walk's jittery accelerations (a
    median 9 m/s² error without the averaging, i.e. comparing with the middle frame's sample)."""
    problem, terms = _blocks(trial, factory, 8, 40, weight=1.0, loss="none")
    (r,) = residuals(problem, jnp.zeros((problem.num_frames, problem.skeleton.num_dofs)))
    valid = np.asarray(terms[0].data["valid"])
    assert valid.sum() > 0.9 * valid.size
    error = np.linalg.norm(np.asarray(r), axis=-1)[valid]
    assert np.median(error) < median and error.max() < largest


def test_foot_contact_flags_planted_feet(trial):
    """Flagged ankles of the true motion move by a median 2 mm between solver frames (at most 1.5 cm: the
    flags' edges); both feet get flags, not everywhere."""
    problem, terms = _blocks(trial, sensor_terms.foot_contact, 0, 40, weight=1.0, loss="none")
    (r,) = residuals(problem, jnp.zeros((problem.num_frames, problem.skeleton.num_dofs)))
    flags = np.asarray(terms[0].data["planted"])
    assert flags[:, 0].any() and flags[:, 1].any() and not flags.all()
    step = np.linalg.norm(np.asarray(r), axis=-1)[flags]
    assert np.median(step) < 0.002 and step.max() < 0.015


def test_a_missing_sensor_file_is_named(trial, tmp_path):
    skeleton, rig, _, _ = trial
    window = TermWindow(0, 10, FPS / STRIDE, skeleton, rig, trial_folder=tmp_path)
    with pytest.raises(ValueError, match=r"imu\.npz: missing \(a term factory reads it\)"):
        sensor_terms.gyroscope(window)
