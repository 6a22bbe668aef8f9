"""``bayescal identify --lam auto`` / ``--k auto``: the choice, the others beside it, JSON and figures."""

import json

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.identify.choose import DEFAULT_RULE, RULES, choose_regularisation
from bayescal.io import read_recording
from bayescal.machines.files import load_machine
from bayescal.measurement import MeasurementModel
from tests.conftest import PRS3_FILE, ROOT

REC = ROOT / "examples" / "prs3" / "recording.csv"


def test_ridge_lam_auto_reports_all_rules_and_writes_json_and_figure(tmp_path, capsys):
    out, figs = tmp_path / "a.json", tmp_path / "figs"
    code = main(["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "ridge", "--lam", "auto",
                 "--json", str(out), "--figures", str(figs)])
    assert code == 0
    text = capsys.readouterr().out
    default = DEFAULT_RULE["ridge"]
    assert f"chosen by '{default}'" in text and all(f"    {r}" in text for r in RULES)
    ans = json.loads(out.read_text())
    reg = ans["regularisation"]
    assert reg["rule"] == default and reg["method"] == "ridge"
    assert ans["lam"] == pytest.approx(reg["value"]) == pytest.approx(reg["choices"][default])
    assert set(reg["choices"]) == set(RULES) and len(reg["curves"]["gcv"]) == len(reg["grid"])
    png = figs / "regularisation_ridge.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    # the same choice as the library gives: its front door, and the rule on the rows in canonical order
    from bayescal.identify.calibrate import calibrate, canonical_order

    model = MeasurementModel.from_recording(load_machine(PRS3_FILE), read_recording(REC))
    cal = calibrate(model, method="ridge", lam="auto")
    assert cal.choice.value == pytest.approx(reg["value"])
    np.testing.assert_allclose([p["value"] for p in ans["parameters"]], cal.result.theta, rtol=1e-12, atol=1e-15)
    order = canonical_order(model)
    choice, _ = choose_regularisation(model if order is None else model.subset(order), "ridge")
    assert choice.value == pytest.approx(reg["value"])


def test_tsvd_k_auto_with_named_rule(tmp_path, capsys):
    out = tmp_path / "a.json"
    code = main(["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "tsvd", "--k", "auto",
                 "--rule", "gcv", "--json", str(out), "--quiet"])
    assert code == 0 and capsys.readouterr().out == ""
    ans = json.loads(out.read_text())
    assert ans["regularisation"]["rule"] == "gcv"
    assert ans["k"] == ans["regularisation"]["value"] == ans["regularisation"]["choices"]["gcv"]


def test_rule_without_auto_and_bad_values_are_usage_errors(capsys):
    assert main(["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "ridge", "--lam", "1",
                 "--rule", "gcv"]) == 2
    assert "--rule" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "tsvd", "--k", "many"])
    assert e.value.code == 2
    assert "'auto'" in capsys.readouterr().err


def test_auto_lambda_reports_rms_before_against_the_start():
    from bayescal.identify import identify
    from bayescal.identify.choose import choose_regularisation
    from bayescal.io import read_recording
    from bayescal.machines.files import load_machine
    from bayescal.measurement import MeasurementModel
    from tests.conftest import PRS3_FILE, ROOT

    m = load_machine(PRS3_FILE)
    model = MeasurementModel.from_recording(m, read_recording(ROOT / "examples/prs3/recording.csv"))
    _, res = choose_regularisation(model, "ridge")
    plain = identify(model, method="ridge", lam=1.0)
    assert res.rms_before == plain.rms_before
    assert res.rms_after["position"] < 0.2 * res.rms_before["position"]
