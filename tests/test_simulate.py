"""bayescal/simulate.py: what it refuses, and says, when the tolerances drawn from cannot make a machine."""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.errors import InputError
from bayescal.simulate import simulate_recording


def test_tolerances_beyond_the_limit_are_refused_before_drawing(prs3):
    # --tolerance-scale 1e300 drew errors of 1e298 mm and the kinematics' SVD failed (LinAlgError, a traceback)
    with pytest.raises(InputError, match=r"tolerance: expected one-sigma errors from 0 to 1e\+09 .*got up to 5e\+298"):
        simulate_recording(prs3, 5, seed=1, tolerance=prs3.tolerance * 1e300)


def test_a_true_machine_that_cannot_assemble_says_why(prs3):
    # "could not find 5 solvable poses within q_limits" blamed q_limits, where the nominal machine solves
    with pytest.raises(InputError, match=r"could not find 5 solvable poses within q_limits; the nominal machine solves "
                       r"there, the true one drawn from the tolerances does not"):
        simulate_recording(prs3, 5, seed=1, tolerance=prs3.tolerance * 1e5)
    assert simulate_recording(prs3, 5, seed=1).recording.n_poses == 5
    assert np.isfinite(simulate_recording(prs3, 5, seed=1, tolerance=prs3.tolerance * 0).theta_true).all()
