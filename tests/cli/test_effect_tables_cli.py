"""End to end: simulate an effect, diagnose --write-machine, then identify, grid and simulate with the written machine."""

import json

import numpy as np

from bayescal.cli import main
from bayescal.io import read_recording
from bayescal.machines.files import load_machine
from tests.conftest import PRS3_FILE


def test_diagnose_writes_a_machine_that_identify_grid_and_simulate_apply(tmp_path, capsys):
    rec, cal = tmp_path / "rec.csv", tmp_path / "cal.toml"
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses", "120", "--seed", "3",
                 "--effect", "joint_compliance:0.5", "--aux", "payload_kg", "--out", str(rec), "--quiet"]) == 0
    code = main(["diagnose", str(rec), "--machine", str(PRS3_FILE), "--json", str(tmp_path / "d.json"),
                 "--write-machine", str(cal)])
    out = capsys.readouterr().out
    assert code == 0
    assert f"wrote {cal}: the geometry fitted jointly with joint_compliance, and [effect.joint_compliance]" in out
    answer = json.loads((tmp_path / "d.json").read_text())
    assert answer["verdict"] == "joint_compliance"
    assert answer["written_machine"] == {"path": str(cal), "effects": ["joint_compliance"], "warning": ""}
    m = load_machine(cal)
    fitted = {p["name"]: p["value"] for e in answer["effects"] if e["name"] == "joint_compliance" for p in e["parameters"]}
    assert dict(m.effects[0].values) == fitted
    assert not list(tmp_path.glob("*.tmp*"))  # written atomically: no temporary left behind

    # identify with the written machine: the effect is applied, the geometry is left with noise only
    # (MAP: plain LS moves near-unidentifiable parameters far beyond their tolerances and is refused as implausible)
    assert main(["identify", str(rec), "--machine", str(cal), "--method", "map", "--json", str(tmp_path / "id.json"),
                 "--write-machine", str(tmp_path / "cal2.toml")]) == 0
    out = capsys.readouterr().out
    assert "effects applied at their stored values" in out
    ident = json.loads((tmp_path / "id.json").read_text())
    noise = m.noise.sigma_position * np.sqrt(3)
    assert ident["rms_before"]["position"] < 1.1 * noise and ident["rms_after"]["position"] < 1.1 * noise
    assert main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "map", "--json", str(tmp_path / "id0.json"),
                 "--quiet"]) == 0
    assert json.loads((tmp_path / "id0.json").read_text())["rms_after"]["position"] > 1.3 * noise
    assert "[effect.joint_compliance]" in (tmp_path / "cal2.toml").read_text()  # identify keeps the tables

    # grid: the compensation under a stated payload differs from the one without
    for payload in ("0", "25"):
        assert main(["grid", str(rec), "--machine", str(cal), "--nodes", "3", "--aux", f"payload_kg={payload}",
                     "--out", str(tmp_path / f"g{payload}.csv"), "--json", str(tmp_path / f"g{payload}.json")]) == 0
    assert "joint_compliance applied at payload_kg = 25" in capsys.readouterr().out
    g0, g25 = (np.loadtxt(tmp_path / f"g{p}.csv", delimiter=",", skiprows=1) for p in ("0", "25"))
    np.testing.assert_array_equal(g0[:, :3], g25[:, :3])
    assert np.abs(g25[:, 3:6] - g0[:, 3:6]).max() > 2e-3  # 25 kg on ~0.5 um/N drives: microns
    assert json.loads((tmp_path / "g25.json").read_text())["aux"] == {"payload_kg": 25.0}
    assert main(["grid", str(rec), "--machine", str(cal), "--aux", "payload_kg"]) == 2
    assert "--aux payload_kg: expected NAME=VALUE" in capsys.readouterr().err
    assert main(["grid", str(rec), "--machine", str(cal), "--aux", "payload=5"]) == 2
    assert "(--aux) payload: unknown channel; expected one of: time_s, temp_C, payload_kg" in capsys.readouterr().err
    assert main(["grid", str(rec), "--machine", str(PRS3_FILE), "--aux", "payload_kg=5"]) == 2
    assert "carries no [effect.*] tables" in capsys.readouterr().err

    # simulate from the written machine applies the effect: its truth machine explains the recording
    rec2 = tmp_path / "rec2.csv"
    assert main(["simulate", "--machine", str(cal), "--poses", "60", "--seed", "9", "--aux", "payload_kg",
                 "--out", str(rec2), "--quiet"]) == 0
    truth = tmp_path / "rec2.truth.toml"
    assert "[effect.joint_compliance]" in truth.read_text()
    assert main(["identify", str(rec2), "--machine", str(truth), "--method", "map", "--json", str(tmp_path / "id2.json"),
                 "--quiet"]) == 0
    assert json.loads((tmp_path / "id2.json").read_text())["rms_before"]["position"] < 1.2 * noise
    assert read_recording(rec2).aux["payload_kg"].shape == (60,)


def test_bad_effect_table_is_exit_2_naming_file_and_key(tmp_path, capsys):
    bad = tmp_path / "m.toml"
    bad.write_text(PRS3_FILE.read_text() + '\n[effect.backlash]\n"backlash.q1" = 1.0\n"backlash.q2" = 1.0\n"dead_band.q3" = 1.0\n')
    assert main(["identify", str(PRS3_FILE.parent / "recording.csv"), "--machine", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "effect.backlash.\"dead_band.q3\"" in err and "not a parameter of backlash" in err
    assert len(err.strip().splitlines()) == 1
