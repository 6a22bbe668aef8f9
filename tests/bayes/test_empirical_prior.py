"""The empirical-Bayes prior scale: a closed form on a linear model, the scale recovered, intervals that hold."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.stats import multivariate_normal

from bayescal.bayes import empirical_bayes_map, linearise, map_estimate, prior_from_machine
from bayescal.errors import InputError
from bayescal.measurement import MeasurementModel


@pytest.fixture(scope="module")
def lin(prs3, sim6):
    return linearise(MeasurementModel.from_recording(prs3, sim6.recording))


def _data(lin, machine, c, rng):
    theta = c * prior_from_machine(machine).sample(1, rng)[0]
    y = lin.predict(theta).y + rng.normal(size=lin.y0.shape) * lin.sigma
    return lin.with_measured(y), theta


def test_closed_form_on_a_linear_model(prs3, lin):
    """On a linear model: c maximises the Gaussian marginal likelihood (scipy's dense density, continuous
    search) and the MAP / covariance are the ridge solution and (A^T A / c^0 + I / c^2)^-1 in scaled units."""
    model, _ = _data(lin, prs3, 2.5, np.random.default_rng(3))
    res = empirical_bayes_map(model)
    idx = np.flatnonzero(res.free)
    S = prs3.tolerance[idx]
    A = (model.J[:, :, idx] / model.sigma[None, :, None]).reshape(-1, idx.size) * S
    z = ((model.y_measured - model.y0) / model.sigma).reshape(-1)  # theta_ref = 0, prior mean 0
    N = z.size

    def neg_ev(logc):
        return -multivariate_normal(np.zeros(N), np.eye(N) + np.exp(2 * logc) * A @ A.T).logpdf(z)

    c_star = float(np.exp(minimize_scalar(neg_ev, bounds=(-3, 3), method="bounded").x))
    c = res.extras["prior_scale"]
    assert c == pytest.approx(c_star, rel=0.06)  # the evidence grid is about 0.1 decade in lam
    H = A.T @ A + np.eye(idx.size) / c**2
    np.testing.assert_allclose(res.theta[idx], S * np.linalg.solve(H, A.T @ z), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(res.covariance, S[:, None] * np.linalg.inv(H) * S[None, :], rtol=1e-6)


@pytest.mark.parametrize("c_true", [0.5, 3.0])
def test_scale_is_recovered(prs3, lin, c_true):
    cs = [empirical_bayes_map(_data(lin, prs3, c_true, np.random.default_rng(10 + i))[0]).extras["prior_scale"]
          for i in range(6)]
    assert 0.6 * c_true < np.median(cs) < 1.5 * c_true, cs


def test_intervals_hold_when_the_machine_is_worse_than_its_tolerances(prs3, lin):
    """Truths at 2x the tolerances: the tolerance prior's 90 % intervals are overconfident, the empirical ones hold."""
    rng = np.random.default_rng(7)
    inside = {"tolerance": [], "empirical": []}
    for _ in range(25):
        model, theta = _data(lin, prs3, 2.0, rng)
        for kind in inside:
            res = map_estimate(model, free="all", prior_scale=kind)
            z = (res.theta - theta) / np.sqrt(np.diag(res.covariance))
            inside[kind].append(np.mean(np.abs(z) <= 1.645))
    assert np.mean(inside["tolerance"]) < 0.8, inside
    assert 0.84 < np.mean(inside["empirical"]) < 0.96, inside
    with pytest.raises(InputError, match="prior_scale"):
        map_estimate(model, prior_scale="guess")


def test_cli_prior_scale_option(tmp_path, capsys):
    import json

    from bayescal.cli import main
    from bayescal.io import read_recording
    from bayescal.machines.files import load_machine
    from tests.conftest import PRS3_FILE, ROOT

    rec = ROOT / "examples" / "prs3" / "recording.csv"
    out = tmp_path / "a.json"
    code = main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "map", "--prior-scale", "empirical",
                 "--json", str(out)])
    assert code == 0 and "prior scale:" in capsys.readouterr().out
    ans = json.loads(out.read_text())
    res = map_estimate(MeasurementModel.from_recording(load_machine(PRS3_FILE), read_recording(rec)),
                       prior_scale="empirical")
    assert ans["prior_scale"] == pytest.approx(res.extras["prior_scale"])
    np.testing.assert_allclose([p["value"] for p in ans["parameters"]], res.theta, rtol=1e-10, atol=1e-14)
    assert main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "ls", "--prior-scale", "empirical"]) == 2
    # empirical is the CLI default; 'tolerance' is the plain MAP (= ridge lam 1)
    out2 = tmp_path / "b.json"
    assert main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "map", "--json", str(out2)]) == 0
    assert json.loads(out2.read_text())["prior_scale"] == pytest.approx(ans["prior_scale"])
    out3 = tmp_path / "c.json"
    assert main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "map", "--prior-scale", "tolerance",
                 "--json", str(out3)]) == 0
    plain = map_estimate(MeasurementModel.from_recording(load_machine(PRS3_FILE), read_recording(rec)))
    d3 = json.loads(out3.read_text())
    assert "prior_scale" not in d3
    np.testing.assert_allclose([p["value"] for p in d3["parameters"]], plain.theta, rtol=1e-10, atol=1e-14)
