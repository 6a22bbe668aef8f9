"""``bayescal identify`` with a gross pose: outliers by CSV line in the JSON and the report, for every method."""

import csv
import json

import numpy as np
import pytest

from bayescal.cli import main
from tests.conftest import PRS3_FILE, ROOT

REC = ROOT / "examples" / "prs3" / "recording.csv"
GROSS_LINE = 13  # +0.3 mm in x on this line: unweighted --lam auto picks lambda ~ 4e-7 and diverges


@pytest.fixture(scope="module")
def gross(tmp_path_factory):
    rows = list(csv.reader(REC.read_text().splitlines()))
    rows[GROSS_LINE - 1][3] = repr(float(rows[GROSS_LINE - 1][3]) + 0.3)
    path = tmp_path_factory.mktemp("gross") / "gross.csv"
    with path.open("w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    return path


def _run(rec, tmp_path, *extra):
    out = tmp_path / "a.json"
    code = main(["identify", str(rec), "--machine", str(PRS3_FILE), "--json", str(out), "--quiet", *extra])
    return code, json.loads(out.read_text())


def test_lam_auto_is_not_derailed_by_one_gross_pose(gross, tmp_path):
    code, ans = _run(gross, tmp_path, "--method", "ridge", "--lam", "auto")
    assert code == 0 and ans["success"]
    _, clean = _run(REC, tmp_path, "--method", "ridge", "--lam", "auto")
    # a sensible lambda: that of the clean recording within a factor of 2 (the unweighted rules pick 4e-7)
    assert 0.5 < ans["lam"] / clean["lam"] < 2
    assert [o["line"] for o in ans["outliers"]] == [GROSS_LINE]
    o = ans["outliers"][0]
    assert o["statistic"] > 1000 and o["p_value"] < 1e-10
    assert ans["outlier_handling"].startswith("down-weighted (Student-t IRLS")
    # the calibration is that of the clean recording to within its uncertainty
    free = [i for i, p in enumerate(clean["parameters"]) if p["std"] is not None]
    v = np.array([ans["parameters"][i]["value"] for i in free])
    c, s = (np.array([clean["parameters"][i][k] for i in free]) for k in ("value", "std"))
    assert np.max(np.abs(v - c) / s) < 1.0
    assert clean["outliers"] == [] and clean["outlier_handling"].startswith("none flagged")
    # every pose's values are there for reports and figures
    assert len(ans["outlier_test"]["statistic"]) == 36 and ans["outlier_test"]["line"][0] == 2


@pytest.mark.parametrize("method", [["--method", "tsvd", "--k", "auto"], ["--method", "map", "--robust", "huber"]])
def test_other_methods_name_the_gross_pose(gross, tmp_path, method):
    code, ans = _run(gross, tmp_path, *method)
    assert code == 0
    assert [o["line"] for o in ans["outliers"]] == [GROSS_LINE]
    assert ans["outlier_handling"].startswith("down-weighted")
    assert ans["rms_after"]["position"] < 0.06  # the gross pose alone: 0.3 / sqrt(36) = 0.05 mm


def test_kalman_is_not_derailed_by_a_gross_first_pose(tmp_path):
    rows = list(csv.reader(REC.read_text().splitlines()))
    rows[1][4] = repr(float(rows[1][4]) - 0.5)  # the first pose the filter sees, y off by 0.5 mm
    bad = tmp_path / "first.csv"
    with bad.open("w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    _, clean = _run(REC, tmp_path, "--method", "kalman")
    code, ans = _run(bad, tmp_path, "--method", "kalman")
    _, off = _run(bad, tmp_path, "--method", "kalman", "--robust", "off")
    assert code == 0 and [o["line"] for o in ans["outliers"]] == [2]
    v, c, o = (np.array([p["value"] for p in a["parameters"]]) for a in (ans, clean, off))
    s = np.array([p["std"] for p in clean["parameters"] if p["std"] is not None])
    free = np.array([p["std"] is not None for p in clean["parameters"]])
    assert np.max(np.abs(v - c)[free] / s) < 1.0
    assert np.max(np.abs(o - c)[free] / s) > 2.0  # without the weights the filter is pulled away
    assert np.mean(ans["history"]["nis"][1:]) < 1.5 * 6


def test_report_lists_flagged_poses_and_off_keeps_them(gross, tmp_path, capsys):
    assert main(["identify", str(gross), "--machine", str(PRS3_FILE), "--method", "map", "--robust", "off",
                 "--prior-scale", "tolerance"]) == 0  # (the empirical scale would follow the gross pose: implausible)
    text = capsys.readouterr().out
    assert "outliers        studentised deleted residual" in text and "kept: no robust refit" in text
    assert main(["identify", str(gross), "--machine", str(PRS3_FILE), "--method", "map"]) == 0
    text = capsys.readouterr().out
    row = next(line for line in text.splitlines() if line.strip().startswith(f"{GROSS_LINE} "))
    assert float(row.split()[1]) > 1000  # line, statistic, p (family), p (single), Cook, weight
    assert "1 pose(s) no model of the machine explains: down-weighted" in text


def test_bad_outlier_options_are_input_errors(gross, capsys):
    assert main(["identify", str(gross), "--machine", str(PRS3_FILE), "--method", "map", "--outlier-alpha", "2"]) == 2
    assert "--outlier-alpha" in capsys.readouterr().err
    assert main(["identify", str(gross), "--machine", str(PRS3_FILE), "--method", "map", "--nu", "0"]) == 2
    assert "--nu" in capsys.readouterr().err


def test_a_mismatch_of_every_pose_is_not_called_outliers(tmp_path):
    """2 mm added to every x (a tracker frame offset): poses stand out in the robust fit too; not outliers."""
    rows = list(csv.reader(REC.read_text().splitlines()))
    for r in rows[1:]:
        r[3] = repr(float(r[3]) + 2.0)
    rec = tmp_path / "offset.csv"
    with rec.open("w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    code, ans = _run(rec, tmp_path, "--method", "map")
    _, off = _run(rec, tmp_path, "--method", "map", "--robust", "off")
    assert ans["outliers"] == []
    # and the calibration is refused as implausible, with the wrong frame named (docs/real-instruments.md)
    assert code == 1 and ans["plausible"] is False and any("wrong frame" in c for c in ans["plausibility"]["causes"])
    assert "model mismatch" in ans["outlier_handling"] and "--frame fit" in ans["outlier_handling"]
    assert [p["value"] for p in ans["parameters"]] == [p["value"] for p in off["parameters"]]  # the unweighted fit
