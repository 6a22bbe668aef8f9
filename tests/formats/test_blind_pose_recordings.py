"""Blind run: hand-written 3-PRS machine files and pose recordings (docs/formats.md sections 1-4).

The files come from ``handwritten.py`` (no bayescal code); the true machine's tool poses are
the spec's equations solved by numpy. bayescal's answers are read as docs/formats.md states
them, and the calibrated machine it writes is checked by predicting the true machine with
the spec's kinematics alone.
"""

from __future__ import annotations

import numpy as np
import pytest

from .blind import answer, check_identify_answer, diagnose_checked, read_prs3, run
from .handwritten import (
    draw_q,
    pose_rows,
    prs3_nominal,
    prs3_perturbed,
    prs3_tool,
    prs3_tool_poses,
    prs3_toml,
    rows_of,
    write_csv,
)

NOM = prs3_nominal()
TRUE = prs3_perturbed(NOM, 1)
Q = draw_q(NOM.q_limits, 40, 3)
PTS, ROTS = prs3_tool_poses(TRUE, Q)
Q_TEST = draw_q(NOM.q_limits, 15, 99)
PTS_TEST = np.array([prs3_tool(TRUE, q)[0] for q in Q_TEST])
SIGMA = NOM.sigma_position


def predicts_truth(cal_path) -> float:
    """Largest tool-point error (mm) of the written calibrated machine at fresh poses."""
    cal, _ = read_prs3(cal_path)
    pred = np.array([prs3_tool(cal, q)[0] for q in Q_TEST])
    return float(np.max(np.linalg.norm(pred - PTS_TEST, axis=1)))


def nominal_error() -> float:
    pred = np.array([prs3_tool(NOM, q)[0] for q in Q_TEST])
    return float(np.max(np.linalg.norm(pred - PTS_TEST, axis=1)))


RECORDING_VARIANTS = {
    "plain": dict(order=None, csv={}),
    "permuted_crlf_bom_ws": dict(order=["z", "rx", "q3", "x", "ry", "q1", "y", "rz", "q2"],
                                 csv=dict(crlf=True, bom=True, trailing_ws=True)),
    "aux_no_final_newline": dict(order=["pose_id", "q1", "q2", "q3", "x", "y", "z", "rx", "ry", "rz", "temp_C"],
                                 csv=dict(final_newline=False), aux=True),
}


def _recording(path, variant):
    v = RECORDING_VARIANTS[variant]
    cols = pose_rows(Q, PTS, ROTS, dof=6, sigma=SIGMA, seed=1)
    if v.get("aux"):
        cols["pose_id"] = np.arange(1, len(Q) + 1)
        cols["temp_C"] = np.full(len(Q), 20.5)
    header, rows = rows_of(cols, v["order"])
    write_csv(path, header, rows, **v["csv"])


@pytest.mark.parametrize("machine_variant", ["plain", "shuffled"])
@pytest.mark.parametrize("rec_variant", list(RECORDING_VARIANTS))
def test_identify_reads_variants_and_the_calibrated_machine_predicts_the_truth(
    tmp_path, capsys, machine_variant, rec_variant
):
    (tmp_path / "m.toml").write_text(prs3_toml(NOM, variant=machine_variant))
    _recording(tmp_path / "r.csv", rec_variant)
    rc, _, err = run(capsys, "identify", tmp_path / "r.csv", "--machine", tmp_path / "m.toml", "--method", "map",
                     "--json", tmp_path / "a.json", "--write-machine", tmp_path / "cal.toml", "--quiet")
    assert rc == 0, err
    a = answer(tmp_path / "a.json")
    check_identify_answer(a)
    assert a["machine"] == NOM.name and a["method"] == "map"
    assert a["outliers"] == []
    # a clean 6-DOF recording: residual at the noise (3 components of sigma each), well below before
    assert a["rms_after"]["position"] < 2.5 * SIGMA and a["rms_before"]["position"] > 10 * SIGMA
    names = {p["name"] for p in a["parameters"]}
    assert {"chain1.link_length", "chain2.rail_origin.x", "chain3.sphere_center.z"} <= names
    assert all(p["unit"] in ("mm", "rad") for p in a["parameters"] if p["name"].startswith("chain"))
    # the calibrated machine, read with tomllib and the spec's kinematics, predicts the true machine
    assert predicts_truth(tmp_path / "cal.toml") < 0.1 * nominal_error()
    _, d = read_prs3(tmp_path / "cal.toml")
    assert set(d) >= {"kind", "chain", "tool"} and len(d["chain"]) == 3


def test_five_and_three_dof_recordings(tmp_path, capsys):
    # the machine file from a Windows editor: a byte-order mark and CRLF line ends
    (tmp_path / "m.toml").write_bytes(b"\xef\xbb\xbf" + prs3_toml(NOM, variant="shuffled").replace("\n", "\r\n").encode())
    for dof in (5, 3):
        cols = pose_rows(Q, PTS, ROTS, dof=dof, sigma=SIGMA, seed=2)
        header, rows = rows_of(cols)
        write_csv(tmp_path / f"r{dof}.csv", header[::-1], [r[::-1] for r in rows])
        rc, _, err = run(capsys, "identify", tmp_path / f"r{dof}.csv", "--machine", tmp_path / "m.toml",
                         "--method", "map", "--json", tmp_path / f"a{dof}.json", "--quiet")
        assert rc == 0, err
        a = answer(tmp_path / f"a{dof}.json")
        check_identify_answer(a, angle=dof == 5)
        assert a["rms_after"]["position"] < 2.5 * SIGMA


def test_unit_suffixes_give_the_same_answer(tmp_path, capsys):
    """Section 4: x_um, y_m, rx_deg ... are converted; the answer equals the mm/rad one."""
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    cols = pose_rows(Q, PTS, ROTS, dof=6, sigma=SIGMA, seed=3)
    header, rows = rows_of(cols)
    write_csv(tmp_path / "mm.csv", header, rows, fmt="{:.17g}")
    units = {"x": ("x_um", 1e3), "y": ("y_m", 1e-3), "z": ("z_mm", 1.0), "rx": ("rx_deg", 180 / np.pi),
             "ry": ("ry_mrad", 1e3), "q2": ("q2_um", 1e3)}
    cols = pose_rows(Q, PTS, ROTS, dof=6, sigma=SIGMA, seed=3, units=units)
    header, rows = rows_of(cols)
    write_csv(tmp_path / "units.csv", header, rows, fmt="{:.17g}")
    out = {}
    for name in ("mm", "units"):
        rc, _, err = run(capsys, "identify", tmp_path / f"{name}.csv", "--machine", tmp_path / "m.toml",
                         "--method", "map", "--json", tmp_path / f"{name}.json", "--quiet")
        assert rc == 0, err
        out[name] = answer(tmp_path / f"{name}.json")
    for p, r in zip(out["mm"]["parameters"], out["units"]["parameters"]):
        assert p["name"] == r["name"] and p["value"] == pytest.approx(r["value"], abs=1e-6 * (p["std"] or 1))


@pytest.mark.parametrize(("factor", "unit", "suffix"), [(1e-3, "metre", "_m"), (1e3, "micro", "_um")])
def test_positions_in_another_unit_without_suffix_are_refused(tmp_path, capsys, factor, unit, suffix):
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    cols = pose_rows(Q, PTS * factor, ROTS, dof=3, sigma=0.0, seed=4)
    header, rows = rows_of(cols)
    write_csv(tmp_path / "r.csv", header, rows)
    rc, _, err = run(capsys, "identify", tmp_path / "r.csv", "--machine", tmp_path / "m.toml",
                     "--json", tmp_path / "a.json")
    assert rc == 2
    assert "r.csv" in err and unit in err.lower() and f"x{suffix}" in err
    assert not (tmp_path / "a.json").exists()


def test_rotation_in_degrees_without_suffix_is_refused(tmp_path, capsys):
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    cols = pose_rows(Q, PTS, ROTS, dof=6, sigma=0.0, seed=4)
    for k in ("rx", "ry", "rz"):
        cols[k] = cols[k] * 180 / np.pi
    header, rows = rows_of(cols)
    write_csv(tmp_path / "r.csv", header, rows)
    rc, _, err = run(capsys, "identify", tmp_path / "r.csv", "--machine", tmp_path / "m.toml")
    assert rc == 2 and "degree" in err.lower() and "_deg" in err


def test_per_pose_sigma_columns(tmp_path, capsys):
    """Section 4: sigma_position / sigma_angle per pose; a machine file without [measurement]."""
    (tmp_path / "m.toml").write_text(prs3_toml(NOM, measurement=False))
    sig = np.where(np.arange(len(Q)) % 2 == 0, 0.003, 0.008)
    rng = np.random.default_rng(5)
    cols = pose_rows(Q, PTS + rng.normal(0, 1, PTS.shape) * sig[:, None], ROTS, dof=6, sigma=0.0, seed=5)
    cols["sigma_position"] = sig
    cols["sigma_angle"] = np.full(len(Q), 5e-5)
    header, rows = rows_of(cols, ["sigma_angle"] + list(cols)[:-1])
    write_csv(tmp_path / "r.csv", header, rows, crlf=True)
    rc, _, err = run(capsys, "identify", tmp_path / "r.csv", "--machine", tmp_path / "m.toml", "--method", "map",
                     "--json", tmp_path / "a.json", "--quiet")
    assert rc == 0, err
    a = answer(tmp_path / "a.json")
    check_identify_answer(a)
    # the stated per-pose noise is the noise (the angles are noiseless here, so only the
    # 3n position rows count): chi-square per position residual near 1
    assert 0.5 < a["chi2"] / (3 * len(Q)) < 1.2


@pytest.mark.parametrize("fmt", ["plain", "bom_crlf"])
def test_outlier_is_named_by_its_csv_line(tmp_path, capsys, fmt):
    """Section 4: header = line 1, so pose index i sits on line i + 2, whatever the line ends."""
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    pts = PTS.copy()
    pts[12] += [0.4, -0.3, 0.2]
    cols = pose_rows(Q, pts, ROTS, dof=6, sigma=SIGMA, seed=6)
    header, rows = rows_of(cols)
    write_csv(tmp_path / "r.csv", header, rows, **(dict(bom=True, crlf=True) if fmt == "bom_crlf" else {}))
    rc, _, err = run(capsys, "identify", tmp_path / "r.csv", "--machine", tmp_path / "m.toml", "--method", "map",
                     "--json", tmp_path / "a.json", "--quiet")
    assert rc in (0, 1), err
    a = answer(tmp_path / "a.json")
    check_identify_answer(a)
    assert [o["line"] for o in a["outliers"]] == [14]
    assert a["outliers"][0]["p_value"] < 0.01
    assert isinstance(a["outlier_handling"], str) and a["outlier_handling"]


def test_diagnose_names_one_gross_pose_and_says_none(tmp_path, capsys):
    """Section 4 in diagnose: one 0.54 mm gross reading among 5 um ones is an outlier named by
    its line, not "unexplained" structure (it used to drag the first fit so that 8 of 40 poses
    stood out, and the screen gave up)."""
    (tmp_path / "m.toml").write_text(prs3_toml(NOM))
    pts = PTS.copy()
    pts[12] += [0.4, -0.3, 0.2]
    header, rows = rows_of(pose_rows(Q, pts, ROTS, dof=6, sigma=SIGMA, seed=6))
    write_csv(tmp_path / "r.csv", header, rows, bom=True, crlf=True)
    a = diagnose_checked(capsys, tmp_path / "r.csv", tmp_path / "m.toml", tmp_path / "d.json")
    assert a["verdict"] == "none"
    assert [o["line"] for o in a["outliers"]] == [14]
    assert "excluded" in a["outlier_handling"]
