"""The seed-2 study (LS vs RE vs TSVD) in its quick mode: runs, writes its outputs, its findings hold."""

import json
import os
import subprocess
import sys

from tests.conftest import ROOT


def test_seed2_quick(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, str(ROOT / "studies" / "seed2_ls_re_tsvd.py"), "--quick", "--reps", "1", "--out", str(tmp_path)],
        env=env, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["checks"] and all(c["holds"] for c in summary["checks"])
    sits = summary["situations"]
    assert {"3-PRS 6-DOF", "3-PRS 5-DOF"} <= set(sits)
    five = sits["3-PRS 5-DOF"]
    assert "ill-posed" in five["ls_seed_set_message"] and five["n_reduced_set"] < five["n_seed_set"]
    for s in sits.values():
        err = s["output_error_mm"]
        assert err["RE (auto)"] < 0.2 * s["before_rms_position_mm"] and err["TSVD (auto)"] < 0.2 * s["before_rms_position_mm"]
        # the repetitions' linearised curves agree with Gauss-Newton where the ratios are decided
        assert s["linearised_vs_gauss_newton_rel_gap"]["best_and_default"] < 0.02
        for method in ("ridge", "tsvd"):
            assert all(st["median"] >= 1.0 - 1e-12 for st in s[f"ratios_{method}"].values())
            a = s["attainable"][method]
            assert 0.0 < a["ceiling"] <= 1.0 and set(a["fixed_rates"]) <= set(s[f"ratios_{method}"])
    for name in ("3prs_6dof_output_error.png", "3prs_5dof_history.png", "3prs_6dof_rules_ridge.png",
                 "repetitions_ratio.png", "findings.md", "3prs_table_chain.csv", "3prs_table_output.md"):
        assert (tmp_path / name).stat().st_size > 500, name
    assert isinstance(summary["target_attainable_by_any_rule"], bool)
    assert "What any rule can attain" in (tmp_path / "findings.md").read_text()
    assert "RU-PUS-PRS" in (tmp_path / "findings.md").read_text()  # runs it, or says why not
