"""Stacked geometries (a sampler's walkers over every pose): found in the parameter rows, and the same poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bayescal.machines.base import geometry_blocks
from bayescal.machines.files import load_machine
from bayescal.machines.framed import Frame, InstrumentFrame

ROOT = Path(__file__).resolve().parents[2]


def test_geometry_blocks_finds_runs_of_equal_rows_only_where_they_pay():
    theta = np.repeat(np.arange(12.0).reshape(3, 4), [10, 14, 8], axis=0)
    starts, runs = geometry_blocks(theta)
    np.testing.assert_array_equal(starts, [0, 10, 24])
    np.testing.assert_array_equal(runs, [10, 14, 8])
    # one differing entry starts a run of its own
    theta[15, 2] += 1e-12
    np.testing.assert_array_equal(geometry_blocks(theta)[1], [10, 5, 1, 8, 8])
    # rows that mostly differ (one geometry per pose), or too few rows: none
    assert geometry_blocks(np.arange(40.0).reshape(10, 4)) is None
    assert geometry_blocks(np.zeros((3, 4))) is None


def _machines():
    prs3 = load_machine(ROOT / "examples" / "prs3" / "machine.toml")
    positioner = load_machine(ROOT / "examples" / "positioner" / "machine.toml")
    rng = np.random.default_rng(0)
    frame = Frame(rng.normal(size=3) * 50, Rotation.from_rotvec(rng.normal(size=3) * 0.3).as_matrix())
    return {"prs3": prs3, "positioner framed": InstrumentFrame(positioner, frame, fit=True)}


@pytest.mark.parametrize("name", ["prs3", "positioner framed"])
def test_stacked_walkers_give_each_walker_s_own_poses(name):
    # what a vectorised log posterior asks for: walkers x poses rows, each walker's geometry repeated over the
    # poses; the per-walker geometry (computed once per block) must give the poses of one call per walker
    m = _machines()[name]
    rng = np.random.default_rng(1)
    q = m.sample_q(9, rng)
    walkers = rng.normal(size=(4, m.n_params)) * m.tolerance
    stacked = m.forward(np.tile(q, (4, 1)), np.repeat(walkers, 9, axis=0))
    assert stacked.success.all()
    for k, th in enumerate(walkers):
        one = m.forward(q, th)
        np.testing.assert_allclose(stacked.position[9 * k : 9 * k + 9], one.position, rtol=0, atol=1e-9)
        np.testing.assert_allclose(stacked.rotation[9 * k : 9 * k + 9], one.rotation, rtol=0, atol=1e-12)
    # the walkers differ: a block path that reused one walker's geometry for all would fail above
    assert np.abs(stacked.position[:9] - stacked.position[9:18]).max() > 1e-4
