"""Blind run: bad hand-written input gives exit code 2, a message naming file, line/key and
what was expected, and no output file (docs/formats.md: "reject what does not fit with a clear
message that names the file, the line or key, and what was expected")."""

from __future__ import annotations

import numpy as np
import pytest

from .blind import run
from .handwritten import draw_q, effect_table, pose_rows, prs3_nominal, prs3_tool, prs3_toml, rows_of, write_csv

NOM = prs3_nominal()
Q = draw_q(NOM.q_limits, 12, 41)
POSES = [prs3_tool(NOM, q) for q in Q]
COLS = pose_rows(Q, np.array([p for p, _ in POSES]), np.array([r for _, r in POSES]), dof=6, sigma=0.005, seed=42)

MACHINE_BREAKS = {
    # name: (text edit of the plain machine file, words the message must hold)
    "misspelt key": (("link_length = 400", "link_lenght = 400", 2), ["link_lenght", "expected", "link_length"]),
    "missing key": (("revolute_axis = [0, 1, 0]\n", "", 1), ["chain[1].revolute_axis", "missing"]),
    "wrong type": (("link_length = 400", 'link_length = "400"', 1), ["chain[1].link_length", "expected", "number"]),
    "short vector": (("point = [0, 0, -100]", "point = [0, -100]", 1), ["tool.point", "expected", "3"]),
    "instrument origin": ((None, "[instrument]\norigin = [1.0, 2.0]\nrotation_vector = [0, 0, 0]\n", 0),
                          ["instrument.origin", "expected"]),
    "unknown effect parameter": ((None, effect_table("backlash", {"backlash.q1": 1.0, "backlash.q2": 1.0,
                                                                  "dead_band.q3": 1.0}), 0),
                                 ["effect.backlash", "dead_band.q3", "expected"]),
    "not toml": (("[tool]", "[tool", 1), ["m.toml", "TOML"]),
}


def _plain_machine() -> str:
    # integers where whole (as the "shuffled" writer does) keep the edits above simple
    return prs3_toml(NOM, variant="shuffled").replace("   # mm", "")


def _outputs(tmp_path):
    return [tmp_path / "a.json", tmp_path / "cal.toml", tmp_path / "rep.html"]


@pytest.mark.parametrize("case", list(MACHINE_BREAKS))
@pytest.mark.parametrize("command", ["identify", "diagnose"])
def test_bad_machine_file(tmp_path, capsys, case, command):
    (old, new, count), words = MACHINE_BREAKS[case]
    text = _plain_machine()
    if old is None:
        text += "\n" + new
    else:
        assert text.count(old) >= count, old
        text = text.replace(old, new, 1) if count == 1 else text.replace(old, new)
    (tmp_path / "m.toml").write_text(text)
    header, rows = rows_of(COLS)
    write_csv(tmp_path / "r.csv", header, rows)
    rc, out, err = run(capsys, command, tmp_path / "r.csv", "--machine", tmp_path / "m.toml",
                       "--json", tmp_path / "a.json", "--write-machine", tmp_path / "cal.toml",
                       "--report", tmp_path / "rep.html")
    assert rc == 2, out + err
    assert "m.toml" in err and all(w in err for w in words), err
    assert not any(p.exists() for p in _outputs(tmp_path))


def _break(col, row_index, value):
    header, rows = rows_of(COLS)
    rows = [list(r) for r in rows]
    rows[row_index][header.index(col)] = value
    return header, rows


RECORDING_BREAKS = {
    "empty cell": (lambda: _break("q2", 3, ""), ["line 5", "q2", "expected"]),
    "not a number": (lambda: _break("z", 0, "12.5.1"), ["line 2", "'z'", "expected a number", "12.5.1"]),
    "nan": (lambda: _break("rx", 6, "nan"), ["line 8", "rx", "finite"]),
    "outside q_limits": (lambda: _break("q3", 9, "600"), ["line 11", "q3", "q_limits"]),
    "duplicate column": (lambda: (["q1", "q2", "q3", "x", "y", "z", "x"],
                                  [r[:6] + [r[3]] for r in rows_of(COLS)[1]]), ["line 1", "'x'", "duplicate"]),
    "actuator count": (lambda: (["q1", "q2", "x", "y", "z"], [r[:2] + r[3:6] for r in rows_of(COLS)[1]]),
                       ["line 1", "actuator", "expected q1..q3"]),
    "short row": (lambda: (rows_of(COLS)[0], [r if i != 4 else r[:-1] for i, r in enumerate(rows_of(COLS)[1])]),
                  ["line 6", "expected"]),
    "bad sigma": (lambda: (rows_of(COLS)[0] + ["sigma_position"],
                           [r + ["-1" if i == 2 else "0.005"] for i, r in enumerate(rows_of(COLS)[1])]),
                  ["line 4", "sigma_position", "expected a positive", "got -1.0"]),
}


@pytest.mark.parametrize("case", list(RECORDING_BREAKS))
def test_bad_recording(tmp_path, capsys, case):
    make, words = RECORDING_BREAKS[case]
    header, rows = make()
    (tmp_path / "m.toml").write_text(_plain_machine())
    write_csv(tmp_path / "r.csv", header, rows, crlf=True, bom=True)
    for command in ("identify", "diagnose"):
        rc, out, err = run(capsys, command, tmp_path / "r.csv", "--machine", tmp_path / "m.toml",
                           "--json", tmp_path / "a.json", "--write-machine", tmp_path / "cal.toml",
                           "--report", tmp_path / "rep.html")
        assert rc == 2, out + err
        assert "r.csv" in err and all(w in err for w in words), err
        assert not any(p.exists() for p in _outputs(tmp_path))
    rc, out, err = run(capsys, "grid", tmp_path / "r.csv", "--machine", tmp_path / "m.toml", "--out", tmp_path / "g.csv",
                       "--json", tmp_path / "a.json")
    assert rc == 2 and "r.csv" in err
    assert not (tmp_path / "g.csv").exists() and not (tmp_path / "a.json").exists()


def test_missing_module_file_is_named(tmp_path, capsys):
    (tmp_path / "m.toml").write_text('kind = "hybrid"\n\n[[module]]\nfile = "head.toml"\nrole = "tool"\n')
    header, rows = rows_of(COLS)
    write_csv(tmp_path / "r.csv", header, rows)
    rc, _, err = run(capsys, "identify", tmp_path / "r.csv", "--machine", tmp_path / "m.toml", "--json", tmp_path / "a.json")
    assert rc == 2 and "head.toml" in err and not (tmp_path / "a.json").exists()
