"""The view with appended nuisance parameters (bayescal/machines/appended.py)."""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.constraints.model import PIVOT_TOLERANCE, PivotAugmented
from bayescal.machines.files import load_machine
from bayescal.machines.appended import AppendedParameters
from bayescal.errors import InputError
from bayescal.sensors.mounts import SensorMounts

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


def test_every_appended_view_checks_theta_rows_against_the_poses_as_the_machine_does():
    # review: AppendedParameters had its own copy of Machine.check_theta without the row count, so a pivot or
    # sensor-mounting view took 3 rows of theta for 5 poses where the machine (and every other view) refuses
    m = load_machine(PRS3_FILE)
    for v in (PivotAugmented(m, ("1",)), SensorMounts(m, ("sensor.link.tilt.x",), (1e-3,))):
        assert v.check_theta(np.zeros((5, v.n_params)), 5).shape == (5, v.n_params)
        with pytest.raises(InputError, match="theta: 3 rows for 5 poses"):
            v.check_theta(np.zeros((3, v.n_params)), 5)
        with pytest.raises(InputError, match=rf"theta: expected shape \({v.n_params},\)"):
            v.check_theta(np.zeros(m.n_params))
