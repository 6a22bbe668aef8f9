"""Effects as unknowns with the geometry (bayescal.effects.joint_model): prediction, Jacobian, MAP, posterior.

The joint model is checked against what it must agree with but does not
share: the stored-effect application of every command (effects at fixed
values, bayescal.effects.stored), central differences, the diagnosis'
own joint Gauss-Newton (bayescal.effects.model.fit_map), and
self-normalised importance sampling of the same posterior.
"""

import numpy as np
import pytest

from bayescal.bayes.mcmc import log_posterior_function, sample_posterior
from bayescal.bayes.priors import map_estimate, prior_from_machine
from bayescal.effects.joint_model import EffectModel, effect_model
from bayescal.effects.model import fit_map
from bayescal.effects.stored import StoredEffect, StoredEffectsTransform
from bayescal.errors import InputError
from bayescal.measurement import MeasurementModel
from bayescal.simulate import simulate_recording

BACKLASH = StoredEffect("backlash", (("backlash.q1", 20.0), ("backlash.q2", 30.0), ("backlash.q3", 25.0)))
# joint compliance with a payload channel: compliances, platform mass, centre of mass and mounting tilt
COMPLIANCE = StoredEffect("joint_compliance", (("compliance.q1", 0.4), ("compliance.q2", 0.6), ("compliance.q3", 0.5),
                                               ("platform_mass", 30.0), ("com.x", 5.0), ("com.y", -3.0), ("com.z", 10.0),
                                               ("gravity.tilt_1", 0.01), ("gravity.tilt_2", -0.02)))


def _recording(machine, n, seed, aux=None, theta_true=None):
    """A recording of ``machine`` (with its tables applied), at drawn geometric errors unless ``theta_true``."""
    return simulate_recording(machine, n, seed=seed, effects=[StoredEffectsTransform(machine, machine.effects)], aux=aux,
                              theta_true=theta_true)


@pytest.fixture(scope="module")
def backlash_case(prs3):
    m = prs3.with_effects((BACKLASH,))
    rec = _recording(m, 40, seed=11).recording
    return m, rec, effect_model(m, rec)


@pytest.fixture(scope="module")
def compliance_case(prs3):
    m = prs3.with_effects((COMPLIANCE,))
    payload = np.random.default_rng(5).uniform(0.0, 25.0, 40)
    rec = _recording(m, 40, seed=12, aux={"payload_kg": payload}).recording
    return m, rec, effect_model(m, rec)


def _sensor_case(stored: StoredEffect):
    """The sensor test column (tests/sensors/chain.py) with tilt sensors on its turning bodies and a stored table."""
    from tests.test_contract import sensor_column

    m, rec = sensor_column()
    m = m.with_effects((stored,))
    return m, rec, effect_model(m, rec)


@pytest.fixture(scope="module")
def deflection_sensor_case():
    from tests.test_contract import DEFLECTION

    return _sensor_case(DEFLECTION)


@pytest.fixture(scope="module")
def backlash_sensor_case():
    from tests.test_contract import SERIAL_BACKLASH

    return _sensor_case(SERIAL_BACKLASH)


def _at(machine, stored, eta):
    """The stored tables of ``stored`` at the values ``eta`` (in parameter order)."""
    out, k = [], 0
    for st in stored:
        n = len(st.values)
        out.append(StoredEffect(st.name, tuple((name, float(v)) for (name, _), v in zip(st.values, eta[k:k + n])),
                                settings=st.settings))
        k += n
    return machine.with_effects(tuple(out))


@pytest.mark.parametrize("case", ["backlash_case", "compliance_case", "backlash_sensor_case", "deflection_sensor_case"])
def test_prediction_is_the_stored_effects_prediction_at_any_values(case, request):
    """h(q + dq(eta), theta) equals the commands' prediction of a machine file holding eta as its tables.

    With body tilt sensors too: their rows see an effect's dq and a bending member's turn of their bodies the
    same way in the joint fit, in a written machine's tables and in stacked blocks (a sampler's walkers).
    """
    m, rec, em = request.getfixturevalue(case)
    P = em.geo.n_params  # the geometry, with the sensors' mountings where there are sensors
    assert P == m.n_params + (0 if em.geo.sensors is None else em.geo.sensors.n_params)
    assert em.n_params == P + len(em.effect_params)
    assert em.machine.layout.names[P:][0].startswith(f"effect.{m.effects[0].name}.")
    rng = np.random.default_rng(3)
    for _ in range(2):
        theta = em.theta_start + rng.normal(size=em.n_params) * em.machine.tolerance * 0.3
        fixed = MeasurementModel.from_recording(_at(m.with_effects(()), m.effects, theta[P:]), rec)
        np.testing.assert_allclose(em.predict(theta).y, fixed.predict(theta[:P]).y, rtol=0, atol=1e-10)
    # stacked blocks (one per walker) are each block's own prediction
    X = em.theta_start + rng.normal(size=(3, em.n_params)) * em.machine.tolerance * 0.3
    stacked = em.predict(np.repeat(X, em.n_poses, axis=0)).y.reshape(3, em.n_poses, -1)
    for b in range(3):
        np.testing.assert_allclose(stacked[b], em.predict(X[b]).y, rtol=0, atol=1e-12)
    with pytest.raises(InputError, match="one parameter vector per block"):
        em.predict(np.repeat(X, em.n_poses, axis=0)[1 : 1 + em.n_poses])


@pytest.mark.parametrize("case", ["backlash_case", "compliance_case"])
def test_jacobian_matches_central_differences(case, request):
    _, _, em = request.getfixturevalue(case)
    theta = em.theta_start + 0.2 * em.machine.tolerance * np.random.default_rng(4).normal(size=em.n_params)
    pred = em.predict(theta)
    J = em.jacobian(theta, pred)
    h = 1e-5 * em.machine.tolerance
    for j in range(em.n_params):
        e = np.zeros(em.n_params)
        e[j] = h[j]
        fd = (em.predict(theta + e).y - em.predict(theta - e).y) / (2 * h[j])
        # per tolerance of the parameter, in instrument sigmas: what the fit sees
        err = np.abs(fd - J[:, :, j]) * em.machine.tolerance[j] / em.row_sigma
        assert err.max() < 1e-4, em.machine.layout.names[j]


def test_joint_map_is_the_diagnosis_joint_fit(compliance_case):
    """map_estimate on the joint model and the diagnosis' own Gauss-Newton (fit_map) find the same MAP and covariance."""
    m, rec, em = compliance_case
    res = map_estimate(em, free="all")
    fit = fit_map(em.geo, list(em.effects), eta0=em.theta_start[m.n_params:])
    assert res.success and fit.success
    x_fit = np.concatenate([fit.theta, fit.eta])
    z = np.abs(res.theta - x_fit) / np.sqrt(np.diag(fit.covariance))
    assert z.max() < 1e-3
    np.testing.assert_allclose(np.sqrt(np.diag(res.covariance)), np.sqrt(np.diag(fit.covariance)), rtol=1e-3)
    # the effect is found: every compliance within 4 sigma of the truth the recording was made with
    eta = res.theta[m.n_params:m.n_params + 3]
    sd = np.sqrt(np.diag(res.covariance))[m.n_params:m.n_params + 3]
    assert np.all(np.abs(eta - [0.4, 0.6, 0.5]) < 4 * sd)
    # and its prior is the effect's, centred where the effect says (EffectParam.prior_mean), not at the stored value
    prior = prior_from_machine(em.machine)
    assert np.all(prior.std[m.n_params:] == [p.prior_sd for p in em.effect_params])
    assert np.all(prior.lower[m.n_params:m.n_params + 4] == 0.0)  # compliances and mass cannot be negative


def test_written_tables_carry_the_fitted_values(backlash_case):
    m, _, em = backlash_case
    theta = em.theta_start.copy()
    theta[m.n_params:] = [1.5, 2.5, 3.5]
    (st,) = em.stored_effects(theta)
    assert st.name == "backlash" and st.values == (("backlash.q1", 1.5), ("backlash.q2", 2.5), ("backlash.q3", 3.5))
    assert st.units == ("um",) * 3


def test_joint_posterior_agrees_with_importance_sampling(prs3):
    """The sampler's marginals of the backlash and of two geometric parameters against self-normalised importance sampling.

    Sampled: the three backlash parameters (small, so the truncation at zero matters) and two rail origins;
    the others held at nominal, where the recording's machine has them.  Importance draws from a t with
    1.5 times the Laplace scale, weighted by the same log posterior.
    """
    small = StoredEffect("backlash", (("backlash.q1", 1.0), ("backlash.q2", 3.0), ("backlash.q3", 2.0)))
    m = prs3.with_effects((small,))
    em = effect_model(m, _recording(m, 30, seed=13, theta_true=np.zeros(prs3.n_params)).recording)
    names = ["chain1.rail_origin.z", "chain2.rail_origin.z", "effect.backlash.backlash.q1",
             "effect.backlash.backlash.q2", "effect.backlash.backlash.q3"]
    res = sample_posterior(em, free=names, n_steps=600, seed=2)
    assert res.success, res.message
    prior = prior_from_machine(em.machine)
    idx = np.flatnonzero(res.free)
    lp = log_posterior_function(em, prior, idx, guess=em.predict(res.theta).poses)
    rng = np.random.default_rng(9)
    mean, L = res.bend.x0, res.bend.basis * 1.5  # the Laplace approximation at the MAP, 1.5 times as wide
    k, df = 6000, 5.0
    z = rng.standard_normal((k, idx.size)) * np.sqrt(df / rng.chisquare(df, size=k))[:, None]
    x = mean + z @ L.T
    logq = -0.5 * (df + idx.size) * np.log1p(np.sum(z**2, axis=1) / df)
    lw = np.concatenate([lp(x[i:i + 2500])[:, 0] for i in range(0, k, 2500)]) - logq
    w = np.exp(lw - lw[np.isfinite(lw)].max())
    w[~np.isfinite(w)] = 0.0
    w /= w.sum()
    ess = 1.0 / np.sum(w**2)
    assert ess > 600
    is_mean = w @ x
    is_sd = np.sqrt(w @ (x - is_mean) ** 2)
    mc = res.samples
    # Monte Carlo error of both: the chain's ESS and the importance ESS, in posterior sds
    tol = 4 * np.sqrt(1 / np.min(res.ess_bulk) + 1 / ess)
    assert np.all(np.abs(mc.mean(axis=0) - is_mean) / is_sd < tol)
    assert np.all(np.abs(mc.std(axis=0) / is_sd - 1) < 0.1)
    # the truncation at zero is sampled: no draw of a backlash below it
    assert mc[:, 2:].min() >= 0.0


def test_effect_model_refuses_what_it_cannot_fit(prs3, backlash_case):
    _, rec, em = backlash_case
    with pytest.raises(InputError, match="no \\[effect"):
        effect_model(prs3, rec)
    with pytest.raises(InputError, match="must not apply stored effects"):
        EffectModel(MeasurementModel.from_recording(prs3.with_effects((BACKLASH,)), rec), em.effects)


def test_grid_std_carries_the_effect_parameters(compliance_case):
    """A compensation grid from the joint fit: correction and std against central differences of the nodes' tool points.

    ``p(x) = forward(q + dq_nodes(eta), theta)`` at every node under a stated payload, differentiated by
    central differences in every parameter (geometry and effect), gives ``sqrt(diag(G C G^T))``; the
    grid's linearised std must equal it, and exceed the std with the effect held at its values.
    """
    from bayescal.bayes.grid import actuator_nodes, compensation_grid

    m, rec, em = compliance_case
    res = map_estimate(em, free="all")
    view, idx = em.machine.geometry_part
    assert idx.size == em.n_params and view.n_params == em.n_params  # nothing is nuisance here, the effects are kept
    axes = tuple(np.linspace(lo, hi, 2) for lo, hi in m.q_limits)
    aux = {"payload_kg": 12.0}
    grid = compensation_grid(view, res.theta, covariance=res.covariance, axes=axes, aux=aux)
    q_cmd = actuator_nodes(axes)

    def tool(x):
        return view.forward(view.node_actuators(q_cmd, x, aux)[0], x).position

    # the correction is the fitted machine's, with the fitted effect applied under the payload
    fitted = m.with_effects(em.stored_effects(res.theta))
    from bayescal.effects.stored import static_effect_delta_q

    direct = fitted.forward(q_cmd + static_effect_delta_q(fitted, fitted.effects, q_cmd, aux), res.theta[:m.n_params]).position
    np.testing.assert_allclose(-grid.correction.reshape(-1, 3), direct - m.forward(q_cmd, None).position, atol=1e-12)
    h = 1e-4 * em.machine.tolerance
    G = np.stack([(tool(res.theta + h[k] * np.eye(em.n_params)[k]) - tool(res.theta - h[k] * np.eye(em.n_params)[k]))
                  / (2 * h[k]) for k in range(em.n_params)], axis=2)
    std_fd = np.sqrt(np.einsum("nak,kl,nal->na", G, res.covariance, G))
    np.testing.assert_allclose(grid.std.reshape(-1, 3), std_fd, rtol=1e-4, atol=1e-9)
    # held at the fitted values (identify without --fit-effects: the geometry's covariance given the effect),
    # the std is smaller at every node
    held_fit = map_estimate(MeasurementModel.from_recording(fitted, rec), free="all")
    held = compensation_grid(fitted, held_fit.theta, covariance=held_fit.covariance, axes=axes, aux=aux)
    ratio = np.linalg.norm(grid.std, axis=-1) / np.linalg.norm(held.std, axis=-1)
    assert np.all(ratio > 1.0), ratio


def test_parameters_not_sampled_stay_where_the_answer_holds_them(prs3):
    """With an effect parameter left out of ``free``, the sampler's target holds it at the stored value, as the MAP does."""
    m = prs3.with_effects((BACKLASH,))
    em = effect_model(m, _recording(m, 30, seed=14, theta_true=np.zeros(prs3.n_params)).recording)
    names = ["chain1.rail_origin.z", "effect.backlash.backlash.q1", "effect.backlash.backlash.q2"]
    res = sample_posterior(em, free=names, n_steps=40, seed=1)  # a short chain: only its target is looked at
    q3 = em.machine.layout.names.index("effect.backlash.backlash.q3")
    assert res.theta[q3] == res.theta_map[q3] == 25.0  # the table's value, not the prior's mean (0)
    prior = prior_from_machine(em.machine)
    idx = np.flatnonzero(res.free)
    draws = res.tree["posterior"]["theta"].values.reshape(-1, idx.size)[:20]
    lp = res.tree["sample_stats"]["lp"].values.reshape(-1)[:20]
    held = log_posterior_function(em, prior, idx, base=res.theta_map)(draws)[:, 0]
    np.testing.assert_allclose(lp, held, rtol=1e-10)
    at_prior_mean = log_posterior_function(em, prior, idx)(draws)[:, 0]
    assert np.all(at_prior_mean < held - 10)  # holding q3 at 0 would be another, far worse, target


@pytest.mark.parametrize("kind,name,mag,why", [
    ("raspm", "redundancy_preload", 300.0, "depends on the geometry"),
    ("prs3", "screw_periodic_error", 3.0, "search of the residuals"),
])
def test_tables_a_machine_file_cannot_define_alone_are_refused(kind, name, mag, why):
    from bayescal.effects.simulate import simulate_with_effects
    from bayescal.machines.files import load_machine
    from tests.conftest import ROOT

    m = load_machine(ROOT / "examples" / kind / "machine.toml")
    sim = simulate_with_effects(m, 30, seed=1, effects=[(name, mag)])
    st = StoredEffect(name, tuple((p["name"], p["value"]) for p in sim.info["effects"][name]["parameters"]))
    with pytest.raises(InputError, match=why):
        effect_model(m.with_effects((st,)), sim.recording)
