"""studies/delta_klipper.py --quick on the FLSUN Q5 (GPL-3.0 data read from ../shared, skipped without it)."""

import json
import os
from pathlib import Path

import pytest

from tests.studies.conftest import load_study

ROOT = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get("BAYESCAL_SHARED", ROOT / ".." / "shared"))
DATA = SHARED / "data" / "real" / "delta_flsun_q5"
pytestmark = pytest.mark.skipif(not (DATA / "printer-post-calibration.cfg").exists(), reason="../shared data not present")


def test_quick_run_writes_tables_and_figures(tmp_path):
    mod = load_study("delta_klipper")
    assert mod.main(["--quick", "--out", str(tmp_path), "--data", str(DATA)]) == 0
    res = json.loads((tmp_path / "delta_klipper.json").read_text())
    ida = {(c["data"], c["parameters"]): c for c in res["identifiability"]}
    # heights + distances: Klipper's ten keys have rank 9, angle_c the rotation about z
    k = ida[("heights + distances", "Klipper")]
    assert k["rank"] == 9 and k["fixed"] == ["angle_c"]
    # heights alone cannot tell the three arm lengths from the rest
    assert {"arm_length_b", "arm_length_c"} <= set(ida[("heights only", "Klipper")]["fixed"])
    # bayescal's 21: the rigid motions in the bed plane and the effector offset stay free
    b = ida[("heights + distances", "bayescal")]
    assert b["rank"] == 15 and {"tool.point.x", "tool.point.y", "tool.point.z"} <= set(b["fixed"])
    real = res["loo_real"][0]["summary"]
    assert real["Klipper"]["in_sample_rms"] < real["Klipper"]["loo_rms"]
    assert res["plans"][0]["measure"] == "height" and res["plans"][1]["n"] == 6
    md = (tmp_path / "delta_klipper.md").read_text()
    assert "## Leave-one-measurement-out on the real printer" in md and "arm_length_c" in md
    assert (tmp_path / "delta_klipper_sv.png").stat().st_size > 1000
    assert (tmp_path / "delta_klipper_loo.png").stat().st_size > 1000
