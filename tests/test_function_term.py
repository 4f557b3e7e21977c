"""Terms written as decorated functions (bcmocap.residuals.residual_term): the kind each becomes, its errors, that the
solver gives it exactly what it gives the same term written as a class, and the tutorial's gyroscope term."""

from __future__ import annotations

import pickle
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bcmocap.geometry import SE3, SO3
from bcmocap.io.sensors import write_imu
from bcmocap.kinematics import Motion
from bcmocap.residuals import (CameraPairTerm, CameraTerm, FrameTerm, MultiFrameTerm, PairTerm, PerCamera, TermWindow,
                               residual_term)
from bcmocap.residuals.variables import Euclidean
from bcmocap.sim import standard_capture
from bcmocap.sim.sensors import simulate_imu
from bcmocap.solver.objective import UserTerms
from bcmocap.solver.window import cost, make_window_problem, normal_equations, residuals, window_history

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "gyro_term"
sys.path.insert(0, str(EXAMPLE))
import gyro_term  # noqa: E402


# ---- the same five terms, as functions and as classes -------------------------------------------------------


@residual_term(statics={"offset": 1})
def root_height(state, data, variables):
    return (state.motion.root_position[2:3] + variables["offset"] - data)[None], jnp.ones(1, bool)


@residual_term(frames=2)
def root_step(states, data, variables):
    return (states[1].motion.root_position - states[0].motion.root_position - data)[None], jnp.ones(1, bool)


@residual_term(frames=3)
def centre_acceleration(states, data, variables):
    c = states.world_from_camera.translation()  # (3, C, 3)
    return c[2] - 2.0 * c[1] + c[0] - data, jnp.ones(data.shape[0], bool)


@residual_term(camera=True, statics={"shift": PerCamera(Euclidean(2), 18)})
def shifted_pixels(view, data, variables):
    pixels, valid = view.camera.project(view.cam_from_world.apply(data["points"]))
    return pixels + variables["shift"] - data["pixels"], valid


@residual_term(frames=2, camera=True, rotation_only=True)
def camera_turn(view, data, variables):
    turn = view[1].cam_from_world.rotation() @ view[0].cam_from_world.rotation().inverse()
    return (SO3(data).inverse() @ turn).log()[None], jnp.ones(1, bool)


class RootHeight(FrameTerm):
    def static_variables(self):
        return {"offset": 1}

    def residual(self, x, data, variables):
        return (x.motion.root_position[2:3] + variables["offset"] - data)[None], jnp.ones(1, bool)


class RootStep(PairTerm):
    def residual(self, x, data, variables):
        return (x[1].motion.root_position - x[0].motion.root_position - data)[None], jnp.ones(1, bool)


class CentreAcceleration(MultiFrameTerm):
    span = 3

    def residual(self, x, data, variables):
        c = x.world_from_camera.translation()
        return c[2] - 2.0 * c[1] + c[0] - data, jnp.ones(data.shape[0], bool)


class ShiftedPixels(CameraTerm):
    def static_variables(self):
        return {"shift": PerCamera(Euclidean(2), 18)}

    def residual(self, x, data, variables):
        pixels, valid = x.camera.project(x.cam_from_world.apply(data["points"]))
        return pixels + variables["shift"] - data["pixels"], valid


class CameraTurn(CameraPairTerm):
    rotation_only = True

    def residual(self, x, data, variables):
        turn = x[1].cam_from_world.rotation() @ x[0].cam_from_world.rotation().inverse()
        return (SO3(data).inverse() @ turn).log()[None], jnp.ones(1, bool)


def test_each_decorated_function_becomes_its_kind():
    expected = [(root_height, "frame", 1, False), (root_step, "pair", 2, False), (centre_acceleration, "span", 3, False),
                (shifted_pixels, "camera", 1, True), (camera_turn, "camera_pair", 2, True)]
    for term, kind, span, per_camera in expected:
        assert (term.kind, term.span, term.per_camera) == (kind, span, per_camera), term.__name__
    assert camera_turn.rotation_only and not shifted_pixels.__dict__.get("rotation_only", False)
    assert root_height(np.zeros(3)).static_variables() == {"offset": 1}
    assert root_height(np.zeros(3), name="height").label == "height" and root_step(np.zeros(3)).label == "root_step"


def test_a_decorated_term_class_pickles_by_reference():
    """The solver's program cache keys on the terms' classes by reference, as it does for a class written out."""
    assert pickle.loads(pickle.dumps(gyro_term.gyro_turn)) is gyro_term.gyro_turn


@pytest.mark.parametrize("arguments, message", [
    (dict(frames=0), "frames must be 1, 2"),
    (dict(frames=3, camera=True), "frames must be 1, 2"),
    (dict(camera=True, frame_variables={"wobble": 6}), "cannot declare per-frame variables"),
    (dict(frames=2, rotation_only=True), "rotation_only is for two-frame camera terms"),
])
def test_a_combination_without_a_kind_is_refused_naming_the_function(arguments, message):
    def bad(x, data, variables):
        return x, data

    with pytest.raises(ValueError, match=f"residual_term '.*bad'.*{message}"):
        residual_term(bad, **arguments)


@pytest.fixture(scope="module")
def window():
    """Twelve frames of the standard walk, one frame before them, and per-term data."""
    capture = standard_capture("walk", seconds=0.3, width=64, height=36)
    rng = np.random.default_rng(0)
    t, c = capture.num_frames, capture.rig.num_cameras
    points = rng.normal(size=(t, c, 2, 3)) + np.array([0.0, 0.0, 3.0])
    data = {"height": np.full(t, 1.0), "step": rng.normal(scale=0.01, size=(t, 3)),
            "acceleration": rng.normal(scale=0.01, size=(t, c, 3)),
            "pixels": {"points": points, "pixels": rng.normal(30.0, 5.0, size=(t, c, 2, 2))},
            "turn": np.asarray(SO3.exp(jnp.asarray(rng.normal(scale=0.01, size=(t, c, 3)))).wxyz)}
    return capture, data


def _system(capture, terms, seed=1):
    start, stop = 3, 13
    cut = [t.window(start, stop) for t in terms]
    h = window_history(cut)
    reference = jax.tree.map(lambda a: a[start - h : stop], capture.motion)
    problem = make_window_problem(capture.skeleton, capture.rig, cut, reference, h)
    rng = np.random.default_rng(seed)
    y = jnp.asarray(rng.normal(scale=1e-3, size=(stop - start, problem.frame_size)))
    z = jnp.asarray(rng.normal(scale=1e-3, size=(problem.num_statics,)))
    return problem, y, z


@pytest.mark.slow
def test_a_function_term_gets_exactly_what_its_class_gets(window):
    """Residuals and normal equations (banded blocks, the static border, gradients) of a window with all five kinds
    written as decorated functions are bit for bit those of the same terms written as classes."""
    capture, d = window
    made = [root_height(d["height"], weight=3.0), root_step(d["step"], weight=2.0),
            centre_acceleration(d["acceleration"], weight=0.5), shifted_pixels(d["pixels"]),
            camera_turn(d["turn"], weight=4.0)]
    written = [RootHeight(d["height"], weight=3.0), RootStep(d["step"], weight=2.0),
               CentreAcceleration(d["acceleration"], weight=0.5), ShiftedPixels(d["pixels"]),
               CameraTurn(d["turn"], weight=4.0)]
    (a, y, z), (b, _, _) = _system(capture, made), _system(capture, written)
    for r_made, r_written in zip(residuals(a, y, z), residuals(b, y, z)):
        np.testing.assert_array_equal(np.asarray(r_made), np.asarray(r_written))
    for x, w in zip(jax.tree.leaves(normal_equations(a, y, z)), jax.tree.leaves(normal_equations(b, y, z))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(w))


# ---- the tutorial's gyroscope term ----------------------------------------------------------------------


def test_the_tutorial_term_is_in_the_tutorial_and_short():
    """docs/residual-terms.md shows examples/gyro_term/gyro_term.py whole, and it fits in 25 lines."""
    source = (EXAMPLE / "gyro_term.py").read_text()
    assert len(source.splitlines()) <= 25
    tutorial = (Path(__file__).resolve().parents[1] / "docs" / "residual-terms.md").read_text()
    assert f"```python\n{source}```" in tutorial


@pytest.fixture(scope="module")
def gyro_window(tmp_path_factory, window):
    """The walk's exact gyro in a trial folder, and a window of the tutorial's term over frames [3, 13)."""
    capture, _ = window
    folder = tmp_path_factory.mktemp("trial")
    claps = np.array([0, capture.num_frames - 1])
    write_imu(folder / "imu.npz", simulate_imu(capture.skeleton, capture.rig, capture.motion, capture.fps, claps,
                                               seed=1, gyro_noise=0.0, gyro_bias=0.0, accel_noise=0.0, accel_bias=0.0))
    term_window = TermWindow(3, 13, capture.fps, capture.skeleton, capture.rig, trial_folder=folder)
    (term,) = UserTerms(gyro_term.gyroscope, {"weight": 1.0}, "gyro_term:gyroscope")(term_window)
    return capture, term


def test_the_tutorial_term_vanishes_at_the_true_motion(gyro_window):
    capture, term = gyro_window
    problem, _, _ = _system(capture, [term_for_window(term)])
    (r,) = residuals(problem, jnp.zeros((problem.num_frames, problem.frame_size)))
    assert np.abs(np.asarray(r)).max() < 1e-8


def test_the_tutorial_term_gradient_is_the_finite_difference_one(gyro_window):
    """The normal equations' gradient of the gyro term (IRLS: the exact gradient) against central differences of the
    window's cost, at a motion off the truth."""
    capture, term = gyro_window
    problem, y, _ = _system(capture, [term_for_window(term)], seed=3)
    y = 30.0 * y
    grad = np.asarray(jax.jit(lambda motion: normal_equations(problem, motion).grad)(y))  # compiled once
    window_cost = jax.jit(lambda motion: cost(problem, motion))
    eps, rng = 1e-6, np.random.default_rng(4)
    for _ in range(6):
        i, j = rng.integers(problem.num_frames), rng.integers(problem.frame_size)
        step = jnp.zeros_like(y).at[i, j].set(eps)
        fd = (float(window_cost(y + step)) - float(window_cost(y - step))) / (2 * eps)
        assert abs(fd - grad[i, j]) <= 1e-6 * max(1.0, abs(grad[i, j])), (i, j, fd, grad[i, j])


def term_for_window(term):
    """The tutorial term (made for frames [3, 13)) as a sequence term that :func:`_system` cuts to those frames."""
    padded = jax.tree.map(lambda a: np.concatenate([np.repeat(np.asarray(a)[:1], 3, axis=0), np.asarray(a),
                                                     np.repeat(np.asarray(a)[-1:], 5, axis=0)]), term.data)
    return type(term)(padded, weight=term.weight, name=term.name)
