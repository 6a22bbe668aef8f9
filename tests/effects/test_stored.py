"""[effect.<name>] tables in machine files: strict reading, writing, round trips and application (docs/formats.md section 7)."""

import numpy as np
import pytest

from bayescal.bayes.grid import compensation_grid
from bayescal.effects import EFFECTS, get_effect
from bayescal.effects.simulate import simulate_with_effects
from bayescal.effects.stored import (
    StoredEffect, StoredEffectsTransform, effect_delta_q, effect_tables_toml, machine_file_text, parse_aux_values,
    static_effect_delta_q,
)
from bayescal.errors import InputError, MachineFileError
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.measurement import MeasurementModel
from bayescal.simulate import simulate_recording
from tests.conftest import PRS3_FILE

GOOD = PRS3_FILE.read_text()

# joint_compliance as fitted with a payload_kg channel: compliances, one platform mass, centre of mass, mounting tilt
REST = '"platform_mass" = 30.0\n"com.x" = 0.0\n"com.y" = 0.0\n"com.z" = 0.0\n"gravity.tilt_1" = 0.0\n"gravity.tilt_2" = 0.0\n'
COMPLIANCE = '[effect.joint_compliance]\n"compliance.q1" = 0.4\n"compliance.q2" = 0.6\n"compliance.q3" = 0.5\n' + REST
THERMAL_T = "[effect.thermal_expansion]\n" + "".join(f'"drift.q{i}" = {i}.5\n"alpha.q{i}" = 1{i}.0\n"link.q{i}" = 0.{i}\n' for i in (1, 2, 3))
#: joint_compliance without a payload channel: the weight deflections c_i m_p g (um)
W_REST = (("com.x", 0.0), ("com.y", 0.0), ("com.z", 0.0), ("gravity.tilt_1", 0.0), ("gravity.tilt_2", 0.0))


def _weight(c):
    return tuple((f"weight_deflection.q{i + 1}", v * 30.0 * 9.80665) for i, v in enumerate(c)) + W_REST
BACKLASH = '[effect.backlash]\n"backlash.q1" = 20.0\n"backlash.q2" = 30.0\n"backlash.q3" = 25.0\n'


def _machine(tmp_path, tables: str):
    p = tmp_path / "m.toml"
    p.write_text(GOOD + "\n" + tables)
    return load_machine(p), p


def test_tables_round_trip_through_the_machine_file(tmp_path):
    m, _ = _machine(tmp_path, COMPLIANCE + THERMAL_T + BACKLASH)
    assert [e.name for e in m.effects] == ["joint_compliance", "thermal_expansion", "backlash"]
    assert dict(m.effects[1].values)["alpha.q2"] == 12.0
    assert m.effects[0].units == ("um/N",) * 3 + ("kg", "mm", "mm", "mm", "rad", "rad")  # units come from the effect, as comments
    text = machine_file_text(m)
    assert '"compliance.q1" = 0.4' in text and "# um/N" in text
    again = machine_from_text(text)
    assert [(e.name, e.values) for e in again.effects] == [(e.name, e.values) for e in m.effects]
    assert machine_file_text(again) == text  # a fixed point
    # the geometry reads as without the tables; with_effects(()) drops them
    plain = load_machine(PRS3_FILE)
    assert plain.effects == () and machine_file_text(plain) == plain.to_toml()
    assert m.with_effects(()).to_toml() == plain.to_toml()


@pytest.mark.parametrize(
    "tables,key,match",
    [
        ('[effect.gravity_sag]\n"sag.q1" = 1.0\n', "effect.gravity_sag", "unknown effect 'gravity_sag'; expected one of"),
        (COMPLIANCE.replace('"compliance.q3"', '"compliance.q4"'), 'effect.joint_compliance."compliance.q4"', "not a parameter"),
        (COMPLIANCE.replace('"compliance.q3" = 0.5\n', ""), "effect.joint_compliance", r"missing parameter\(s\) compliance.q3"),
        (COMPLIANCE.replace("0.6", '"soft"'), 'effect.joint_compliance."compliance.q2"', "finite number"),
        (COMPLIANCE.replace("0.6", "true"), 'effect.joint_compliance."compliance.q2"', "finite number"),
        (COMPLIANCE.replace("0.6", "inf"), 'effect.joint_compliance."compliance.q2"', "finite number"),
        ("effect = 3\n", "effect", "expected a table"),
        ("[effect]\nbacklash = 3.0\n", "effect.backlash", "expected a table"),
        ('[effect.redundancy_preload]\n"preload_deflection.q1" = 1.0\n', "effect.redundancy_preload", "cannot act on this 3-PRS"),
        (THERMAL_T.replace('"drift.q1"', '"shift.q1"'), "effect.thermal_expansion", "different parametrisations"),
    ],
)
def test_bad_tables_name_file_and_key(tmp_path, tables, key, match):
    p = tmp_path / "m.toml"
    if tables.startswith("effect = "):
        p.write_text(tables + GOOD)  # a top-level key must come before the tables
    else:
        p.write_text(GOOD + "\n" + tables)
    with pytest.raises(MachineFileError, match=match) as err:
        load_machine(p)
    assert err.value.key == key
    assert str(p) in str(err.value)


def test_every_registered_effect_writes_and_reads_its_own_parameters(prs3):
    """Generic: names and units from Effect.params, for each registered effect that can act on the 3-PRS."""
    q = np.repeat(prs3.home_q()[None, :], 2, axis=0)
    for name in EFFECTS:
        eff = get_effect(name)
        aux = {"temp_C": np.array([21.0, 22.0])}
        if eff.not_applicable(prs3, aux):
            continue
        f = eff.features(prs3, q, np.zeros(prs3.n_params), aux, None, prs3.forward(q) if eff.needs_poses else None)
        params = eff.params(prs3, f)
        st = StoredEffect(name, tuple((p.name, 0.25 + i) for i, p in enumerate(params)), tuple(p.unit for p in params))
        m = machine_from_text(machine_file_text(prs3, None, (st,)))
        assert m.effects[0].values == st.values and m.effects[0].units == st.units


def test_application_maps_names_not_file_order(prs3, sim6):
    """A table in any key order gives the dq of the effect bound to its values in parameter order."""
    eff = get_effect("joint_compliance")
    c = dict(_weight([0.3, 0.9, 0.6]))
    st = StoredEffect("joint_compliance", tuple(reversed(list(c.items()))))
    rec = sim6.recording
    dq = effect_delta_q(prs3, (st,), rec.q, rec.aux)
    bound = eff.bind(prs3, list(c.values()))
    q_ref, _ = bound.transform(rec.q, np.zeros(prs3.n_params), dict(rec.aux), np.arange(rec.n_poses))
    np.testing.assert_allclose(dq, q_ref - rec.q, rtol=0, atol=1e-11)  # forward-kinematics round-off
    assert np.abs(dq).max() > 1e-3  # a 30 kg platform on 0.3-0.9 um/N drives: microns
    # the measurement model of the machine carrying it sees q + dq
    model = MeasurementModel.from_recording(prs3.with_effects((st,)), rec)
    np.testing.assert_allclose(model.q, rec.q + dq, atol=1e-12)
    plain = MeasurementModel.from_recording(prs3, rec)
    np.testing.assert_array_equal(plain.q, rec.q)


def test_stored_true_effects_explain_a_recording_to_the_noise(prs3):
    """The simulator's true effect values, written as tables on the true geometry, leave only noise."""
    for name, mag, aux in [("joint_compliance", 0.5, ["payload_kg"]), ("thermal_expansion", 12.0, ["temp_C"]), ("backlash", 30.0, [])]:
        sim = simulate_with_effects(prs3, 80, seed=4, effects=[(name, mag)], record=aux)
        truth = sim.info["effects"][name]["parameters"]
        st = StoredEffect(name, tuple((p["name"], p["value"]) for p in truth), tuple(p["unit"] for p in truth))
        true_m = machine_from_text(machine_file_text(prs3, sim.theta_true, (st,)))
        model = MeasurementModel.from_recording(true_m, sim.recording)
        chi2 = float(np.sum((model.residual(model.predict(None)) / model.sigma) ** 2))
        n = model.residual(model.predict(None)).size
        assert chi2 / n < 1.3, name  # noise alone: 1 +- 0.06
        without = MeasurementModel.from_recording(true_m.with_effects(()), sim.recording)
        chi2_without = float(np.sum((without.residual(without.predict(None)) / without.sigma) ** 2))
        assert chi2_without / n > 2.0, name  # and the effect is really there


def test_mode_and_channels_are_checked_when_applied(tmp_path, prs3):
    m, p = _machine(tmp_path, THERMAL_T)
    sim = simulate_with_effects(prs3, 20, seed=1, record=["time_s"])
    with pytest.raises(MachineFileError, match="time_s") as err:  # per-kelvin table, recording with time only
        MeasurementModel.from_recording(m, sim.recording)
    assert str(p) in str(err.value) and err.value.key.startswith("effect.thermal_expansion")
    bare = simulate_recording(prs3, 20, seed=1)
    with pytest.raises(InputError, match=r"\[effect.thermal_expansion\] cannot be applied.*temp_C"):
        MeasurementModel.from_recording(m, bare.recording)


def test_simulating_a_machine_with_tables_applies_them(prs3):
    st = StoredEffect("joint_compliance", _weight([0.5, 0.5, 0.5]))
    m = prs3.with_effects((st,))
    with_eff = simulate_recording(m, 30, seed=2, effects=[StoredEffectsTransform(m, m.effects)])
    plain = simulate_recording(prs3, 30, seed=2)
    np.testing.assert_array_equal(with_eff.recording.q, plain.recording.q)
    shift = np.linalg.norm(with_eff.recording.position - plain.recording.position, axis=1)
    assert shift.min() > 1e-3  # microns of sag at every pose, same noise draws otherwise


def test_grid_applies_tables_under_the_stated_channels(prs3):
    comp = StoredEffect("joint_compliance", tuple((f"compliance.q{i}", 0.5) for i in (1, 2, 3)) + (("platform_mass", 30.0),) + W_REST)
    back = StoredEffect("backlash", (("backlash.q1", 30.0), ("backlash.q2", 30.0), ("backlash.q3", 30.0)))
    theta = np.zeros(prs3.n_params)
    cov = np.eye(prs3.n_params) * 1e-8
    g0 = compensation_grid(prs3, theta, covariance=cov, n=3)
    assert np.abs(g0.correction).max() < 1e-9
    # nodes have no approach direction: backlash leaves the grid unchanged
    gb = compensation_grid(prs3.with_effects((back,)), theta, covariance=cov, n=3)
    np.testing.assert_allclose(gb.correction, g0.correction, atol=1e-12)
    # compliance: the sag of the payload (at the tool point) grows linearly with its mass
    mc = prs3.with_effects((comp,))
    c0 = compensation_grid(mc, theta, covariance=cov, n=3, aux={"payload_kg": 0.0}).correction
    c15 = compensation_grid(mc, theta, covariance=cov, n=3, aux={"payload_kg": 15.0}).correction
    c30 = compensation_grid(mc, theta, covariance=cov, n=3, aux={"payload_kg": 30.0}).correction
    assert np.abs(c0).max() > 1e-3 and np.abs(c30 - c0).max() > 1e-3
    np.testing.assert_allclose(c30 - c0, 2 * (c15 - c0), rtol=2e-3, atol=1e-7)
    # the static dq is the per-node dq of a recording whose poses do not move (no approach)
    q = g0.q[:5]
    np.testing.assert_allclose(static_effect_delta_q(mc, mc.effects, q, {"payload_kg": 5.0}),
                               effect_delta_q(mc, mc.effects, q, {"payload_kg": np.full(5, 5.0)}), atol=1e-15)
    assert np.all(static_effect_delta_q(prs3, (back,), q) == 0)
    with pytest.raises(InputError, match="temp_C"):
        compensation_grid(machine_from_text(machine_file_text(prs3, None, ())).with_effects(
            (StoredEffect("thermal_expansion", tuple((f"{k}.q{i}", 1.0) for k in ("drift", "alpha", "link") for i in (1, 2, 3))),)),
            theta, covariance=cov, n=2)


def test_aux_values_parse_strictly():
    assert parse_aux_values(["payload_kg=5", "temp_C = 25.5"]) == {"payload_kg": 5.0, "temp_C": 25.5}
    for bad in (["payload_kg"], ["payload_kg=heavy"], ["=5"], ["temp_C=nan"], ["a=1", "a=2"]):
        with pytest.raises(InputError, match="--aux"):
            parse_aux_values(bad)


def test_tables_text_is_valid_toml_for_awkward_names():
    st = StoredEffect("backlash", (("backlash.q1", 1e-300), ("backlash.q2", -0.0), ("backlash.q3", 12345678.123456789)))
    import tomllib

    doc = tomllib.loads(effect_tables_toml((st,)))
    assert doc["effect"]["backlash"] == dict(st.values)


def test_tables_work_for_other_kinds_alike():
    """Generic over machine kinds: the redundant RASPM with its preload, the RU-PUS-PRS with backlash."""
    from tests.conftest import ROOT

    for kind, name, mag in [("raspm", "redundancy_preload", 300.0), ("rupus_prs", "backlash", 30.0)]:
        m = load_machine(ROOT / "examples" / kind / "machine.toml")
        sim = simulate_with_effects(m, 30, seed=1, effects=[(name, mag)])
        truth = sim.info["effects"][name]["parameters"]
        st = StoredEffect(name, tuple((p["name"], p["value"]) for p in truth))
        true_m = machine_from_text(machine_file_text(m, sim.theta_true, (st,)))
        assert true_m.effects[0].units == tuple(p["unit"] for p in truth)
        model = MeasurementModel.from_recording(true_m, sim.recording)
        r = model.residual(model.predict(None))
        assert float(np.mean((r / model.sigma) ** 2)) < 1.3, kind


def test_predict_poses_is_the_model_of_a_recording(prs3, sim6):
    st = StoredEffect("backlash", (("backlash.q1", 20.0), ("backlash.q2", 40.0), ("backlash.q3", 30.0)))
    m = prs3.with_effects((st,))
    from bayescal.effects.stored import predict_poses

    rec = sim6.recording
    model = MeasurementModel.from_recording(m, rec)
    np.testing.assert_allclose(predict_poses(m, rec.q, rec.aux).position, model.predict(None).y[:, :3], atol=1e-9)
    np.testing.assert_allclose(predict_poses(prs3, rec.q).position, prs3.forward(rec.q).position, atol=0)


def test_stated_inputs_sit_beside_the_parameters(tmp_path, prs3):
    """Effect.settings_keys (e.g. the gravity direction of a machine on its side) are read, applied and written."""
    side = COMPLIANCE.replace("[effect.joint_compliance]\n", "[effect.joint_compliance]\ngravity = [1.0, 0.0, 0.0]\n")
    m, _ = _machine(tmp_path, side)
    assert dict(m.effects[0].settings) == {"gravity": [1.0, 0.0, 0.0]}
    np.testing.assert_allclose(m.effects[0].effect().down, [1.0, 0.0, 0.0])
    text = machine_file_text(m)
    assert '"gravity" = [1.0, 0.0, 0.0]' in text and machine_file_text(machine_from_text(text)) == text
    up, _ = _machine(tmp_path, COMPLIANCE)
    q = prs3.sample_q(4, np.random.default_rng(1))
    aux = {"payload_kg": np.full(4, 10.0)}
    assert np.abs(effect_delta_q(m, m.effects, q, aux) - effect_delta_q(up, up.effects, q, aux)).max() > 1e-3
    with pytest.raises(MachineFileError, match="an input of joint_compliance") as err:
        _machine(tmp_path, side.replace("[1.0, 0.0, 0.0]", '"sideways"'))
    assert err.value.key == 'effect.joint_compliance."gravity"'


def test_effect_values_beyond_the_file_limit_are_refused(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text(GOOD + "\n" + COMPLIANCE.replace("0.6", "1e300"))
    with pytest.raises(MachineFileError, match=r"magnitude at most 1e\+09") as err:
        load_machine(p)
    assert err.value.key == 'effect.joint_compliance."compliance.q2"'


@pytest.mark.parametrize("item, match", [("payload_kg=-1e6", "payload_kg from 0 to"), ("payload_kg=1e300", "payload_kg from 0 to 100000"),
                                         ("temp_C=-300", "temp_C from -273.15"), ("time_s=-1", "time_s from 0")])
def test_aux_values_outside_physics_are_refused(item, match):
    # grid --aux payload_kg=-1e6 moved the drives off the machine and the error blamed the grid's --range
    with pytest.raises(InputError, match=f"--aux {item}: expected {match}"):
        parse_aux_values([item])
    assert parse_aux_values(["payload_kg=0", "temp_C=-273.15"]) == {"payload_kg": 0.0, "temp_C": -273.15}
