"""Blind run: hand-written distance, height and ballbar recordings (docs/formats.md section 6).

Rows are written as another program would (``handwritten.py``): the measure column in any
place, empty ``b_q*`` cells on height and ballbar rows, optional ``pivot`` and
``sigma_position`` columns, an auxiliary channel. Values from the spec's kinematics.
"""

from __future__ import annotations

import numpy as np
import pytest

from .blind import answer, check_parameters, diagnose_checked, identify_map, read_prs3, run
from .handwritten import draw_q, prs3_nominal, prs3_perturbed, prs3_tool, prs3_toml, write_csv

NOM = prs3_nominal()
TRUE = prs3_perturbed(NOM, 4)
SIG = 0.002


def _rows(seed: int, *, pivots: bool, order: str = "spec", value_unit: str = ""):
    """Distance, height and ballbar rows; returns header and rows of text cells."""
    rng = np.random.default_rng(seed)
    qa = draw_q(NOM.q_limits, 60, seed)
    qb = draw_q(NOM.q_limits, 60, seed + 1)
    pivot_pts = {"P1": np.array([10.0, -20.0, 60.0]), "P2": np.array([-40.0, 30.0, 40.0])}
    out = []
    for i in range(60):
        pa = prs3_tool(TRUE, qa[i])[0]
        kind = ("distance", "height", "ballbar")[i % 3]
        piv = ""
        if kind == "distance":
            v = np.linalg.norm(pa - prs3_tool(TRUE, qb[i])[0])
        elif kind == "height":
            v = pa[2]
        else:
            piv = "P1" if (i // 3) % 2 == 0 or not pivots else "P2"
            v = np.linalg.norm(pa - pivot_pts[piv])
        v += rng.normal(0, SIG)
        factor = 1e3 if value_unit == "_um" else 1.0
        out.append(dict(measure=kind, a=qa[i], b=qb[i] if kind == "distance" else None, value=v * factor, pivot=piv,
                        temp_C=20.0 + 0.01 * i, sigma_position=SIG * factor))
    cols = ["measure"] + [f"a_q{k}" for k in (1, 2, 3)] + [f"b_q{k}" for k in (1, 2, 3)] + ["value" + value_unit]
    if pivots:
        cols.append("pivot")
    cols += ["temp_C", "sigma_position" + value_unit]
    if order == "shuffled":
        cols = ["temp_C", "value" + value_unit, "b_q2", "a_q3", "measure", "b_q1", "a_q1", "b_q3", "a_q2",
                "sigma_position" + value_unit] + (["pivot"] if pivots else [])
    rows = []
    for r in out:
        cell = {"measure": r["measure"], "value" + value_unit: f"{r['value']:.9f}", "pivot": r["pivot"],
                "temp_C": f"{r['temp_C']:.3f}", "sigma_position" + value_unit: f"{r['sigma_position']:g}"}
        for k in range(3):
            cell[f"a_q{k + 1}"] = f"{r['a'][k]:.6f}"
            cell[f"b_q{k + 1}"] = "" if r["b"] is None else f"{r['b'][k]:.6f}"
        rows.append([cell[c] for c in cols])
    return cols, rows


def _max_error(cal_path) -> tuple[float, float]:
    cal, _ = read_prs3(cal_path)
    q = draw_q(NOM.q_limits, 12, 77)
    # constraints do not fix where the machine sits in x, y or how it is turned about z:
    # compare what they measure, distances between tool points and heights
    def rel(m):
        p = np.array([prs3_tool(m, qi)[0] for qi in q])
        return np.r_[np.linalg.norm(p[1:] - p[:-1], axis=1), p[:, 2]]
    t = rel(TRUE)
    return float(np.max(np.abs(rel(cal) - t))), float(np.max(np.abs(rel(NOM) - t)))


@pytest.mark.parametrize(("order", "pivots", "fmt", "unit"), [
    ("spec", False, {}, ""),
    ("shuffled", True, dict(crlf=True, bom=True, trailing_ws=True), ""),
    ("spec", True, dict(final_newline=False), "_um"),
])
def test_identify_constraint_recording(tmp_path, capsys, order, pivots, fmt, unit):
    (tmp_path / "m.toml").write_text(prs3_toml(NOM, variant="shuffled"))
    header, rows = _rows(5, pivots=pivots, order=order, value_unit=unit)
    write_csv(tmp_path / "c.csv", header, rows, **fmt)
    a = identify_map(capsys, tmp_path / "c.csv", tmp_path / "m.toml", tmp_path / "a.json", "--write-machine",
                     tmp_path / "cal.toml")
    assert isinstance(a["machine"], str) and a["method"] == "map"
    check_parameters(a["parameters"])
    assert a["outliers"] == []
    assert 0 <= a["rms_after"]["position"] < 2 * SIG < a["rms_before"]["position"]
    names = {p["name"] for p in a["parameters"]}
    assert any(n.startswith("pivot") or "pivot" in n for n in names), "ballbar pivots are fitted parameters"
    cal_err, nom_err = _max_error(tmp_path / "cal.toml")
    assert cal_err < 0.25 * nom_err


def test_diagnose_clean_constraint_recording_says_none(tmp_path, capsys):
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    header, rows = _rows(6, pivots=False)
    write_csv(tmp_path / "c.csv", header, rows)
    a = diagnose_checked(capsys, tmp_path / "c.csv", tmp_path / "m.toml", tmp_path / "d.json", "--write-machine",
                         tmp_path / "cal.toml")
    assert a["verdict"] == "none"
    read_prs3(tmp_path / "cal.toml")


def test_outlier_row_named_by_line(tmp_path, capsys):
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    header, rows = _rows(7, pivots=False)
    iv = header.index("value")
    rows[20][iv] = f"{float(rows[20][iv]) + 0.3:.9f}"  # line 22
    write_csv(tmp_path / "c.csv", header, rows, crlf=True)
    identify_map(capsys, tmp_path / "c.csv", tmp_path / "m.toml", tmp_path / "a.json", ok=(0, 1))
    assert [o["line"] for o in answer(tmp_path / "a.json")["outliers"]] == [22]


@pytest.mark.parametrize(("bad", "expect"), [
    ("measure=angle", ["line 3", "measure"]),
    ("b_q1=", ["line 2", "b_q1"]),
    ("b_q2=7.5", ["line 3", "b_q2"]),
    ("value=abc", ["line 4", "value"]),
])
def test_bad_constraint_rows_are_named(tmp_path, capsys, bad, expect):
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    header, rows = _rows(8, pivots=False)
    col, val = bad.split("=")
    line = {"measure": 3, "b_q1": 2, "b_q2": 3, "value": 4}[col]
    rows[line - 2][header.index(col)] = val
    write_csv(tmp_path / "c.csv", header, rows)
    rc, _, err = run(capsys, "identify", tmp_path / "c.csv", "--machine", tmp_path / "m.toml",
                     "--json", tmp_path / "a.json", "--write-machine", tmp_path / "cal.toml")
    assert rc == 2
    assert "c.csv" in err and all(e in err for e in expect), err
    assert not (tmp_path / "a.json").exists() and not (tmp_path / "cal.toml").exists()


@pytest.mark.parametrize(("rename", "expect"), [
    ({"value": "value_deg"}, ["value_deg", "length", "value_um"]),
    ({"temp_C": "value_um"}, ["value_um", "same quantity", "'value'"]),
    ({"sigma_position": "sigma_position_rad"}, ["sigma_position_rad", "length"]),
])
def test_bad_unit_suffixes_are_named(tmp_path, capsys, rename, expect):
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    header, rows = _rows(9, pivots=False)
    header = [rename.get(h, h) for h in header]
    write_csv(tmp_path / "c.csv", header, rows)
    rc, _, err = run(capsys, "identify", tmp_path / "c.csv", "--machine", tmp_path / "m.toml",
                     "--json", tmp_path / "a.json")
    assert rc == 2 and "c.csv" in err and "line 1" in err and all(e in err for e in expect), err
    assert not (tmp_path / "a.json").exists()
