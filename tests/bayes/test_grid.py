"""Compensation grid: standardised node errors on simulated machines; CSV; samples vs linearised std; CLI."""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.bayes import map_estimate
from bayescal.bayes.grid import compensation_grid
from bayescal.cli import main
from bayescal.errors import InputError
from bayescal.measurement import MeasurementModel
from bayescal.simulate import simulate_recording
from tests.conftest import PRS3_FILE


def test_standardised_node_errors_mean_0_spread_1(prs3):
    z = []
    for seed in range(12):
        sim = simulate_recording(prs3, 20, seed=100 + seed, dof=6)
        model = MeasurementModel.from_recording(prs3, sim.recording)
        res = map_estimate(model, free="all")
        grid = compensation_grid(prs3, res.theta, covariance=res.covariance, free=res.free, n=4)
        q = grid.q
        true_err = prs3.forward(q, sim.theta_true).position - prs3.forward(q, None).position
        z.append((true_err - (-grid.correction.reshape(-1, 3))) / grid.std.reshape(-1, 3))
    z = np.concatenate(z)
    assert abs(z.mean()) < 0.2
    assert 0.8 < z.std() < 1.2


def test_sample_std_matches_linearised(prs3, sim6):
    model = MeasurementModel.from_recording(prs3, sim6.recording)
    res = map_estimate(model)
    rng = np.random.default_rng(0)
    draws = rng.multivariate_normal(res.theta[res.free], res.covariance, size=400)
    lin = compensation_grid(prs3, res.theta, covariance=res.covariance, free=res.free, n=3)
    smp = compensation_grid(prs3, res.theta, samples=draws, free=res.free, n=3)
    np.testing.assert_allclose(smp.std, lin.std, rtol=0.15)
    np.testing.assert_array_equal(smp.correction, lin.correction)
    csv = lin.to_csv().splitlines()
    assert csv[0] == "q1,q2,q3,dx,dy,dz,sx,sy,sz" and len(csv) == 1 + 27
    row = np.array(csv[5].split(","), dtype=float)
    np.testing.assert_allclose(row[3:6], lin.correction.reshape(-1, 3)[4], rtol=1e-8)
    with pytest.raises(InputError, match="covariance"):
        compensation_grid(prs3, res.theta, covariance=np.eye(2), free=res.free)


def test_grid_cli(tmp_path, prs3, sim6):
    from bayescal.io import write_recording

    rec = tmp_path / "rec.csv"
    write_recording(rec, sim6.recording)
    out = tmp_path / "grid.csv"
    rc = main(["grid", str(rec), "--machine", str(PRS3_FILE), "--nodes", "3", "--out", str(out),
               "--figure", str(tmp_path / "g.png"), "--json", str(tmp_path / "g.json"), "--quiet"])
    assert rc == 0 and out.exists() and (tmp_path / "g.png").stat().st_size > 1000
    assert len(out.read_text().splitlines()) == 28
    assert main(["grid", str(rec), "--machine", str(PRS3_FILE), "--nodes", "1", "--quiet"]) == 2


def test_grid_summary_against_hand_computed_values():
    from bayescal.bayes.grid import grid_summary

    corr = np.array([[[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]]])  # norms 5 and 0
    std = np.array([[[1.0, 2.0, 2.0], [0.0, 0.0, 0.0]]])  # 3-D std 3 and 0
    s = grid_summary(corr, std)
    assert s == {"max_correction_mm": 5.0, "rms_correction_mm": np.sqrt(12.5), "max_std_mm": 3.0,
                 "rms_std_mm": np.sqrt(4.5)}


def test_node_std_against_finite_differences_and_a_loop_over_draws(prs3):
    # the std at every node computed directly: G by central differences of the forward kinematics, G C G^T in
    # full with a correlated C on a subset of parameters; the sample std one draw at a time
    from tests.bayes.test_accuracy import assert_grid_std_is_direct

    free = np.arange(prs3.n_params) % 3 == 0
    assert_grid_std_is_direct(prs3, lambda th, **kw: compensation_grid(prs3, th, n=2, **kw), free, 5, "compensation_grid")


def test_the_grid_carries_identify_map_answer():
    # bayescal grid --method map spans the calibration identify --method map writes: the same noise test
    # (the positioner's stated sigma is far too large: the estimated one is used), outliers and prior scale
    import bayescal
    from tests.conftest import ROOT

    s = bayescal.load(ROOT / "examples" / "positioner" / "machine.toml", ROOT / "examples" / "positioner" / "recording.csv",
                      frame="fit")
    answer = bayescal.grid(s, nodes=3)
    cal = bayescal.calibrate(s, method="map", free="all")
    np.testing.assert_array_equal(answer.identification.theta, cal.result.theta)
    np.testing.assert_array_equal(answer.identification.covariance, cal.result.covariance)
    # which is not the plain MAP under the stated noise: the std the grid carries is several times smaller
    plain = map_estimate(s.fit_model, free="all")
    assert np.trace(answer.identification.covariance) < 0.2 * np.trace(plain.covariance)
    # the filter too: identify --method kalman's filter, run on the noise the MAP found
    kal = bayescal.grid(s, nodes=3, method="kalman")
    np.testing.assert_array_equal(kal.identification.theta, bayescal.calibrate(s, method="kalman", free="all").result.theta)
