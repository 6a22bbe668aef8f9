"""thermal_expansion against an independent simulation of growing parts (tests/physics/thermal_growth.py)."""

import numpy as np
import pytest

from bayescal.diagnose import diagnose
from bayescal.effects import get_effect
from bayescal.effects.thermal_expansion import link_factors
from bayescal.machines.files import machine_from_text
from bayescal.simulate import draw_poses, measure
from tests.physics.statics_3prs import random_prs3_text
from tests.physics.thermal_growth import PartGrowth


def _case(seed, n=90, alpha_frame=0.0):
    rng = np.random.default_rng(seed)
    m = machine_from_text(random_prs3_text(rng), f"random-{seed}.toml")
    theta = rng.normal(size=m.n_params) * m.tolerance
    q = draw_poses(m, n, rng, theta)
    t = np.cumsum(rng.uniform(20, 40, n))
    temp = 20 + rng.uniform(-2, 2) + 8 * (1 - np.exp(-(t - t[0]) / 1500)) + rng.normal(0, 0.02, n)
    a_s, a_l = rng.uniform(8, 25, 3), rng.uniform(10, 25, 3)  # um/m/K
    bearing = np.where(rng.random(3) < 0.5, 0.0, m.q_limits[:, 1] + 50.0)  # screws fixed at either end
    growth = PartGrowth(m, temp, alpha_screw=a_s, bearing_mm=bearing, alpha_link=a_l, alpha_frame=alpha_frame)
    return m, theta, q, temp, a_s, a_l, bearing, growth, rng


def test_link_factor_is_one_over_the_link_inclination(prs3, rng):
    q = prs3.sample_q(6, rng)
    poses = prs3.forward(q)
    K = link_factors(prs3, q, np.zeros(prs3.n_params), poses)
    g = prs3.geometry_arrays(None)
    A = poses.state.p[:, None, :] + np.einsum("nij,kj->nki", poses.state.R, g["sphere_center"])
    L = A - (g["rail_origin"][None] + q[:, :, None] * g["rail_direction"][None])
    Lh = L / np.linalg.norm(L, axis=2, keepdims=True)
    np.testing.assert_allclose(K, np.einsum("ij,ni->nij", np.eye(3), 1.0 / np.einsum("nki,ki->nk", Lh, g["rail_direction"])),
                               atol=1e-8)
    assert np.all(np.diagonal(K, axis1=1, axis2=2) < -1.0)  # hanging links: a longer link lowers the platform


def test_effect_equals_the_grown_machine_to_second_order():
    m, theta, q, temp, a_s, a_l, bearing, growth, _ = _case(2, n=20)
    n = len(q)
    q_true, th = growth.transform(q, np.broadcast_to(theta, (n, m.n_params)), {}, np.arange(n))
    truth = m.forward(q_true, th)
    eff = get_effect("thermal_expansion")
    poses = m.forward(q, theta)
    f = eff.features(m, q, theta, {"temp_C": temp}, None, poses)
    lam = 1e-3 * a_l * m.geometry_arrays(theta)["link_length"]  # um/K
    home = f.const["q0"][None]
    Kbar = link_factors(m, home, theta, m.forward(home, theta))[0]  # the reference: K at the home pose
    drift = 1e-3 * a_s * (f.const["q0"] - bearing) + Kbar @ lam  # um/K
    model = m.forward(q + eff.delta_q(f, np.concatenate([drift, a_s, lam])), theta)
    moved = np.abs(truth.position - poses.position).max()
    assert moved > 0.02
    np.testing.assert_allclose(model.position, truth.position, atol=2e-3 * moved)


@pytest.mark.parametrize("seed,alpha_frame", [(1, 0.0), (3, 23.0)])
def test_growing_screws_and_links_are_named_and_recovered(seed, alpha_frame):
    # with an aluminium base growing radially (outside the model's exact form: its projection on the
    # actuators changes a little with the pose) the verdict and the screw coefficients still hold
    m, theta, q, temp, a_s, a_l, bearing, growth, rng = _case(seed, alpha_frame=alpha_frame)
    rec = measure(m, q, theta, 6, rng, aux={"temp_C": temp}, effects=[growth])
    d = diagnose(m, rec, seed=1, n_perm=19)
    assert d.verdict == "thermal_expansion" and d.selected == ("thermal_expansion",)
    got = {p.name: p for p in next(e for e in d.effects if e.name == "thermal_expansion").parameters}
    lam = 1e-3 * a_l * m.geometry_arrays(theta)["link_length"]
    for i in range(3):
        for name, truth in ((f"alpha.q{i + 1}", a_s[i]), (f"link.q{i + 1}", lam[i])):
            assert abs(got[name].value - truth) < 4 * got[name].std, (got[name], truth)
    assert d.p_final > 1e-3


def test_map_fit_does_not_clamp_a_shrinking_screw_so_the_diagnosis_can_reject_it():
    # fit_map leaves EffectParam.lower unenforced on purpose (docs/diagnose.md, "Physical signs"): a screw
    # that shrinks when warmed (impossible for steel) must come out significantly negative, where
    # Effect.nonphysical rejects it, not at the bound 0, where the rest of the effect would pass as a detection
    from bayescal.effects import fit_map
    from bayescal.measurement import MeasurementModel

    m, theta, q, temp, a_s, a_l, bearing, _, rng = _case(4)
    a_s = np.array([-60.0, a_s[1], a_s[2]])  # um/m/K, far outside any metal
    growth = PartGrowth(m, temp, alpha_screw=a_s, bearing_mm=bearing, alpha_link=a_l)
    rec = measure(m, q, theta, 6, rng, aux={"temp_C": temp}, effects=[growth])
    model = MeasurementModel.from_recording(m, rec)
    eff = get_effect("thermal_expansion")
    zero = np.zeros(m.n_params)
    f = eff.features(m, model.pose_q, zero, {"temp_C": temp}, model.pose_order, m.forward(model.pose_q, zero))
    fit = fit_map(model, [(eff, f)])
    names = [p.name for p in fit.params]
    k = names.index("alpha.q1")
    std = fit.std_eta()
    assert next(p for p in fit.params if p.name == "alpha.q1").lower == 0.0
    assert fit.eta[k] < -5 * std[k]  # below the bound, not clamped to it
    assert abs(fit.eta[k] - a_s[0]) < 4 * std[k]  # and near the simulated value
    why = eff.nonphysical(fit.params, fit.eta, std)
    assert why is not None and "alpha.q1" in why and "alpha.q2" not in why and "alpha.q3" not in why
