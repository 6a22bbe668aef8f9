"""Every bundled example machine file loads and passes the conformance check."""

from pathlib import Path

import pytest

from bayescal.machines import check_machine, load_machine
from tests.conftest import ROOT

FILES = sorted(p for p in (ROOT / "examples").glob("*/machine.toml"))


@pytest.mark.parametrize("path", FILES, ids=lambda p: Path(p).parent.name)
def test_example_machine_passes_check_machine(path):
    m = load_machine(path)
    assert check_machine(m) == [], path
