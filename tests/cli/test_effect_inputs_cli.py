"""diagnose --effect-input and the machine file's stated effect inputs; the written geometry's confound in the answer."""

import json
from types import SimpleNamespace

import pytest

from bayescal.cli import main
from bayescal.cli.diagnose import effect_inputs
from bayescal.errors import InputError
from bayescal.machines.files import load_machine
from tests.conftest import PRS3_FILE


def test_effect_inputs_are_parsed_and_checked(prs3):
    got = effect_inputs(prs3, ["joint_compliance.platform_mass_kg=45", "joint_compliance.gravity=0, 0.1,-1"])
    assert got == {"joint_compliance": {"platform_mass_kg": 45.0, "gravity": [0.0, 0.1, -1.0]}}
    for item, msg in [
        ("joint_compliance.platform_mass_kg", "expected NAME.KEY=VALUE"),
        ("compliance.mass=3", "unknown effect 'compliance'"),
        ("joint_compliance.mass=3", "has no input 'mass'; expected one of gravity, payload_offset"),
        ("joint_compliance.platform_mass_kg=heavy", "expected a number or comma-separated numbers"),
        ("joint_compliance.platform_mass_kg=-5", "expected a positive mass in kg"),
        ("joint_compliance.platform_com_mm=1,2", "expected a 3-vector in mm"),
    ]:
        with pytest.raises(InputError, match=msg):
            effect_inputs(prs3, [item])
    # the machine file's stated inputs are the default, the command line overrides them
    stated = SimpleNamespace(name="joint_compliance", settings=(("platform_mass_kg", 30.0), ("gravity", [0.0, 0.0, -1.0])))
    machine = SimpleNamespace(effects=(stated,))
    assert effect_inputs(machine, ["joint_compliance.platform_mass_kg=40"]) == {
        "joint_compliance": {"platform_mass_kg": 40.0, "gravity": [0.0, 0.0, -1.0]}}


def test_stated_inputs_pin_the_written_geometry_and_the_answer_says_how_well(tmp_path, capsys):
    rec = tmp_path / "rec.csv"
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses", "100", "--seed", "4",
                 "--effect", "joint_compliance:0.5", "--aux", "payload_kg", "--out", str(rec), "--quiet"]) == 0
    base = ["diagnose", str(rec), "--machine", str(PRS3_FILE), "--effects", "joint_compliance", "--quiet"]
    assert main(base + ["--json", str(tmp_path / "u.json"), "--write-machine", str(tmp_path / "u.toml")]) == 0
    unknown = json.loads((tmp_path / "u.json").read_text())["written_geometry"]
    assert unknown["confounded"] and "zero offset" in unknown["note"]
    assert unknown["tool_std_um"] > 2 * unknown["geometric_tool_std_um"]
    assert {g["name"].split(".")[1] for g in unknown["trade_off"]["geometry"]} & {"rail_origin", "link_length"}
    # bayescal simulate's joint compliance: a 30 kg platform, centre of mass at the platform origin, upright
    inputs = ["--effect-input", "joint_compliance.platform_mass_kg=30", "--effect-input", "joint_compliance.platform_com_mm=0,0,0",
              "--effect-input", "joint_compliance.gravity=0,0,-1"]
    assert main(base + inputs + ["--json", str(tmp_path / "s.json"), "--write-machine", str(tmp_path / "s.toml")]) == 0
    stated = json.loads((tmp_path / "s.json").read_text())["written_geometry"]
    assert stated["tool_std_um"] < unknown["tool_std_um"] / 3
    written = load_machine(tmp_path / "s.toml")
    assert dict(written.effects[0].settings)["platform_mass_kg"] == 30.0
    # diagnosing again with the written machine uses its stated inputs
    assert main(["diagnose", str(rec), "--machine", str(tmp_path / "s.toml"), "--effects", "joint_compliance", "--quiet",
                 "--json", str(tmp_path / "again.json")]) == 0
    again = json.loads((tmp_path / "again.json").read_text())["written_geometry"]
    assert again["tool_std_um"] == pytest.approx(stated["tool_std_um"], rel=0.05)
    # ... and so does the library's door on the same files (it used the documented defaults before)
    import bayescal

    lib = bayescal.diagnose(tmp_path / "s.toml", rec, effects=["joint_compliance"]).to_dict()["written_geometry"]
    assert json.loads(json.dumps(lib)) == again
    assert main(base + ["--effect-input", "joint_compliance.mass=3"]) == 2
    assert "has no input 'mass'" in capsys.readouterr().err
