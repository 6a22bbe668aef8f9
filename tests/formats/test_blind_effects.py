"""Blind run: diagnose answers and [effect.*] tables in hand-written machine files (sections 3, 7).

The machine files and effect tables are written as text by ``handwritten.py``. The spec
names the effects but not their equations, so recordings that carry an effect are made
by ``bayescal simulate`` from the hand-written machine file (its positions only; the true
values come from its truth JSON), as the brief allows.
"""

from __future__ import annotations

import csv
import json
import tomllib

import numpy as np
import pytest

from .blind import answer, check_identify_answer, diagnose_checked, identify_map, run
from .handwritten import draw_q, effect_table, pose_rows, prs3_nominal, prs3_tool, prs3_toml, rows_of, write_csv

NOM = prs3_nominal()


def _simulate(tmp_path, capsys, name, *args):
    (tmp_path / "nominal.toml").write_text(prs3_toml(NOM))
    rc, _, err = run(capsys, "simulate", "--machine", tmp_path / "nominal.toml", "--out", tmp_path / f"{name}.csv",
                     "--quiet", *args)
    assert rc == 0, err
    truth = json.loads((tmp_path / f"{name}.truth.json").read_text())
    return truth


def _true_geometry_file(tmp_path, name, tables: str, variant="shuffled"):
    """The true machine's geometry, re-written by hand, plus hand-written effect tables."""
    d = tomllib.loads((tmp_path / f"{name}.truth.toml").read_text())
    from .handwritten import Chain, Prs3

    m = Prs3(tuple(Chain(tuple(c["rail_origin"]), tuple(c["rail_direction"]), tuple(c["revolute_axis"]),
                         c["link_length"], tuple(c["sphere_center"])) for c in d["chain"]),
             tuple(d["tool"]["point"]), name="true A")
    return prs3_toml(m, variant=variant, effects=tables)


def test_diagnose_clean_recording_with_idle_channels_says_none(tmp_path, capsys):
    """Section 3: a clean recording (channels that drive nothing) gives verdict "none"."""
    (tmp_path / "m.toml").write_text(prs3_toml(NOM, variant="shuffled"))
    from .handwritten import prs3_perturbed

    true = prs3_perturbed(NOM, 9)
    q = draw_q(NOM.q_limits, 60, 31)
    poses = [prs3_tool(true, qi) for qi in q]
    cols = pose_rows(q, np.array([p for p, _ in poses]), np.array([r for _, r in poses]), dof=6, sigma=0.005,
                     seed=32)
    cols["time_s"] = np.arange(60) * 30.0
    cols["temp_C"] = 20 + 5 * (1 - np.exp(-cols["time_s"] / 600))
    cols["payload_kg"] = np.tile([0.0, 5.0, 10.0, 20.0], 15)
    header, rows = rows_of(cols, ["time_s"] + list(cols)[:-3] + ["payload_kg", "temp_C"])
    write_csv(tmp_path / "r.csv", header, rows, crlf=True, bom=True)
    a = diagnose_checked(capsys, tmp_path / "r.csv", tmp_path / "m.toml", tmp_path / "d.json", "--write-machine",
                         tmp_path / "cal.toml")
    assert a["verdict"] == "none"
    assert not any(e["detected"] for e in a["effects"])
    d = tomllib.loads((tmp_path / "cal.toml").read_text())
    assert d["kind"] == "3-PRS" and "effect" not in d


def test_backlash_diagnosed_written_and_applied_from_a_hand_written_table(tmp_path, capsys):
    truth = _simulate(tmp_path, capsys, "bl", "--poses", "120", "--seed", "3", "--effect", "backlash:30")
    true_bl = {p["name"]: p["value"] for p in truth["effects"]["backlash"]["parameters"]}
    a = diagnose_checked(capsys, tmp_path / "bl.csv", tmp_path / "nominal.toml", tmp_path / "d.json",
                         "--write-machine", tmp_path / "cal.toml")
    assert a["verdict"] == "backlash" and a["effects"][0]["name"] == "backlash"
    assert a["located"]["channel"].endswith(("q1", "q2", "q3"))
    for p in a["effects"][0]["parameters"]:
        assert p["unit"] == "um" and abs(p["value"] - true_bl[p["name"]]) < 4 * p["std"]
    # section 7: the written machine carries the effect, parameter names and units as in the answer
    d = tomllib.loads((tmp_path / "cal.toml").read_text())
    assert set(d["effect"]["backlash"]) == set(true_bl)
    # ... and its geometry with that table predicts the recording to the noise (identify applies it)
    identify_map(capsys, tmp_path / "bl.csv", tmp_path / "cal.toml", tmp_path / "cal.json", ok=(0, 1))
    assert answer(tmp_path / "cal.json")["rms_before"]["position"] < 0.012
    # the same kind of table written by hand (keys in another order, comments), on the true geometry
    table = effect_table("backlash", dict(reversed(list(true_bl.items()))))
    (tmp_path / "with.toml").write_text(_true_geometry_file(tmp_path, "bl", table))
    (tmp_path / "without.toml").write_text(_true_geometry_file(tmp_path, "bl", ""))
    rms = {}
    for name in ("with", "without"):
        rc, _, err = run(capsys, "identify", tmp_path / "bl.csv", "--machine", tmp_path / f"{name}.toml",
                         "--method", "map", "--json", tmp_path / f"{name}.json", "--write-machine",
                         tmp_path / f"{name}.cal.toml", "--quiet")
        assert rc in (0, 1), err
        ans = answer(tmp_path / f"{name}.json")
        check_identify_answer(ans)
        rms[name] = ans["rms_before"]["position"]
    # the true geometry with the table predicts the recording to the noise; without, it cannot
    assert rms["with"] < 0.012 < 0.015 < rms["without"]
    kept = tomllib.loads((tmp_path / "with.cal.toml").read_text())["effect"]["backlash"]
    assert kept == pytest.approx(true_bl)


@pytest.mark.parametrize("settings", [{}, {"gravity": "[0.0, 0.0, -1.0]", "payload_offset": "[0, 0, 0]"}])
def test_joint_compliance_table_with_and_without_optional_inputs(tmp_path, capsys, settings):
    truth = _simulate(tmp_path, capsys, "jc", "--poses", "60", "--seed", "4", "--effect", "joint_compliance:0.5",
                      "--aux", "payload_kg")
    params = {p["name"]: p["value"] for p in truth["effects"]["joint_compliance"]["parameters"]}
    table = effect_table("joint_compliance", params, extra=settings)
    (tmp_path / "with.toml").write_text(_true_geometry_file(tmp_path, "jc", table))
    identify_map(capsys, tmp_path / "jc.csv", tmp_path / "with.toml", tmp_path / "a.json", ok=(0, 1))
    assert answer(tmp_path / "a.json")["rms_before"]["position"] < 0.012
    # grid and simulate apply the hand-written table too
    rc, _, err = run(capsys, "grid", tmp_path / "jc.csv", "--machine", tmp_path / "with.toml", "--nodes", "3",
                     "--aux", "payload_kg=10", "--out", tmp_path / "g.csv", "--json", tmp_path / "g.json", "--quiet")
    assert rc == 0, err
    with open(tmp_path / "g.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 27 and {"q1", "q2", "q3", "dx", "dy", "dz", "sx", "sy", "sz"} <= set(rows[0])
    assert isinstance(answer(tmp_path / "g.json"), dict)
    rc, _, err = run(capsys, "simulate", "--machine", tmp_path / "with.toml", "--poses", "5", "--seed", "1",
                     "--aux", "payload_kg", "--out", tmp_path / "s.csv", "--quiet")
    assert rc == 0, err
    t = tomllib.loads((tmp_path / "s.truth.toml").read_text())
    assert t["effect"]["joint_compliance"]["compliance.q2"] == pytest.approx(params["compliance.q2"])


@pytest.mark.parametrize("reference", [None, "20.0"])
def test_thermal_table_with_and_without_reference(tmp_path, capsys, reference):
    truth = _simulate(tmp_path, capsys, "th", "--poses", "60", "--seed", "5", "--effect", "thermal_expansion",
                      "--aux", "time_s,temp_C")
    params = {p["name"]: p["value"] for p in truth["effects"]["thermal_expansion"]["parameters"]}
    table = effect_table("thermal_expansion", params, comments=False,
                         extra={} if reference is None else {"reference_C": reference})
    (tmp_path / "with.toml").write_text(_true_geometry_file(tmp_path, "th", table, variant="plain"))
    identify_map(capsys, tmp_path / "th.csv", tmp_path / "with.toml", tmp_path / "a.json", ok=(0, 1))
    assert answer(tmp_path / "a.json")["rms_before"]["position"] < 0.012
