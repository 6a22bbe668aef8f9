import numpy as np
import pytest

from bayescal.effects import EFFECTS, Backlash, actuator_loads, approach_direction, check_effect, fit_map, get_effect
from bayescal.effects.check import EffectCheckError
from bayescal.effects.simulate import parse_effect_spec, simulate_with_effects
from bayescal.errors import InputError
from bayescal.identify import identify
from bayescal.measurement import MeasurementModel

AUX = {"temp_C": np.linspace(20, 25, 12), "time_s": np.linspace(0, 3000, 12), "payload_kg": np.linspace(0, 20, 12)}


#: Effects of serial chains only (their links and stages), checked on the telescope and the arm in tests/physics.
SERIAL_ONLY = ("gravity_deflection", "gravity_backlash")


@pytest.mark.parametrize("name", [n for n in EFFECTS if n != "redundancy_preload" and n not in SERIAL_ONLY])
def test_effect_conformance_and_jacobian(prs3, name):
    # check_effect compares delta_q_jacobian with central finite differences, among other things
    check_effect(get_effect(name), prs3, aux=AUX)


@pytest.mark.parametrize("name", SERIAL_ONLY)
def test_serial_only_effects_say_why_not_on_a_parallel_kind(prs3, name):
    assert "serial chains" in get_effect(name).not_applicable(prs3, {})


def test_thermal_time_mode_conformance(prs3):
    check_effect(get_effect("thermal_expansion"), prs3, aux={"time_s": AUX["time_s"]})


def test_check_effect_catches_a_wrong_jacobian(prs3):
    class Broken(Backlash):
        """Physics: backlash with a Jacobian off by a factor of two."""

        name = "broken_backlash"

        def delta_q_jacobian(self, features, eta):
            return 2 * super().delta_q_jacobian(features, eta)

    with pytest.raises(EffectCheckError, match="finite differences"):
        check_effect(Broken(), prs3)


def test_redundancy_preload_not_applicable_on_3prs(prs3):
    why = get_effect("redundancy_preload").not_applicable(prs3, {})
    assert why and "not applicable" in why and "3 actuators" in why


def test_thermal_needs_a_channel(prs3):
    assert "temp_C" in get_effect("thermal_expansion").not_applicable(prs3, {"payload_kg": np.zeros(3)})


def test_approach_direction_closed_form():
    q = np.array([[1.0, 5.0], [2.0, 4.0], [2.0, 6.0], [0.5, 6.5]])
    expected = np.array([[0, 0], [1, -1], [0, 1], [-1, 1]])
    np.testing.assert_array_equal(approach_direction(q), expected)
    # rows out of time order: the order argument restores the sequence
    perm = np.array([2, 0, 3, 1])
    np.testing.assert_array_equal(approach_direction(q[perm], order=perm), expected[perm])


def test_actuator_loads_equal_virtual_work_by_finite_differences(prs3, rng):
    # f_i = F . d p_com / d q_i: an independent path through the forward kinematics only
    q = prs3.sample_q(5, rng)
    poses = prs3.forward(q)
    mass = np.full(5, 30.0)
    f = actuator_loads(prs3, q, None, poses, mass)
    F = np.array([0.0, 0.0, -30.0 * 9.80665])
    h = 1e-4
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        dp = (prs3.forward(q + e, guess=poses).state.p - prs3.forward(q - e, guess=poses).state.p) / (2 * h)
        np.testing.assert_allclose(f[:, i], dp @ F, rtol=1e-6)


def test_fit_without_effects_equals_ridge_map(prs3, sim6):
    model = MeasurementModel.from_recording(prs3, sim6.recording)
    fit = fit_map(model)
    ref = identify(model, method="ridge", lam=1.0, free="all")
    np.testing.assert_allclose(fit.theta / prs3.tolerance, ref.theta / prs3.tolerance, atol=1e-6)
    assert fit.chi2 == pytest.approx(ref.chi2, rel=1e-8)


def test_bound_effect_in_the_simulator(prs3, rng):
    from bayescal.simulate import measure

    q = prs3.sample_q(30, rng)
    theta = np.zeros(prs3.n_params)
    bound = get_effect("backlash").bind(prs3, [40.0, 40.0, 40.0])
    clean = measure(prs3, q, theta, 3, None)
    bl = measure(prs3, q, theta, 3, None, effects=[bound])
    diff = bl.position - clean.position
    assert np.linalg.norm(diff[0]) == pytest.approx(0.0, abs=1e-12)  # first pose: approach unknown
    # the rest: exactly the kinematics at q - 20 um * approach sign (the slider lags the command;
    # the moves between random poses are far longer than the 40 um band)
    s = approach_direction(q)
    expected = prs3.forward(q - 0.02 * s).position - clean.position
    np.testing.assert_allclose(diff, expected, atol=1e-9)
    sim = simulate_with_effects(prs3, 30, seed=4, dof=3, effects=[("backlash", 40.0)])
    assert sim.info["effects"]["backlash"]["parameters"][0]["name"] == "backlash.q1"


def test_parse_effect_spec():
    assert parse_effect_spec("backlash:12.5") == ("backlash", 12.5)
    assert parse_effect_spec("joint_compliance") == ("joint_compliance", get_effect("joint_compliance").default_magnitude)
    with pytest.raises(InputError, match="unknown effect"):
        parse_effect_spec("wobble:3")
    with pytest.raises(InputError, match="magnitude"):
        parse_effect_spec("backlash:lots")
    # issue 30 probe: an empty magnitude took the default, 1e300 um was simulated
    with pytest.raises(InputError, match=r"backlash:: expected NAME\[:magnitude\] with a number"):
        parse_effect_spec("backlash:")
    with pytest.raises(InputError, match=r"expected a magnitude from 0 to 1e\+09 \(um\)"):
        parse_effect_spec("backlash:1e300")


def test_an_effect_given_twice_is_refused(prs3):
    # --effect backlash --effect backlash:2 simulated one of them, silently
    with pytest.raises(InputError, match="--effect backlash: given more than once"):
        simulate_with_effects(prs3, 5, seed=1, effects=[("backlash", 1.0), ("backlash", 2.0)])


@pytest.mark.parametrize("name", ["joint_compliance", "screw_periodic_error", "thermal_expansion"])
def test_measurement_rows_jacobian_of_effect_parameters(prs3, sim6, name):
    # d h / d eta = (d h / d q) (d dq / d eta), against finite differences of the full model (6-DOF rows)
    from bayescal.effects.model import effect_residual

    model = MeasurementModel.from_recording(prs3, sim6.recording)
    n = model.n_poses
    aux = {"temp_C": np.linspace(20, 26, n), "payload_kg": np.linspace(0, 20, n)}
    eff = get_effect(name)
    theta = np.zeros(prs3.n_params)
    feats = eff.features(prs3, model.q, theta, aux, None, prs3.forward(model.q))
    params = eff.params(prs3, feats)
    eta = np.array([p.prior_mean + 0.5 * p.prior_sd for p in params])
    q_eff = model.q + eff.delta_q(feats, eta)
    from dataclasses import replace

    sub = replace(model, q=q_eff)
    pred = sub.predict(theta)
    J = np.einsum("ndm,nmk->ndk", sub.rows_jacobian(prs3.actuator_jacobian(q_eff, theta, pred.poses), pred),
                  eff.delta_q_jacobian(feats, eta))
    for k, p in enumerate(params):
        h = 1e-3 * p.prior_sd
        e = np.zeros(len(eta))
        e[k] = h
        # residual = y - h, so its derivative is -J
        fd = -(effect_residual(model, [(eff, feats)], theta, eta + e) - effect_residual(model, [(eff, feats)], theta, eta - e)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], fd, atol=1e-6 * max(np.abs(fd).max(), 1e-9) + 1e-10)


def test_nonphysical_flags_only_parameters_significantly_below_their_bound(prs3):
    f = get_effect("joint_compliance")
    params = f.params(prs3, None)
    bounded = [p.name for p in params if p.lower is not None]
    assert bounded == ["weight_deflection.q1", "weight_deflection.q2", "weight_deflection.q3"]
    assert all(p.lower == 0.0 for p in params if p.lower is not None)
    std = np.full(8, 10.0)
    assert f.nonphysical(params, np.array([50, -5, -29, -300, 300, 0, 0.5, -0.5]), std) is None  # within 3 sigma: noise
    why = f.nonphysical(params, np.array([50, -5, -100, -300, 300, 0, 0.5, -0.5]), std)
    assert why and "weight_deflection.q3" in why and "weight_deflection.q2" not in why
    b = get_effect("backlash")
    assert "backlash.q1" in b.nonphysical(b.params(prs3, None), np.array([-40.0, 10.0, 10.0]), np.full(3, 5.0))
    t = get_effect("thermal_expansion")
    tf = t.features(prs3, np.zeros((4, 3)) + 400.0, None, {"temp_C": np.full(4, 21.0)}, None, None)
    tp = t.params(prs3, tf)
    assert [p.name for p in tp][6:] == ["link.q1", "link.q2", "link.q3"]
    eta = np.zeros(len(tp))
    eta[4] = -30.0  # alpha.q2: a screw that shrinks when warmed
    assert "alpha.q2" in t.nonphysical(tp, eta, np.full(len(tp), 2.0))
    assert t.nonphysical(tp, -eta, np.full(len(tp), 2.0)) is None  # drifts may take either sign; alpha > 0 is fine
    eta[4], eta[7] = 0.0, -30.0  # link.q2: a link that shrinks when warmed
    assert "link.q2" in t.nonphysical(tp, eta, np.full(len(tp), 2.0))


def test_preload_compliance_ratios_must_not_be_negative():
    # a compliance ratio c_s / c_r is a ratio of two positive compliances; the offset and geometry take either sign
    from bayescal.effects import get_effect as ge
    from bayescal.machines.files import load_machine
    from tests.conftest import ROOT

    m = load_machine(ROOT / "examples" / "raspm" / "machine.toml")
    p = ge("redundancy_preload")
    params = p.params(m, p.features(m, m.sample_q(3, np.random.default_rng(0)), np.zeros(m.n_params), {}, None, None))
    eta, std = np.zeros(len(params)), np.full(len(params), 0.05)
    eta[:3] = [1.2, 0.8, 2.0]
    eta[3:] = -0.3
    assert p.nonphysical(params, eta, std) is None
    eta[1] = -0.5
    why = p.nonphysical(params, eta, std)
    assert why and "compliance_ratio.q3" in why and "q1" not in why


def test_joint_compliance_inadmissible_when_no_drive_carries_the_weight():
    # RU-PUS-PRS: a weight at the platform origin (the centre of the passive post's universal joint) loads
    # only the post; a changing payload at the tool point (50 mm above it) loads the drives through its moment
    from bayescal.machines.files import load_machine
    from tests.conftest import PRS3_FILE

    m = load_machine(PRS3_FILE.parent.parent / "rupus_prs" / "machine.toml")
    sim = simulate_with_effects(m, 15, seed=1, dof=6, record=("payload_kg",))
    eff = get_effect("joint_compliance")
    aux = dict(sim.recording.aux)
    f = eff.features(m, sim.recording.q, np.zeros(m.n_params), {}, None, None)
    assert "no gravity load" in eff.inadmissible(f)
    f = eff.features(m, sim.recording.q, np.zeros(m.n_params), aux, None, None)
    assert eff.inadmissible(f) is None and "compliance.q2" in [p.name for p in eff.params(m, f)]


def test_simulating_an_effect_that_cannot_act_is_an_error():
    from bayescal.machines.files import load_machine
    from tests.conftest import PRS3_FILE

    m = load_machine(PRS3_FILE.parent.parent / "rupus_prs" / "machine.toml")
    with pytest.raises(InputError, match=r"--effect joint_compliance:0.5: has no effect on the RU-PUS-PRS.*no gravity load"):
        simulate_with_effects(m, 10, seed=1, effects=[("joint_compliance", 0.5)])


def test_preload_directions_keep_one_orientation_where_a_component_crosses_zero():
    from bayescal.effects.redundancy_preload import orient_directions

    # a direction turning through 60 degrees: its first component changes sign half way
    a = np.linspace(-0.5, 0.5, 11)
    nu = np.stack([np.sin(a), np.cos(a), np.zeros(11)], axis=1)
    flips = np.where(np.arange(11) % 3 == 0, -1.0, 1.0)[:, None]  # given up to sign, as an SVD returns them
    out = orient_directions(nu * flips)
    np.testing.assert_allclose(out, nu)  # continuous, and the dominant component (the second) positive


def test_effect_settings_are_checked_and_applied(prs3):
    jc = get_effect("joint_compliance", gravity=[2.0, 0.0, 0.0])
    np.testing.assert_allclose(jc.down, [1.0, 0.0, 0.0])
    assert get_effect("thermal_expansion", reference_C=23.0).reference_C == 23.0
    with pytest.raises(InputError, match="unknown setting.*mass.*expected some of: gravity, payload_offset, platform_mass_kg, platform_com_mm"):
        get_effect("joint_compliance", mass=30.0)
    with pytest.raises(InputError, match="non-zero 3-vector"):
        get_effect("joint_compliance", gravity=[0.0, 0.0, 0.0])
    with pytest.raises(InputError, match="expected some of: none"):
        get_effect("backlash", gravity=[0.0, 0.0, -1.0])


def test_gram_matrix_of_the_joint_fit_is_the_same_on_both_sides_of_the_blas_switch():
    """fit_map's normal matrix comes from einsum below _GRAM_BLAS_ROWS rows and from BLAS above (issue 32):
    both are A^T A, to round-off, against an independent column-by-column sum."""
    import numpy as np

    from bayescal.effects.model import _GRAM_BLAS_ROWS, _gram

    rng = np.random.default_rng(3)
    for rows in (_GRAM_BLAS_ROWS - 1, _GRAM_BLAS_ROWS):
        A = rng.normal(size=(rows, 7))
        ref = np.array([[float(np.dot(A[:, i], A[:, j])) for j in range(7)] for i in range(7)])
        np.testing.assert_allclose(_gram(A), ref, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("effects", [[], [("backlash", 20.0)]])
def test_linearised_fold_fits_match_refits(prs3, effects):
    # the diagnosis' cross-validation on large recordings: each fold's fit one Gauss-Newton step from the
    # full fit.  Against the refit of every fold (fit_map on the training rows, then the held-out rows
    # predicted through the kinematics): the held-out residuals agree to a small fraction of how far the
    # fold's fit moved them away from the full fit's
    from bayescal.effects.model import effect_residual, linear_fold_residuals

    sim = simulate_with_effects(prs3, 300, seed=8, dof=6, effects=effects)
    model = MeasurementModel.from_recording(prs3, sim.recording)
    pairs = []
    if effects:
        eff = get_effect("backlash")
        f = eff.features(prs3, model.pose_q, np.zeros(prs3.n_params), {}, model.pose_order, None)
        pairs = [(eff, f)]
    full = fit_map(model, pairs)
    folds = [np.arange(i, model.n_poses, 5) for i in range(5)]
    linear = linear_fold_residuals(model, pairs, full.theta, full.eta, folds)
    for test, lin in zip(folds, linear):
        train = np.setdiff1d(np.arange(model.n_poses), test)
        fit = fit_map(model.subset(train), [(e, f.subset(train)) for e, f in pairs], theta0=full.theta, eta0=full.eta)
        exact = effect_residual(model.subset(test), [(e, f.subset(test)) for e, f in pairs], fit.theta, fit.eta)
        moved = np.abs(exact - full.residual[test]).max()
        assert moved > 1e-5  # leaving a fold out changes its residuals: the comparison has teeth
        np.testing.assert_allclose(lin, exact, rtol=0, atol=2e-3 * moved)  # 0.8-2e-4 of it measured


def test_an_aux_channel_given_twice_is_refused(prs3):
    with pytest.raises(InputError, match=r"--aux: a channel given more than once \(time_s,time_s\)"):
        simulate_with_effects(prs3, 5, seed=1, record=["time_s", "time_s"])
