"""identify --write-machine on a hybrid machine writes FORMATS.md section 5's file-per-module form."""

import json
import tomllib

import numpy as np

from bayescal.cli import main
from bayescal.machines import load_machine
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
