"""The calibrated machine a diagnosis writes: geometry fitted with the selected effects, and [effect.*] tables."""

import dataclasses

import numpy as np
import pytest

from bayescal.diagnose import diagnose
from bayescal.diagnose.calibrated import calibrated_machine
from bayescal.effects import fit_map, get_effect
from bayescal.effects.simulate import simulate_with_effects
from bayescal.effects.stored import machine_file_text
from bayescal.identify import identify
from bayescal.machines.files import machine_from_text
from bayescal.measurement import MeasurementModel
from bayescal.simulate import draw_poses

CASES = [("joint_compliance", 0.5, ["payload_kg"]), ("thermal_expansion", 12.0, ["temp_C"]), ("backlash", 30.0, [])]


def _diagnose(machine, rec, name=None, seed=0):
    # one effect tried, few permutations: the same fit as the full diagnosis, at a fraction of the time
    return diagnose(machine, rec, effects=None if name is None else [name], seed=seed, n_perm=19, n_folds=3)


@pytest.mark.parametrize("name,mag,aux", CASES)
def test_written_machine_round_trips_and_predicts_like_the_diagnosis_model(prs3, name, mag, aux):
    sim = simulate_with_effects(prs3, 120, seed=1, effects=[(name, mag)], record=aux)
    d = _diagnose(prs3, sim.recording, name, seed=1)
    assert d.verdict == name
    cal = calibrated_machine(prs3, d)
    assert cal.effects == (name,) and cal.warning == ""
    assert f"[effect.{name}]" in cal.text
    # the tables round-trip: the values of the diagnosis answer, by name
    (st,) = cal.machine.effects
    (trial,) = [t for t in d.effects if t.name == name]
    assert dict(st.values) == {p.name: p.value for p in trial.parameters}
    assert machine_file_text(cal.machine) == machine_file_text(machine_from_text(machine_file_text(cal.machine)))
    # the written machine predicts the recording like the joint fit of the diagnosis (geometry + effect)
    model = MeasurementModel.from_recording(cal.machine, sim.recording)
    r_written = model.residual(model.predict(None))
    base = MeasurementModel.from_recording(prs3, sim.recording)
    eff = get_effect(name)
    fit0 = fit_map(base)
    f = eff.features(prs3, base.q, fit0.theta, dict(sim.recording.aux), None, base.predict(fit0.theta).poses)
    fit = fit_map(base, [(eff, f)], theta0=fit0.theta)
    assert np.abs(r_written[:, :3] - fit.residual[:, :3]).max() < 2e-4  # 0.2 um of 10-50 um residuals
    # identify on the written machine, same recording: the geometry is left with noise only
    res = identify(model, method="ls", free="auto")
    noise = prs3.noise.sigma_position * np.sqrt(3)
    assert res.success
    assert res.rms_after["position"] < 1.1 * noise
    assert base.rms(fit0.residual)["position"] > 1.15 * noise  # which the geometry alone cannot reach


def test_verdict_none_writes_the_geometry_only_calibration(prs3):
    sim = simulate_with_effects(prs3, 60, seed=2, effects=[], record=["payload_kg"])
    d = _diagnose(prs3, sim.recording)
    assert d.verdict == "none"
    cal = calibrated_machine(prs3, d)
    assert cal.effects == () and cal.machine.effects == () and "[effect." not in cal.text
    np.testing.assert_allclose(d.theta_final, d.theta_geometric)
    expected = machine_from_text(prs3.to_toml(d.theta_geometric))
    q = draw_poses(prs3, 20, np.random.default_rng(0))
    np.testing.assert_allclose(cal.machine.forward(q).position, expected.forward(q).position, atol=1e-9)


def test_unexplained_is_written_with_a_warning(prs3):
    sim = simulate_with_effects(prs3, 60, seed=2, effects=[("backlash", 30.0)])
    d = _diagnose(prs3, sim.recording, "backlash")
    forged = dataclasses.replace(d, verdict="unexplained")
    cal = calibrated_machine(prs3, forged)
    assert "unexplained" in cal.warning and "backlash" in cal.warning
    assert cal.effects == ("backlash",)  # the effects that were selected, with the geometry fitted with them
    none_selected = dataclasses.replace(d, verdict="unexplained", selected=())
    cal = calibrated_machine(prs3, none_selected)
    assert cal.effects == () and "geometry-only" in cal.warning


def test_stored_effects_of_the_input_machine_are_fitted_afresh(prs3):
    sim = simulate_with_effects(prs3, 60, seed=3, effects=[("backlash", 30.0)])
    d = _diagnose(prs3, sim.recording, "backlash")
    with_tables = calibrated_machine(prs3, d).machine
    again = _diagnose(with_tables, sim.recording, "backlash")  # the tables are not applied: backlash found again
    assert again.verdict == "backlash"
    cal = calibrated_machine(with_tables, again)
    assert [e.name for e in cal.machine.effects] == ["backlash"]  # replaced, not doubled


def test_write_puts_a_hybrid_in_module_files_and_keeps_its_header(tmp_path):
    # the library object wrote its inline text ([module.machine]) where the command line wrote the
    # docs/formats.md section 5 form; both now go through one writer
    import tomllib

    from bayescal.diagnose.calibrated import CalibratedMachine
    from bayescal.machines.files import load_machine
    from tests.conftest import ROOT

    nominal = load_machine(ROOT / "examples" / "hybrid_table" / "machine.toml")
    theta = 1e-3 * np.random.default_rng(2).normal(size=nominal.n_params)
    text = "# calibrated by a test\n" + machine_file_text(nominal, theta)
    cm = CalibratedMachine(text=text, machine=machine_from_text(text, path="<test>"), effects=())
    paths = cm.write(tmp_path / "cal.toml")
    assert len(paths) > 1 and all(p.is_file() for p in paths)
    main_text = paths[0].read_text()
    assert main_text.startswith("# calibrated by a test\n")
    assert all("file" in m and "machine" not in m for m in tomllib.loads(main_text)["module"])
    q = nominal.sample_q(10, np.random.default_rng(3))
    a, b = load_machine(paths[0]).forward(q), nominal.forward(q, theta)
    assert a.success.all() and np.abs(a.position - b.position).max() < 1e-9
    # any other kind: the text itself, one file
    from tests.conftest import PRS3_FILE

    prs = load_machine(PRS3_FILE)
    one = CalibratedMachine(text="# x\n" + machine_file_text(prs, None), machine=prs, effects=())
    (p,) = one.write(tmp_path / "prs.toml")
    assert p.read_text() == one.text
