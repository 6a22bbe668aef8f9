import json

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.diagnose import diagnose, distance_correlation, holm
from bayescal.effects.simulate import simulate_with_effects
from bayescal.errors import InputError
from tests.conftest import PRS3_FILE

CLEAR = [
    ("backlash", 30.0, ()),
    ("joint_compliance", 0.5, ("payload_kg",)),
    ("thermal_expansion", 15.0, ("temp_C",)),
    ("screw_periodic_error", 20.0, ()),
]


@pytest.mark.parametrize("name,magnitude,aux", CLEAR)
def test_effect_named_and_parameters_recovered(prs3, name, magnitude, aux):
    sim = simulate_with_effects(prs3, 80, seed=7, dof=6, effects=[(name, magnitude)], record=aux)
    d = diagnose(prs3, sim.recording, seed=1)
    assert d.verdict == name
    assert d.selected[0] == name
    trial = next(e for e in d.effects if e.name == name)
    assert trial.detected and trial.evidence > np.log(100)
    assert trial.rms_after < trial.rms_before
    truth = {p["name"]: p["value"] for p in sim.info["effects"][name]["parameters"]}
    for p in trial.parameters:
        # within 4 of its reported standard deviations (a loose bound across 3-7 parameters)
        assert abs(p.value - truth[p.name]) < 4 * p.std, (p, truth[p.name])


def test_clean_data_gives_none(prs3):
    sim = simulate_with_effects(prs3, 80, seed=8, dof=6, record=("time_s", "temp_C", "payload_kg"))
    d = diagnose(prs3, sim.recording, seed=1)
    assert d.verdict == "none"
    assert not any(e.detected for e in d.effects)
    assert d.p_geometric > 1e-3


def test_cli_json_matches_formats(tmp_path, capsys):
    rec = tmp_path / "rec.csv"
    assert main([
        "simulate", "--machine", str(PRS3_FILE), "--poses", "70", "--seed", "3", "--dof", "3",
        "--effect", "backlash:40", "--aux", "time_s", "--out", str(rec), "--quiet",
    ]) == 0
    assert "time_s" in rec.read_text().splitlines()[0]
    out = tmp_path / "d.json"
    figs = tmp_path / "figs"
    assert main(["diagnose", str(rec), "--machine", str(PRS3_FILE), "--json", str(out), "--figures", str(figs)]) == 0
    report = capsys.readouterr().out
    assert "VERDICT backlash" in report and "backlash.q1" in report
    ans = json.loads(out.read_text())
    names = {"joint_compliance", "thermal_expansion", "backlash", "screw_periodic_error", "redundancy_preload"}
    assert ans["verdict"] in names | {"none", "unexplained"}
    assert ans["verdict"] == "backlash"
    evid = [e["evidence"] for e in ans["effects"]]
    assert ans["effects"][0]["name"] == "backlash" and evid[0] == max(evid)
    for e in ans["effects"]:
        assert e["name"] in names and isinstance(e["detected"], bool)
        assert isinstance(e["evidence"], float) and e["rms_before"] > 0 and e["rms_after"] > 0
        for p in e["parameters"]:
            assert set(p) == {"name", "value", "std", "unit"} and isinstance(p["value"], float)
    assert set(ans["located"]) >= {"channel", "strength"} and 0 <= ans["located"]["strength"] <= 1
    assert (figs / "residuals_vs_channels.png").stat().st_size > 1000


def test_forced_effect_without_its_channel_is_an_error(tmp_path, capsys):
    rec = tmp_path / "rec.csv"
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses", "30", "--seed", "3", "--out", str(rec), "--quiet"]) == 0
    code = main(["diagnose", str(rec), "--machine", str(PRS3_FILE), "--effects", "thermal_expansion"])
    assert code == 2
    err = capsys.readouterr().err
    assert "thermal_expansion" in err and "temp_C" in err and "rec.csv" in err
    assert main(["diagnose", str(rec), "--machine", str(PRS3_FILE), "--effects", "wobble"]) == 2
    assert "unknown effect" in capsys.readouterr().err


def test_too_few_poses_are_errors(prs3):
    sim = simulate_with_effects(prs3, 20, seed=2, dof=6)
    with pytest.raises(InputError, match="too few poses"):
        diagnose(prs3, sim.recording, effects=["screw_periodic_error"])
    tiny = simulate_with_effects(prs3, 6, seed=2, dof=6)
    with pytest.raises(InputError, match="at least 10"):
        diagnose(prs3, tiny.recording)


def test_simulate_rejects_unknown_aux(tmp_path, capsys):
    code = main(["simulate", "--machine", str(PRS3_FILE), "--poses", "10", "--seed", "1", "--aux", "humidity",
                 "--out", str(tmp_path / "r.csv")])
    assert code == 2 and "humidity" in capsys.readouterr().err


def test_distance_correlation_closed_forms(rng):
    x = rng.normal(size=80)
    assert distance_correlation(x, x) == pytest.approx(1.0)
    assert distance_correlation(x, 3 * x - 2) == pytest.approx(1.0)
    # non-monotone: y = x^2 has zero Pearson correlation with symmetric x, but dcor sees it
    xs = np.linspace(-1, 1, 81)
    assert abs(np.corrcoef(xs, xs**2)[0, 1]) < 1e-12
    assert distance_correlation(xs, xs**2) > 0.4
    assert distance_correlation(rng.normal(size=400), rng.normal(size=400)) < 0.15


def test_holm_by_hand():
    np.testing.assert_allclose(holm([0.01, 0.04, 0.03, 0.5]), [0.04, 0.09, 0.09, 0.5])



def test_quadratic_straightness_is_not_a_screw_error():
    # a rail bowing quadratically along the stroke (outside the library): a sine with a pitch of about the
    # stroke imitates it.  Case 25 of the concealed study (seed 2026) was named screw_periodic_error before
    # the pitch was restricted to at least two full periods in the recorded stroke.
    from studies.diagnose_concealed import make_case, run_case

    case = make_case("outside_straightness", 25, 2026)
    row = run_case(case)
    assert row["verdict"] != "screw_periodic_error"
    assert "screw_periodic_error" not in row["selected"].split("+")


def test_fitted_pitch_fits_twice_in_the_stroke(prs3):
    sim = simulate_with_effects(prs3, 80, seed=7, dof=6, effects=[("screw_periodic_error", 20.0)])
    d = diagnose(prs3, sim.recording, effects=["screw_periodic_error"], seed=1)
    span = float(np.ptp(sim.recording.q, axis=0).max())
    pitch = next(e for e in d.effects if e.name == "screw_periodic_error").parameters[0].value
    assert pitch <= span / 2


RASPM_FILE = PRS3_FILE.parent.parent / "raspm" / "machine.toml"


def test_redundancy_preload_direction_is_an_internal_force_on_the_raspm():
    from bayescal.effects import get_effect
    from bayescal.machines.files import load_machine

    m = load_machine(RASPM_FILE)
    sim = simulate_with_effects(m, 12, seed=4, dof=6)
    theta = np.zeros(m.n_params)
    nu = get_effect("redundancy_preload").features(m, sim.recording.q, theta, {}, None, None).per_pose["nu"]
    x = m.forward(sim.recording.q, theta).state.x
    _, Ja = m.ik_jacobian(x, theta)
    # self-equilibrated: J_a^T nu = 0, unit length, and not the trivial direction of the ignored actuator alone
    np.testing.assert_allclose(np.einsum("nmk,nm->nk", Ja, nu), 0.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(nu, axis=1), 1.0)
    assert np.all(np.abs(nu[:, list(m.nonredundant)]).max(axis=1) > 0.1)


def test_clean_raspm_names_no_effect():
    from bayescal.machines.files import load_machine

    m = load_machine(RASPM_FILE)
    sim = simulate_with_effects(m, 40, seed=5, dof=6)
    d = diagnose(m, sim.recording, seed=1)
    assert d.verdict == "none"
    assert "redundancy_preload" in [e.name for e in d.effects]
    assert not d.selected


def test_negative_compliance_is_not_reported_as_a_detection(prs3):
    # a machine that "yields upwards" under gravity: the compliance fit explains it only with c < 0
    from bayescal.effects import get_effect

    # (compliances under a 30 kg platform and the payload, centre of mass at the origin, no tilt)
    values = np.concatenate([[0.6, -0.6, 0.6, 30.0], np.zeros(5)])
    bound = get_effect("joint_compliance").bind(prs3, values)
    sim = simulate_with_effects(prs3, 80, seed=7, dof=6, record=("payload_kg",), extra=[bound])
    d = diagnose(prs3, sim.recording, seed=1)
    assert d.verdict != "joint_compliance" and "joint_compliance" not in d.selected
    why = dict(d.skipped)["joint_compliance"]
    assert "non-physical" in why and "compliance.q2" in why
    assert "q1" not in why and "q3" not in why
    assert "joint_compliance" not in [e.name for e in d.effects]  # not listed as a tried-and-scored explanation


def _raspm_signature_fractions(m, dof):
    """Per actuator: share of a preload's whitened signature that the geometric parameters cannot absorb."""
    from bayescal.effects import get_effect
    from bayescal.measurement import MeasurementModel

    sim = simulate_with_effects(m, 150, seed=3, dof=dof)
    model = MeasurementModel.from_recording(m, sim.recording)
    theta = np.zeros(m.n_params)
    pred = model.predict(theta)
    A = (model.jacobian(theta, pred) / model.sigma[None, :, None]).reshape(-1, m.n_params)
    Jq = model.rows_jacobian(m.actuator_jacobian(model.q, theta, pred.poses), pred) / model.sigma[None, :, None]
    eff = get_effect("redundancy_preload")
    nu = eff.features(m, model.q, theta, {}, None, pred.poses).per_pose["nu"]
    # one drive's deflection along the internal-force direction, dq_i = d nu_i(x), per drive
    B = (Jq * nu[:, None, :]).reshape(-1, 4)
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    U = U[:, s > 1e-9 * s[0]]
    out = []
    for k in m.nonredundant:
        b = B[:, k]
        out.append(np.linalg.norm(b - U @ (U.T @ b)) / np.linalg.norm(b))
    # the ignored (redundant) actuator's column moves nothing
    assert np.allclose(B[:, m.redundant[0]], 0.0)
    return np.array(out)


@pytest.mark.parametrize("dof", [6, 3])
def test_raspm_preload_signature_is_nearly_but_not_exactly_geometric(dof):
    # docs/diagnose.md: about 99 % of the preload's signature lies in the span of the geometric
    # parameters, so a preload is visible only from deflections of some hundred um; but it is not
    # exactly absorbed (the joint system has full column rank), so it is identifiable in principle
    from bayescal.machines.files import load_machine

    frac = _raspm_signature_fractions(load_machine(RASPM_FILE), dof)
    assert np.all(frac < 0.05), frac
    assert np.all(frac > 1e-3), frac


def test_raspm_preload_unabsorbed_part_is_second_order_in_the_workspace_size():
    # why 99 % is absorbed: d_i nu_i(x) = constant (an actuator zero offset) + linear in the pose
    # (spanned by each chain's rail, tilt, link and platform-joint parameters) + O(|x - x0|^2);
    # only the quadratic remainder is left, so halving the workspace quarters it
    from bayescal.machines.files import machine_from_text

    text = RASPM_FILE.read_text()
    rng_lines = {"x = [-300.0, 300.0]": (300.0, "x"), "z = [-200.0, 200.0]": (200.0, "z"),
                 "rotation = [-0.4363323129985824, 0.4363323129985824]": (0.4363323129985824, "rotation")}
    fr = []
    for k in (1.0, 0.5):
        t = text
        for line, (half, key) in rng_lines.items():
            assert line in t
            t = t.replace(line, f"{key} = [{-half * k!r}, {half * k!r}]")
        fr.append(_raspm_signature_fractions(machine_from_text(t, "half.toml"), 6))
    ratio = fr[1] / fr[0]
    assert np.all((ratio > 0.1) & (ratio < 0.4)), ratio  # ~1/4, not ~1/2 (first order) or ~1 (exactly absorbed: 0)


def test_recording_of_another_machine_is_a_clear_error(prs3):
    from bayescal.machines.files import machine_from_text

    sim = simulate_with_effects(prs3, 20, seed=3, dof=3)
    short = machine_from_text(PRS3_FILE.read_text().replace("link_length    = 400.0", "link_length    = 120.0"), "short.toml")
    with pytest.raises(InputError, match=r"short\.toml cannot solve this recording.*pose 1.*check the machine file"):
        diagnose(short, sim.recording)


@pytest.fixture(scope="module")
def warmup_with_beam_breaks(prs3):
    """A thermal warm-up with three gross poses: the geometric screen over-flags, the retest against the final
    model names the three, and the diagnosis runs again (tests/outliers/test_screen.py)."""
    from dataclasses import replace

    sim = simulate_with_effects(prs3, 100, seed=20, dof=6, effects=[("thermal_expansion", 25.0)], record=("temp_C",))
    rng = np.random.default_rng(0)
    pos = sim.recording.position.copy()
    for i in (30, 55, 80):
        d = rng.normal(size=3)
        pos[i] += 10 ** rng.uniform(1.0, 2.0) * prs3.noise.sigma_position * d / np.linalg.norm(d)
    return replace(sim.recording, position=pos)


def test_a_rerun_runs_the_location_tests_once(prs3, warmup_with_beam_breaks, monkeypatch):
    """The first pass of a diagnosis that is run again (outliers retested) never asks for its location tests."""
    import bayescal.diagnose.core as core

    calls = []
    real = core.locate
    monkeypatch.setattr(core, "locate", lambda *a, **k: calls.append(a[0].shape[0]) or real(*a, **k))
    passes = []
    real_diagnose = core.diagnose
    monkeypatch.setattr(core, "diagnose", lambda *a, **k: passes.append(k.get("_screen")) or real_diagnose(*a, **k))
    d = core.diagnose(prs3, warmup_with_beam_breaks, seed=1)
    assert len(passes) == 2 and passes[1] is not None  # the first pass and the rerun with the retested screen
    assert calls == [100]
    assert d.verdict == "thermal_expansion" and [o["line"] for o in d.to_dict()["outliers"]] == [32, 57, 82]
    assert d.location.channels and d.location.strongest.significant


def test_a_large_recordings_rerun_starts_its_fits_from_the_first_pass(prs3, warmup_with_beam_breaks, monkeypatch):
    """From LARGE_POSES poses a rerun's fits start from the first pass's fits of the same effects, with no coarse
    start; the answer moves within the fits' stop tests only (here: 100 poses with the threshold lowered)."""
    import bayescal.diagnose.core as core

    ref = core.diagnose(prs3, warmup_with_beam_breaks, seed=1)
    starts = []
    real = core.fit_map

    def spy(model, effects=(), **kw):
        fit = real(model, effects, **kw)
        if effects and model.n_poses == 100:  # the candidates' fits (not the cross-validation's folds)
            starts.append((tuple(e.name for e, _ in effects), kw.get("coarse", True), kw.get("theta0"), fit))
        return fit

    monkeypatch.setattr(core, "fit_map", spy)
    monkeypatch.setattr(core, "LARGE_POSES", 50)
    _without_the_candidates_test(monkeypatch)  # the rerun of the final retest, alone
    d = core.diagnose(prs3, warmup_with_beam_breaks, seed=1)
    first = {names: fit for names, coarse, _, fit in starts[: len(starts) // 2]}
    rerun = starts[len(starts) // 2:]
    assert [names for names, *_ in rerun] == list(first)  # every fit of the first pass, again
    for names, coarse, theta0, _ in rerun:
        assert coarse is False and np.array_equal(theta0, first[names].theta)
    assert d.verdict == ref.verdict and d.selected == ref.selected
    # the same poses; their statistics from the final model's test at the first pass's fit (here) and at the
    # answer's own fit with the candidates' screen (ref, which runs no second pass of fits): close, not equal
    out, ref_out = d.to_dict()["outliers"], ref.to_dict()["outliers"]
    assert [o["line"] for o in out] == [o["line"] for o in ref_out] == [32, 57, 82]
    for o, q in zip(out, ref_out):
        assert o["statistic"] == pytest.approx(q["statistic"], rel=0.05)
    for t, r in zip(d.effects, ref.effects):
        assert t.name == r.name and t.evidence == pytest.approx(r.evidence, abs=0.02)
        for p, q in zip(t.parameters, r.parameters):
            assert abs(p.value - q.value) < 0.05 * q.std


def _without_the_candidates_test(monkeypatch):
    """Switch off the candidates' test before the fits: the geometric screen complete at once, judged by the final
    model alone."""
    import bayescal.diagnose.core as core
    from bayescal.outliers.screen import screen_outliers

    monkeypatch.setattr(core, "first_round", lambda model, **kw: screen_outliers(model, **kw))
    monkeypatch.setattr(core, "_outliers_pretested", lambda *a: None)


def test_the_poses_are_judged_against_every_candidate_before_any_fit(prs3, monkeypatch):
    """The poses the screen's first round flags are tested against the geometry with every candidate effect
    (linearised) before the fits: a warm-up's first poses, which the geometric screen flags, are released then,
    the final model agrees, the screen's later rounds never run and no effect is fitted twice.  The answer is the
    one the rerun after the final retest gives (with the candidates' test switched off; LARGE_POSES lowered so
    that this rerun starts from the first pass's fits, as on a large recording)."""
    import bayescal.diagnose.core as core
    from bayescal.outliers.screen import complete_screen

    sim = simulate_with_effects(prs3, 100, seed=20, dof=6, effects=[("thermal_expansion", 25.0)], record=("temp_C",))
    monkeypatch.setattr(core, "LARGE_POSES", 50)
    fits, passes, screened = [], [], []
    real_fit, real_diagnose, real_screened = core.fit_map, core.diagnose, core._screened_by_candidates

    def spy_fit(model, effects=(), **kw):
        if effects and model.n_poses == 100:
            fits.append(tuple(e.name for e, _ in effects))
        return real_fit(model, effects, **kw)

    monkeypatch.setattr(core, "fit_map", spy_fit)
    monkeypatch.setattr(core, "diagnose", lambda *a, **k: passes.append(k.get("_screen")) or real_diagnose(*a, **k))
    monkeypatch.setattr(core, "_screened_by_candidates", lambda *a: screened.append(real_screened(*a)) or screened[-1])
    d = core.diagnose(prs3, sim.recording, seed=1)
    assert len(passes) == 1  # one pass: the candidates released every pose the first round flagged
    (s, restart, pretested), = screened
    first = s.screen.replaced
    assert restart is None and pretested and not s.screen.excluded.any()
    assert not first.complete and first.test.flagged.any() and not first.excluded.any()
    # the geometric screen's warm-up poses, had its later rounds run
    assert np.flatnonzero(complete_screen(s.base_model, first).excluded).tolist() == [0, 2, 8]
    assert len(fits) == len(set(fits))  # every fit once
    ans = d.to_dict()
    assert d.verdict == "thermal_expansion" and ans["outliers"] == []

    # without the test before the fits: the first pass fits everything, the final model releases the same poses
    fits.clear()
    passes.clear()
    _without_the_candidates_test(monkeypatch)
    ref = core.diagnose(prs3, sim.recording, seed=1)
    assert len(passes) == 2 and len(fits) > len(set(fits))
    assert ref.verdict == d.verdict and ref.selected == d.selected and ref.to_dict()["outliers"] == []
    # the final model's judgment, in the same words whichever screen it confirmed
    assert ans["outlier_handling"] == ref.to_dict()["outlier_handling"]
    assert "judged against the geometry with thermal_expansion" in ans["outlier_handling"]
    # the selected effect's parameters, fitted cold here and from the first pass's fit there: within the stop
    # tests (a periodic screw error's pitch, not selected, has several optima: its start decides among them)
    a, b = ref.to_dict()["effects"], ans["effects"]
    assert [(e["name"], e["detected"]) for e in a] == [(e["name"], e["detected"]) for e in b]
    for ea, eb in zip(a, b):
        if ea["name"] in ref.selected:
            for pa, pb in zip(ea["parameters"], eb["parameters"]):
                assert pa["name"] == pb["name"] and abs(pa["value"] - pb["value"]) < 0.05 * pa["std"]


def test_with_no_effect_selected_the_geometric_screen_comes_back():
    """A screen from the candidates gives way to the geometric screen it replaced when the final model is the
    geometry alone; any other screen stands."""
    from types import SimpleNamespace

    import bayescal.diagnose.core as core

    geometric = SimpleNamespace(replaced=None, complete=True)
    early = SimpleNamespace(replaced=geometric)
    assert core._outliers_retested(SimpleNamespace(screen=early, base_model=None), [], None) is geometric
    assert core._outliers_retested(SimpleNamespace(screen=geometric, base_model=None), [], None) is None
    assert core._outliers_retested(SimpleNamespace(screen=None), [], None) is None


def test_the_geometric_screen_that_comes_back_is_judged_by_its_passs_final_model(prs3, monkeypatch):
    """A pass on the candidates' screen that selects no effect runs again on the geometric screen (the thermal
    warm-up's first poses out); where that pass selects an effect, its final model still judges the poses and
    releases them (a third pass), as a first pass's would: they are not reported as outliers."""
    import bayescal.diagnose.core as core

    sim = simulate_with_effects(prs3, 100, seed=20, dof=6, effects=[("thermal_expansion", 25.0)], record=("temp_C",))
    calls, passes = [], []
    real_selection, real_diagnose = core._forward_selection, core.diagnose

    def first_selects_nothing(s, cands, single, folds, fit0, cv0, *rest):
        calls.append(1)
        return ([], fit0, cv0) if len(calls) == 1 else real_selection(s, cands, single, folds, fit0, cv0, *rest)

    monkeypatch.setattr(core, "_forward_selection", first_selects_nothing)
    monkeypatch.setattr(core, "diagnose", lambda *a, **k: passes.append(k) or real_diagnose(*a, **k))
    d = core.diagnose(prs3, sim.recording, seed=1)
    assert len(passes) == 3
    geometric = passes[1]["_screen"]
    assert np.flatnonzero(geometric.excluded).tolist() == [0, 2, 8] and passes[1]["_judge"]
    ans = d.to_dict()
    assert d.verdict == "thermal_expansion" and ans["outliers"] == []
    assert "judged against the geometry with thermal_expansion" in ans["outlier_handling"]


def test_with_no_effect_selected_a_first_round_the_candidates_replaced_is_completed(prs3, warmup_with_beam_breaks):
    """Where the candidates replaced the screen's first round alone, the geometric screen that comes back is the
    complete one (its later rounds run then): the poses screen_outliers names, not the first round's nothing."""
    from types import SimpleNamespace

    import bayescal.diagnose.core as core
    from bayescal.measurement import MeasurementModel
    from bayescal.outliers.screen import first_round, screen_outliers

    model = MeasurementModel.from_recording(prs3, warmup_with_beam_breaks)
    first = first_round(model)
    assert first.test.flagged.any() and not first.excluded.any()
    back = core._outliers_retested(SimpleNamespace(screen=SimpleNamespace(replaced=first), base_model=model), [], None)
    ref = screen_outliers(model)
    assert back.complete and ref.excluded.any() and np.array_equal(back.excluded, ref.excluded)
