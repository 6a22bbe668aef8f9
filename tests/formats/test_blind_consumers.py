"""Blind run: grid, compare, plan, simulate and klipper on hand-written files, and bayescal's
written recordings read back with an independent reader (docs/formats.md sections 2, 6)."""

from __future__ import annotations

import csv
import os
import tomllib
from pathlib import Path

import numpy as np
import pytest

from .blind import answer, run
from .handwritten import (
    draw_q,
    pose_rows,
    positioner_nominal,
    prs3_nominal,
    prs3_tool,
    prs3_toml,
    rows_of,
    serial_perturbed,
    serial_toml,
    serial_transform,
    write_csv,
)
from .test_blind_constraints import _rows

NOM = prs3_nominal()
# the checkout sits beside shared/ (<clone>/../shared); BAYESCAL_SHARED points elsewhere (a git worktree)
SHARED = Path(os.environ.get("BAYESCAL_SHARED", Path(__file__).resolve().parents[2] / ".." / "shared"))
KLIPPER_CFG = SHARED / "data" / "real" / "delta_flsun_q5" / "printer-post-calibration.cfg"


def read_pose_csv(path) -> tuple[list[str], np.ndarray]:
    """Section 2 read by hand: one header row, then one numeric row per pose."""
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    header, body = rows[0], rows[1:]
    assert body and all(len(r) == len(header) for r in body)
    return header, np.array([[float(c) for c in r] for r in body])


def read_constraint_csv(path, *, template: bool = False) -> list[dict]:
    """Section 6 read by hand (a plan is a template: its value cells are to be filled in)."""
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert rows
    n = sum(1 for k in rows[0] if k.startswith("a_q"))
    for r in rows:
        assert r["measure"] in ("distance", "height", "ballbar")
        assert r["value"] == "" if template else float(r["value"]) == float(r["value"])
        assert all(r[f"a_q{k}"] != "" for k in range(1, n + 1))
        b = [r.get(f"b_q{k}", "") for k in range(1, n + 1)]
        assert all(c != "" for c in b) if r["measure"] == "distance" else all(c == "" for c in b)
    return rows


def test_grid_on_hand_written_serial_and_constraint_recordings(tmp_path, capsys):
    ser = positioner_nominal()
    true = serial_perturbed(ser, 5)
    (tmp_path / "s.toml").write_text(serial_toml(ser))
    q = draw_q(ser.q_limits, 30, 61)
    t = np.array([serial_transform(true, qi) for qi in q])
    header, rows = rows_of(pose_rows(q, t[:, :3, 3], t[:, :3, :3], dof=5, sigma=0.005, seed=62))
    write_csv(tmp_path / "s.csv", header, rows, crlf=True)
    rc, _, err = run(capsys, "grid", tmp_path / "s.csv", "--machine", tmp_path / "s.toml", "--nodes", "3",
                     "--out", tmp_path / "g.csv", "--json", tmp_path / "g.json", "--quiet")
    assert rc == 0, err
    h, g = read_pose_csv(tmp_path / "g.csv")
    assert h[:3] == ["q1", "q2", "q3"] and {"dx", "dy", "dz", "sx", "sy", "sz"} <= set(h) and len(g) == 27
    assert np.all(g[:, [h.index(k) for k in ("sx", "sy", "sz")]] >= 0)

    (tmp_path / "p.toml").write_text(prs3_toml(NOM))
    header, rows = _rows(11, pivots=True, order="shuffled")
    write_csv(tmp_path / "c.csv", header, rows, bom=True)
    rc, _, err = run(capsys, "grid", tmp_path / "c.csv", "--machine", tmp_path / "p.toml", "--nodes", "2",
                     "--out", tmp_path / "gc.csv", "--quiet")
    assert rc == 0, err
    h, g = read_pose_csv(tmp_path / "gc.csv")
    assert len(g) == 8 and np.all(np.isfinite(g))


def test_compare_and_plan_on_a_hand_written_constraint_recording(tmp_path, capsys):
    (tmp_path / "p.toml").write_text(prs3_toml(NOM, variant="shuffled"))
    header, rows = _rows(12, pivots=False)
    write_csv(tmp_path / "c.csv", header, rows, crlf=True, trailing_ws=True)
    rc, _, err = run(capsys, "compare", "--machine", tmp_path / "p.toml", "--recording", tmp_path / "c.csv",
                     "--methods", "ridge,tsvd", "--trials", "3", "--eval-poses", "10", "--json", tmp_path / "cmp.json",
                     "--no-progress", "--quiet")
    assert rc in (0, 1), err
    assert isinstance(answer(tmp_path / "cmp.json"), dict)
    rc, _, err = run(capsys, "plan", "--machine", tmp_path / "p.toml", "--n", "4", "--measure", "height",
                     "--given", tmp_path / "c.csv", "--radius", "20", "--out", tmp_path / "plan.csv", "--quiet")
    assert rc == 0, err
    rows = read_constraint_csv(tmp_path / "plan.csv", template=True)
    assert len(rows) == 4 and {r["measure"] for r in rows} == {"height"}


@pytest.mark.parametrize("dof", [6, 5, 3])
def test_simulated_recording_follows_section_2(tmp_path, capsys, dof):
    """bayescal's own recording, read by hand: the spec's columns, and the spec's kinematics of
    its .truth.toml reproduce its positions to the noise."""
    (tmp_path / "m.toml").write_text(prs3_toml(NOM, variant="shuffled"))
    rc, _, err = run(capsys, "simulate", "--machine", tmp_path / "m.toml", "--poses", "8", "--seed", "3",
                     "--dof", str(dof), "--aux", "temp_C", "--out", tmp_path / "r.csv", "--quiet")
    assert rc == 0, err
    h, data = read_pose_csv(tmp_path / "r.csv")
    extra = {6: ["rx", "ry", "rz"], 5: ["nx", "ny", "nz"], 3: []}[dof]
    assert h[:6 + len(extra)] == ["q1", "q2", "q3", "x", "y", "z"] + extra and "temp_C" in h
    from .blind import read_prs3

    true, _ = read_prs3(tmp_path / "r.truth.toml")
    for row in data:
        p = prs3_tool(true, row[:3])[0]
        assert np.linalg.norm(p - row[3:6]) < 6 * 0.005


def test_ballbar_simulation_follows_section_6(tmp_path, capsys):
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    rc, _, err = run(capsys, "simulate", "--machine", tmp_path / "m.toml", "--poses", "6", "--seed", "2",
                     "--ballbar", "20", "--planes", "xy,xz", "--out", tmp_path / "b.csv", "--quiet")
    assert rc == 0, err
    rows = read_constraint_csv(tmp_path / "b.csv")
    assert {r["measure"] for r in rows} == {"ballbar"} and len(rows) == 12
    assert all(abs(float(r["value"]) - 20.0) < 1.0 for r in rows)


@pytest.mark.skipif(not KLIPPER_CFG.exists(), reason="shared Klipper config not present")
@pytest.mark.parametrize("crlf", [False, True])
def test_klipper_writes_spec_files(tmp_path, capsys, crlf):
    text = KLIPPER_CFG.read_text(encoding="utf-8")
    cfg = tmp_path / "printer.cfg"
    cfg.write_bytes(text.replace("\n", "\r\n" if crlf else "\n").encode("utf-8"))
    # as a blind run calls it: the defaults (its fluidd.cfg did not travel with it: skipped with a note)
    rc, _, err = run(capsys, "klipper", cfg, "--out", tmp_path / "calib", "--json", tmp_path / "k.json", "--quiet")
    assert rc == 0, err
    d = tomllib.loads((tmp_path / "calib" / "machine.toml").read_text())
    assert isinstance(d["kind"], str)
    rows = read_constraint_csv(tmp_path / "calib" / "recording.csv")
    assert {"height", "distance"} <= {r["measure"] for r in rows}
    rc, _, err = run(capsys, "identify", tmp_path / "calib" / "recording.csv", "--machine",
                     tmp_path / "calib" / "machine.toml", "--method", "map", "--free", "all",
                     "--json", tmp_path / "a.json", "--quiet")
    assert rc in (0, 1), err
    a = answer(tmp_path / "a.json")
    assert a["rms_after"]["position"] <= a["rms_before"]["position"]
