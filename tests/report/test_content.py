"""What a report says: the JSON answer's numbers, the sections of each kind, outliers marked."""

from __future__ import annotations

import json
from dataclasses import replace
from importlib import resources

import numpy as np
import pytest

from bayescal.errors import InputError
from bayescal.report import render_report
from tests.report.parse import tables


def test_template_is_package_data():
    assert resources.files("bayescal.report").joinpath("templates/report.html.j2").is_file()


@pytest.mark.parametrize("kind", ["identify", "kalman", "mcmc"])
def test_parameter_table_equals_json_answer(reports, kind):
    ans = json.loads((reports / f"{kind}.json").read_text())
    t = tables((reports / f"{kind}.html").read_text())
    rows = {r[0][0]: r for r in t["parameters"]}
    assert len(rows) == len(ans["parameters"])
    for p in ans["parameters"]:
        r = rows[p["name"]]
        assert r[1][1] == p["value"]  # exact: the report carries repr of the same float
        assert r[2][1] == p["std"]
        assert r[3][0] == p["unit"]
    cov = ans["covariance"]
    assert len(cov["matrix"]) == len(cov["names"]) == sum(p["estimated"] for p in ans["parameters"])
    C = np.array(cov["matrix"])
    std = np.sqrt(np.diag(C))
    got = {p["name"]: p["std"] for p in ans["parameters"]}
    np.testing.assert_allclose(std, [got[n] for n in cov["names"]], rtol=1e-12)


def test_report_states_inputs_with_hashes(reports):
    import hashlib

    from tests.conftest import PRS3_FILE

    t = tables((reports / "identify.html").read_text())
    files = {r[1][0]: r[2][0] for r in t["input-files"]}
    assert files[str(PRS3_FILE)] == hashlib.sha256(PRS3_FILE.read_bytes()).hexdigest()
    versions = dict((r[0][0], r[1][0]) for r in t["versions"])
    assert {"bayescal", "numpy", "scipy", "jinja2"} <= set(versions)
    machine = {r[0][0]: r[1] for r in t["machine"]}
    assert machine["instrument sigma, position"][1] > 0


def test_diagnose_report_has_verdict_located_channel_and_effects(reports):
    ans = json.loads((reports / "diagnose.json").read_text())
    html = (reports / "diagnose.html").read_text()
    t = tables(html)
    verdict = {r[0][0]: r[1][0] for r in t["verdict-evidence"]}
    assert verdict["verdict"] == ans["verdict"]
    if ans["located"]:
        assert verdict["located channel"].startswith(ans["located"]["channel"])
    assert [r[0][0] for r in t["effects"]][: len(ans["effects"])] == [e["name"] for e in ans["effects"]]
    assert len(t["channels"]) == len(ans["channels"])


def test_residual_rows_and_outliers_marked(reports):
    """An answer naming outliers (their CSV lines) gets those rows marked."""
    from bayescal.identify import identify
    from bayescal.io import read_recording
    from bayescal.machines.files import load_machine
    from bayescal.measurement import MeasurementModel
    from tests.conftest import PRS3_FILE, ROOT

    machine = load_machine(PRS3_FILE)
    model = MeasurementModel.from_recording(machine, read_recording(ROOT / "examples" / "prs3" / "recording.csv"))
    res = identify(model, method="ridge", lam=1.0)

    # the answer's outliers as identify writes them (docs/formats.md section 4: CSV line, header = line 1)
    flagged = replace(res, extras={**res.extras, "outliers": [{"line": 4, "statistic": 30.0}, {"line": 7, "statistic": 40.0}]})

    html = render_report("identify", flagged, machine=machine, model=model)
    rows = tables(html)["pose-residuals"]
    assert len(rows) == model.n_poses
    marked = [i for i, r in enumerate(rows) if r[-1][0] == "outlier"]
    assert marked == [2, 5]
    # the residual column is the per-pose position error norm of the result, um
    pos = 1e3 * np.linalg.norm(res.residuals_after[:, :3], axis=1)
    np.testing.assert_allclose([r[2][1] for r in rows], pos, rtol=1e-12)
    assert 'class="outlier"' in html


def test_unknown_kind_is_an_input_error():
    with pytest.raises(InputError, match="report kind"):
        render_report("nonsense", None)


def test_names_are_escaped(reports):
    """Text from files never becomes markup."""
    from bayescal.report.kinds import inputs_section

    html = render_report("compensate", __import__("bayescal.compensation", fromlist=["read_grid"]).read_grid(reports / "bic.csv"),
                         inputs={"command": "bayescal <script>alert(1)</script>", "files": [], "versions": {}})
    assert "<script>alert(1)" not in html and "&lt;script&gt;" in html
    assert inputs_section({}, None)["title"] == "Inputs"


def test_cli_report_marks_the_gross_pose_and_states_plausibility(tmp_path):
    """Through the command line: one pose +0.3 mm in x is marked in the residual table by its CSV line."""
    import csv

    from bayescal.cli import main
    from tests.conftest import PRS3_FILE, ROOT

    rows = list(csv.reader((ROOT / "examples" / "prs3" / "recording.csv").read_text().splitlines()))
    x = rows[0].index("x")
    rows[12][x] = repr(float(rows[12][x]) + 0.3)  # CSV line 13, pose 12
    rec = tmp_path / "gross.csv"
    with rec.open("w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    html_path, json_path = tmp_path / "r.html", tmp_path / "a.json"
    assert main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "map", "--report", str(html_path),
                 "--json", str(json_path), "--quiet"]) == 0
    assert [o["line"] for o in json.loads(json_path.read_text())["outliers"]] == [13]
    html = html_path.read_text()
    res = tables(html)["pose-residuals"]
    marked = [i for i, r in enumerate(res) if r[-1][0] == "outlier"]
    assert marked == [11]  # 0-based pose 11 = CSV line 13
    assert "Plausible: no machine parameter beyond 10 tolerances" in html and "down-weighted" in html


def test_compare_summary_is_in_the_metrics_own_unit():
    # rms_angle is in rad: the summary table says urad (as the text report), not the positions' um x 1e3
    from bayescal.compare.result import comparison_from_records
    from bayescal.compare.trial import CompareConfig
    from tests.conftest import PRS3_FILE

    config = CompareConfig(machine_text=PRS3_FILE.read_text(), methods="ls", trials=3)
    values = [4e-5, 5e-5, 6e-5]
    records = [{"trial": t, "nominal": {"rms_angle": 1e-3}, "n_free": 1,
                "methods": {"ls": {"success": True, "message": "", "rms_angle": v}}} for t, v in enumerate(values)]
    cmp = comparison_from_records(records, config, metric="rms_angle", n_resamples=10)
    html = render_report("compare", cmp)
    assert "median rms_angle (urad)" in html and "rms_angle (um)" not in html
    (row,) = tables(html)["methods"]
    assert row[3][1] == pytest.approx(1e6 * float(np.median(values)))
    assert row[4][1] == pytest.approx(1e6 * float(np.mean(values)))


def test_noise_yardstick_of_a_distance_and_height_recording_is_sigma():
    # one value per row: pure noise gives an RMS of sigma, not sigma sqrt(3) as for a measured point; a
    # machine that states no noise gets no yardstick
    from dataclasses import replace

    from bayescal.constraints.model import ConstraintModel
    from bayescal.identify import identify
    from bayescal.machines.files import load_machine
    from bayescal.machines.base import MeasurementNoise
    from bayescal.constraints.simulate import simulate_distances
    from tests.conftest import PRS3_FILE

    m = load_machine(PRS3_FILE)
    rec = simulate_distances(m, 20, seed=3, heights=15).recording
    model = ConstraintModel.from_recording(m, rec)
    res = identify(model, method="map")
    html = render_report("identify", res, machine=m, model=model)
    assert f"instrument noise alone gives about {1e3 * m.noise.sigma_position:.2f} um" in html
    silent = replace(m, noise=MeasurementNoise())
    assert not silent.noise.given
    assert "instrument noise alone" not in render_report("identify", res, machine=silent, model=model)


def _delta_ballbar():
    from bayescal.constraints.model import ConstraintModel
    from bayescal.machines.files import load_machine
    from bayescal.constraints.simulate import simulate_ballbar
    from tests.conftest import ROOT

    m = load_machine(ROOT / "examples" / "delta" / "machine.toml")
    rec = simulate_ballbar(m, 40.0, n_points=12, planes=("xy", "xz"), pivot=[1.0, 2.0, 80.0], seed=3).recording
    return m, ConstraintModel.from_recording(m, rec)


def test_a_ballbar_kalman_report_lists_the_pivots_with_their_tolerance():
    # the filter's answer has the model's parameters (geometry, then the pivots); the report's tolerance
    # column must be the model's too, not the machine file's (which has no pivots: an IndexError before)
    from bayescal.bayes.kalman import kalman_filter

    m, model = _delta_ballbar()
    res = kalman_filter(model)
    html = render_report("identify", res, machine=m, model=model)
    rows = {r[0][0]: r for r in tables(html)["parameters"]}
    assert len(rows) == model.n_params > m.n_params
    assert rows["pivot.1.x"][4][1] == pytest.approx(model.machine.tolerance[model.machine.layout.names.index("pivot.1.x")])
    assert rows["tower1.radius"][4][1] == pytest.approx(m.tolerance[m.layout.names.index("tower1.radius")])


@pytest.mark.parametrize("method", ["map", "kalman"])
def test_combinations_the_prior_decides_are_in_the_report_and_the_answer(method):
    # with free="auto" a method with a prior estimates the confounded parameters and the prior decides the
    # split (docs/cli.md, identify --free): the report must name them, not say every parameter is identifiable
    from bayescal.bayes.kalman import kalman_filter
    from bayescal.identify import identify

    m, model = _delta_ballbar()
    res = identify(model, method="map") if method == "map" else kalman_filter(model)
    assert res.decided_by_prior and res.to_dict()["decided_by_prior"] == list(res.decided_by_prior)
    html = render_report("identify", res, machine=m, model=model)
    assert "Every parameter that was asked for is identifiable" not in html
    assert "decided by the prior" in html
    assert [r[0][0] for r in tables(html)["decided-by-prior"]] == list(res.decided_by_prior)
