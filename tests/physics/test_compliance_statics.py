"""joint_compliance against an independent full-statics simulation of the 3-PRS (tests/physics/statics_3prs.py)."""

import numpy as np
import pytest

from bayescal.diagnose import diagnose
from bayescal.effects import get_effect
from bayescal.effects.joint_compliance import GRAVITY, gravity_direction
from bayescal.machines.files import machine_from_text
from bayescal.simulate import draw_poses, measure
from tests.physics.statics_3prs import CompliantDrives, GravityLoad, deflected_q, link_forces, random_prs3_text, tilted_down

UP = np.array([0.0, 0.0, -1.0])


def _truth(c, mp, com, down, d0=UP, payload=True) -> dict:
    """The effect's parameters of the simulated physics, by name."""
    e = np.eye(3)[[i for i in range(3) if i != int(np.argmax(np.abs(d0)))]]
    e = e - np.outer(e @ d0, d0)
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    tilt = e @ (down / (down @ d0))
    names = ["com.x", "com.y", "com.z", "gravity.tilt_1", "gravity.tilt_2"]
    values = [*com, *tilt]
    if payload:
        names += [f"compliance.q{i}" for i in (1, 2, 3)] + ["platform_mass"]
        values += [*c, mp]
    else:
        names += [f"weight_deflection.q{i}" for i in (1, 2, 3)]
        values += list(c * mp * GRAVITY)
    return dict(zip(names, values))


def _case(seed: int, *, n=90, max_tilt_deg=15.0, down=None, payload=True):
    rng = np.random.default_rng(seed)
    m = machine_from_text(random_prs3_text(rng), f"random-{seed}.toml")
    theta = rng.normal(size=m.n_params) * m.tolerance
    q = draw_poses(m, n, rng, theta)
    down = tilted_down(rng, max_tilt_deg) if down is None else np.asarray(down, float)
    com = np.array([*rng.uniform(-80, 80, 2), rng.uniform(-150, 50)])  # platform frame, mm
    mp = rng.uniform(20, 100)  # kg
    c = rng.uniform(0.2, 1.0, 3)  # um/N
    mass = rng.choice(np.arange(0.0, 26.0, 5.0), n) if payload else np.zeros(n)
    load = GravityLoad(mp, com, down)
    rec = measure(m, q, theta, 6, rng, aux={"payload_kg": mass} if payload else {}, effects=[CompliantDrives(m, c, load, mass)])
    return m, rec, c, mp, com, down


def test_statics_of_a_symmetric_pose_by_hand(prs3):
    # symmetric machine at a symmetric pose, weight on the axis: each drive carries m g / 3 along the rail
    q = np.full((1, 3), 500.0)
    poses = prs3.forward(q)
    geom = prs3.geometry_arrays(None)
    F = link_forces(geom, poses.state.p[0], poses.state.R[0], q[0], GravityLoad(30.0, np.zeros(3), UP), 0.0)
    np.testing.assert_allclose(F[:, 2], 30.0 * GRAVITY / 3, rtol=1e-12)  # the links hold the platform up
    # the revolute joints leave each link force in the plane of the link and the revolute axis
    A = poses.state.p[0] + geom["sphere_center"] @ poses.state.R[0].T
    L = A - (geom["rail_origin"] + q[0][:, None] * geom["rail_direction"])
    np.testing.assert_allclose(np.einsum("ik,ik->i", F, np.cross(L, geom["revolute_axis"])), 0.0, atol=1e-9)
    qd = deflected_q(prs3, None, q, np.full(3, 0.5), GravityLoad(30.0, np.zeros(3), UP), np.zeros(1))
    np.testing.assert_allclose(qd - q, -0.5e-3 * 30.0 * GRAVITY / 3, rtol=1e-6)  # the sliders sink


def test_statics_obey_virtual_work(prs3, rng):
    # the drives' loads do the work gravity does when the sliders move: sum_i load_i dq_i = W . dx_c + W_L . dx_t
    geom = prs3.geometry_arrays(None)
    load = GravityLoad(40.0, np.array([30.0, -20.0, -60.0]), tilted_down(rng, 20.0))
    for q in prs3.sample_q(4, rng):
        poses = prs3.forward(q[None])
        F = link_forces(geom, poses.state.p[0], poses.state.R[0], q, load, 12.0)
        axial = -np.einsum("ik,ik->i", F, geom["rail_direction"])
        dq = 1e-4 * rng.normal(size=3)

        def potential(qq):
            ps = prs3.forward(qq[None], guess=poses)
            x_c = ps.state.p[0] + ps.state.R[0] @ load.com_platform_mm
            return GRAVITY * load.down @ (load.platform_mass_kg * x_c + 12.0 * ps.position[0])

        work = potential(q + dq) - potential(q - dq)
        assert axial @ (2 * dq) == pytest.approx(work, rel=1e-6)


@pytest.mark.parametrize("seed", [1, 3])
def test_effect_equals_full_statics_to_second_order(seed):
    # the effect at the true parameters against the iterated statics: the model linearises the load at the
    # undeflected pose, so they differ by (deflection / mechanism size) of the deflection
    m, rec, c, mp, com, down = _case(seed, n=15)
    rng = np.random.default_rng(seed + 100)
    theta = rng.normal(size=m.n_params) * m.tolerance
    q = m.sample_q(15, rng)
    mass = rng.uniform(0, 25, 15)
    eff = get_effect("joint_compliance")
    f = eff.features(m, q, theta, {"payload_kg": mass}, None, m.forward(q, theta))
    err = []
    for scale in (1.0, 0.1):
        qd = deflected_q(m, theta, q, scale * c, GravityLoad(mp, com, down), mass)
        truth = _truth(scale * c, mp, com, down)
        eta = np.array([truth[p.name] for p in eff.params(m, f)])
        dq = eff.delta_q(f, eta)
        if scale == 1.0:
            assert np.abs(qd - q).max() > 0.02  # tens of um
        err.append(np.abs(dq - (qd - q)).max() / np.abs(qd - q).max())
    assert err[0] < 3e-3
    assert err[1] < err[0] / 5  # the relative misfit shrinks with the deflection: it is the linearisation only


def _check_recovered(d, truth, names, z=4.0):
    assert d.verdict == "joint_compliance" and d.selected[0] == "joint_compliance"
    trial = next(e for e in d.effects if e.name == "joint_compliance")
    got = {p.name: p for p in trial.parameters}
    assert set(got) == set(truth)
    for name in names:
        p = got[name]
        assert abs(p.value - truth[name]) < z * p.std, (p, truth[name])
    # the residual after the fit is at the noise level
    assert d.p_final > 1e-3
    assert d.rms_cv_final < 1.2 * d.rms_noise


@pytest.mark.parametrize("seed", [2, 5])
def test_tilted_machine_with_off_centre_mass_and_payload_is_named_and_recovered(seed):
    m, rec, c, mp, com, down = _case(seed)
    d = diagnose(m, rec, seed=1, n_perm=19)
    truth = _truth(c, mp, com, down)
    _check_recovered(d, truth, list(truth))


def test_without_payload_the_weight_deflections_are_recovered():
    m, rec, c, mp, com, down = _case(3, payload=False)
    d = diagnose(m, rec, seed=1, n_perm=19)
    truth = _truth(c, mp, com, down, payload=False)
    _check_recovered(d, truth, list(truth))


def test_machine_mounted_on_its_side_needs_its_gravity_direction():
    # rails horizontal: gravity along +x of the base frame, far outside the fitted tilt of an upright machine
    side = np.array([1.0, 0.0, 0.0])
    m, rec, c, mp, com, down = _case(1, down=side)
    d = diagnose(m, rec, seed=1, n_perm=19, effect_settings={"joint_compliance": {"gravity": side}})
    truth = _truth(c, mp, com, side, d0=side)
    _check_recovered(d, truth, list(truth))
    assert gravity_direction(side, np.zeros(2))[0] @ side == pytest.approx(1.0)


def test_payload_offset_from_the_tool_point_matches_the_statics():
    # a payload hanging 150 mm beside and 80 mm above the tool point, stated as the effect's input
    m, _, c, mp, com, down = _case(6, n=10)
    rng = np.random.default_rng(60)
    q = m.sample_q(12, rng)
    mass = rng.uniform(5, 25, 12)
    offset = np.array([150.0, 0.0, 80.0])
    qd = deflected_q(m, None, q, c, GravityLoad(mp, com, down, payload_offset_mm=offset), mass)
    truth = _truth(c, mp, com, down)
    err = []
    for eff in (get_effect("joint_compliance", payload_offset=offset), get_effect("joint_compliance")):
        f = eff.features(m, q, None, {"payload_kg": mass}, None, m.forward(q))
        dq = eff.delta_q(f, np.array([truth[p.name] for p in eff.params(m, f)]))
        err.append(np.abs(dq - (qd - q)).max() / np.abs(qd - q).max())
    # stated: the second-order remainder only (deflections of up to 0.5 mm here); at the tool point: a first-order misfit
    assert err[0] < 6e-3 and err[1] > 10 * err[0], err
