"""NaN and inf never pass a boundary unnamed (issue 25, item 4): every reader refuses them in its arrays
with the file and the place, the solver checks inside its compiled loop, and no NaN is written to a BVH.

(NaN is data only where a format says so: a C3D gap, a missing 2D joint of ``bcmocap kcs``; ±inf ASF
limits mean no limit.)
"""

import json
import shutil
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks._fuzz import READERS  # the fuzz harness's seed files and readers


def _seed(name: str, tmp_path: Path) -> Path:
    folder = tmp_path / name
    folder.mkdir()
    READERS[name].make_seed(folder)
    return folder


def _replace_line(path: Path, start: str, new: str) -> None:
    lines = path.read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if line.strip().startswith(start))
    lines[k] = new
    path.write_text("\n".join(lines) + "\n")


def _non_finite(value, depth: int = 0) -> list[str]:
    """Where a reader's result holds a NaN or inf float (arrays, numbers, containers, dataclasses)."""
    import dataclasses

    if depth > 6 or isinstance(value, (str, bytes)):
        return []
    if isinstance(value, float):
        return [] if np.isfinite(value) else ["a number"]
    if isinstance(value, np.ndarray) or hasattr(value, "__jax_array__") or type(value).__module__.startswith("jax"):
        a = np.asarray(value)
        return ["an array"] if a.dtype.kind == "f" and not np.all(np.isfinite(a)) else []
    if isinstance(value, dict):
        items = list(value.values())
    elif isinstance(value, (list, tuple)):
        items = list(value)[:100]
    elif dataclasses.is_dataclass(value):
        items = [getattr(value, f.name, None) for f in dataclasses.fields(value)]
    elif hasattr(value, "__dict__"):
        items = list(vars(value).values())
    else:
        return []
    return [w for item in items for w in _non_finite(item, depth + 1)]


TEXT_TARGETS = {"bvh": ["seed.bvh"], "amc": ["seed.amc"], "capture_json": ["capture.json", "rig.json"],
                "intrinsics_yaml": ["seed.yml"], "intrinsics_json": ["seed.json"],
                "model_json": ["model/skeleton.json", "model/rig.json"], "config_toml": ["seed.toml"],
                "config_json": ["seed.json"], "ply": ["ascii.ply"]}


@pytest.mark.parametrize("name", sorted(TEXT_TARGETS))
def test_a_nan_or_inf_in_any_number_of_a_text_file_is_refused_naming_the_file(tmp_path, name):
    """Every 4th number of each file (up to 20) replaced by nan, inf or -inf in turn: the reader raises a
    ValueError naming the file, or what it returns is finite."""
    from benchmarks._fuzz import NUMBER

    seed = _seed(name, tmp_path)
    for target in TEXT_TARGETS[name]:
        data = (seed / target).read_bytes()
        for k, m in enumerate(list(NUMBER.finditer(data))[::4][:20]):
            value = (b"nan", b"inf", b"-inf")[k % 3]
            case = tmp_path / f"case_{target.replace('/', '_')}_{k}"
            shutil.copytree(seed, case)
            (case / target).write_bytes(data[:m.start()] + value + data[m.end():])
            try:
                result = READERS[name].read(case)
            except ValueError as exc:
                assert Path(target).name in str(exc), str(exc)
                continue
            assert not _non_finite(result), f"{target}: {m.group().decode()} -> {value.decode()} was read as it is"


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_bvh_offsets_and_frame_time_must_be_finite(tmp_path, value):
    folder = _seed("bvh", tmp_path)
    bvh = folder / "seed.bvh"
    text = bvh.read_text()
    lines = text.splitlines()
    k = [i for i, line in enumerate(lines) if line.strip().startswith("OFFSET")][1]  # a joint's offset
    lines[k] = lines[k].replace("OFFSET", "OFFSET " + value).rsplit(" ", 1)[0]  # its x replaced
    bvh.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=rf"seed\.bvh:\d+: OFFSET .*holds '{value}'"):
        READERS["bvh"].read(folder)
    bvh.write_text(text)
    _replace_line(bvh, "Frame Time", f"Frame Time: {value}")
    with pytest.raises(ValueError, match=r"seed\.bvh:\d+: expected a positive, finite frame time"):
        READERS["bvh"].read(folder)


def test_asf_limits_may_be_unbounded_but_not_nan(tmp_path):
    folder = _seed("asf", tmp_path)
    asf = folder / "seed.asf"
    text = asf.read_text()
    k = text.index("limits")
    end = text.index(")", k)
    asf.write_text(text[:k] + "limits (-inf inf" + text[end:])
    READERS["asf"].read(folder)  # ±inf: that dof has no limit
    asf.write_text(text[:k] + "limits (nan 10" + text[end:])
    with pytest.raises(ValueError, match=r"seed\.asf:\d+: limits '\(nan 10\)' hold NaN"):
        READERS["asf"].read(folder)


def test_c3d_gaps_are_nan_but_an_infinite_coordinate_is_refused(tmp_path):
    import ezc3d

    from bcmocap.io.c3d import read_c3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = ("A", "B")
    data = np.ones((4, 2, 3))
    data[0, 0, 1] = np.nan  # a gap
    c["data"]["points"] = data
    c.write(str(tmp_path / "gap.c3d"))
    assert np.isnan(read_c3d(tmp_path / "gap.c3d").positions[1, 0]).all()
    data[2, 1, 2] = np.inf
    c["data"]["points"] = data
    c.write(str(tmp_path / "inf.c3d"))
    with pytest.raises(ValueError, match=r"inf\.c3d: point 'B' has an infinite coordinate at frame 2"):
        read_c3d(tmp_path / "inf.c3d")


@pytest.mark.parametrize("name", ["ascii.ply", "binary.ply"])
def test_ply_refuses_nan_and_inf_vertices(tmp_path, name):
    from bcmocap.io.ply import read_ply

    folder = _seed("ply", tmp_path)
    path = folder / name
    data = path.read_bytes()
    header_end = data.index(b"end_header\n") + len(b"end_header\n")
    if name == "ascii.ply":
        rows = data[header_end:].decode().splitlines()
        rows[2] = " ".join(["inf", *rows[2].split()[1:]])
        path.write_bytes(data[:header_end] + ("\n".join(rows) + "\n").encode())
    else:
        body = bytearray(data[header_end:])
        row = len(body) // 4  # 4 vertices of x y z double + r g b uchar
        body[2 * row + 8: 2 * row + 16] = np.array([np.nan], "<f8").tobytes()
        path.write_bytes(data[:header_end] + bytes(body))
    with pytest.raises(ValueError, match=rf"{name}: element 'vertex' row 2 property '[xy]' is (inf|nan)"):
        read_ply(path)


@pytest.mark.parametrize("case", ["pixels", "weights", "homography_pixels_prev", "poses", "points"])
def test_store_blocks_poses_and_points_name_the_file_and_place(tmp_path, case):
    from bcmocap.correspondence_store import CorrespondenceStore

    store = _seed("store", tmp_path) / "store"
    if case == "points":
        points = np.fromfile(store / "points.f64", "<f8")
        points[3 * 4 + 1] = np.inf
        points.tofile(store / "points.f64")
        match = r"points\.f64: point 4 has NaN or inf"
    elif case == "poses":
        with np.load(store / "poses.npz") as z:
            arrays = dict(z)
        arrays["world_from_camera"][3, 1, 5] = np.nan
        np.savez(store / "poses.npz", **arrays)
        match = r"poses\.npz: world_from_camera has NaN or inf at registered frame 3, camera 1"
    else:
        block = store / "block_000003.npz"
        with np.load(block) as z:
            arrays = dict(z)
        arrays[case][1, 0, 0] = np.nan
        np.savez(block, **arrays)
        match = rf"block_000003\.npz: {case} has NaN.* at frame 4, camera 0, slot 0"
    with pytest.raises(ValueError, match=match):
        opened = CorrespondenceStore.open(store)
        opened.frames(0, opened.num_frames)


def test_correspondences_refuse_an_infinite_frame_rate(tmp_path):
    folder = _seed("store", tmp_path)
    index = json.loads((folder / "store" / "index.json").read_text())
    corr = READERS["store"].read(folder)[0]
    with pytest.raises(ValueError, match="fps must be finite, got inf"):
        type(corr)(**{**corr.__dict__, "fps": float("inf")})
    assert index["fps"] == 30.0


def test_a_saved_motion_with_nan_is_refused_naming_the_file(tmp_path):
    from bcmocap.pipeline.run import load_motion

    rotations = np.tile([1.0, 0, 0, 0], (5, 3, 1))
    np.savez(tmp_path / "checkpoint.npz", root_position=np.zeros((5, 3)), rotations=rotations)
    assert load_motion(tmp_path / "checkpoint.npz").num_frames == 5
    rotations[3, 2, 1] = np.nan
    np.savez(tmp_path / "checkpoint.npz", root_position=np.zeros((5, 3)), rotations=rotations)
    with pytest.raises(ValueError, match=r"checkpoint\.npz: rotations holds NaN or inf at frame 3"):
        load_motion(tmp_path / "checkpoint.npz")


def test_write_bvh_never_writes_nan(tmp_path):
    from bcmocap.io.bvh import read_bvh, write_bvh

    folder = _seed("bvh", tmp_path)
    data = READERS["bvh"].read(folder)
    motion = data.motion
    write_bvh(tmp_path / "ok.bvh", data.skeleton, motion, 0.01)
    root = np.array(motion.root_position)
    root[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"bad\.bvh: root_position has NaN/inf \(first at index \(1, 2\)\)"):
        write_bvh(tmp_path / "bad.bvh", data.skeleton, type(motion)(root, motion.rotations), 0.01)
    assert not (tmp_path / "bad.bvh").exists() and read_bvh(tmp_path / "ok.bvh").motion.num_frames == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bvh", "ok.bvh"]  # no temporary file left


# ---- inside the solver --------------------------------------------------------------------------------

def _kink(y, data):
    """Finite everywhere, but its Jacobian is NaN where ``y`` is 0 (|a| = √(a²))."""
    del data
    return jnp.sqrt(y[0] * y[0]) - jnp.array([1.0, 2.0])


def _kink_system(data, y):
    from bcmocap.solver.levenberg_marquardt import NormalEquations

    jac = jax.jacfwd(_kink)(y, data)[:, 0]
    return NormalEquations.dense(jac.T @ jac, jac.T @ _kink(y, data))


@eqx.filter_jit
def _fit_kink(y0):
    from bcmocap.solver.levenberg_marquardt import levenberg_marquardt

    return levenberg_marquardt(_kink, eqx.Partial(_kink_system, None), y0, None)


def test_levenberg_marquardt_flags_non_finite_values_inside_its_loop():
    from bcmocap.solver.levenberg_marquardt import FINITE, START_NOT_FINITE, SYSTEM_NOT_FINITE

    y, report = _fit_kink(jnp.zeros((1, 2)))  # finite cost, NaN Jacobian: stopped at that point, flagged
    assert np.array_equal(np.asarray(y), np.zeros((1, 2))) and not bool(report.converged)
    assert int(report.non_finite) == SYSTEM_NOT_FINITE
    y, report = _fit_kink(jnp.array([[1.0, jnp.nan]]))  # no step from a NaN start
    assert int(report.non_finite) == START_NOT_FINITE and int(report.num_steps) == 0 and not bool(report.converged)
    y, report = _fit_kink(jnp.array([[0.5, 3.0]]))  # away from the kink: solved, nothing flagged
    np.testing.assert_allclose(np.abs(np.asarray(y)[0]), [1.0, 2.0], atol=1e-6)
    assert int(report.non_finite) == FINITE and bool(report.converged)


def test_compiled_solve_has_no_host_callback():
    """A host callback (``eqx.error_if``) keeps a program out of JAX's persistent compilation cache, so every
    process would compile the window solve again (25–44 s)."""
    text = jax.jit(_fit_kink).lower(jnp.zeros((1, 2))).as_text()
    assert "callback" not in text


@pytest.fixture(scope="module")
def solver_setup():
    from test_solver import setup

    return setup.__wrapped__()  # test_solver's small problem: skeleton, rig, truth, points, observations, initial


@pytest.mark.slow
def test_a_window_whose_jacobian_is_not_finite_is_rejected_inside_the_solve(solver_setup):
    from test_solver import T

    from bcmocap.residuals import FrameTerm, Reprojection
    from bcmocap.solver import Problem, SolverOptions, solve

    class KinkedPrior(FrameTerm):
        """|x| of the root's height as √(x²): finite at x = 0, but its Jacobian there is NaN (a bug the
        cost does not show)."""

        def residual(self, state, data, variables):
            x = state.motion.root_position[2] - data
            return jnp.sqrt(x * x)[None, None], jnp.ones(1, bool)

    skeleton, rig, truth, points, (ids, pix, w), _ = solver_setup
    heights = np.asarray(truth.root_position)[:, 2].copy()  # the kink exactly at the initial motion
    problem = Problem(skeleton, rig, [
        Reprojection({"point_ids": ids, "pixels": pix, "weights": w}, points=points, name="reprojection"),
        KinkedPrior(heights, name="kinked prior"),
    ])
    with pytest.raises(FloatingPointError, match=r"solve: window of frames \[0, 6\): levenberg_marquardt: the "
                                                 r"Gauss–Newton system is NaN or inf at a point of finite cost"):
        solve(problem, truth, SolverOptions(window=T, overlap=0, max_steps=3))
