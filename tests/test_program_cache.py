"""Traced window solves stored on disk: the same results bit for bit, and only programs whose code is known."""

import jax.numpy as jnp
import numpy as np
import pytest

from bcmocap.residuals import FrameTerm, JointSmoothness, Reprojection, RootSmoothness, pair_mask
from bcmocap.solver import Problem, SolverOptions, solve
from bcmocap.solver import program_cache

from test_solver import T, setup  # noqa: F401  (the module fixture)

OPTIONS = SolverOptions(window=4, overlap=1)


class KneeLimit(FrameTerm):
    """A researcher's own term: its code is outside bcmocap, so a program holding it is never stored."""

    def residual(self, state, data, variables):
        return state.motion.rotations[4, 1:, None], jnp.ones(3, bool)


def paper_terms(setup):
    skeleton, rig, _, points, (ids, pix, w), _ = setup
    return [Reprojection({"point_ids": ids, "pixels": pix, "weights": w}, points=points),
            RootSmoothness(pair_mask(T), weight=10.0), JointSmoothness(pair_mask(T), skeleton=skeleton)]


@pytest.fixture
def folder(tmp_path, monkeypatch):
    """Programs go to ``tmp_path``; nothing loaded in this process yet (as in a new process)."""
    monkeypatch.setattr(program_cache, "_folder", lambda: tmp_path)
    monkeypatch.setattr(program_cache, "_loaded", {})
    monkeypatch.setattr(program_cache, "_not_storable", set())
    return tmp_path


def solved(problem, init):
    result = solve(problem, init, OPTIONS)
    return np.asarray(result.motion.root_position), np.asarray(result.motion.rotations)


def plain(problem, init, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(program_cache, "_folder", lambda: None)
        return solved(problem, init)


@pytest.mark.slow  # 24 s; the fast tier stores and reloads a program in the damaged-program test
def test_a_stored_program_solves_bit_for_bit_as_the_traced_one(setup, folder, monkeypatch):
    skeleton, rig, *_, init = setup
    problem = Problem(skeleton, rig, paper_terms(setup))
    first = solved(problem, init)
    stored = list(folder.glob("*.bin"))
    assert len(stored) == 1, "every window has the same shapes: one program"
    monkeypatch.setattr(program_cache, "_loaded", {})  # a new process: the program comes from the file

    def no_trace(*args):
        raise AssertionError("the stored program should have been used")

    monkeypatch.setattr(program_cache, "_export", no_trace)
    again = solved(problem, init)
    reference = plain(problem, init, monkeypatch)
    for a, b, c in zip(first, again, reference):
        assert np.array_equal(a, b) and np.array_equal(a, c)


@pytest.mark.slow  # 23 s (two solves traced); moved out of the fast tier for its 5-minute budget
def test_a_program_with_a_researchers_own_term_is_traced_not_stored(setup, folder, monkeypatch):
    skeleton, rig, *_, init = setup
    problem = Problem(skeleton, rig, [*paper_terms(setup), KneeLimit(np.ones(T), weight=100.0)])
    result = solved(problem, init)
    assert not list(folder.glob("*.bin"))
    for a, b in zip(result, plain(problem, init, monkeypatch)):
        assert np.array_equal(a, b)


DAMAGE = {
    "garbage": lambda b: b"not a program",
    "empty": lambda b: b"",
    "truncated": lambda b: b[: len(b) // 2],
    "one byte flipped in the program": lambda b: b[:-100] + bytes([b[-100] ^ 0x01]) + b[-99:],
    "no checksum line (an older writer)": lambda b: b[b.index(b"\n") + 1:],
}


def test_a_damaged_program_is_dropped_with_a_note_traced_again_and_replaced(setup, folder, monkeypatch, capsys):
    """Every kind of damage is found (:func:`is_whole`: what the call reads first); one of them is then followed
    through the solve (each kind took a trace and a solve of 80 s in the heavy tier, for the same path)."""
    skeleton, rig, *_, init = setup
    problem = Problem(skeleton, rig, paper_terms(setup))
    first = solved(problem, init)
    (path,) = folder.glob("*.bin")
    stored = path.read_bytes()
    assert program_cache.is_whole(path)
    for name, damage in DAMAGE.items():
        copy = folder / "damaged.program"
        copy.write_bytes(damage(stored))
        assert not program_cache.is_whole(copy), name
        copy.unlink()
    path.write_bytes(DAMAGE["one byte flipped in the program"](stored))
    monkeypatch.setattr(program_cache, "_loaded", {})
    capsys.readouterr()
    again = solved(problem, init)
    assert "note: dropped the damaged stored program" in capsys.readouterr().err
    assert program_cache.is_whole(path)  # stored anew
    for a, b in zip(first, again):
        assert np.array_equal(a, b)


def test_the_key_covers_settings_shapes_where_arrays_are_and_unknown_code():
    options = ({"max_steps": 50}, SolverOptions())
    key = program_cache.program_key(options, [np.zeros((3, 2))])
    assert key == program_cache.program_key(({"max_steps": 50}, SolverOptions()), [np.zeros((3, 2))])
    assert key != program_cache.program_key(({"max_steps": 51}, SolverOptions()), [np.zeros((3, 2))])
    assert key != program_cache.program_key(options, [np.zeros((3, 3))])
    assert key != program_cache.program_key(options, [np.zeros((3, 2), np.float32)])
    # an array in the first field and None in the second, or the other way round: the same static part
    assert program_cache.program_key(None, (np.zeros(2), None)) != program_cache.program_key(None, (None, np.zeros(2)))
    assert program_cache.program_key((KneeLimit(np.ones(2)),), []) is None
    assert program_cache.program_key((lambda x: x,), []) is None
