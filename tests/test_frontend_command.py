"""Errors of ``bcmocap frontend`` (the whole chain runs in benchmarks/frontend.py and by hand on a rendered
capture; its stages are tested in test_frontend_*.py)."""

from test_frontend_capture import make_capture

from bcmocap.cli import main


def test_frontend_command_errors(tmp_path, capsys):
    assert main(["frontend", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out")]) == 2
    assert "does not exist" in capsys.readouterr().err
    capture = make_capture(tmp_path / "capture")
    assert main(["frontend", str(capture), "--out", str(tmp_path / "out"), "--trial", "walk"]) == 2
    assert "no trial 'walk' (trials: rom, capture)" in capsys.readouterr().err
    assert main(["frontend", str(capture), "--out", str(tmp_path / "out"), "--offsets", "1,2,3"]) == 2
    assert "--offsets gives 3 values for 2 cameras" in capsys.readouterr().err
    assert main(["frontend", str(capture), "--out", str(tmp_path / "out"), "--gyro-timing", "frames"]) == 2
    assert "need a --rolling-shutter-readout to start from" in capsys.readouterr().err
    assert main(["frontend", str(capture), "--out", str(tmp_path / "out"), "--rolling-shutter-readout", "0.01",
                 "--estimate-readout"]) == 2
    assert "--estimate-readout needs --gyro-timing frames" in capsys.readouterr().err
    a_file = tmp_path / "file"
    a_file.write_text("keep me")
    assert main(["frontend", str(capture), "--out", str(a_file)]) == 2
    assert "exists and is not a folder" in capsys.readouterr().err and a_file.read_text() == "keep me"
    assert main(["frontend", str(capture), "--out", str(capture / "out")]) == 2
    assert "is inside the capture folder" in capsys.readouterr().err and not (capture / "out").exists()


def test_a_second_command_on_the_same_output_is_refused(tmp_path, capsys):
    import os

    from bcmocap.io.output_folder import locked_output

    capture = make_capture(tmp_path / "capture")
    out = tmp_path / "out"
    out.mkdir()
    with locked_output(out):  # a `bcmocap run` or `bcmocap frontend` already writing there
        assert main(["frontend", str(capture), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"another bcmocap command (pid {os.getpid()}) is writing" in err
    assert sorted(p.name for p in out.iterdir()) == ["run.lock"]  # nothing else was written
