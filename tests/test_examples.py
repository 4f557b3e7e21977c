"""The examples/ scripts (issue 8): each ``main([...])`` on the smallest input that still exercises it."""

import importlib.util
import re
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # the examples end to end


EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load(name: str):
    """An examples/ script as a module (the folder is not a package)."""
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_synthetic_benchmark_improves_on_the_initial_motion(capsys):
    assert load("synthetic_benchmark").main(["--seconds", "0.5", "--window", "30"]) == 0
    out = capsys.readouterr().out
    assert "simulated 30 frames of CMU 'walk'" in out
    before, after = map(float, re.search(r"joint position \(cm\)\s+([\d.]+)\s+([\d.]+)", out).groups())
    assert after < 1.0 < before


def test_real_capture_names_a_missing_folder(tmp_path, capsys):
    missing = tmp_path / "no_such_capture"
    with pytest.raises(SystemExit) as exc:
        load("real_capture").main([str(missing), "--out", str(tmp_path / "run")])
    assert exc.value.code != 0
    assert f"capture folder {missing} does not exist" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_real_capture_names_a_folder_that_is_not_a_capture(tmp_path, capsys):
    (tmp_path / "cap").mkdir()
    assert load("real_capture").main([str(tmp_path / "cap"), "--out", str(tmp_path / "run")]) == 2
    assert "capture.json" in capsys.readouterr().err


def test_markers_on_the_bundled_c3d_file(tmp_path, capsys):
    assert load("markers").main(["--frames", "0:200", "--groups", "7", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "26 markers" in out and "7 segments" in out and "segment lengths" in out
    assert (tmp_path / "skeleton.bvh").exists()


def test_monocular_reconstructs_a_short_walk(capsys):
    assert load("monocular").main(["--frames", "40"]) == 0
    out = capsys.readouterr().out
    error = float(re.search(r"3D error \(rigid alignment per frame\): ([\d.]+) mm mean", out).group(1))
    assert 0 < error < 150
