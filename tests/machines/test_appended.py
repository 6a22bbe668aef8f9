"""The view with appended nuisance parameters (bayescal/machines/appended.py)."""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.constraints.model import PIVOT_TOLERANCE, PivotAugmented
from bayescal.machines.files import load_machine
from bayescal.machines.appended import AppendedParameters

from ..conftest import PRS3_FILE


def test_a_view_must_say_what_it_appends():
    with pytest.raises(TypeError):
        AppendedParameters(load_machine(PRS3_FILE))


def test_appended_parameters_do_not_move_the_tool_and_leave_the_machine_file():
    m = load_machine(PRS3_FILE)
    v = PivotAugmented(m, ("1",))
    assert v.n_params == m.n_params + 3 and v.layout.names[-3:] == ("pivot.1.x", "pivot.1.y", "pivot.1.z")
    np.testing.assert_array_equal(v.tolerance[-3:], PIVOT_TOLERANCE)
    q = m.sample_q(4, np.random.default_rng(0))
    theta = np.concatenate([m.tolerance * 0.1, [5.0, -3.0, 2.0]])
    p = v.forward(q, theta)
    np.testing.assert_array_equal(p.position, m.forward(q, theta[: m.n_params]).position)
    J = v.tool_jacobian(q, theta, p)
    assert J.shape == (4, 6, v.n_params) and not J[:, :, m.n_params:].any()
    assert v.to_toml(theta) == m.to_toml(theta[: m.n_params])
    with pytest.raises(Exception, match="theta: expected shape"):
        v.check_theta(np.zeros(m.n_params))
