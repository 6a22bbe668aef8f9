"""redundancy_preload against the independent restrained physics (energy minimisation, no delta_q)."""

import numpy as np
import pytest

from bayescal.effects import check_effect, fit_map, get_effect
from bayescal.effects.check import EffectCheckError
from bayescal.effects.redundancy_preload import RedundancyPreload
from bayescal.machines.files import load_machine
from bayescal.measurement import MeasurementModel
from bayescal.redundant.physics import solve_restrained
from bayescal.redundant.restrained_recording import restrained_recording, true_effect_values
from bayescal.simulate import draw_errors
from tests.conftest import ROOT

RASPM = ROOT / "examples" / "raspm" / "machine.toml"


@pytest.fixture(scope="module")
def raspm():
    return load_machine(RASPM)


def test_parameters_named_with_units(raspm):
    eff = get_effect("redundancy_preload")
    f = eff.features(raspm, raspm.sample_q(3, np.random.default_rng(0)), np.zeros(raspm.n_params), {}, None, None)
    params = {p.name: p.unit for p in eff.params(raspm, f)}
    assert params == {
        "compliance_ratio.q1": "1", "compliance_ratio.q3": "1", "compliance_ratio.q4": "1",
        "redundant.chain2_platform_joint_x": "mm", "redundant.chain2_platform_joint_z": "mm",
        "redundant.chain2_slider1_rail_origin_x": "mm", "offset.q2": "mm",
        "redundant.chain2_slider1_rail_direction_tilt": "rad", "redundant.chain2_slider1_link_length": "mm",
    }


def test_conformance_and_both_jacobians_by_finite_differences(raspm):
    check_effect(get_effect("redundancy_preload"), raspm)

    class WrongTheta(RedundancyPreload):
        """Physics: the restrained preload with its geometry Jacobian off by 1 %."""

        name = "wrong_theta"

        def delta_q_theta_jacobian(self, features, eta, theta):
            return 1.01 * super().delta_q_theta_jacobian(features, eta, theta)

    with pytest.raises(EffectCheckError, match="delta_q_theta_jacobian differs from finite differences"):
        check_effect(WrongTheta(), raspm)


@pytest.mark.parametrize("seed, offset, k_range", [(1, 0.0, (150, 500)), (2, 0.3, (50, 800)), (3, -0.5, (150, 500)), (4, 0.1, (300, 320))])
def test_model_matches_the_energy_minimum(raspm, seed, offset, k_range):
    """dq of the effect puts the non-redundant model where solve_restrained settles the true module."""
    m = raspm
    eff = get_effect("redundancy_preload")
    rng = np.random.default_rng(seed)
    theta = draw_errors(m, rng)
    q = m.inverse_planar(m.sample_planar(40, rng))
    q[:, 1] += offset
    k = rng.uniform(*k_range, 4) * 1e3
    st = solve_restrained(m, q, theta, k)
    true_tool = m.tool_from_planar(st.x, theta)[0]
    # the model's geometry has the redundant chain at nominal: its errors are the effect's parameters
    f_true = eff.features(m, q, theta, {}, None, None)
    cols = list(f_true.const["columns"])
    th = theta.copy()
    th[cols] = 0.0
    f = eff.features(m, q, th, {}, None, None)
    params = eff.params(m, f)
    eta = np.array([v for v in true_effect_values(m, _Sim(theta, k), params).values()])
    moved = m.forward(q, th).position
    assert np.abs(moved - true_tool).max() > 0.01  # the preload moves the tool by more than 10 um
    model_tool = m.forward(q + eff.delta_q(f, eta), th).position
    assert np.abs(model_tool - true_tool).max() < 5e-4  # second order: < 0.5 um
    # the same from features at the nominal geometry, moved to the true one by the geometry coupling
    f0 = eff.features(m, q, np.zeros(m.n_params), {}, None, None)
    model_tool = m.forward(q + eff.delta_q_at(f0, eta, th), th).position
    assert np.abs(model_tool - true_tool).max() < 5e-4


class _Sim:
    def __init__(self, theta, k):
        self.theta, self.stiffness = theta, k


def test_zero_compliance_ratios_mean_no_preload(raspm):
    eff = get_effect("redundancy_preload")
    q = raspm.sample_q(5, np.random.default_rng(1))
    f = eff.features(raspm, q, draw_errors(raspm, np.random.default_rng(2)), {}, None, None)
    eta = np.full(len(eff.params(raspm, f)), 0.03)
    eta[:3] = 0.0
    assert np.abs(eff.delta_q(f, eta)).max() == 0.0
    eta[:3] = 1.0
    assert np.abs(eff.delta_q(f, eta)).max() > 1e-3


@pytest.mark.parametrize("seed, offset, dof", [(11, 0.05, 3), (12, 0.5, 3), (13, -0.2, 3), (14, 0.1, 6)])
def test_parameters_recovered_within_their_uncertainty(raspm, seed, offset, dof):
    """Joint MAP fit on restrained recordings: every effect parameter within 4 reported sigmas of the truth."""
    sim = restrained_recording(raspm, 80, seed, offset_mm=offset, dof=dof)
    model = MeasurementModel.from_recording(raspm, sim.recording)
    fit0 = fit_map(model)
    eff = get_effect("redundancy_preload")
    f = eff.features(raspm, model.q, fit0.theta, {}, None, model.predict(fit0.theta).poses)
    fit = fit_map(model, [(eff, f)], theta0=fit0.theta)
    assert fit.success
    rows = fit.n_rows
    assert fit0.chi2 > 2 * rows and fit.chi2 < 1.3 * rows  # the geometry alone fails; with the preload, the noise is left
    truth = true_effect_values(raspm, sim, fit.params)
    std = fit.std_eta()
    z = {p.name: (v - truth[p.name]) / s for p, v, s in zip(fit.params, fit.eta, std)}
    assert max(abs(v) for v in z.values()) < 4.0, z
    # the ratios are told apart from zero (the data see the preload) and the tilt of the redundant rail is sharp
    assert all(fit.eta[i] > 3 * std[i] for i in range(3))


def test_alternating_offsets_pin_the_compliance_ratios(raspm):
    """Commanding the redundant drive's offset at every other pose measures the ratios to about 1 %."""
    sim = restrained_recording(raspm, 80, 11, offset_mm=0.3, alternate_offset=True)
    model = MeasurementModel.from_recording(raspm, sim.recording)
    fit0 = fit_map(model)
    eff = get_effect("redundancy_preload")
    f = eff.features(raspm, model.q, fit0.theta, {}, None, model.predict(fit0.theta).poses)
    fit = fit_map(model, [(eff, f)], theta0=fit0.theta)
    truth = true_effect_values(raspm, sim, fit.params)
    ratios = np.array([truth[p.name] for p in fit.params[:3]])
    assert np.all(np.abs(fit.eta[:3] / ratios - 1) < 0.05)
    assert np.all(fit.std_eta()[:3] / ratios < 0.05)


def test_a_geometry_change_along_the_compliant_internal_force_is_invisible_to_restrained_data(raspm):
    """Why one restrained recording cannot give the non-redundant geometry exactly (docs/diagnose.md).

    A geometric change whose effect on the drives is ``lam C nu(x)`` (``C`` the
    compliances) leaves the equilibrium ``J_a^T K (IK(x) - q) = 0`` unchanged;
    the geometric parameters reproduce that pattern to about 2 %, so a
    tolerance-sized change moves the restrained poses by less than the noise
    while the non-redundant forward kinematics moves by tens of um.
    """
    from bayescal.redundant.physics import internal_force_basis

    m = raspm
    rng = np.random.default_rng(11)
    theta = draw_errors(m, rng)
    k = rng.uniform(150, 500, 4) * 1e3
    xs = m.sample_planar(150, rng)
    q = m.inverse_planar(xs, theta)
    _, Ja = m.ik_jacobian(xs, theta)
    nu = internal_force_basis(Ja)[:, :, 0]
    nu = nu * np.sign(nu[:, :1])
    G = m.ik_parameter_jacobian(xs, theta).reshape(-1, m.n_params)
    d = np.linalg.lstsq(G, (nu / k).reshape(-1), rcond=None)[0]
    d *= 0.05 / np.abs(d).max()
    tool = [m.tool_from_planar(solve_restrained(m, q, t, k).x, t)[0] for t in (theta, theta + d)]
    fk = [m.forward(q, t).position for t in (theta, theta + d)]
    rms = lambda a, b: float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))  # noqa: E731
    assert rms(*tool) < 0.5 * m.noise.sigma_position * np.sqrt(3)
    assert rms(*fk) > 20e-3


def test_in_a_fitted_instrument_frame_the_preload_is_the_base_machines(raspm):
    """--frame fit: the effect reads the inner RASPM; the six frame parameters do not move the incompatibility."""
    from bayescal.machines.framed import Frame, InstrumentFrame

    framed = InstrumentFrame(raspm, Frame.from_rotation_vector([100.0, -50.0, 20.0], [0.01, -0.02, 0.3]), fit=True)
    eff = get_effect("redundancy_preload")
    assert eff.not_applicable(framed, {}) is None
    q = raspm.sample_q(8, np.random.default_rng(3))
    theta = draw_errors(raspm, np.random.default_rng(4))
    f_in = eff.features(raspm, q, theta, {}, None, None)
    f_fr = eff.features(framed, q, np.concatenate([np.full(6, 0.1), theta]), {}, None, None)
    eta = np.r_[1.5, 0.7, 1.1, np.full(6, 0.02)]
    np.testing.assert_allclose(eff.delta_q(f_fr, eta), eff.delta_q(f_in, eta), atol=1e-12)
    assert [p.name for p in eff.params(framed, f_fr)] == [p.name for p in eff.params(raspm, f_in)]
    Jt = eff.delta_q_theta_jacobian(f_fr, eta, np.concatenate([np.zeros(6), theta]))
    assert Jt.shape == (8, 4, 6 + raspm.n_params) and np.all(Jt[:, :, :6] == 0.0)
    check_effect(eff, framed)
