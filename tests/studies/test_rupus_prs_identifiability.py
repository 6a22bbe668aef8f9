import json

from tests.studies.conftest import load_study


def test_quick_run_writes_the_table(tmp_path):
    mod = load_study("rupus_prs_identifiability")
    assert mod.main(["--quick", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "rupus_prs_identifiability.json").read_text())
    ranks = {(c["geometry"], c["dof"]): c["rank"] for c in res["cases"]}
    assert ranks[("nominal", 6)] == 26 and ranks[("nominal", 5)] == 25 and ranks[("nominal", 3)] == 23
    md = (tmp_path / "rupus_prs_identifiability.md").read_text()
    assert "| nominal | 6-DOF | 26 |" in md and "chain3.universal_axis_link.tilt_y" in md
