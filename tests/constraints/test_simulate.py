"""simulate_ballbar refuses circles the nominal machine cannot command within q_limits, and says what fits."""

import re
from pathlib import Path

import numpy as np
import pytest

from bayescal.errors import InputError
from bayescal.io.constraints import DEFAULT_PIVOT
from bayescal.machines.files import load_machine
from bayescal.constraints.simulate import circle_points, simulate_ballbar

ROOT = Path(__file__).resolve().parents[2]
PRS3 = ROOT / "examples" / "prs3" / "machine.toml"


def test_a_circle_leaving_q_limits_is_refused_with_what_fits():
    m = load_machine(PRS3)
    with pytest.raises(InputError) as exc:
        simulate_ballbar(m, 30.0, n_points=24, planes=("xz",), sigma=0.0)
    msg = str(exc.value)
    assert "radius 30 mm" in msg and "plane xz" in msg and "of 24 points" in msg and "q_limits" in msg
    assert "--ballbar" in msg and "--pivot" in msg
    fit = float(re.search(r"at most about ([0-9.]+) mm", msg).group(1))
    assert 5.0 < fit < 30.0
    # the suggestion holds: its circle is written, every reading commanded within q_limits ...
    sim = simulate_ballbar(m, fit, n_points=24, planes=("xz",), sigma=0.0, theta=np.zeros(m.n_params))
    q = sim.recording.qa
    lo, hi = m.q_limits[:, 0], m.q_limits[:, 1]
    assert ((q >= lo) & (q <= hi)).all()
    # ... and puts the nominal tool point on the circle asked for (noise-free readings = the radius)
    pivot = sim.pivots[DEFAULT_PIVOT]
    np.testing.assert_allclose(m.forward(q).position, circle_points(pivot, fit, "xz", 24), atol=1e-8)
    np.testing.assert_allclose(sim.recording.value, fit, atol=1e-8)
    # and a little more than it does not fit (the limit found is a real edge, not a timid guess)
    with pytest.raises(InputError, match="plane xz"):
        simulate_ballbar(m, fit + 0.3, n_points=24, planes=("xz",), sigma=0.0)


def test_an_unreachable_circle_counts_its_points():
    # the RASPM-2T1R moves its tool point in x and z only: every point of an xy circle off the pivot is unreachable
    m = load_machine(ROOT / "examples" / "raspm" / "machine.toml")
    with pytest.raises(InputError, match=r"plane xy: .*cannot be reached.*plane it moves in"):
        simulate_ballbar(m, 3.0, n_points=4, planes=("xy",), sigma=0.0)


@pytest.mark.parametrize("planes", [("xy", "xy"), ()])
def test_planes_must_be_distinct_and_given(planes):
    # --planes xy,xy ran the same circle twice, silently
    m = load_machine(ROOT / "examples" / "delta" / "machine.toml")
    with pytest.raises(InputError, match="planes: expected distinct planes from xy, xz, yz"):
        simulate_ballbar(m, 20.0, n_points=8, planes=planes, sigma=0.0)
