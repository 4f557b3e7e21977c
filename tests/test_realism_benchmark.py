"""benchmarks/realism.py's modelling variants (issue 20 item 3): a variant renders its base condition's capture; one
that differs from it in ``[solver]`` settings only (so the frontend's settings fingerprint is the base's) starts from
a copy of the base run's finished frontend, which ``bcmocap run`` then reuses."""

import json
from pathlib import Path

import pytest

from benchmarks import realism
from bcmocap.pipeline import RunConfig
from bcmocap.pipeline.run import fingerprints
from bcmocap.sim.studio import StudioSettings

BASE = StudioSettings(seconds=2.0, rom_seconds=3.0, seed=3, reference_width=640, reference_height=480)


@pytest.mark.parametrize("variant", list(realism.VARIANTS))
def test_variant_shares_its_base_capture_and_frontend_unless_it_changes_it(variant):
    source = realism.VARIANTS[variant][0]
    assert realism.base_condition(variant) == source and source in realism.CONDITIONS
    settings = realism.capture_settings(variant, BASE)
    assert settings == realism.capture_settings(source, BASE)
    config = RunConfig()
    mine, theirs = realism.run_config(variant, config, settings), realism.run_config(source, config, settings)
    own = mine.frontend != theirs.frontend
    assert realism.own_frontend(variant) == own == (variant in ("rolling_shutter+gyro", "calibration+self_calibration",
                                                               realism.MODELLED))
    assert (fingerprints(mine)["frontend"] == fingerprints(theirs)["frontend"]) == (not own)
    # a readout or self-calibration re-fits the registered poses in the world stage; compliance changes the solve only
    camera_model = own or mine.solver.rolling_shutter_readout > 0 or mine.solver.self_calibration
    assert (fingerprints(mine)["world"] == fingerprints(theirs)["world"]) == (not camera_model)
    assert (fingerprints(mine)["initial"] == fingerprints(theirs)["initial"]) == (not camera_model)
    assert fingerprints(mine)["solve"] != fingerprints(theirs)["solve"]
    a, b = mine.to_dict(), theirs.to_dict()
    assert {k: v for k, v in a.items() if k not in ("solver", "frontend")} == \
        {k: v for k, v in b.items() if k not in ("solver", "frontend")}


def test_modelled_terms_follow_the_capture():
    settings = realism.capture_settings(realism.MODELLED, BASE)
    config = realism.run_config(realism.MODELLED, RunConfig(), settings)
    assert settings.readout_ms > 0 and config.frontend.rolling_shutter_readout == pytest.approx(settings.readout_ms / 1000)
    s = config.solver
    assert s.rolling_shutter_readout == 0 and s.self_calibration and config.frontend.self_calibration
    assert s.mount_compliance == pytest.approx((settings.mount_wobble_mm / 1000, settings.mount_wobble_deg))
    wobble = realism.run_config("mount_wobble+compliance", RunConfig(), realism.capture_settings("mount_wobble", BASE))
    assert wobble.solver.mount_compliance == pytest.approx((0.003, 1.5))
    assert wobble.solver.rolling_shutter_readout == 0 and not wobble.solver.self_calibration
    readout = realism.run_config("rolling_shutter+readout", RunConfig(), realism.capture_settings("rolling_shutter", BASE))
    assert readout.solver.rolling_shutter_readout > 0 and readout.frontend.rolling_shutter_readout == 0


def _base_run(tmp_path: Path, frontend_finished: bool = True) -> Path:
    run = tmp_path / "runs" / "base"
    for part in ("rom", "capture"):
        (run / "frontend" / part / "correspondences").mkdir(parents=True)
        (run / "frontend" / part / "registration.json").write_text(json.dumps({"settings": {"stride": 2}}))
        (run / "frontend" / part / "correspondences" / "index.json").write_text("{}")
    (run / "frontend" / "reference" / "model").mkdir(parents=True)
    (run / "frontend" / "reference" / "model" / "points3D.bin").write_bytes(b"points")
    (run / "frontend" / "tracks" / "capture").mkdir(parents=True)
    (run / "frontend" / "tracks" / "capture" / "cache.npz").write_bytes(b"cache")
    stages = {"frontend": {"fingerprint": "f", "seconds": 1.0}} if frontend_finished else {}
    (run / "run.json").write_text(json.dumps({"format": "bcmocap-run", "capture": "c", "stages": stages}))
    return run


def test_seed_frontend_copies_the_trials_and_reference_only(tmp_path):
    source, run = _base_run(tmp_path), tmp_path / "runs" / "variant"
    realism.seed_frontend(source, run)
    for part in ("rom", "capture"):
        assert (run / "frontend" / part / "registration.json").read_text() == \
            (source / "frontend" / part / "registration.json").read_text()
        assert (run / "frontend" / part / "correspondences" / "index.json").is_file()
    assert (run / "frontend" / "reference" / "model" / "points3D.bin").read_bytes() == b"points"
    assert not (run / "frontend" / "tracks").exists()  # the tracking cache is not read after the frontend
    assert not (run / "run.json").exists()  # bcmocap run itself decides the frontend is reusable
    assert sorted(p.name for p in run.parent.iterdir()) == ["base", "variant"]  # no staging folder left


def test_seed_frontend_leaves_a_started_run_and_refuses_an_unfinished_base(tmp_path):
    source, run = _base_run(tmp_path), tmp_path / "runs" / "variant"
    (run / "frontend" / "rom").mkdir(parents=True)
    realism.seed_frontend(source, run)  # a started variant resumes as it is
    assert not (run / "frontend" / "capture").exists()
    unfinished = _base_run(tmp_path / "other", frontend_finished=False)
    with pytest.raises(ValueError, match="frontend stage has not finished"):
        realism.seed_frontend(unfinished, tmp_path / "runs" / "fresh")
    assert not (tmp_path / "runs" / "fresh").exists()


def test_lens_errors_compare_the_given_and_corrected_lenses_with_the_rendered_ones(tmp_path):
    import numpy as np

    capture, run = tmp_path / "capture", tmp_path / "run"
    (capture / "ground_truth").mkdir(parents=True)
    (capture / "intrinsics").mkdir()
    (run / "frontend").mkdir(parents=True)
    true = {"a": [200.0, 200.0, 320.0, 180.0, 1.2], "b": [250.0, 250.0, 319.5, 179.5, 1.2]}
    given = {"a": [202.0, 202.0, 323.0, 176.0, 1.2], "b": [250.0, 250.0, 319.5, 179.5, 1.2]}
    (capture / "ground_truth" / "rig.json").write_text(json.dumps(
        {"cameras": [{"name": n, "intrinsics": {"model": "FOV", "params": p}} for n, p in true.items()]}))
    for n, p in given.items():
        (capture / "intrinsics" / f"{n}.json").write_text(json.dumps({"model": "FOV", "params": p}))
    assert realism.lens_errors(capture, run) is None  # no self-calibration in this run
    np.savez(run / "frontend" / "intrinsics.npz", correction=np.array([[np.log(200 / 202), -3.0, 4.0], [0.0, 0.0, 0.0]]),
             cameras=np.array(["a", "b"]))
    errors = realism.lens_errors(capture, run)
    assert errors["given"]["focal_error_pct_max"] == pytest.approx(1.0) and errors["given"]["centre_error_px_max"] == 5.0
    assert errors["corrected"]["focal_error_pct_max"] == pytest.approx(0.0, abs=1e-9)
    assert errors["corrected"]["centre_error_px_max"] == pytest.approx(0.0, abs=1e-9)
