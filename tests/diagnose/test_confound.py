"""The written geometry's uncertainty and its leading trade-off (bayescal/diagnose/confound.py)."""

import numpy as np
import pytest

from bayescal.diagnose.confound import geometry_confound
from bayescal.effects import fit_map
from bayescal.effects.base import Effect, EffectParam, Features
from bayescal.measurement import MeasurementModel
from bayescal.simulate import draw_errors, draw_poses, measure


class ZeroShift(Effect):
    """Test effect: a constant shift of every actuator, exactly a zero offset (um, prior 0 +- 100)."""

    name = "zero_shift"
    summary = "a constant actuator shift"
    magnitude_unit = "um"

    def features(self, machine, q, theta, aux, order, poses):
        return Features({"one": np.ones(q.shape[0])}, {})

    def params(self, machine, features):
        return tuple(EffectParam(f"shift.q{i + 1}", "um", 100.0) for i in range(machine.n_actuators))

    def delta_q(self, features, eta):
        return 1e-3 * features.per_pose["one"][:, None] * np.asarray(eta)[None, :]

    def delta_q_jacobian(self, features, eta):
        n, m = features.per_pose["one"].shape[0], len(eta)
        return np.broadcast_to(1e-3 * np.eye(m), (n, m, m)).copy()

    def simulated_values(self, machine, features, magnitude, rng):
        return np.full(machine.n_actuators, magnitude)


@pytest.fixture(scope="module")
def fits(prs3):
    rng = np.random.default_rng(7)
    theta = draw_errors(prs3, rng)
    q = draw_poses(prs3, 60, rng, theta)
    rec = measure(prs3, q, theta, 6, rng)
    model = MeasurementModel.from_recording(prs3, rec)
    eff = ZeroShift()
    f = eff.features(prs3, model.q, None, {}, None, None)
    fit0 = fit_map(model)
    fit = fit_map(model, [(eff, f)], theta0=fit0.theta)
    return prs3, model, eff, fit0, fit


def test_geometry_only_is_its_own_yardstick(fits):
    prs3, model, eff, fit0, _ = fits
    c = geometry_confound(prs3, model.q, fit0, fit0, [])
    assert c.tool_std_um == pytest.approx(c.geometric_tool_std_um)
    assert not c.confounded and c.effect == ()
    # by hand: RMS over the poses of the tool point's posterior std
    G = prs3.tool_jacobian(model.q, fit0.theta, prs3.forward(model.q, fit0.theta))[:, :3, :]
    var = np.einsum("nip,pq,niq->", G, fit0.covariance[: prs3.n_params, : prs3.n_params], G) / model.n_poses
    assert c.tool_std_um == pytest.approx(1e3 * np.sqrt(var), rel=1e-9)


def test_an_effect_that_is_a_zero_offset_is_named_against_the_rail_origins(fits):
    prs3, model, eff, fit0, fit = fits
    c = geometry_confound(prs3, model.q, fit, fit0, [eff])
    # the data fix rail_origin.z_i + shift_i only: the written geometry is as uncertain as the prior split allows
    assert c.confounded and c.tool_std_um > 10 * c.geometric_tool_std_um
    geo = {n: v for n, v, _ in c.geometry}
    top_geo, dg, ug = c.geometry[0]
    assert top_geo.startswith("chain") and ug == "mm"
    i = top_geo[len("chain")]
    # chain i's actuator offset: its rail origin up and its link shorter (on this machine both move the platform
    # like raising the slider, the link by 1 / cos of its angle to the rail), against shift i the other way
    dz, dl = geo[f"chain{i}.rail_origin.z"], geo[f"chain{i}.link_length"]
    assert dz * dl < 0
    partner = dict((n, v) for n, v, _ in c.effect)[f"shift.q{i}"]
    assert 1e3 * dz * partner < 0
    # the whole trade-off moves the tool nowhere under the effect: J_theta d_theta + J_q d_shift = 0 (what the data fix)
    full = geometry_confound(prs3, model.q, fit, fit0, [eff], top=prs3.n_params)
    d_theta = np.zeros(prs3.n_params)
    for n, v, _ in full.geometry:
        d_theta[prs3.layout.index(n)] = v
    d_shift = 1e-3 * np.array([dict((n, v) for n, v, _ in full.effect)[f"shift.q{k}"] for k in (1, 2, 3)])
    poses = prs3.forward(model.q, fit.theta)
    moved = prs3.tool_jacobian(model.q, fit.theta, poses) @ d_theta + prs3.actuator_jacobian(model.q, fit.theta, poses) @ d_shift
    assert np.abs(moved[:, :3]).max() < 0.05 * 1e-3 * c.trade_tool_um
    assert "CONFOUNDED" in c.report() and top_geo in c.report()
    d = c.to_dict()
    assert d["confounded"] and d["trade_off"]["geometry"][0]["name"] == top_geo


def test_a_long_recording_is_averaged_over_evenly_spread_poses(fits, monkeypatch):
    import bayescal.diagnose.confound as confound

    prs3, model, eff, fit0, fit = fits
    full = geometry_confound(prs3, model.q, fit, fit0, [eff])
    monkeypatch.setattr(confound, "MAX_POSES", 30)
    half = geometry_confound(prs3, model.q, fit, fit0, [eff])
    assert half.tool_std_um != full.tool_std_um  # the subsample was used
    assert half.tool_std_um == pytest.approx(full.tool_std_um, rel=0.15)
    assert half.geometric_tool_std_um == pytest.approx(full.geometric_tool_std_um, rel=0.15)
