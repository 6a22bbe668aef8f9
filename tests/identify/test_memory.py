"""identify refuses a recording whose arrays would not fit in memory, before computing (issue 30, item 10)."""

from __future__ import annotations

import pytest

import bayescal
from bayescal import limits
from bayescal.errors import InputError
from bayescal.identify import identify

from ..conftest import PRS3_FILE, ROOT


def test_identify_refuses_what_would_not_fit(monkeypatch):
    model = bayescal.load(PRS3_FILE, ROOT / "examples" / "prs3" / "recording.csv").fit_model
    need = 10.0 * 8 * model.n_poses * model.dof * model.n_params
    monkeypatch.setattr(limits, "memory_budget", lambda: need / 2)
    with pytest.raises(InputError, match=r"216 measured components x 36 parameters needs about .*every k-th row"):
        identify(model, method="map")
    monkeypatch.setattr(limits, "memory_budget", lambda: need * 2)
    assert identify(model, method="map").success
