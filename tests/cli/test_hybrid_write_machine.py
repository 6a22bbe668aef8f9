"""identify --write-machine on a hybrid machine writes docs/formats.md section 5's file-per-module form."""

import json
import tomllib

import numpy as np

from bayescal.cli import main
from bayescal.machines.files import load_machine
from tests.conftest import ROOT

HYB = ROOT / "examples" / "hybrid_table"


def test_hybrid_calibration_is_written_as_module_files_that_predict_like_the_fit(tmp_path):
    out = tmp_path / "cal.toml"
    code = main(["identify", str(HYB / "recording.csv"), "--machine", str(HYB / "machine.toml"), "--method", "map",
                 "--json", str(tmp_path / "a.json"), "--write-machine", str(out), "--quiet"])
    assert code == 0
    doc = tomllib.loads(out.read_text())
    assert doc["kind"] == "hybrid"
    files = [m["file"] for m in doc["module"]]
    assert all((tmp_path / f).is_file() for f in files) and "machine" not in doc["module"][0]
    # the files alone predict what the fit predicts
    cal = load_machine(out)
    nominal = load_machine(HYB / "machine.toml")
    theta = np.array([p["value"] for p in json.loads((tmp_path / "a.json").read_text())["parameters"]])
    q = nominal.sample_q(20, np.random.default_rng(4))
    a, b = cal.forward(q), nominal.forward(q, theta)
    assert a.success.all() and b.success.all()
    assert np.abs(a.position - b.position).max() < 1e-9
    assert np.abs(a.rotation - b.rotation).max() < 1e-12


def test_hybrid_with_effect_tables_keeps_them_in_the_main_file(tmp_path):
    # docs/formats.md section 7: a machine read with [effect.*] tables is written with them (before: the
    # file-per-module form dropped them, and the calibrated hybrid predicted without its backlash)
    import shutil

    for name in ("machine.toml", "head.toml", "table.toml"):
        shutil.copy(HYB / name, tmp_path / name)
    machine = tmp_path / "machine.toml"
    machine.write_text(machine.read_text() + '\n[effect.backlash]\n"backlash.q1" = 5.0\n"backlash.q2" = 6.0\n'
                       '"backlash.q3" = 7.0\n"backlash.q4" = 50.0\n')
    out = tmp_path / "out" / "cal.toml"
    code = main(["identify", str(HYB / "recording.csv"), "--machine", str(machine), "--method", "map",
                 "--write-machine", str(out), "--mkdir", "--quiet"])
    assert code == 0
    (eff,) = load_machine(out).effects
    assert eff.name == "backlash"
    assert dict(eff.values) == {"backlash.q1": 5.0, "backlash.q2": 6.0, "backlash.q3": 7.0, "backlash.q4": 50.0}
    assert eff.units == ("um", "um", "um", "urad")


def test_diagnose_writes_a_hybrid_in_the_file_per_module_form_with_its_effects(tmp_path):
    # docs/formats.md section 5: [[module]] tables each name a file; diagnose --write-machine wrote the modules
    # inline ([module.machine]), which only bayescal reads, while identify wrote the contract's form
    rec = tmp_path / "rec.csv"
    assert main(["simulate", "--machine", str(HYB / "machine.toml"), "--poses", "40", "--seed", "3", "--effect",
                 "backlash", "--out", str(rec), "--quiet"]) == 0
    out = tmp_path / "cal.toml"
    code = main(["diagnose", str(rec), "--machine", str(HYB / "machine.toml"), "--effects", "backlash",
                 "--json", str(tmp_path / "d.json"), "--write-machine", str(out), "--quiet"])
    assert code == 0
    answer = json.loads((tmp_path / "d.json").read_text())
    doc = tomllib.loads(out.read_text())
    assert doc["kind"] == "hybrid"
    assert all("file" in m and "machine" not in m for m in doc["module"])
    assert all((tmp_path / m["file"]).is_file() for m in doc["module"])
    assert out.read_text().startswith("# calibrated by bayescal diagnose")
    cal = load_machine(out)
    assert [e.name for e in cal.effects] == answer["written_machine"]["effects"]
    # the module files hold the fitted geometry, not the nominal one
    nominal = load_machine(HYB / "machine.toml")
    q = nominal.sample_q(10, np.random.default_rng(4))
    a, b = cal.forward(q), nominal.forward(q)
    assert a.success.all() and 1e-6 < np.abs(a.position - b.position).max() < 1.0
