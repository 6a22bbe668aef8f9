"""Leave-one-out of Klipper's fit and bayescal's MAP on a simulated Klipper printer and on synthetic configs as
the reader reads them (no ../shared data needed)."""

from dataclasses import replace

import numpy as np
import pytest

from bayescal.bayes.map_identify import identify_map
from bayescal.bayes.priors import map_estimate
from bayescal.constraints.model import ConstraintModel
from bayescal.design.relations import grid_points, relation_candidates
from bayescal.io.constraints import ConstraintRecording
from bayescal.errors import InputError
from bayescal.klipper.cfg import read_klipper_config
from bayescal.klipper import KlipperDelta, klipper_machine, klipper_recording, read_klipper_delta
from bayescal.klipper.loo import loo_bayescal, loo_klipper, noise_scale_map, rms
from tests import klipper_configs as synth

NOMINAL = KlipperDelta(
    delta_radius=105.0, angle_deg=np.array([210.0, 330.0, 90.0]), arm_length=np.full(3, 216.0),
    position_endstop=np.full(3, 219.0), step_dist=np.full(3, 0.0125), print_radius=90.0, minimum_z=0.0,
)
TRUE = replace(NOMINAL, delta_radius=104.2, angle_deg=np.array([210.3, 329.6, 90.0]),
               arm_length=np.array([216.5, 215.8, 216.3]), position_endstop=np.array([218.7, 219.3, 219.1]))


def _pattern_on(kd: KlipperDelta) -> ConstraintRecording:
    """Klipper-like pattern: 7 heights (centre and a ring) and 12 distances, commanded on the nominal printer."""
    m = klipper_machine(NOMINAL)
    ring = [[60 * np.cos(a), 60 * np.sin(a), 0.0] for a in np.deg2rad(np.arange(0, 360, 60))]
    h = relation_candidates(m, "height", np.array([[0.0, 0.0, 0.0]] + ring))
    pts = grid_points(np.array([0.0, 0.0, 0.0]), 40.0, 20.0)
    d = relation_candidates(m, "distance", pts, min_distance=35.0).subset(np.arange(0, 48, 4)[:12])
    rec = ConstraintRecording(
        measure=h.measure + d.measure, qa=np.vstack([h.qa, d.qa]), qb=np.vstack([h.qb, d.qb]),
        value=np.zeros(h.n_rows + d.n_rows), sigma=np.r_[np.full(h.n_rows, 0.02), np.full(d.n_rows, 0.05)],
    )
    # the true printer's heights and distances at those commanded positions (Klipper's own model)
    true = klipper_machine(kd, q_span=rec.qa)
    return replace(rec, value=ConstraintModel.from_recording(true, rec).predict(None).y[:, 0])


@pytest.fixture(scope="module")
def exact():
    return _pattern_on(TRUE)


def test_klippers_loo_is_exact_when_its_model_is(exact):
    # noise-free data from a printer Klipper's nine parameters describe: every refit predicts the left-out row
    assert exact.n_rows == 19
    r = loo_klipper(NOMINAL, exact, rows=[0, 3, 8, 15])
    assert rms(r.loo_error) < 1e-5 and rms(r.in_sample) < 1e-6
    assert np.isnan(r.loo_error[1]) and np.isfinite(r.loo_error[3])


def test_bayescal_loo_rows_match_separate_fits(exact):
    rng = np.random.default_rng(4)
    noisy = replace(exact, value=exact.value + exact.sigma * rng.normal(size=exact.n_rows))
    m = klipper_machine(NOMINAL, q_span=exact.qa)
    keep = np.delete(np.arange(noisy.n_rows), 11)
    for noise, fit in (
        ("stated", lambda model: map_estimate(model, free="all")),
        ("identify", lambda model: identify_map(model, "all")[0]),  # what `identify --method map --free all` runs
    ):
        r = loo_bayescal(m, noisy, rows=[2, 11], noise=noise)
        # row 11 by hand: MAP on the other 18, prediction of row 11
        theta = fit(ConstraintModel.from_recording(m, noisy.subset(keep))).theta
        pred = ConstraintModel.from_recording(m, noisy.subset([11])).predict(theta).y[0, 0]
        assert abs(r.loo_error[11] - (noisy.value[11] - pred)) < 1e-9
        # the prior keeps 21 parameters from 18 rows sensible: errors at the noise level, not millimetres
        assert rms(r.loo_error) < 0.3


def test_noise_scale_is_estimated_and_floored_at_one(exact):
    m = klipper_machine(NOMINAL, q_span=exact.qa)
    rng = np.random.default_rng(7)
    noisy = replace(exact, value=exact.value + 6.0 * exact.sigma * rng.normal(size=exact.n_rows))
    _, s = noise_scale_map(m, noisy)
    assert 3.0 < s < 12.0
    _, s1 = noise_scale_map(m, exact)
    assert s1 == 1.0


# ---------------------------------------------------------------- on configs as the reader reads them
def _from_config(tmp_path, block):
    cfg = read_klipper_config(synth.write_config(tmp_path, block=block))
    kd = read_klipper_delta(cfg)
    rec = klipper_recording(cfg, kd)
    return kd, rec, klipper_machine(kd, q_span=np.vstack([rec.qa, rec.qb[np.isfinite(rec.qb).all(axis=1)]]))


@pytest.mark.parametrize("keep", [
    None,  # manual height, 7 probed heights, 6 distances, includes, every saved section
    ("height0", "height1", "height2"),  # the least DELTA_CALIBRATE saves: 3 probed heights, nothing else
])
def test_loo_runs_on_configs_that_read(tmp_path, keep):
    block = synth.calibration_block()
    if keep is not None:
        block = [ln for ln in block if not ln.startswith(("height", "distance", "manual")) or ln.startswith(keep)]
    kd, rec, m = _from_config(tmp_path, block)
    rows = [0, 1, rec.n_rows - 1]
    # Klipper's fit started away from the truth (the saved points are exact for kd, to Klipper's 3 decimals)
    start = replace(kd, delta_radius=kd.delta_radius + 1.5, arm_length=kd.arm_length + 1.0)
    for r in (loo_klipper(start, rec, rows=rows), loo_bayescal(m, rec, rows=rows)):
        assert np.all(np.isfinite(r.loo_error[rows])) and np.all(np.isfinite(r.in_sample))
        assert np.isnan(r.loo_error[np.setdiff1d(np.arange(rec.n_rows), rows)]).all()
    if keep is None:  # enough rows for Klipper's nine parameters: its refits predict the left-out rows
        assert rms(loo_klipper(start, rec, rows=rows).loo_error) < 1e-3


def test_loo_refuses_a_recording_without_two_rows(exact):
    with pytest.raises(InputError, match="at least 2 measurements"):
        loo_klipper(NOMINAL, exact.subset([0]))
