"""The front door (bayescal.api): the verbs give what the command line gives."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bayescal
from bayescal.cli import main

from .conftest import PRS3_FILE, ROOT

REC = ROOT / "examples" / "prs3" / "recording.csv"


def test_calibrate_is_identify(tmp_path):
    s = bayescal.load(PRS3_FILE, REC)
    cal = bayescal.calibrate(s, method="map")
    out = tmp_path / "a.json"
    assert main(["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "map", "--json", str(out), "--quiet"]) == 0
    ans = json.loads(out.read_text())
    lib = {p["name"]: p for p in json.loads(json.dumps(cal.to_dict(), default=lambda o: np.asarray(o).tolist()))["parameters"]}
    for p in ans["parameters"]:
        assert lib[p["name"]]["value"] == p["value"] and lib[p["name"]]["std"] == p["std"]
    assert cal.parameters["chain1.link_length"].unit == "mm"
    assert "<table>" in cal._repr_html_()


def test_write_machine_then_predict(tmp_path):
    s = bayescal.load(PRS3_FILE, REC)
    cal = bayescal.calibrate(s, method="map")
    path = cal.write_machine(tmp_path / "cal.toml")[0]
    m = bayescal.load_machine(path)
    assert m.calibration is not None and m.calibration.noise_scale == cal.noise_scale
    p = bayescal.predict(path, REC)
    # the calibration's own poses, predicted from its written machine: the fit's residual, within the regions
    assert p.summary["fit"]["n"] == 36 and p.summary["fit"]["coverage_90"] > 0.8
    # the written machine (errors folded into its geometry) predicts what the fit's residual says, to rounding
    assert p.summary["fit"]["rms_error_position_mm"] == pytest.approx(cal.result.rms_after["position"], rel=1e-6)


def test_the_library_snippet_of_the_docs_runs(tmp_path, monkeypatch, capsys):
    text = (ROOT / "docs" / "index.md").read_text(encoding="utf-8")
    block = text.split("## The library in ten lines", 1)[1].split("```python", 1)[1].split("```", 1)[0]
    monkeypatch.chdir(tmp_path)
    exec(compile(block.replace('"examples/', f'"{ROOT.as_posix()}/examples/'), "docs/index.md", "exec"), {})
    out = capsys.readouterr().out
    assert "bayescal identification" in out and "ParameterEstimate(name='chain1.link_length'" in out
    assert (tmp_path / "calibrated.toml").is_file()


def test_load_takes_a_constraint_recording(tmp_path, capsys):
    # a printer's heights through the front door, as `bayescal identify` takes them (docs/formats.md section 6)
    machine = ROOT / "examples" / "delta" / "machine.toml"
    m = bayescal.machines.files.load_machine(machine)
    rng = np.random.default_rng(1)
    q = m.sample_q(30, rng)
    z = m.forward(q).position[:, 2] + rng.normal(scale=m.noise.sigma_position, size=30)
    rows = ["measure,a_q1,a_q2,a_q3,value"] + [f"height,{a!r},{b!r},{c!r},{h!r}" for (a, b, c), h in zip(q.tolist(), z.tolist())]
    rec = tmp_path / "h.csv"
    rec.write_text("\n".join(rows) + "\n")
    model = bayescal.load(machine, rec)
    from bayescal.constraints.model import ConstraintModel

    assert isinstance(model, ConstraintModel) and model.n_poses == 30
    out = tmp_path / "a.json"
    code = main(["identify", str(rec), "--machine", str(machine), "--json", str(out), "--quiet"])
    assert code == 0, capsys.readouterr()
    ans = json.loads(out.read_text())
    lib = bayescal.calibrate(model).to_dict()
    assert [p["value"] for p in lib["parameters"]] == [p["value"] for p in ans["parameters"]]
    with pytest.raises(bayescal.errors.InputError, match="constraint recording"):
        bayescal.load(machine, rec, frame="fit")
