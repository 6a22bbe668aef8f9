"""Results that refuse to be implausible; the rigid-transform check; the frame block of the answer."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bayescal.bayes.kalman import kalman_filter
from bayescal.bayes.priors import map_estimate
from bayescal.identify import identify
from bayescal.instrument import assess_plausibility, check_frame, frame_answer, prepare_model
from bayescal.instrument.plausibility import judge_fit
from bayescal.stats import posterior_effective_params
from bayescal.io import read_recording
from bayescal.measurement import MeasurementModel
from bayescal.simulate import simulate_recording
from tests.instrument.frames import random_frame, to_instrument

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "prs3" / "recording.csv"


def _quiet(f, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return f(*a, **k)


def test_least_squares_on_the_example_is_not_plausible(prs3):
    model = MeasurementModel.from_recording(prs3, read_recording(EXAMPLE))
    res = _quiet(identify, model, method="ls")
    p = assess_plausibility(model, res.theta, res.free, res.residuals_after)
    assert not p.plausible
    names = {d["name"] for d in p.parameters}
    assert "chain3.rail_origin.x" in names and all(d["sigmas"] > 10 for d in p.parameters)
    assert any(c.startswith("unidentifiable combination") and "chain3.rail_origin.x" in c for c in p.causes)
    # the same data with the tolerance prior: plausible
    m = _quiet(map_estimate, model)
    assert assess_plausibility(model, m.theta, m.free, m.residuals_after).plausible


def test_no_residual_degrees_of_freedom(prs3):
    rec = read_recording(EXAMPLE).subset(np.arange(3))
    model = MeasurementModel.from_recording(prs3, rec)
    res = _quiet(map_estimate, model, free="auto")
    p = assess_plausibility(model, res.theta, res.free)
    assert not p.plausible and any("no residual degrees of freedom" in r for r in p.reasons)


def test_a_prior_counts_effective_parameters(prs3):
    # MAP: the filter factors summed (the hat matrix's trace) is what the prior leaves to the data
    rec = read_recording(EXAMPLE).subset(np.arange(3))
    model = MeasurementModel.from_recording(prs3, rec)
    res = _quiet(map_estimate, model, free="all")
    n_rows, p_eff = model.n_poses * model.dof, float(res.filter_factors.sum())
    assert p_eff < n_rows < int(res.free.sum())
    dof_reason = lambda p: [r for r in p.reasons if "no residual degrees of freedom" in r]  # noqa: E731
    assert dof_reason(assess_plausibility(model, res.theta, res.free))
    assert not dof_reason(assess_plausibility(model, res.theta, res.free, effective_params=p_eff))
    r = dof_reason(assess_plausibility(model, res.theta, res.free, effective_params=float(n_rows)))
    assert r and "effective parameters" in r[0]


def test_frame_parameters_are_exempt(prs3):
    sim = simulate_recording(prs3, 30, seed=3, dof=6)
    o, R = random_frame(np.random.default_rng(3))
    m, model, _ = prepare_model(prs3, to_instrument(sim.recording, o, R), frame="fit")
    theta = np.zeros(m.n_params)
    theta[:3] = 5e4  # 50 m off the start: far beyond any tolerance, but the frame has none
    assert assess_plausibility(model, theta, np.ones(m.n_params, bool)).plausible


def test_causes_wrong_frame_units_and_outliers(prs3):
    sim = simulate_recording(prs3, 40, seed=4, dof=6)
    rec = sim.recording
    shifted = replace(rec, position=rec.position + np.array([2.0, -1.0, 1.5]))
    chk = check_frame(prs3, shifted)
    assert chk.fires and "--frame fit" in chk.message()
    assert not check_frame(prs3, rec).fires
    model = MeasurementModel.from_recording(prs3, shifted)
    theta = np.zeros(prs3.n_params)
    theta[prs3.layout.index("chain1.link_length")] = 20 * prs3.tolerance[prs3.layout.index("chain1.link_length")]
    free = np.ones(prs3.n_params, bool)
    p = assess_plausibility(model, theta, free, check=chk)
    assert not p.plausible and any(c.startswith("wrong frame") for c in p.causes)
    # inches: the spreads disagree by 25.4
    inch = replace(rec, position=rec.position / 25.4)
    p = assess_plausibility(MeasurementModel.from_recording(prs3, inch), theta, free, check=check_frame(prs3, inch))
    assert any(c.startswith("wrong units") for c in p.causes)
    # one gross pose carries the chi-square
    res = np.random.default_rng(0).normal(size=(40, 6)) * np.r_[[prs3.noise.sigma_position] * 3, [prs3.noise.sigma_angle] * 3]
    res[13, 0] = 0.5
    p = assess_plausibility(MeasurementModel.from_recording(prs3, rec), theta, free, res)
    assert any(c.startswith("outliers") and "line 15" in c for c in p.causes)


def test_frame_answer_std_matches_the_covariance(prs3):
    sim = simulate_recording(prs3, 36, seed=6, dof=6)
    o, R = random_frame(np.random.default_rng(6))
    m, model, _ = prepare_model(prs3, to_instrument(sim.recording, o, R), frame="fit")
    res = _quiet(map_estimate, model, free="auto")
    ans = frame_answer(m, res.theta, res.free, res.covariance)["frame"]
    assert np.allclose(ans["origin"], m.frame_at(res.theta).origin)
    assert np.allclose(ans["std"]["origin"], res.std[:3])
    # the rotation vector's std by finite differences of the composed frame (linear propagation)
    from scipy.spatial.transform import Rotation

    C = res.covariance[3:6, 3:6]
    M = np.empty((3, 3))
    for j in range(3):
        d = np.zeros(m.n_params)
        d[3 + j] = 1e-7
        rp = Rotation.from_matrix(m.frame_at(res.theta + d).rotation).as_rotvec()
        rm = Rotation.from_matrix(m.frame_at(res.theta - d).rotation).as_rotvec()
        M[:, j] = (rp - rm) / 2e-7
    assert np.allclose(ans["std"]["rotation_vector"], np.sqrt(np.diag(M @ C @ M.T)), rtol=1e-4)
    assert frame_answer(prs3, res.theta[6:], res.free[6:], None) == {}


def test_frame_answer_reaches_the_frame_under_a_view_of_fitted_effects(prs3):
    """Effect parameters fitted with a framed geometry follow its parameters: the frame block is the frame's."""
    from bayescal.effects.base import EffectParam
    from bayescal.effects.joint_model import EffectAugmented

    sim = simulate_recording(prs3, 24, seed=7, dof=6)
    o, R = random_frame(np.random.default_rng(7))
    m, model, _ = prepare_model(prs3, to_instrument(sim.recording, o, R), frame="fit")
    res = _quiet(map_estimate, model, free="auto")
    view = EffectAugmented(m, (EffectParam("dead_band.q1", "um", 30.0),), ("backlash",))
    assert view.framed and view.instrument_frame is m
    k = int(res.free.sum())
    cov = np.zeros((k + 1, k + 1))
    cov[:k, :k], cov[k, k] = res.covariance, 4.0
    ans = frame_answer(view, np.r_[res.theta, 12.0], np.r_[res.free, True], cov)
    assert ans == frame_answer(m, res.theta, res.free, res.covariance) and "std" in ans["frame"]


@pytest.mark.parametrize("dof", [6, 3])
def test_base_frame_recordings_do_not_trigger_the_check(prs3, dof):
    for seed in range(5):
        rec = simulate_recording(prs3, 30, seed=100 + seed, dof=dof).recording
        chk = check_frame(prs3, rec)
        assert not chk.fires
        # nor is a cause named: the drawn errors move the points mostly rigidly (a tenth of a millimetre), which
        # is within what the tolerances explain, not a missing --frame fit
        assert chk.cause() is None and chk.warning() is None


def test_tool_offset_of_the_check_is_the_true_one(prs3, tmp_path):
    """Points measured with a tool 20 mm longer (and off-axis): the check's closed-form tool offset is the true one."""
    text = (ROOT / "examples" / "prs3" / "machine.toml").read_text()
    d = np.array([1.5, -0.5, -20.0])
    (tmp_path / "long.toml").write_text(text.replace("point = [0.0, 0.0, -100.0]", "point = [1.5, -0.5, -120.0]"))
    from bayescal.machines.files import load_machine

    rec = simulate_recording(prs3, 30, seed=8, dof=3).recording
    exact = replace(rec, position=load_machine(tmp_path / "long.toml").forward(rec.q).position)
    chk = check_frame(prs3, exact)
    assert np.allclose(chk.tool_offset, d, atol=1e-8) and chk.rms_tool < 1e-8
    assert chk.explanation == "tool" and not chk.fires and chk.cause().startswith("wrong tool point")


def test_an_exchange_a_rotation_undoes_is_a_frame():
    """Points in a plane (the planar RASPM module moves in x and z): exchanging x and y is a turn by 90 degrees,
    so the recording is in another frame, not mirrored, and --frame fit is the right advice."""
    from bayescal.machines.files import load_machine

    m = load_machine(ROOT / "examples" / "raspm" / "machine.toml")
    rec = simulate_recording(m, 30, seed=2, dof=3).recording
    p = rec.position.copy()
    p[:, [0, 1]] = p[:, [1, 0]]
    chk = check_frame(m, replace(rec, position=p))
    assert chk.explanation == "frame" and chk.fires and chk.rms_swapped >= chk.rms_rigid / chk.DROP


def test_a_posteriors_effective_parameters_are_its_hat_matrix_trace():
    # linear-Gaussian closed form: P_post = (J^T J + P^-1)^-1 and the hat matrix J P_post J^T
    rng = np.random.default_rng(5)
    J = rng.normal(size=(12, 8))
    prior = np.diag(rng.uniform(0.5, 2.0, 8) ** 2)
    post = np.linalg.inv(J.T @ J + np.linalg.inv(prior))
    assert posterior_effective_params(prior, post) == pytest.approx(np.trace(J @ post @ J.T), rel=1e-10)
    assert posterior_effective_params(prior, prior) == 0.0  # the data determined nothing


def test_kalman_on_two_poses_is_judged_like_map(prs3):
    # both fit under the tolerance prior: MAP was plausible, the filter "had no residual degrees of freedom"
    model = MeasurementModel.from_recording(prs3, read_recording(EXAMPLE).subset(np.arange(2)))
    kal = _quiet(kalman_filter, model, free="all")
    _, p = judge_fit(prs3, model, kal)
    assert p.plausible, p.reasons
    n_eff = kal.prior_effective_params
    assert 0 < n_eff < model.n_poses * model.dof < int(kal.free.sum())


@pytest.mark.parametrize("column", [0, 2])
def test_one_mistyped_cell_is_not_blamed_on_the_units(prs3, column):
    """A decimal shift in one cell (163 for 16.3 mm) moves the spread; wrong units move every pose (issue 30)."""
    rec = simulate_recording(prs3, 36, seed=5, dof=6).recording
    p = rec.position.copy()
    p[7, column] = 10 * p[7, column] + (150.0 if abs(p[7, column]) < 15 else 0.0)  # a gross shift whatever the value
    typo = replace(rec, position=p)
    chk = check_frame(prs3, typo)
    assert abs(np.log(chk.scale)) > 0.05  # the whole recording's spread disagrees ...
    assert abs(np.log(chk.scale_one_out)) < 0.01 and chk.odd_line == 9 and chk.odd_column == "xyz"[column]
    theta = np.zeros(prs3.n_params)
    theta[0] = 20 * prs3.tolerance[0]
    causes = assess_plausibility(MeasurementModel.from_recording(prs3, typo), theta, np.ones(prs3.n_params, bool),
                                 check=chk).causes
    assert not any(c.startswith("wrong units") for c in causes)
    assert any(c.startswith("one pose makes the spread") and "CSV line 9" in c and f"column {'xyz'[column]}" in c
               for c in causes)
    # ... while a recording in inches scales every pose: leaving one out does not help
    inch = check_frame(prs3, replace(rec, position=rec.position / 25.4))
    assert abs(np.log(inch.scale_one_out) - np.log(25.4)) < 0.05
