"""`bcmocap demo` end to end on a short capture, and the examples on tiny inputs."""

import json
import os
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

from bcmocap.cli import main

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_demo_writes_metrics_and_bvh(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--simulated-measurements", "--seconds", "0.5", "--out", str(out), "--window", "30"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("joint_position_error_cm", "joint_angle_error_deg"):
        assert set(metrics[key]) == {"mean", "median", "max"}
    assert metrics["frames"] == 30 and metrics["seconds"] > 0
    # the optimisation must actually help, and reach the accuracy on this short walk
    assert metrics["joint_position_error_cm"]["mean"] < 1.0 < metrics["initial"]["joint_position_error_cm"]["mean"]
    assert metrics["joint_angle_error_deg"]["mean"] < 1.5
    from bcmocap.io import read_bvh

    assert read_bvh(out / "motion.bvh").motion.num_frames == 30
    assert "after optimisation" in capsys.readouterr().out


def test_demo_refuses_a_file_as_output(tmp_path):
    target = tmp_path / "file"
    target.write_text("keep me")
    assert main(["demo", "--simulated-measurements", "--seconds", "0.5", "--out", str(target)]) == 2
    assert main(["demo", "--out", str(target)]) == 2  # the full chain checks before it renders anything
    assert target.read_text() == "keep me"


@pytest.mark.slow
def test_custom_residual_example_runs(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["custom_residual.py", "--seconds", "0.5"])
    runpy.run_path(str(ROOT / "examples" / "custom_residual.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "hinge angle range" in out and "mean joint position error" in out


def test_expected_failures_of_any_stage_end_in_one_line(tmp_path, monkeypatch, capsys):
    """ValueError, OSError, MemoryError and a non-finite solve from inside a command, and Ctrl-C, print one
    line, no traceback."""
    import bcmocap.pipeline.run as run_module

    capture = tmp_path / "capture"
    capture.mkdir()
    for raised, code, line in [
        (OSError(28, "No space left on device", str(tmp_path / "out" / "x.npz")), 2, "out: writing x.npz needed more space"),
        (MemoryError(), 2, "out of memory"),
        (FloatingPointError("solve: window of frames [0, 60) has a non-finite cost"), 2, "window of frames [0, 60)"),
        (KeyboardInterrupt(), 130, "interrupted (rerun the same command to resume)"),
    ]:
        def fail(*args, raised=raised, **kwargs):
            raise raised

        monkeypatch.setattr(run_module, "run_pipeline", fail)
        assert main(["run", str(capture), "--out", str(tmp_path / "out")]) == code
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("bcmocap run: ") and line in err, err


def test_importing_bcmocap_leaves_float32_and_the_solver_says_what_to_do():
    """No import-time side effect: a fresh interpreter importing bcmocap keeps JAX's float32 default, and
    bcmocap.solve refuses it with the fix in the message; enable_float64 turns it on."""

    code = (
        "import jax, bcmocap\n"
        "assert not jax.config.read('jax_enable_x64')\n"
        "try:\n"
        "    bcmocap.solve(None, None)\n"
        "except RuntimeError as err:\n"
        "    print(err)\n"
        "bcmocap.enable_float64()\n"
        "assert jax.numpy.zeros(1).dtype == 'float64'\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "bcmocap.solve needs float64 in JAX: call bcmocap.enable_float64()" in out.stdout
    import bcmocap

    assert {"Skeleton", "Motion", "Rig", "Problem", "solve", "paper_problem", "FrameTerm"} <= set(bcmocap.__all__)
    assert all(hasattr(bcmocap, name) for name in bcmocap.__all__)


def test_import_bcmocap_loads_its_public_api_on_first_use():

    code = ("import sys, bcmocap\n"
            "assert 'jax' not in sys.modules, 'import bcmocap imported JAX'\n"
            "bcmocap.Skeleton\n"
            "assert 'jax' in sys.modules\n"
            "try:\n"
            "    bcmocap.no_such_name\n"
            "except AttributeError as err:\n"
            "    print(err)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "module 'bcmocap' has no attribute 'no_such_name'" in out.stdout


def test_the_command_line_imports_no_jax_until_a_command_needs_it():
    """`bcmocap view` starts its server before JAX is imported (the page loads meanwhile): the command line, the
    view command and the viewer's server import no JAX, and float64 set before JAX is imported still holds."""
    code = ("import sys, bcmocap.cli, bcmocap.pipeline.view_command, bcmocap.pipeline.view_input, bcmocap.viewer.server\n"
            "assert 'jax' not in sys.modules, 'jax was imported'\n"
            "from bcmocap.precision import enable_float64\n"
            "enable_float64()\n"
            "import jax\n"
            "assert jax.numpy.zeros(1).dtype == 'float64'\n")
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300, env=env)
    assert out.returncode == 0, out.stderr


def test_a_script_running_the_pipeline_in_float32_is_stopped_before_it_reads_the_capture(tmp_path):
    """Camera models hold JAX arrays: read in float32, a capture's intrinsics lose digits and the frontend
    registers differently, so run_pipeline refuses to start (naming the fix) instead of running on."""
    code = ("from bcmocap.pipeline.run import run_pipeline\n"
            f"run_pipeline({str(tmp_path / 'no capture')!r}, {str(tmp_path / 'out')!r})\n")
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300, env=env)
    assert out.returncode != 0 and "needs float64" in out.stderr and "enable_float64" in out.stderr, out.stderr
    assert not (tmp_path / "out").exists()
