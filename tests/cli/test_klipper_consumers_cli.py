"""The real FLSUN Q5 delta printer (GPL-3.0 data, read from ../shared, never copied): its Klipper
calibration read by `bayescal klipper`, then diagnosed, compared on its own 7 heights and 12
distances, and gridded."""

import json
import os
from pathlib import Path

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.effects import EFFECTS

# the checkout sits beside shared/ (<clone>/../shared); BAYESCAL_SHARED points elsewhere (a git worktree)
SHARED = Path(os.environ.get("BAYESCAL_SHARED", Path(__file__).resolve().parents[2] / ".." / "shared"))
POST = SHARED / "data" / "real" / "delta_flsun_q5" / "printer-post-calibration.cfg"
pytestmark = pytest.mark.skipif(not POST.exists(), reason="../shared/data/real/delta_flsun_q5 not present")


@pytest.fixture(scope="module")
def q5(tmp_path_factory):
    d = tmp_path_factory.mktemp("q5")
    assert main(["klipper", str(POST), "--out", str(d), "--quiet"]) == 0
    return d / "machine.toml", d / "recording.csv", d


def test_diagnose_the_printer(q5):
    machine, rec, d = q5
    out = d / "diag.json"
    assert main(["diagnose", str(rec), "--machine", str(machine), "--json", str(out), "--quiet"]) == 0
    ans = json.loads(out.read_text())
    assert ans["verdict"] in ("none", "unexplained", *EFFECTS)
    assert ans["n_poses"] == 19 and ans["dof"] == 1
    assert all(2 <= o["line"] <= 20 for o in ans["outliers"])
    # the noise yardstick is the recording's sigma_position column (0.02 mm probe heights, 0.05 mm
    # caliper distances), row by row, not the machine file's single value
    sig = [float(line.split(",")[8]) for line in rec.read_text().splitlines()[1:]]
    assert rec.read_text().splitlines()[0].split(",")[8] == "sigma_position" and len(set(sig)) == 2
    assert ans["rms_noise"] == pytest.approx(float(np.sqrt(np.mean(np.square(sig)))), rel=1e-12)


def test_compare_on_the_printers_own_measurements(q5):
    machine, rec, d = q5
    out = d / "cmp.json"
    assert main(["compare", "--machine", str(machine), "--recording", str(rec), "--methods", "map,tsvd", "--trials", "4",
                 "--eval-poses", "20", "--json", str(out), "--quiet"]) == 0
    ans = json.loads(out.read_text())
    assert ans["config"]["n_poses"] == 19 and ans["config"]["dof"] == 1
    # printers drawn from the tolerances: the calibration from 19 readings beats the uncalibrated geometry
    assert ans["summary"]["map"]["n"] == 4
    assert ans["summary"]["map"]["median"] < ans["nominal"]["median"]


def test_grid_of_the_printer_in_tool_space(q5):
    machine, rec, d = q5
    out = d / "grid.json"
    assert main(["grid", str(rec), "--machine", str(machine), "--space", "tool", "--nodes", "3", "--json", str(out), "--quiet"]) == 0
    ans = json.loads(out.read_text())
    assert ans["space"] == "tool" and ans["n_nodes"] == 27 and ans["max_std_mm"] > 0
