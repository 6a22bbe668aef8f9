"""joint_compliance with link weights on a 6R arm, against an independent statics simulation (tests/physics/serial_statics.py).

The independent code composes docs/formats.md section 5's transforms itself and
takes the gravity torques from the potential energy by finite differences;
it never calls the effect's ``delta_q``, the machine's weight bodies or its
Jacobians.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.effects import fit_map, get_effect
from bayescal.io.recording import write_recording
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.measurement import MeasurementModel
from bayescal.simulate import draw_errors, draw_poses, measure
from tests.physics.serial_statics import Chain, CompliantJoints, Weights, gravity_torques

ROOT = Path(__file__).resolve().parents[2]
ARM6 = ROOT / "examples" / "arm6" / "machine.toml"


def _tilted(rng, max_deg):
    axis = rng.normal(size=3)
    axis[2] = 0.0
    axis /= np.linalg.norm(axis)
    a = np.radians(rng.uniform(0.5, 1.0) * max_deg)
    return np.cos(a) * np.array([0.0, 0.0, -1.0]) + np.sin(a) * axis


def _weights(rng, down, payload_offset=(0.0, 0.0, 0.0)):
    mass = rng.uniform(0.5, 9.0, 6)  # kg, an arm's links from the shoulder housing to the flange
    com = rng.uniform(-150.0, 150.0, (6, 3))  # mm, each link's frame
    return Weights(mass, com, np.asarray(down, float), np.asarray(payload_offset, float))


@pytest.mark.parametrize("seed", [0, 1])
def test_loads_equal_the_potential_energy_derivative_with_links_tilt_and_payload(seed):
    m = load_machine(ARM6)
    rng = np.random.default_rng(seed)
    theta = draw_errors(m, rng)  # a geometry off nominal: the loads follow the geometry the effect is evaluated at
    chain = Chain.from_text(m.to_toml(theta))
    w = _weights(rng, _tilted(rng, 20.0), payload_offset=rng.uniform(-80, 80, 3))
    q = m.sample_q(15, rng)
    payload = rng.uniform(0.0, 12.0, 15)
    eff = get_effect("joint_compliance", link_mass_kg=w.link_mass_kg, link_com_mm=w.link_com_mm.ravel(),
                     gravity=w.down, payload_offset=w.payload_offset_mm)
    f = eff.features(m, q, theta, {"payload_kg": payload}, None, m.forward(q, theta))
    assert [p.name for p in eff.params(m, f)] == [f"compliance.q{i}" for i in range(1, 7)] + ["gravity.tilt_1", "gravity.tilt_2"]
    c = rng.uniform(1.0, 50.0, 6)  # urad/(N m)
    got = eff.delta_q(f, np.concatenate([c, [0.0, 0.0]]))  # rad
    tau = gravity_torques(chain, q, w, payload)  # N mm
    expected = 1e-9 * c * tau
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())
    # the shoulder and elbow carry tens of N m: the links dominate (a payload-free check of the size)
    assert np.abs(tau[:, 1]).max() > 1e4
    # without the links (platform only: the last link) the model would miss most of the shoulder torque
    last = Weights(np.r_[np.zeros(5), w.link_mass_kg[5]], w.link_com_mm, w.down, w.payload_offset_mm)
    assert np.abs(gravity_torques(chain, q, last, payload) - tau)[:, 1].max() > 0.5 * np.abs(tau[:, 1]).max()


def test_gravity_tilt_parameters_turn_the_load_direction():
    # the fitted tilts tilt the stated direction exactly as gravity_direction says: the loads at (d0, t) equal the
    # independent ones at the tilted direction
    from bayescal.effects.joint_compliance import gravity_direction

    m = load_machine(ARM6)
    rng = np.random.default_rng(7)
    chain = Chain.from_text(m.to_toml())
    tilt = np.array([0.08, -0.05])
    d = gravity_direction(np.array([0.0, 0.0, -1.0]), tilt)[0]
    w = _weights(rng, d)
    q = m.sample_q(6, rng)
    eff = get_effect("joint_compliance", link_mass_kg=w.link_mass_kg, link_com_mm=w.link_com_mm)
    f = eff.features(m, q, np.zeros(m.n_params), {}, None, m.forward(q))
    c = np.full(6, 10.0)
    np.testing.assert_allclose(eff.delta_q(f, np.r_[c, tilt]), 1e-9 * c * gravity_torques(chain, q, w, 0.0), rtol=1e-6,
                               atol=1e-12)


def _truth_error_um(m, theta_true, predict, seed):
    """Tool point RMS (um) of ``predict(q)`` against the true geometry on 200 fresh poses."""
    q = draw_poses(m, 200, np.random.default_rng(1000 + seed), theta_true)
    return 1e3 * float(np.sqrt(np.mean(np.sum((predict(q) - m.forward(q, theta_true).position) ** 2, axis=1))))


def test_diagnose_with_stated_link_masses_recovers_the_compliances_and_the_geometry(tmp_path):
    m = load_machine(ARM6)
    seed = 3
    rng = np.random.default_rng(seed)
    theta = draw_errors(m, rng)
    n = 150
    q = draw_poses(m, n, rng, theta)
    down = _tilted(rng, 3.0)
    w = _weights(rng, down)
    c = rng.uniform(2.0, 12.0, 6)  # urad/(N m): 0.1-0.5 mrad at the shoulder, a few tenths of a mm at the tool
    truth = CompliantJoints(Chain.from_text(m.to_toml(theta)), c, w)
    rec = measure(m, q, theta, 6, rng, effects=[truth])  # no payload channel: the links' known loads fix c
    clean = measure(m, q, theta, 6, rng)
    path = tmp_path / "arm.csv"
    write_recording(path, rec)
    inputs = ["--effect-input", "joint_compliance.link_mass_kg=" + ",".join(repr(float(x)) for x in w.link_mass_kg),
              "--effect-input", "joint_compliance.link_com_mm=" + ",".join(repr(float(x)) for x in w.link_com_mm.ravel())]
    out = tmp_path / "calibrated.toml"
    assert main(["diagnose", str(path), "--machine", str(ARM6), "--quiet", "--json", str(tmp_path / "d.json"),
                 "--write-machine", str(out)] + inputs) == 0
    d = json.loads((tmp_path / "d.json").read_text())
    assert d["verdict"] == "joint_compliance"
    trial = next(e for e in d["effects"] if e["name"] == "joint_compliance")
    assert "known" in trial["note"]
    got = {p["name"]: p for p in trial["parameters"]}
    assert set(got) == {f"compliance.q{i}" for i in range(1, 7)} | {"gravity.tilt_1", "gravity.tilt_2"}
    for i in range(6):
        p = got[f"compliance.q{i + 1}"]
        assert p["unit"] == "urad/(N m)"
        assert abs(p["value"] - c[i]) < 4 * p["std"], (i, p, c[i])
    # the shoulder and elbow compliances are well determined by the links' loads (not at their prior of 100)
    assert got["compliance.q2"]["std"] < 0.2 * c[1] and got["compliance.q3"]["std"] < 0.2 * c[2]
    # the written machine (geometry and effect with its stated link masses) predicts the true geometry about as
    # well as a calibration of the same poses without compliance
    written = load_machine(out)
    stored = dict(written.effects[0].settings)
    np.testing.assert_allclose(stored["link_mass_kg"], w.link_mass_kg)
    geometry = written.with_effects(())
    err = _truth_error_um(m, theta, lambda qq: geometry.forward(qq).position, seed)
    th_clean = fit_map(MeasurementModel.from_recording(m, clean)).theta
    th_unaware = fit_map(MeasurementModel.from_recording(m, rec)).theta
    err_clean = _truth_error_um(m, theta, lambda qq: m.forward(qq, th_clean).position, seed)
    err_unaware = _truth_error_um(m, theta, lambda qq: m.forward(qq, th_unaware).position, seed)
    print(f"written {err:.1f} um, clean {err_clean:.1f} um, compliance-unaware {err_unaware:.1f} um")
    assert err < 1.5 * err_clean + 5.0
    assert err_unaware > 3 * err


def test_without_link_masses_a_parallel_kind_is_unchanged(prs3):
    # platform-only model: the machine's default weight body reproduces the features and loads used before
    rng = np.random.default_rng(11)
    q = prs3.sample_q(10, rng)
    theta = draw_errors(prs3, rng)
    poses = prs3.forward(q, theta)
    eff = get_effect("joint_compliance")
    for aux in ({}, {"payload_kg": rng.uniform(0, 20, 10)}):
        f = eff.features(prs3, q, theta, aux, None, poses)
        assert f.const["known"] is False and eff.model_note(f) == ""
        names = [p.name for p in eff.params(prs3, f)]
        eta = np.array([p.start_value for p in eff.params(prs3, f)]) + 0.1 * rng.normal(size=len(names))
        eta[-2:] = [0.03, -0.02]
        dq = eff.delta_q(f, eta)
        # by hand, from the platform frame and the actuator Jacobian (the formula of the class docstring)
        J = prs3.actuator_jacobian(q, theta, poses)
        k = 3
        if "payload_kg" in aux:
            cc, mp = eta[:3], eta[3]
            W, k = cc * mp * 9.80665, 4
        else:
            cc, W = np.zeros(3), eta[:3]
        from bayescal.effects.joint_compliance import gravity_direction

        d = gravity_direction(np.array([0.0, 0.0, -1.0]), eta[k + 3 : k + 5])[0]
        xc = poses.state.p + np.einsum("nij,j->ni", poses.rotation, eta[k : k + 3])
        Jc = J[:, :3] + np.cross(J[:, 3:], (xc - poses.position)[:, :, None], axis=1)
        phi = np.einsum("k,nkm->nm", d, Jc)
        psi = np.einsum("k,nkm->nm", d, J[:, :3])
        load = 9.80665 * aux.get("payload_kg", np.zeros(10))
        np.testing.assert_allclose(dq, 1e-3 * (W * phi + cc * load[:, None] * psi), rtol=1e-12, atol=1e-15)
    # the default weight body is that platform: origin, rotation and velocity of the platform origin
    wb = prs3.weight_bodies(q, theta, poses)
    assert wb.names == ("platform",) and prs3.body_inertials is None
    np.testing.assert_allclose(wb.origin[:, 0], poses.state.p)
    # a stated platform mass as link_mass_kg (one body): known loads, the compliances are the parameters
    known = get_effect("joint_compliance", link_mass_kg=[40.0], link_com_mm=[10.0, 0.0, -30.0])
    f = known.features(prs3, q, theta, {}, None, poses)
    c = np.array([0.3, 0.5, 0.4])
    legacy = eff.features(prs3, q, theta, {"payload_kg": np.zeros(10)}, None, poses)
    np.testing.assert_allclose(known.delta_q(f, np.r_[c, 0.0, 0.0]),
                               eff.delta_q(legacy, np.r_[c, 40.0, 10.0, 0.0, -30.0, 0.0, 0.0]), rtol=1e-12)


def test_link_mass_inputs_are_checked():
    from bayescal.errors import InputError

    m = load_machine(ARM6)
    q = m.sample_q(3, np.random.default_rng(0))
    with pytest.raises(InputError, match="6 weight bodies of this serial machine"):
        get_effect("joint_compliance", link_mass_kg=[1.0, 2.0]).features(m, q, np.zeros(m.n_params), {}, None, None)
    with pytest.raises(InputError, match="without link_mass_kg"):
        get_effect("joint_compliance", link_com_mm=[0.0, 0.0, 1.0])
    with pytest.raises(InputError, match="both given"):
        get_effect("joint_compliance", link_mass_kg=[1.0] * 6, platform_mass_kg=3.0)
    with pytest.raises(InputError, match="expected 6 centres of mass"):
        get_effect("joint_compliance", link_mass_kg=[1.0] * 6, link_com_mm=[0.0, 1.0, 2.0])
    with pytest.raises(InputError, match=">= 0"):
        get_effect("joint_compliance", link_mass_kg=[1.0, -2.0])
    # unstated on a chain of links: the trial note says the link weights are left out
    eff = get_effect("joint_compliance")
    f = eff.features(m, q, np.zeros(m.n_params), {}, None, None)
    assert "link weights left out" in eff.model_note(f)
    assert "link_mass_kg" in eff.confound_note()


def test_machine_file_table_with_link_masses_round_trips(tmp_path):
    text = ARM6.read_text() + (
        '\n[effect.joint_compliance]\nlink_mass_kg = [3.7, 8.4, 2.3, 1.2, 1.2, 0.2]\n'
        'link_com_mm = [[0, -20, 10], [0, 0, 210], [0, 0, 180], [0, 10, 0], [0, 0, 10], [0, 0, 5]]\n'
        + "".join(f'"compliance.q{i}" = {3.0 + i}\n' for i in range(1, 7))
        + '"gravity.tilt_1" = 0.0\n"gravity.tilt_2" = 0.0\n')
    m = machine_from_text(text, "arm.toml")
    st = m.effects[0]
    assert dict(st.settings)["link_com_mm"][1] == [0.0, 0.0, 210.0]
    from bayescal.effects.stored import effect_delta_q, machine_file_text

    again = machine_from_text(machine_file_text(m), "again.toml")
    q = m.sample_q(4, np.random.default_rng(2))
    np.testing.assert_allclose(effect_delta_q(again, again.effects, q), effect_delta_q(m, m.effects, q), rtol=1e-14)
    assert np.abs(effect_delta_q(m, m.effects, q)).max() > 1e-5  # tens of urad
    # the legacy parameter set is refused once the loads are known, naming what is expected
    from bayescal.errors import MachineFileError

    bad = text.replace('"gravity.tilt_2" = 0.0\n', '"gravity.tilt_2" = 0.0\n"platform_mass" = 3.0\n')
    with pytest.raises(MachineFileError, match="platform_mass"):
        machine_from_text(bad, "bad.toml")
    with pytest.raises(MachineFileError, match="weight bodies"):
        machine_from_text(text.replace("link_mass_kg = [3.7, 8.4, ", "link_mass_kg = [").replace("[[0, -20, 10], [0, 0, 210], ", "["),
                          "short.toml")


# the effect's numbers before link weights existed (commit a06264c), on the 3-PRS example: platform only, no link masses
_GOLDEN = [
    ([147.09975, 147.09975, 147.09975, 20.0, -10.0, -40.0, 0.05, -0.03],
     [[-0.06358996297587764, -0.035582486593080664, -0.047681285413188335], [-0.04364317849535599, -0.03764798553807184, -0.06555965913965983], [-0.05289491644240223, -0.02751211564303057, -0.06644470953374328]],
     [[-0.00029669104465069446, 0.0, 0.0, -0.0005690947165411794, -4.303215468216463e-05, -0.0002212483346039061, 0.04167647561047581, -0.006795764379838698], [0.0, -0.0002559350749275362, 0.0, 0.00024262621655024433, -0.0006316758315587878, 8.375833596252672e-06, -0.023735023231224037, 0.012856276679211263], [0.0, 0.0, -0.00044568164894678494, 0.00032637328154155057, 0.0006746984024824773, 0.0002128351674961137, -0.010600273487823251, -0.010458329471189019]]),
    ([0.3, 0.5, 0.7, 45.0, 20.0, -10.0, -40.0, 0.05, -0.03],
     [[-0.05723096667828987, -0.053373729889621004, -0.10013069936769549], [-0.04400546048764274, -0.06735080186268405, -0.1628132767678473], [-0.0649521654881476, -0.060062703340045605, -0.20980610422283033]],
     [[-0.1466848682921425, 0.0, 0.0, -0.0008728635699071197, -0.0005121852448870613, -3.8728939213948164e-05, -0.0001991235011435155, 0.04603261585001438, -0.00695396608098433], [0.0, -0.1347016037253681, 0.0, -0.0012549328512690612, 0.0003639393248253665, -0.0009475137473381817, 1.2563750394379008e-05, -0.04303657146417014, 0.027136132898445773], [0.0, 0.0, -0.23259039538263904, -0.0030594507598507917, 0.000685383891237256, 0.001416866645213202, 0.00044695385174183867, -0.02917138159985668, -0.032538075888785316]]),
]


def test_without_link_masses_the_3prs_numbers_are_those_of_before():
    m = load_machine(ROOT / "examples" / "prs3" / "machine.toml")
    rng = np.random.default_rng(21)
    q = m.sample_q(3, rng)
    theta = rng.normal(size=m.n_params) * m.tolerance
    poses = m.forward(q, theta)
    for aux, (eta, dq, jac1) in zip(({}, {"payload_kg": np.array([0.0, 7.5, 20.0])}), _GOLDEN):
        eff = get_effect("joint_compliance", payload_offset=[10.0, -5.0, 30.0])
        f = eff.features(m, q, theta, aux, None, poses)
        np.testing.assert_allclose(eff.delta_q(f, np.array(eta)), dq, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(eff.delta_q_jacobian(f, np.array(eta))[1], jac1, rtol=1e-12, atol=1e-15)
