"""Every bundled example machine file loads and passes the conformance check."""

from pathlib import Path

import numpy as np
import pytest

from bayescal.machines.check import check_machine
from bayescal.machines.files import load_machine
from tests.conftest import ROOT

FILES = sorted(p for p in (ROOT / "examples").glob("*/machine.toml"))
#: The examples with a q_limits box (decided when the tests are collected: a machine without one has
#: no box to be truthful about, so it is not a case of that test rather than a skipped one).
FILES_WITH_LIMITS = [p for p in FILES if load_machine(p).q_limits is not None]


@pytest.mark.parametrize("path", FILES, ids=lambda p: Path(p).parent.name)
def test_example_machine_passes_check_machine(path):
    m = load_machine(path)
    assert check_machine(m) == [], path


def test_some_examples_have_q_limits():
    assert FILES_WITH_LIMITS, "no example machine declares q_limits: the box test below checks nothing"


@pytest.mark.parametrize("path", FILES_WITH_LIMITS, ids=lambda p: Path(p).parent.name)
def test_actuator_box_reachable_is_truthful(path):
    """A machine declaring its q_limits box all reachable assembles at the box's corners and inside it;
    one declaring it not has somewhere in the box where it does not (else tool-space grids are imposed for nothing)."""
    m = load_machine(path)
    lo, hi = m.q_limits[:, 0], m.q_limits[:, 1]
    n = m.n_actuators
    rng = np.random.default_rng(0)
    corners = lo + (hi - lo) * (rng.random((64, n)) < 0.5)  # random corners (2**n of them can be many)
    inner = lo + (hi - lo) * rng.random((64, n))
    ok = np.concatenate([m.forward(corners).success, m.forward(inner).success])
    if m.actuator_box_reachable:
        assert ok.all(), f"{path}: declares its q_limits box reachable, but {np.sum(~ok)} of 128 vectors do not assemble"
    else:
        assert not ok.all(), f"{path}: declares its q_limits box not all reachable, yet every vector drawn assembles"
