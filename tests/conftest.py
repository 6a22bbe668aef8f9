"""Shared fixtures: the bundled 3-PRS machine and seeded simulated recordings."""

from __future__ import annotations

import os
import zlib

# Small dense problems: BLAS threads only add contention on a 2-core machine (set before numpy loads).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
# No progress lines (bayescal.progress): on a loaded machine a command may run past their delay, and tests
# compare what the commands write on stderr (tests/test_progress.py turns them back on)
os.environ.setdefault("BAYESCAL_PROGRESS", "off")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from bayescal.machines.files import load_machine
from bayescal.simulate import simulate_recording

ROOT = Path(__file__).resolve().parents[1]
PRS3_FILE = ROOT / "examples" / "prs3" / "machine.toml"


@pytest.fixture(scope="session")
def prs3():
    return load_machine(PRS3_FILE)


@pytest.fixture
def rng(request):
    """A generator of the test's own, seeded from its id: its draws do not depend on which tests ran before it.

    (A session-wide generator made a test's problem depend on the tests collected before it, so adding a
    test elsewhere could turn a fragile draw into a failure.)
    """
    return np.random.default_rng([20261122, zlib.crc32(request.node.nodeid.encode())])


@pytest.fixture(scope="session")
def sim6(prs3):
    return simulate_recording(prs3, 36, seed=11, dof=6)
