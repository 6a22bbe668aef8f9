"""A batch answer does not depend on the order of the rows (issue #30, item 9): the automatic lambda and k too."""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.identify.calibrate import calibrate
from bayescal.io import read_recording
from bayescal.machines.files import load_machine
from bayescal.measurement import MeasurementModel

from ..conftest import PRS3_FILE, ROOT


@pytest.mark.parametrize("method,kw", [("ridge", {"lam": "auto"}), ("tsvd", {"k": "auto"})])
def test_automatic_rules_choose_the_same_for_any_row_order(method, kw):
    machine = load_machine(PRS3_FILE)
    model = MeasurementModel.from_recording(machine, read_recording(ROOT / "examples" / "prs3" / "recording.csv"))
    a = calibrate(model, method=method, **kw)
    perm = np.random.default_rng(3).permutation(model.n_poses)
    b = calibrate(model.subset(perm), method=method, **kw)
    assert a.choice.value == b.choice.value
    # the same answer to rounding (the issue saw parameters move by up to 0.34 std)
    np.testing.assert_allclose(a.result.theta, b.result.theta, atol=1e-9 * machine.tolerance.max())
    np.testing.assert_allclose(a.result.residuals_after[perm], b.result.residuals_after, atol=1e-9)
