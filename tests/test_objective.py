"""bcmocap.solver.objective: user term factories by import path, their checks, and the run config's
``[[solver.user_terms]]``."""

import textwrap

import numpy as np
import pytest

from bcmocap.pipeline.config import RunConfig, load_config
from bcmocap.residuals import FrameTerm
from bcmocap.solver.objective import ObjectiveWeights, TermWindow, UserTerms, import_term_factory

from conftest import make_rig, make_skeleton


class RootHeight(FrameTerm):
    """The root's height equals ``data`` (m)."""

    def residual(self, state, data, variables):
        return (state.motion.root_position[2] - data)[None, None], np.ones(1, bool)

    @classmethod
    def from_window(cls, window, height=1.0, weight=1.0):
        return cls(np.full(window.num_frames, height), weight=weight, name="root height")


@pytest.fixture(scope="module")
def window():
    skeleton = make_skeleton()
    return TermWindow(10, 16, 20.0, skeleton, make_rig(skeleton))


def test_window_times_are_seconds_since_the_first_clap(window):
    np.testing.assert_allclose(window.times, [0.5, 0.55, 0.6, 0.65, 0.7, 0.75])
    assert window.num_frames == 6 and window.first_frame_has_previous


def test_import_path_names_a_factory_or_a_term_class(tmp_path, monkeypatch, window):
    (tmp_path / "my_terms.py").write_text(textwrap.dedent("""
        from test_objective import RootHeight

        def heights(window, height):
            return [RootHeight.from_window(window, height=height)]

        not_callable = 3
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    factory = import_term_factory("my_terms:heights")
    (term,) = UserTerms(factory, {"height": 2.0}, "my_terms:heights")(window)
    np.testing.assert_array_equal(term.data, np.full(6, 2.0))
    from_class = import_term_factory("test_objective:RootHeight")  # a Term class: its from_window
    assert UserTerms(from_class, {"weight": 3.0})(window)[0].weight == 3.0
    for path, message in [("my_terms", "expected 'package.module:name'"), ("../x:y", "expected"),
                          ("no_such_module_xyz:f", "cannot import 'no_such_module_xyz'"),
                          ("my_terms:missing", "has no 'missing'"), ("my_terms:not_callable", "is not callable"),
                          ("bcmocap.residuals:FrameTerm", "needs a from_window classmethod")]:
        with pytest.raises(ValueError, match=message):
            import_term_factory(path)


def test_user_terms_are_checked_against_the_window(window):
    wrong_length = lambda w: RootHeight(np.ones(w.num_frames + 1), name="short")
    with pytest.raises(ValueError, match=r"term factory f \(frames \[10, 16\)\): short: data.* expected leading axes \(6,\)"):
        UserTerms(wrong_length, name="f")(window)
    with pytest.raises(ValueError, match="term factory g: returned str, not a bcmocap Term"):
        UserTerms(lambda w: ["x"], name="g")(window)
    with pytest.raises(ValueError, match="NaN/inf"):
        UserTerms(lambda w: RootHeight(np.full(w.num_frames, np.nan)), name="h")(window)


def test_config_user_terms(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text(textwrap.dedent("""
        [[solver.user_terms]]
        factory = "my_terms:heights"
        height = 2.0
        cameras = ["head", "chest"]

        [[solver.user_terms]]
        factory = "test_objective:RootHeight"
    """))
    config = load_config(path)
    first, second = config.solver.user_terms
    assert first.factory == "my_terms:heights" and first.settings == {"height": 2.0, "cameras": ["head", "chest"]}
    assert second.settings == {}
    assert RunConfig.from_dict(config.to_dict()) == config  # the saved config.json reads back the same
    for text, message in [('[solver]\nuser_terms = "x:y"', "must be a list of tables"),
                          ("[[solver.user_terms]]\nweight = 1.0", "must be a table with a 'factory' string"),
                          ('[[solver.user_terms]]\nfactory = "a:b"\nweight = nan', r"user_terms\[0\].weight must be finite"),
                          ('[[solver.user_terms]]\nfactory = "a:b"\nx = {y = 1}', "must be a number, string, boolean")]:
        path.write_text(text)
        with pytest.raises(ValueError, match=message):
            load_config(path)


def test_camera_effects_choose_the_reprojection_and_add_their_priors():
    """Rolling shutter, self-calibration and mount compliance (the run config's solver keys) become the terms that
    model them, with priors on what they estimate; the paper's terms are the default."""
    from bcmocap.pipeline.run import camera_effects
    from bcmocap.residuals import Reprojection
    from bcmocap.residuals.rolling_shutter import READOUT, TIME_OFFSET, RollingShutterReprojection
    from bcmocap.residuals.self_calibration import INTRINSICS_CORRECTION, SelfCalibratingReprojection
    from bcmocap.residuals.variables import CAMERA_OFFSETS
    from bcmocap.correspondences import Correspondences
    from bcmocap.solver.objective import paper_terms

    t, c, n, m = 4, 3, 5, 2
    corr = Correspondences(np.zeros((n, 3)), np.zeros((t, c, n), np.int32), np.zeros((t, c, n, 2)), np.ones((t, c, n)),
                           np.zeros((t, c, m, 2)), np.zeros((t, c, m, 2)), np.zeros((t, c, m)),
                           np.tile([1.0, 0, 0, 0, 0, 0, 0], (t, c, 1)), np.ones((t, c), bool), 30.0)
    skeleton = make_skeleton()
    kinds = lambda terms: [type(term).__name__ for term in terms]  # noqa: E731
    assert kinds(paper_terms(corr, skeleton))[0] == Reprojection.__name__
    config = RunConfig.from_dict({"solver": {"rolling_shutter_readout": 0.02, "estimate_readout": True,
                                             "self_calibration": True, "mount_compliance": [0.003, 2.0]}})
    terms = paper_terms(corr, skeleton, effects=camera_effects(config.solver))
    shutter = terms[0]
    assert isinstance(shutter, RollingShutterReprojection) and shutter.calibrate and shutter.estimate_readout
    assert float(shutter.readout) == pytest.approx(0.02 * corr.fps)
    declared = {name for t in terms for name in t.static_variables()}
    assert declared == {READOUT, INTRINSICS_CORRECTION}
    assert {name for t in terms for name in t.frame_variables()} == {CAMERA_OFFSETS}
    assert {"readout prior", "intrinsics prior", "mount compliance", "mount smoothness"} <= {t.label for t in terms}
    only_calibration = paper_terms(corr, skeleton,
                                   effects=camera_effects(RunConfig.from_dict({"solver": {"self_calibration": True}}).solver))
    assert isinstance(only_calibration[0], SelfCalibratingReprojection)
    # estimating each camera's time offset makes the reprojection a rolling-shutter one (readout 0) with its prior
    timed = paper_terms(corr, skeleton, effects=camera_effects(
        RunConfig.from_dict({"solver": {"estimate_time_offsets": True}}).solver))
    assert isinstance(timed[0], RollingShutterReprojection) and timed[0].estimate_time_offsets
    assert float(timed[0].readout) == 0.0 and timed[0].num_cameras == c
    assert {name for t in timed for name in t.static_variables()} == {TIME_OFFSET}
    assert "time offset prior" in {t.label for t in timed}
    for bad in ({"mount_compliance": [0.003, 0.0]}, {"rolling_shutter_readout": 2.0}):
        with pytest.raises(ValueError, match="solver\\.(mount_compliance|rolling_shutter_readout)"):
            RunConfig.from_dict({"solver": bad})


def test_registered_pose_sigmas_are_both_zero_or_both_positive():
    for bad in ((0.02, 0.0), (0.0, 0.01), (-0.02, 0.01), (float("nan"), 0.01)):
        with pytest.raises(ValueError, match=r"ObjectiveWeights.registered_pose must be \(m, rad\), both 0 or both > 0"):
            ObjectiveWeights(registered_pose=bad)
    assert ObjectiveWeights(registered_pose=(0.02, 0.01)).registered_pose == (0.02, 0.01)


def test_measured_time_offsets_centre_their_prior():
    """Time offsets measured beforehand (the cameras' gyros) are the centre of the prior on the solver's offsets, in
    the solver's frame periods; a measurement per camera is required."""
    import dataclasses

    import jax.numpy as jnp

    from bcmocap.correspondences import Correspondences
    from bcmocap.residuals.rolling_shutter import TIME_OFFSET
    from bcmocap.solver.objective import CameraEffects, paper_terms

    t, c, n, m = 4, 3, 5, 2
    corr = Correspondences(np.zeros((n, 3)), np.zeros((t, c, n), np.int32), np.zeros((t, c, n, 2)), np.ones((t, c, n)),
                           np.zeros((t, c, m, 2)), np.zeros((t, c, m, 2)), np.zeros((t, c, m)),
                           np.tile([1.0, 0, 0, 0, 0, 0, 0], (t, c, 1)), np.ones((t, c), bool), 30.0)
    effects = CameraEffects(estimate_time_offsets=True, time_offset_sigma_seconds=0.001,
                            time_offsets_measured=(0.002, -0.004, 0.002))
    prior = next(term for term in paper_terms(corr, make_skeleton(), effects=effects) if term.label == "time offset prior")
    at_measurement = jnp.asarray([[0.06], [-0.12], [0.06]])  # s × 30 frames/s
    r, _ = prior.residual(None, jnp.asarray(1.0), {TIME_OFFSET: at_measurement})
    np.testing.assert_allclose(np.asarray(r), 0.0, atol=1e-12)
    r, _ = prior.residual(None, jnp.asarray(1.0), {TIME_OFFSET: at_measurement + 0.03})
    np.testing.assert_allclose(np.asarray(r), 1.0)  # 1 ms off is one σ
    per_camera = next(term for term in paper_terms(corr, make_skeleton(), effects=dataclasses.replace(
        effects, time_offset_sigma_seconds=(0.001, 0.01, 0.001))) if term.label == "time offset prior")
    r, _ = per_camera.residual(None, jnp.asarray(1.0), {TIME_OFFSET: at_measurement + 0.03})
    np.testing.assert_allclose(np.asarray(r), [[1.0, 0.1, 1.0]])  # σ 10 ms on the camera that was not measured
    with pytest.raises(ValueError, match="time_offset_sigma_seconds: 2 values for 3 cameras"):
        paper_terms(corr, make_skeleton(), effects=dataclasses.replace(effects, time_offset_sigma_seconds=(0.1, 0.1)))
    with pytest.raises(ValueError, match="time_offsets_measured: 2 values for 3 cameras"):
        paper_terms(corr, make_skeleton(), effects=dataclasses.replace(effects, time_offsets_measured=(0.0, 0.0)))
