"""A bad pose is not physics: gross errors named as outliers and left out of the diagnosis (bayescal/outliers/screen.py)."""

import json
from dataclasses import replace

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.diagnose import diagnose
from bayescal.outliers.screen import MAX_FRACTION, screen_outliers
from bayescal.effects.simulate import simulate_with_effects
from bayescal.io import write_recording
from bayescal.measurement import MeasurementModel
from tests.conftest import PRS3_FILE


def _beam_breaks(rec, idx, sigma, rng, low=10.0, high=100.0):
    """The recording with gross errors (10 to 100 sigma, random directions) at poses ``idx``."""
    pos = rec.position.copy()
    for i in idx:
        d = rng.normal(size=3)
        pos[i] += 10 ** rng.uniform(np.log10(low), np.log10(high)) * sigma * d / np.linalg.norm(d)
    return replace(rec, position=pos)


@pytest.mark.parametrize("effect,verdict", [((), "none"), ((("backlash", 30.0),), "backlash")])
def test_gross_poses_named_and_verdict_describes_the_rest(prs3, effect, verdict):
    sim = simulate_with_effects(prs3, 80, seed=20, dof=6, effects=list(effect), record=("time_s", "temp_C"))
    bad = np.array([37, 50])
    rec = _beam_breaks(sim.recording, bad, prs3.noise.sigma_position, np.random.default_rng(0))
    d = diagnose(prs3, rec, seed=1, n_perm=49)
    ans = d.to_dict()
    assert [o["line"] for o in ans["outliers"]] == list(bad + 2)
    assert all(o["p_value"] < 0.01 for o in ans["outliers"])
    assert ans["outlier_handling"].startswith("excluded")
    assert d.verdict == verdict
    assert "outliers: 2 pose(s)" in d.report()


def test_clean_recording_has_no_outliers_and_cli_json_carries_the_keys(prs3, tmp_path):
    sim = simulate_with_effects(prs3, 60, seed=8, dof=6, record=("time_s",))
    rec = tmp_path / "rec.csv"
    write_recording(rec, sim.recording)
    out = tmp_path / "d.json"
    assert main(["diagnose", str(rec), "--machine", str(PRS3_FILE), "--json", str(out), "--quiet"]) == 0
    ans = json.loads(out.read_text())
    assert ans["verdict"] == "none"
    assert ans["outliers"] == [] and ans["outlier_handling"].startswith("no pose flagged")


def test_many_bad_poses_are_structure_not_outliers(prs3):
    sim = simulate_with_effects(prs3, 60, seed=9, dof=6)
    rng = np.random.default_rng(1)
    bad = rng.choice(60, int(2 * MAX_FRACTION * 60), replace=False)
    rec = _beam_breaks(sim.recording, bad, prs3.noise.sigma_position, rng, low=50.0, high=60.0)
    screen = screen_outliers(MeasurementModel.from_recording(prs3, rec))
    assert not screen.excluded.any() and "structure" in screen.action
    assert screen.outliers() == []


def test_physics_tails_are_not_outliers_when_judged_against_the_final_model(prs3):
    """Thermal warm-up: the geometric screen also flags the first poses (lines 2, 4 and 10 here); judged
    against geometry + thermal_expansion only the three gross poses remain, and the diagnosis is rerun.
    (A warm-up strong enough that its first poses stand out even against the fit without the gross
    ones: the screen releases poses that only the gross ones dragged out of line.)"""
    sim = simulate_with_effects(prs3, 100, seed=20, dof=6, effects=[("thermal_expansion", 25.0)], record=("temp_C",))
    bad = np.array([30, 55, 80])
    rec = _beam_breaks(sim.recording, bad, prs3.noise.sigma_position, np.random.default_rng(0))
    screen = screen_outliers(MeasurementModel.from_recording(prs3, rec))
    assert set(bad) < set(np.flatnonzero(screen.excluded))  # the geometric screen alone over-flags
    d = diagnose(prs3, rec, seed=1, n_perm=49)
    assert d.verdict == "thermal_expansion"
    assert [o["line"] for o in d.to_dict()["outliers"]] == list(bad + 2)
    assert "judged against the geometry with thermal_expansion" in d.to_dict()["outlier_handling"]


def test_the_screen_keeps_each_rounds_fit_and_a_retest_naming_its_poses_starts_from_it(prs3):
    """Every geometric fit of the screen is kept with the poses it left out; a retest whose poses are those of a
    round hands that fit on (the rerun's first fit, bit for bit), and one naming other poses none."""
    from bayescal.effects.model import fit_map
    from bayescal.outliers.screen import _retest
    from bayescal.outliers.stats import exclusion_weights, weighted_model

    sim = simulate_with_effects(prs3, 100, seed=20, dof=6, effects=[("thermal_expansion", 25.0)], record=("temp_C",))
    rec = _beam_breaks(sim.recording, np.array([30, 55, 80]), prs3.noise.sigma_position, np.random.default_rng(0))
    model = MeasurementModel.from_recording(prs3, rec)
    screen = screen_outliers(model)
    assert len(screen.fits) >= 2 and not screen.fits[0][0].any()  # the first round excludes nothing
    for mask, fit in screen.fits:
        again = fit_map(weighted_model(model, exclusion_weights(mask) if mask.any() else None))
        assert np.array_equal(fit.theta, again.theta) and fit.chi2 == again.chi2
        assert screen.fit_for(mask) is fit
    assert screen.fit is screen.fits[-1][1] and np.array_equal(screen.fits[-1][0], screen.excluded)
    other = screen.excluded.copy()
    other[0] = not other[0]
    assert screen.fit_for(other) is None
    # a retest on a linear system in which no pose stands out: it names the first round's poses (none)
    rng = np.random.default_rng(4)
    A, r = rng.normal(size=(600, 5)), rng.normal(size=600)
    new = _retest(model, A, r, screen, alpha=0.01, judged="judged here", released="released")
    assert new is not None and not new.excluded.any()
    assert new.fit is screen.fits[0][1] and new.fits == screen.fits


@pytest.mark.parametrize("bad,effects", [([30, 55, 80], [("thermal_expansion", 25.0)]), ([], [])])
def test_the_first_round_completed_is_the_screen_bit_for_bit(prs3, bad, effects):
    """The first round alone (what a diagnosis asks the candidates about) excludes nothing and flags what the
    screen's first round flags; completed, it is the screen's answer, every round's fit and test alike.  A
    complete screen completes to itself."""
    from bayescal.outliers.screen import complete_screen, first_round

    sim = simulate_with_effects(prs3, 100, seed=20, dof=6, effects=effects, record=("temp_C",))
    rec = _beam_breaks(sim.recording, np.array(bad, dtype=int), prs3.noise.sigma_position, np.random.default_rng(0))
    model = MeasurementModel.from_recording(prs3, rec)
    lines = np.arange(model.n_poses) + 7
    ref = screen_outliers(model, lines=lines)
    first = first_round(model, lines=lines)
    assert not first.complete and not first.excluded.any() and first.outliers() == []
    assert np.array_equal(first.test.flagged, ref.fits[1][0] if len(ref.fits) > 1 else ref.excluded)
    done = complete_screen(model, first)
    assert done.complete and complete_screen(model, done) is done
    assert np.array_equal(done.excluded, ref.excluded) and done.action == ref.action
    assert done.outliers() == ref.outliers()
    assert np.array_equal(done.test.lines, lines) and np.array_equal(done.test.statistic, ref.test.statistic)
    assert len(done.fits) == len(ref.fits)
    for (m_d, f_d), (m_r, f_r) in zip(done.fits, ref.fits):
        assert np.array_equal(m_d, m_r) and np.array_equal(f_d.theta, f_r.theta)
    assert bool(bad) == (len(ref.fits) > 1) == first.test.flagged.any()  # later rounds for the gross poses only
    if bad:  # a first round of another recording is refused, not finished on this one
        from bayescal.errors import InputError

        other = first_round(model.subset(np.arange(60)))
        with pytest.raises(InputError, match="first round of 60 poses; expected one of this recording's 100"):
            complete_screen(model, other)


def test_the_screens_later_rounds_start_warm_on_large_recordings_and_agree(prs3, monkeypatch):
    """From WARM_ROUNDS_POSES poses a round's fit starts from the round before's: the same poses flagged and
    excluded, every parameter within a small fraction of its posterior std of the rounds' cold fits."""
    import bayescal.outliers.screen as scr

    sim = simulate_with_effects(prs3, 100, seed=20, dof=6, effects=[("thermal_expansion", 25.0)], record=("temp_C",))
    rec = _beam_breaks(sim.recording, np.array([30, 55, 80]), prs3.noise.sigma_position, np.random.default_rng(0))
    model = MeasurementModel.from_recording(prs3, rec)
    cold = screen_outliers(model)
    starts = []
    real = scr.fit_map
    monkeypatch.setattr(scr, "fit_map", lambda m, **kw: starts.append(kw.get("theta0")) or real(m, **kw))
    monkeypatch.setattr(scr, "WARM_ROUNDS_POSES", 50)
    warm = screen_outliers(model)
    assert len(warm.fits) == len(cold.fits) >= 2
    assert starts[0] is None and all(s is not None for s in starts[1:])
    assert np.array_equal(warm.excluded, cold.excluded)
    for (m_w, f_w), (m_c, f_c) in zip(warm.fits, cold.fits):
        assert np.array_equal(m_w, m_c)
        std = np.sqrt(np.diag(f_c.covariance))[: prs3.n_params]
        assert np.all(np.abs(f_w.theta - f_c.theta) <= 0.05 * std)
    assert sum(f.iterations for _, f in warm.fits[1:]) < sum(f.iterations for _, f in cold.fits[1:])


def test_the_candidates_test_declines_what_it_cannot_linearise(prs3, monkeypatch):
    """A candidate that cannot be evaluated or differentiated at its start values: no test before the fits (the
    geometric screen stands, the final model still judges), never an error."""
    import bayescal.outliers.screen as scr
    from bayescal.errors import KinematicsError

    sim = simulate_with_effects(prs3, 100, seed=20, dof=6, effects=[("thermal_expansion", 25.0)], record=("temp_C",))
    model = MeasurementModel.from_recording(prs3, sim.recording)
    screen = screen_outliers(model)
    assert screen.excluded.any()  # the warm-up's first poses: something the candidates could release

    class _Effect:
        name = "stub"

        def params(self, machine, features):
            return ()

    def nan_system(*a):
        A, r = np.ones((model.n_poses * model.dof, 3)), np.zeros(model.n_poses * model.dof)
        A[5, 1] = np.nan
        return A, r

    monkeypatch.setattr(scr, "joint_system", nan_system)
    assert scr.retest_with_candidates(model, [(_Effect(), None)], screen.fit.theta, screen) is None

    def fails(*a):
        raise KinematicsError("pose 3 cannot be solved")

    monkeypatch.setattr(scr, "joint_system", fails)
    assert scr.retest_with_candidates(model, [(_Effect(), None)], screen.fit.theta, screen) is None
    assert scr.retest_with_candidates(model, [], screen.fit.theta, screen) is None
