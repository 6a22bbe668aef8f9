"""The discrepancy studies' pieces: their physics in closed form, one trial, the real recordings' folds."""

from __future__ import annotations

import numpy as np

from bayescal.io import read_recording
from bayescal.machines.files import load_machine

from ..conftest import ROOT
from .conftest import load_study

dc = load_study("discrepancy_coverage")
rd = load_study("real_discrepancy", siblings=True)


def test_the_sag_is_a_cantilever_along_gravity():
    machine = load_machine(dc.MACHINE)
    rng = np.random.default_rng(0)
    q = machine.sample_q(20, rng)
    rigid = machine.forward(q, None).position
    bent, aux = dc._mismatch("bending", machine, np.zeros(machine.n_params), q, np.random.default_rng(1))
    tilt = np.radians(aux["tilt_deg"])
    g = np.column_stack([np.zeros(20), np.sin(tilt), -np.cos(tilt)])
    d = bent - rigid
    along = np.einsum("ni,ni->n", d, g)
    np.testing.assert_allclose(d, along[:, None] * g, atol=1e-9)  # along gravity only
    r = np.linalg.norm(rigid - np.einsum("ni,ni->n", rigid, g)[:, None] * g, axis=1) / 1000.0
    np.testing.assert_allclose(along, dc.BEND_MM_PER_M3 * r**3, rtol=1e-9)  # k r^3 (r in m)


def test_a_clean_trial_keeps_no_discrepancy():
    t = dc.trial("clean", 0)
    assert not t.kept and t.err_on == t.err_off and 0.8 <= t.cov_on <= 1.0


def test_real_positioner_folds_with_the_discrepancy():
    m = load_machine(ROOT / "examples" / "positioner" / "machine.toml")
    r = read_recording(ROOT / "examples" / "positioner" / "recording.csv")
    res = rd.run("positioner", m, r.subset(np.arange(0, r.n_poses, 2)), 3, modes=("auto",))
    assert 0.8 <= res["auto"]["coverage_90"] <= 1.0
    assert res["auto"]["mean_error_mm"] < 0.3  # the geometry alone leaves 0.38 mm (studies/data/real_discrepancy.json)
