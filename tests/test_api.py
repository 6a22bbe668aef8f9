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
