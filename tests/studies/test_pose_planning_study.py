"""The pose-planning study's --quick mode runs end to end and its units check holds."""

import csv
import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_quick_study_writes_tables_figure_and_invariant_rankings(tmp_path):
    spec = importlib.util.spec_from_file_location("pose_planning", ROOT / "studies" / "pose_planning.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--quick", "--out", str(tmp_path)]) == 0
    for name in ("pose_planning.csv", "units_ranking.csv", "summary.json", "pose_planning.md", "pose_planning.png"):
        assert (tmp_path / name).exists(), name
    with (tmp_path / "units_ranking.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    scaled = [r for r in rows if r["scaling"] in ("tolerance", "candidates")]
    assert scaled and all(float(r["kendall_tau"]) > 1 - 1e-12 for r in scaled)
    assert all(float(r["max_rel_change"]) < 1e-8 for r in scaled)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert set(summary["findings"]) == {f"{d}dof_{m}_planned-{c}" for d in (6, 5) for m in ("ridge", "ls") for c in "DI"}
    with (tmp_path / "pose_planning.csv").open() as fh:
        table = list(csv.DictReader(fh))
    assert {r["design"] for r in table} == {"planned-D", "planned-I", "random"}
    # every design of a trial is evaluated on the same true machine and fresh poses: one row per
    # (dof, trial, n, design), and the paired table pairs every trial
    with (tmp_path / "trials.csv").open() as fh:
        trials = list(csv.DictReader(fh))
    assert len(trials) == 2 * 3 * (2 * 3 + 2)  # dof x trials x (2 planned x 3 pose counts + random at 18, 36)
    # least squares on random sets only at 36 poses: not run (None) at 18, which is not a failure
    r18 = [r for r in table if r["design"] == "random" and r["n_poses"] == "18"]
    assert len(r18) == 2 and all(r["ls_failures"] == "-1" and r["failures"] != "-1" for r in r18)
    assert all(p["pairs"] + p["dropped"] == 3 for p in summary["paired"])
    assert [b["dof"] for b in summary["linear_bound"]] == [6, 5]
    assert all(b["any_plan_lower_rms"] <= b["i_plan_predicted_rms"] for b in summary["linear_bound"])
