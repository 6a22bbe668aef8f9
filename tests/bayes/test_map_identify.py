"""identify --method map as one function: the prior-scale rule and the same answer as the command."""

import json
from dataclasses import replace

import numpy as np

from bayescal.bayes.map_identify import MIN_ROWS_PER_PARAM, default_prior_scale, identify_map
from bayescal.bayes.priors import map_estimate
from bayescal.cli import main
from bayescal.constraints.model import ConstraintModel
from bayescal.io.constraints import constraints_to_csv
from bayescal.klipper import klipper_machine
from bayescal.machines.base import MeasurementNoise
from tests.klipper.test_loo import NOMINAL, TRUE, _pattern_on


def _printer(noise_given: bool):
    rec = _pattern_on(TRUE)
    rec = replace(rec, value=rec.value + rec.sigma * 4.0 * np.random.default_rng(3).normal(size=rec.n_rows))
    m = klipper_machine(NOMINAL, q_span=rec.qa)
    if noise_given:
        m = replace(m, noise=MeasurementNoise(sigma_position=0.05, given=True))
    return m, rec


def test_rule_tolerance_only_with_stated_noise_and_few_rows():
    m, rec = _printer(noise_given=True)
    model = ConstraintModel.from_recording(m, rec)
    assert model.n_poses * model.dof < MIN_ROWS_PER_PARAM * model.n_params
    scale, note = default_prior_scale(model)
    assert scale == "tolerance" and "19 distinct measured components for 21 parameters" in note
    # the noise not stated: the sigmas are weights, the evidence sets the prior against the noise
    m2, _ = _printer(noise_given=False)
    assert default_prior_scale(ConstraintModel.from_recording(m2, rec)) == ("empirical", None)
    # stated noise with rows to spare: empirical (repeated measurements, each with its own noise)
    big = rec.subset(np.tile(np.arange(rec.n_rows), 4))
    big = replace(big, value=big.value + big.sigma * np.random.default_rng(5).normal(size=big.n_rows))
    assert default_prior_scale(ConstraintModel.from_recording(m, big)) == ("empirical", None)
    # copies of the same rows add no information: they do not count towards the scale (a probe found 36 copies of
    # one pose setting it)
    copies = rec.subset(np.tile(np.arange(rec.n_rows), 4))
    scale, note = default_prior_scale(ConstraintModel.from_recording(m, copies))
    assert scale == "tolerance" and "19 distinct measured components, 57 copied rows not counted" in note


def test_identify_map_is_map_estimate_with_the_rule_and_the_command_agrees(tmp_path):
    m, rec = _printer(noise_given=False)
    model = ConstraintModel.from_recording(m, rec)
    res, handling = identify_map(model, "all", robust="off")
    ref = map_estimate(model, free="all", prior_scale="empirical")
    np.testing.assert_allclose(res.theta, ref.theta, atol=1e-10)
    assert res.extras["prior_scale"] == ref.extras["prior_scale"] and "prior_scale_note" not in res.extras
    # the stated-noise machine gets the tolerances and the note
    ms, _ = _printer(noise_given=True)
    res_t, _ = identify_map(ConstraintModel.from_recording(ms, rec), "all", robust="off")
    np.testing.assert_allclose(res_t.theta, map_estimate(ConstraintModel.from_recording(ms, rec), free="all").theta, atol=1e-10)
    assert "prior_scale_note" in res_t.extras
    # the command computes the same
    (tmp_path / "machine.toml").write_text(m.to_toml())
    (tmp_path / "recording.csv").write_text(constraints_to_csv(rec))
    ans = tmp_path / "a.json"
    assert main(["identify", str(tmp_path / "recording.csv"), "--machine", str(tmp_path / "machine.toml"), "--method", "map",
                 "--free", "all", "--robust", "off", "--json", str(ans), "--quiet"]) == 0
    a = json.loads(ans.read_text())
    got = np.array([p["value"] for p in a["parameters"]])
    assert abs(a["prior_scale"] - res.extras["prior_scale"]) < 1e-12
    np.testing.assert_allclose(got[: m.n_params], res.theta[: m.n_params], atol=1e-9)


def test_outlier_retest_uses_the_estimated_prior_scale():
    # the pose test after an empirical-Bayes MAP must use that fit's prior (lam = 1 / c^2), not the tolerances'
    from pathlib import Path

    from bayescal.machines.files import load_machine
    from bayescal.models import model_from_recording, read_any_recording
    from bayescal.outliers import pose_test

    ex = Path(__file__).resolve().parents[2] / "examples" / "delta"
    m = load_machine(ex / "machine.toml")
    model = model_from_recording(m, read_any_recording(ex / "recording.csv"))
    res, handling = identify_map(model, "auto", robust="off")
    c = res.extras["prior_scale"]
    assert abs(np.log(c)) > np.log(1.5)  # far enough from the tolerances for the two tests to differ
    t = handling.test
    kw = dict(free=np.asarray(res.free), alpha=t.alpha, lines=t.lines)
    same = pose_test(model, res.theta, lam=1.0 / c**2, **kw)
    np.testing.assert_allclose(t.statistic, same.statistic, rtol=1e-12)
    np.testing.assert_allclose(t.cooks_distance, same.cooks_distance, rtol=1e-12)
    tol = pose_test(model, res.theta, lam=1.0, **kw)
    assert np.max(np.abs(t.cooks_distance / tol.cooks_distance - 1)) > 0.05


def test_identify_map_reuses_its_robust_pass_as_the_first_map(prs3, sim6, monkeypatch):
    """A clean recording: the robust pass's MAP is the empirical-Bayes search's first MAP (same model, prior,
    start and free set), so it is not fitted twice (issue 32), and the answer is map_estimate's to the bit."""
    import bayescal.bayes.priors as priors
    from bayescal.measurement import MeasurementModel

    model = MeasurementModel.from_recording(prs3, sim6.recording)
    ref = map_estimate(model, free="auto", prior_scale="empirical")
    calls = []
    real = priors.identify
    monkeypatch.setattr(priors, "identify", lambda *a, **k: calls.append(1) or real(*a, **k))
    res, handling = identify_map(model, "auto")
    assert handling.weights is None and handling.test is not None and not handling.test.flagged.any()
    assert np.array_equal(res.theta, ref.theta) and np.array_equal(res.covariance, ref.covariance)
    assert res.extras["prior_scale"] == ref.extras["prior_scale"]
    assert len(calls) == res.extras["prior_scale_rounds"]  # the rescaled MAPs only: the first came from the pass
