"""The front door (bayescal.api): the verbs give what the command line gives."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bayescal
from bayescal.cli import main

from .conftest import PRS3_FILE, ROOT

REC = ROOT / "examples" / "prs3" / "recording.csv"


def _positioner_with_roles(tmp_path):
    """The real positioner recording with every fourth row held out (role = check), as a file."""
    from dataclasses import replace

    rec = bayescal.read_recording(ROOT / "examples" / "positioner" / "recording.csv")
    rec = replace(rec, role=tuple("check" if i % 4 == 3 else "fit" for i in range(rec.n_poses)))
    path = tmp_path / "positioner.csv"
    bayescal.write_recording(path, rec)
    return ROOT / "examples" / "positioner" / "machine.toml", path


def _delta_distances(tmp_path):
    from bayescal.constraints.simulate import simulate_distances
    from bayescal.io.constraints import write_constraints

    machine = ROOT / "examples" / "delta" / "machine.toml"
    path = tmp_path / "distances.csv"
    write_constraints(path, simulate_distances(bayescal.load_machine(machine), 30, seed=2, heights=10).recording)
    return machine, path


CASES = {
    "3-PRS, base frame": (lambda tmp: (PRS3_FILE, REC), {}, []),
    "positioner, fitted frame, held-out rows": (_positioner_with_roles, {"frame": "fit"}, ["--frame", "fit"]),
    "delta, heights and distances": (_delta_distances, {}, []),
    "3-PRS, ridge lam=auto": (lambda tmp: (PRS3_FILE, REC), {"method": "ridge", "lam": "auto"},
                              ["--method", "ridge", "--lam", "auto"]),
    "3-PRS, two parameters held": (lambda tmp: (PRS3_FILE, REC), {"fix": ["chain2.link_length", "tool.point.z"]},
                                   ["--fix", "chain2.link_length,tool.point.z"]),
    "3-PRS, a bound reached and an open one": (
        lambda tmp: (PRS3_FILE, REC), {"bounds": {"chain3.sphere_center.z": (-0.06, None), "tool.point.z": (None, 1.0)}},
        ["--bound", "chain3.sphere_center.z=-0.06:", "--bound", "tool.point.z=:1"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_calibrate_writes_the_json_identify_writes_byte_for_byte(tmp_path, case):
    from bayescal.io.answers import json_text

    files, options, flags = CASES[case]
    machine, rec = files(tmp_path)
    load_kw = {k: v for k, v in options.items() if k == "frame"}
    cal_kw = {k: v for k, v in options.items() if k != "frame"}
    cal = bayescal.calibrate(bayescal.load(machine, rec, **load_kw), **cal_kw)
    out = tmp_path / "cli.json"
    code = main(["identify", str(rec), "--machine", str(machine), "--json", str(out), "--quiet", *flags])
    assert code == 0 and cal.plausibility.plausible
    assert json_text(cal.to_dict()) == out.read_text()
    assert json.loads(json.dumps(cal.to_dict(), allow_nan=False))  # the library's answer is plain JSON
    if case.startswith("positioner"):
        assert cal.to_dict()["check"]["summary"]["n"] == 51 and "frame" in cal.to_dict()
    if case.startswith("delta"):
        assert "pivots" in cal.to_dict()
    if "bound" in case:
        assert cal.to_dict()["at_bound"] == ["chain3.sphere_center.z"]
        assert cal.to_dict()["bounds"] == {"chain3.sphere_center.z": [-0.06, None], "tool.point.z": [None, 1.0]}


def test_a_ballbar_recordings_machine_keeps_its_known_frame_through_either_door(tmp_path):
    # a machine file's [instrument] table (a known frame, which ballbar rows do not see): the library reported no
    # frame, wrote the machine without [instrument] and put the pivots into [calibration] (24 names for 21
    # parameters), where the command reported the frame as known and kept it
    from bayescal.io.answers import json_text

    machine = tmp_path / "m.toml"
    machine.write_text((ROOT / "examples" / "delta" / "machine.toml").read_text()
                       + "\n[instrument]\norigin = [10.0, 0.0, 0.0]\nrotation_vector = [0.0, 0.0, 0.1]\n")
    rec = tmp_path / "bb.csv"
    assert main(["simulate", "--machine", str(machine), "--ballbar", "40", "--planes", "xy,xz", "--poses", "12",
                 "--pivot", "1,2,80", "--seed", "3", "--out", str(rec), "--quiet"]) == 0
    out, cli_machine = tmp_path / "cli.json", tmp_path / "cli.toml"
    assert main(["identify", str(rec), "--machine", str(machine), "--json", str(out), "--write-machine",
                 str(cli_machine), "--quiet"]) == 0
    cal = bayescal.calibrate(bayescal.load(machine, rec))
    assert json_text(cal.to_dict()) == out.read_text()
    assert cal.to_dict()["frame"]["fitted"] is False
    lib_machine = cal.write_machine(tmp_path / "lib.toml")[0]
    assert lib_machine.read_text() == cli_machine.read_text()
    written = bayescal.load_machine(lib_machine)
    assert written.framed and not written.fit
    assert len(written.calibration.names) == bayescal.load_machine(ROOT / "examples" / "delta" / "machine.toml").n_params


def test_an_implausible_calibration_is_not_written(tmp_path):
    from dataclasses import replace

    from bayescal.instrument.plausibility import Plausibility

    cal = bayescal.calibrate(bayescal.load(PRS3_FILE, REC), method="map")
    bad = replace(cal, plausibility=Plausibility(False, ("chain1.link_length is 40 tolerances from nominal",)))
    with pytest.raises(bayescal.InputError, match="not plausible.*40 tolerances"):
        bad.write_machine(tmp_path / "m.toml")
    assert not (tmp_path / "m.toml").exists()
    assert bad.write_machine(tmp_path / "m.toml", force=True)[0].is_file()
    assert cal.parameters["chain1.link_length"].unit == "mm" and "<table>" in cal._repr_html_()


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
    with pytest.raises(bayescal.errors.InputError, match="constraint recording"):
        bayescal.diagnose(machine, rec, frame="fit")


@pytest.mark.parametrize("call, match", [
    (lambda s: bayescal.calibrate(s, method="ridge", lam="abc"), r"lam: expected a number from 0 to 1e\+12 .*got 'abc' \(or 'auto'\)"),
    (lambda s: bayescal.calibrate(s, method="tsvd", k="many"), "k: expected a whole number or 'auto'"),
    (lambda s: bayescal.calibrate(s, method="map", lamda=1), r"unknown option\(s\) lamda; expected method, lam"),
    (lambda s: bayescal.calibrate(str(REC)), "expected what bayescal.load returns .* got str"),
    (lambda s: bayescal.diagnose(PRS3_FILE, REC, n_folds=0), "n_folds: expected a whole number >= 2"),
])
def test_the_front_door_refuses_bad_arguments_by_name(call, match):
    with pytest.raises(bayescal.InputError, match=match):
        call(bayescal.load(PRS3_FILE, REC))


def test_diagnose_gives_the_json_diagnose_writes_byte_for_byte(tmp_path):
    from bayescal.io.answers import json_text

    d = bayescal.diagnose(PRS3_FILE, REC, seed=0)
    out = tmp_path / "d.json"
    assert main(["diagnose", str(REC), "--machine", str(PRS3_FILE), "--json", str(out), "--quiet"]) in (0, 1)
    assert json.loads(json.dumps(d.to_dict(), allow_nan=False))
    assert json_text(d.to_dict()) == out.read_text()


# ------------------------------------------------------------------ predict: the library's answer is the command's
@pytest.fixture(scope="module")
def calibrated_machines(tmp_path_factory):
    """Calibrated machine files of the bundled examples, with the recordings to predict (and the options)."""
    d = tmp_path_factory.mktemp("calibrated")
    prs3_cli, prs3_lib = d / "cli" / "prs3.toml", d / "lib" / "prs3.toml"
    prs3_cli.parent.mkdir()
    assert main(["identify", str(REC), "--machine", str(PRS3_FILE), "--discrepancy", "on", "--write-machine",
                 str(prs3_cli), "--quiet"]) == 0
    bayescal.calibrate(bayescal.load(PRS3_FILE, REC), discrepancy="on").write_machine(prs3_lib)
    pos_machine, pos_rec = _positioner_with_roles(d)
    bayescal.calibrate(bayescal.load(pos_machine, pos_rec, frame="fit")).write_machine(d / "positioner.toml")
    table = ROOT / "examples" / "hybrid_table"
    bayescal.calibrate(bayescal.load(table / "machine.toml", table / "recording.csv")).write_machine(d / "table.toml")
    return {
        "3-PRS, written by identify --discrepancy on": (prs3_cli, REC, {}, prs3_lib),
        "positioner, fitted frame, held-out rows": (d / "positioner.toml", pos_rec, {"frame": "fit"}, None),
        "hybrid table, a file per module": (d / "table.toml", table / "recording.csv", {}, None),
        "3-PRS nominal machine, 5-DOF": (PRS3_FILE, REC, {"dof": 5}, None),
    }


PREDICT_CASES = ("3-PRS, written by identify --discrepancy on", "positioner, fitted frame, held-out rows",
                 "hybrid table, a file per module", "3-PRS nominal machine, 5-DOF")


@pytest.mark.parametrize("case", PREDICT_CASES)
def test_predict_gives_the_json_predict_writes_byte_for_byte(calibrated_machines, tmp_path, case):
    from bayescal.io.answers import json_text

    machine, rec, options, library_written = calibrated_machines[case]
    p = bayescal.predict(machine, rec, **options)
    out = tmp_path / "p.json"
    flags = [x for k, v in options.items() for x in (f"--{k}", str(v))]
    assert main(["predict", str(rec), "--machine", str(machine), "--json", str(out), "--quiet", *flags]) == 0
    assert json_text(p.to_dict()) == out.read_text()
    assert json.loads(json.dumps(p.to_dict(), allow_nan=False)) == json.loads(out.read_text())  # plain JSON
    ans = p.to_dict()
    if library_written is not None:
        # the machine file bayescal.calibrate(...).write_machine writes is the one identify --write-machine writes
        assert library_written.read_bytes() == machine.read_bytes() and "[discrepancy]" in machine.read_text()
        assert ans["notes"] == [] and ans["summary"]["fit"]["n"] == 36
    if case.startswith("positioner"):
        assert ans["summary"]["check"]["n"] == 51 and ans["summary"]["fit"]["n"] == 154 and ans["frame"]["fitted"]
    if case.startswith("hybrid"):
        assert ans["summary"]["fit"]["n"] == 60 and ans["summary"]["fit"]["coverage_90"] > 0.8
    if case.endswith("5-DOF"):
        assert all(len(r["std"]) == 5 for r in ans["rows"]) and "no [calibration]" in ans["notes"][0]


# ------------------------------------------------------------------ grid: the library's answer is the command's
def _prs3_with_compliance(tmp_path):
    """The 3-PRS with a joint-compliance table, and a recording under varying payloads simulated from it."""
    from .cli.test_grid_effects_cli import COMPLIANCE

    machine, rec = tmp_path / "compliance.toml", tmp_path / "payload.csv"
    machine.write_text(PRS3_FILE.read_text() + COMPLIANCE)
    assert main(["simulate", "--machine", str(machine), "--poses", "40", "--seed", "2", "--aux", "payload_kg",
                 "--out", str(rec), "--quiet"]) == 0
    return machine, rec


GRID_CASES = {
    "3-PRS, map": (lambda tmp: (PRS3_FILE, REC), {}, {"nodes": 3}, ["--nodes", "3"]),
    "3-PRS, kalman, a narrowed q1": (lambda tmp: (PRS3_FILE, REC), {}, {"nodes": 3, "method": "kalman",
                                                                        "ranges": {"q1": (460.0, 540.0)}},
                                     ["--nodes", "3", "--method", "kalman", "--range", "q1=460:540"]),
    "positioner, fitted frame, held-out rows": (_positioner_with_roles, {"frame": "fit"}, {"nodes": 4},
                                                ["--nodes", "4", "--frame", "fit"]),
    "delta, heights and distances (tool space)": (_delta_distances, {}, {"nodes": 3}, ["--nodes", "3"]),
    "3-PRS with a compliance table, tool space, 25 kg": (
        _prs3_with_compliance, {}, {"nodes": 3, "space": "tool", "aux": {"payload_kg": 25.0}},
        ["--nodes", "3", "--space", "tool", "--aux", "payload_kg=25"]),
    "3-PRS, map, the links held": (lambda tmp: (PRS3_FILE, REC), {},
                                   {"nodes": 3, "fix": [f"chain{i}.link_length" for i in (1, 2, 3)]},
                                   ["--nodes", "3", "--fix", "chain1.link_length,chain2.link_length,chain3.link_length"]),
    "3-PRS, map, a bound reached": (lambda tmp: (PRS3_FILE, REC), {},
                                    {"nodes": 3, "bounds": {"chain3.sphere_center.z": (-0.06, 0.06)}},
                                    ["--nodes", "3", "--bound", "chain3.sphere_center.z=-0.06:0.06"]),
}


@pytest.mark.parametrize("case", list(GRID_CASES))
def test_grid_gives_the_json_grid_writes_byte_for_byte(tmp_path, case):
    from bayescal.io.answers import json_text

    files, load_kw, options, flags = GRID_CASES[case]
    machine, rec = files(tmp_path)
    g = bayescal.grid(bayescal.load(machine, rec, **load_kw), **options)
    out, csv = tmp_path / "g.json", tmp_path / "g.csv"
    assert main(["grid", str(rec), "--machine", str(machine), "--json", str(out), "--out", str(csv), "--quiet",
                 *flags]) == 0
    assert json_text(g.to_dict()) == out.read_text()
    assert json.loads(json.dumps(g.to_dict(), allow_nan=False))  # plain JSON
    assert g.grid.to_csv() == csv.read_text()
    ans = g.to_dict()
    assert ans["method"] == options.get("method", "map") and ans["max_std_mm"] > 0
    if case.startswith("delta"):
        assert g.space == "tool"  # a linear delta's q_limits box is not all reachable
    if "narrowed" in case:
        assert ans["axes"]["q1"] == [460.0, 500.0, 540.0]
    if "compliance" in case:
        assert ans["effects"] == ["joint_compliance"] and ans["aux"] == {"payload_kg": 25.0}
    if "fix" in options:
        # the links held at nominal: not estimated, so no column of the grid's covariance
        res = g.identification
        assert res.held == tuple(options["fix"])
        assert not any(f for n, f in zip(res.names, res.free) if n in options["fix"])
    if "bounds" in options:
        assert g.identification.at_bound == ("chain3.sphere_center.z",) and ans["bounds"]


def test_grid_from_posterior_draws_gives_the_json_grid_writes(tmp_path):
    from bayescal.io.answers import json_text

    g = bayescal.grid(bayescal.load(PRS3_FILE, REC), method="mcmc", steps=200, surrogate="linear", nodes=3)
    out = tmp_path / "g.json"
    assert main(["grid", str(REC), "--machine", str(PRS3_FILE), "--method", "mcmc", "--steps", "200",
                 "--surrogate", "linear", "--nodes", "3", "--json", str(out), "--quiet"]) == 0
    assert json_text(g.to_dict()) == out.read_text()
    # the chain thinned to about 400 draws (bayescal.bayes.recording_grid.GRID_DRAWS)
    assert g.to_dict()["std_source"].startswith("sample std over") and 400 <= int(g.grid.source.split()[3]) < 800


def test_grid_from_a_posterior_stopped_at_its_ess_gives_the_json_grid_writes(tmp_path):
    from bayescal.io.answers import json_text

    g = bayescal.grid(bayescal.load(PRS3_FILE, REC), method="mcmc", steps=3000, ess=1500, surrogate="linear", nodes=3)
    out = tmp_path / "g.json"
    assert main(["grid", str(REC), "--machine", str(PRS3_FILE), "--method", "mcmc", "--steps", "3000", "--ess", "1500",
                 "--surrogate", "linear", "--nodes", "3", "--json", str(out), "--quiet"]) == 0
    assert json_text(g.to_dict()) == out.read_text()
    post = g.identification
    assert post.success and post.n_steps < 3000 and post.min_ess == 1500 and post.ess_bulk.min() >= 1500
    assert main(["grid", str(REC), "--machine", str(PRS3_FILE), "--ess", "1500", "--nodes", "3"]) == 2  # map


@pytest.mark.parametrize("options, match", [
    ({"method": "ls"}, r"method \(--method\): expected one of map, kalman, mcmc, got 'ls'"),
    ({"ess": 1500}, r"ess \(--ess\): goes with method 'mcmc'; it does nothing with method 'map'"),
    ({"method": "mcmc", "ess": -1}, r"ess \(--ess\): expected a positive effective sample size"),
    ({"ranges": {"x": (0, 1)}}, r"ranges \(--range\) x: actuator space has the axes q1, q2, q3"),
    ({"ranges": {"q1": (540, 460)}}, r"ranges \(--range\) q1=540:460: expected finite LO < HI"),
    ({"aux": {"payload_kg": 5}}, r"aux \(--aux\): .*machine.toml carries no \[effect"),
    ({"nodes": 1}, r"n \(--nodes\): expected at least 2"),
    ({"method": "kalman", "fit_effects": True}, r"fit_effects \(--fit-effects\) goes with method map or mcmc"),
])
def test_grid_refuses_bad_arguments_by_name(options, match):
    with pytest.raises(bayescal.InputError, match=match):
        bayescal.grid(bayescal.load(PRS3_FILE, REC), **options)


def test_grid_nc_csv_goes_with_tool_space(tmp_path):
    g = bayescal.grid(bayescal.load(PRS3_FILE, REC), nodes=2)
    with pytest.raises(bayescal.InputError, match="space 'tool'"):
        g.write_nc_csv(tmp_path / "nc.csv")
    assert not (tmp_path / "nc.csv").exists()


# ------------------------------------------------------------------ identify --method kalman | mcmc, --fit-effects
BAYES_CASES = {
    "3-PRS, kalman": (lambda tmp: (PRS3_FILE, REC), {"method": "kalman"}, ["--method", "kalman"]),
    "3-PRS, unscented kalman with process noise": (
        lambda tmp: (PRS3_FILE, REC), {"method": "kalman", "variant": "ukf", "process_noise": 0.01},
        ["--method", "kalman", "--variant", "ukf", "--process-noise", "0.01"]),
    "delta, heights and distances, kalman": (_delta_distances, {"method": "kalman"}, ["--method", "kalman"]),
}


@pytest.mark.parametrize("case", list(BAYES_CASES))
def test_calibrate_kalman_writes_the_json_identify_writes_byte_for_byte(tmp_path, case):
    from bayescal.io.answers import json_text

    files, options, flags = BAYES_CASES[case]
    machine, rec = files(tmp_path)
    cal = bayescal.calibrate(bayescal.load(machine, rec), **options)
    out = tmp_path / "cli.json"
    assert main(["identify", str(rec), "--machine", str(machine), "--json", str(out), "--quiet", *flags]) == 0
    assert cal.result.success and cal.plausibility.plausible
    assert json_text(cal.to_dict()) == out.read_text()
    ans = json.loads(json.dumps(cal.to_dict(), allow_nan=False))  # plain JSON
    assert ans["method"].startswith("kalman") and "outlier_handling" in ans and "noise" in ans


def test_calibrate_mcmc_writes_the_json_identify_writes(tmp_path):
    import re

    from bayescal.io.answers import json_text

    cal = bayescal.calibrate(bayescal.load(PRS3_FILE, REC), method="mcmc", steps=200, surrogate="linear")
    out, written = tmp_path / "cli.json", tmp_path / "cli.toml"
    assert main(["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "mcmc", "--steps", "200",
                 "--surrogate", "linear", "--json", str(out), "--write-machine", str(written), "--quiet"]) == 0
    # the same bytes but for the sampler's wall-clock time
    def clock(text):
        return re.sub(r'"seconds": [0-9.e+-]+', '"seconds": 0', text)

    assert '"seconds": ' in out.read_text() and clock(json_text(cal.to_dict())) == clock(out.read_text())
    assert cal.result.success and cal.to_dict()["noise"]["verdict"] == json.loads(out.read_text())["noise"]["verdict"]
    assert cal.write_machine(tmp_path / "lib.toml")[0].read_bytes() == written.read_bytes()
    # the posterior's covariance goes with the machine (predict took an MCMC calibration as exact)
    record = bayescal.load_machine(written).calibration
    assert record is not None and record.method == "mcmc"
    free = [n for n, f in zip(cal.result.names, cal.result.free) if f]
    np.testing.assert_allclose(record.covariance_for(free), cal.result.covariance, rtol=1e-9, atol=1e-30)


def test_calibrate_mcmc_stops_at_the_ess_asked_for_as_identify_does(tmp_path):
    import re

    from bayescal.io.answers import json_text

    cal = bayescal.calibrate(bayescal.load(PRS3_FILE, REC), method="mcmc", steps=2000, ess=1500, surrogate="linear")
    out = tmp_path / "cli.json"
    assert main(["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "mcmc", "--steps", "2000",
                 "--ess", "1500", "--surrogate", "linear", "--json", str(out), "--quiet"]) == 0
    d = json.loads(out.read_text())
    assert d["success"] and d["convergence"]["min_ess"] == 1500.0
    assert d["convergence"]["n_steps"] < 2000 and d["convergence"]["min_ess_bulk"] >= 1500
    clock = lambda text: re.sub(r'"seconds": [0-9.e+-]+', '"seconds": 0', text)  # noqa: E731
    assert clock(json_text(cal.to_dict())) == clock(out.read_text())
    # --ess goes with mcmc only, like --steps
    assert main(["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "map", "--ess", "1500"]) == 2
    with pytest.raises(bayescal.InputError, match=r"ess: goes with method .mcmc."):
        bayescal.calibrate(bayescal.load(PRS3_FILE, REC), method="kalman", ess=1500)
    # review: with map it was "unknown option(s) ess", as steps was
    for name, value in (("ess", 1500), ("steps", 300)):
        with pytest.raises(bayescal.InputError, match=rf"{name}: goes with method 'mcmc'; it does nothing with method 'map'"):
            bayescal.calibrate(bayescal.load(PRS3_FILE, REC), method="map", **{name: value})


def test_a_kalman_calibration_carries_its_covariance_to_predict(tmp_path):
    # the filter's final covariance is the calibration's uncertainty: written into [calibration], and predict's
    # regions then agree with those of the MAP it linearises (the same prior and data; EKF to about a percent)
    written = {}
    for method in ("kalman", "map"):
        cal = bayescal.calibrate(bayescal.load(PRS3_FILE, REC), method=method)
        path = cal.write_machine(tmp_path / f"{method}.toml")[0]
        assert bayescal.load_machine(path).calibration.method == method
        written[method] = np.array([r["std"] for r in bayescal.predict(path, REC).to_dict()["rows"]])
    np.testing.assert_allclose(written["kalman"], written["map"], rtol=0.02)


def test_calibrate_fits_effect_tables_as_identify_fit_effects_does(tmp_path):
    from bayescal.effects.stored import StoredEffectsTransform
    from bayescal.io.answers import json_text
    from bayescal.simulate import simulate_recording

    from .cli.test_fit_effects_cli import NAMES, TABLE

    machine, truth, rec = tmp_path / "m.toml", tmp_path / "truth.toml", tmp_path / "rec.csv"
    machine.write_text(PRS3_FILE.read_text() + TABLE)
    truth.write_text(PRS3_FILE.read_text() + TABLE.replace("20.0", "8.0").replace("30.0", "12.0").replace("25.0", "10.0"))
    m = bayescal.load_machine(truth)
    sim = simulate_recording(m, 40, seed=21, effects=[StoredEffectsTransform(m, m.effects)], theta_true=np.zeros(m.n_params))
    bayescal.write_recording(rec, sim.recording)
    cal = bayescal.calibrate(bayescal.load(machine, rec), method="map", fit_effects=True)
    (tmp_path / "lib").mkdir()
    (tmp_path / "cli").mkdir()
    out = tmp_path / "cli" / "a.json"
    assert main(["identify", str(rec), "--machine", str(machine), "--method", "map", "--fit-effects", "--json",
                 str(out), "--write-machine", str(tmp_path / "cli" / "cal.toml"), "--quiet"]) == 0
    assert json_text(cal.to_dict()) == out.read_text()
    # the effects' parameters are identified (they were silently left at the file's values before)
    fitted = {p["name"]: p["value"] for p in cal.to_dict()["parameters"] if p["name"].startswith("effect.")}
    assert sorted(fitted) == NAMES[2:] and abs(fitted[NAMES[2]] - 8.0) < abs(fitted[NAMES[2]] - 20.0)
    # and written into the calibrated machine's table, as identify --write-machine writes it
    path = cal.write_machine(tmp_path / "lib" / "cal.toml")[0]
    assert path.read_bytes() == (tmp_path / "cli" / "cal.toml").read_bytes()
    assert dict(bayescal.load_machine(path).effects[0].values)["backlash.q1"] == pytest.approx(fitted[NAMES[2]])


@pytest.mark.parametrize("options, match", [
    ({"method": "mcmc", "variant": "ukf"}, "variant: goes with method 'kalman'; it does nothing with method 'mcmc'"),
    ({"method": "kalman", "steps": 100}, "steps: goes with method 'mcmc'"),
    ({"method": "kalman", "lam": 1.0}, "lam: goes with method 'ridge'; it does nothing with method 'kalman'"),
    ({"method": "kalman", "discrepancy": "auto"}, "discrepancy: goes with method 'map' or 'ridge'"),
    ({"method": "mcmc", "steps": 5}, r"steps \(--steps\): expected a whole number of at least 20, got 5"),
    ({"method": "mcmc", "resume": True}, r"resume \(--resume\): needs checkpoint"),
    ({"method": "kalman", "walk": 3}, "unknown option 'walk' of method 'kalman'; expected free, "),
    ({"method": "kalman", "fit_effects": True}, r"fit_effects \(--fit-effects\) goes with method map or mcmc"),
    ({"method": "kalman", "alpha": "0.01"}, r"alpha \(--outlier-alpha\): expected a level between 0 and 1"),
])
def test_calibrate_kalman_and_mcmc_refuse_bad_arguments_by_name(options, match):
    with pytest.raises(bayescal.InputError, match=match):
        bayescal.calibrate(bayescal.load(PRS3_FILE, REC), **options)


PLAN_CASES = {
    "poses, criterion D": ({"n_candidates": 300, "n_random": 2, "seed": 3},
                           ["--candidates", "300", "--random-sets", "2", "--seed", "3"]),
    "poses, criterion I, fitted frame": ({"criterion": "I", "n_candidates": 300, "n_random": 0, "frame": "fit"},
                                         ["--criterion", "I", "--candidates", "300", "--random-sets", "0",
                                          "--frame", "fit"]),
}


@pytest.mark.parametrize("case", list(PLAN_CASES))
def test_plan_gives_the_json_plan_writes_byte_for_byte(tmp_path, case):
    from bayescal.design import write_plan
    from bayescal.io.answers import json_text

    options, flags = PLAN_CASES[case]
    p = bayescal.plan(PRS3_FILE, 8, **options)
    out, csv, mine = tmp_path / "p.json", tmp_path / "p.csv", tmp_path / "mine.csv"
    assert main(["plan", "--machine", str(PRS3_FILE), "--n", "8", "--out", str(csv), "--json", str(out), "--quiet",
                 *flags]) == 0
    # byte for byte but the time taken
    assert json_text({**p.to_dict(), "seconds": 0}) == json_text({**json.loads(out.read_text()), "seconds": 0})
    write_plan(mine, p)
    assert mine.read_text() == csv.read_text()


def test_plan_of_heights_gives_the_json_plan_writes(tmp_path):
    from bayescal.design.relations import relation_plan_csv
    from bayescal.io.answers import json_text

    delta = ROOT / "examples" / "delta" / "machine.toml"
    p = bayescal.plan(delta, 4, measure="height", radius=60.0)
    out, csv = tmp_path / "h.json", tmp_path / "h.csv"
    assert main(["plan", "--machine", str(delta), "--measure", "height", "--n", "4", "--radius", "60",
                 "--out", str(csv), "--json", str(out), "--quiet"]) == 0
    assert json_text(p.to_dict()) == out.read_text()
    assert relation_plan_csv(p) == csv.read_text()


@pytest.mark.parametrize("call, match", [
    (lambda: bayescal.plan(PRS3_FILE, 0), r"n \(--n\): expected a whole number >= 1, got 0"),
    (lambda: bayescal.plan(PRS3_FILE, 8, n_candidates=5), r"n_candidates \(--candidates\): expected a whole number >= 8"),
    (lambda: bayescal.plan(PRS3_FILE, 8, radius=5.0), r"--radius \(keyword radius\) goes with --measure height"),
    (lambda: bayescal.plan(PRS3_FILE, 8, certify=2.0), r"certify \(--certify\): expected a fraction in \(0, 1\)"),
    (lambda: bayescal.plan(PRS3_FILE, 8, colour="red"), r"plan: unknown option 'colour'"),
    (lambda: bayescal.plan(ROOT / "examples" / "delta" / "machine.toml", 3, measure="height", box=False),
     r"--no-box: only for poses; not with --measure height"),
    (lambda: bayescal.compare(PRS3_FILE, trials=0), r"trials \(--trials\): expected a positive whole number"),
    (lambda: bayescal.compare(PRS3_FILE, frame="fit"), r"--frame fit \(keyword frame='fit'\): compare draws"),
    (lambda: bayescal.compare(PRS3_FILE, alpha=1.5), r"alpha \(--alpha\): expected a number between 0 and 1"),
    (lambda: bayescal.compare(PRS3_FILE, recording=REC, poses=10), r"poses \(--poses\): every trial re-measures"),
])
def test_plan_and_compare_refuse_bad_arguments_by_name(call, match):
    with pytest.raises(bayescal.InputError, match=match):
        call()


def _timeless(obj):
    """``obj`` without its wall times (keys named seconds): all else byte for byte."""
    if isinstance(obj, dict):
        return {k: _timeless(v) for k, v in obj.items() if k != "seconds"}
    if isinstance(obj, list):
        return [_timeless(v) for v in obj]
    return obj


def test_compare_gives_the_json_compare_writes_byte_for_byte(tmp_path):
    from bayescal.io.answers import json_text

    cmp = bayescal.compare(PRS3_FILE, methods="ls,map", trials=3, poses=24, n_eval=20, seed=4, progress=False,
                           out=tmp_path / "lib")
    out = tmp_path / "c.json"
    assert main(["compare", "--machine", str(PRS3_FILE), "--methods", "ls,map", "--trials", "3", "--poses", "24",
                 "--eval-poses", "20", "--seed", "4", "--json", str(out), "--quiet", "--out", str(tmp_path / "cli")]) == 0
    assert json_text(_timeless(cmp.to_dict())) == json_text(_timeless(json.loads(out.read_text())))
    paths = bayescal.compare.write_comparison_folder(cmp, tmp_path / "lib")
    assert [p.name for p in paths[:2]] == ["table.txt", "comparison.json"] and all(p.exists() for p in paths)
    lib_table, cli_table = ((tmp_path / d / "table.txt").read_text().splitlines() for d in ("lib", "cli"))
    assert lib_table[:-1] == cli_table[:-1] and lib_table[-1].split(" in ")[0] == cli_table[-1].split(" in ")[0]
    lib, cli = (json.loads((tmp_path / d / "comparison.json").read_text()) for d in ("lib", "cli"))
    assert _timeless(lib) == _timeless(cli)


def test_load_klipper_writes_the_files_bayescal_klipper_writes(tmp_path):
    from bayescal.io.answers import json_text
    from tests import klipper_configs as synth

    cfg = synth.write_config(tmp_path / "printer")
    k = bayescal.load_klipper(cfg)
    assert main(["klipper", str(cfg), "--out", str(tmp_path / "cli"), "--json", str(tmp_path / "k.json"),
                 "--quiet"]) == 0
    written = k.write(tmp_path / "lib")
    for path in written:
        assert path.read_text() == (tmp_path / "cli" / path.name).read_text()
    assert json_text(k.to_dict(tmp_path / "cli")) == (tmp_path / "k.json").read_text()
    # ready for the front door: the same session bayescal.load gives from the written files
    s = bayescal.load(k.machine, k.recording)
    assert s.n_poses == k.recording.n_rows == 14 and k.n_heights == 8
    with pytest.raises(bayescal.InputError, match=r"sigma_height \(--sigma-height\): expected a positive number"):
        bayescal.load_klipper(cfg, sigma_height=float("nan"))


SIMULATE_CASES = {
    "poses": ({"seed": 1}, 12, ["--poses", "12", "--seed", "1"]),
    "effects and channels, 5-DOF": ({"seed": 3, "dof": 5, "effects": ["backlash:30"], "aux": ["time_s"]}, 20,
                                    ["--poses", "20", "--seed", "3", "--dof", "5", "--effect", "backlash:30",
                                     "--aux", "time_s"]),
    "ballbar": ({"seed": 2, "ballbar": 40.0, "planes": ["xy", "xz"]}, 8,
                ["--poses", "8", "--seed", "2", "--ballbar", "40", "--planes", "xy,xz"]),
}


@pytest.mark.parametrize("case", list(SIMULATE_CASES))
def test_simulate_writes_the_files_bayescal_simulate_writes(tmp_path, case, capsys):
    options, n, flags = SIMULATE_CASES[case]
    machine = ROOT / "examples" / "delta" / "machine.toml" if case == "ballbar" else PRS3_FILE
    sim = bayescal.simulate_session(machine, n, **options)
    assert main(["simulate", "--machine", str(machine), "--out", str(tmp_path / "cli.csv"), *flags]) == 0
    said = capsys.readouterr().out
    paths = sim.write(tmp_path / "lib.csv")
    for mine, theirs in zip(paths, ("cli.csv", "cli.truth.json", "cli.truth.toml")):
        assert mine.read_text() == (tmp_path / theirs).read_text()
    assert sim.report(tmp_path / "cli.csv") == said.strip()


def test_simulate_at_a_plan_and_its_refusals(tmp_path):
    p = bayescal.plan(PRS3_FILE, 6, n_candidates=200, n_random=0)
    from bayescal.design import write_plan

    write_plan(tmp_path / "poses.csv", p)
    sim = bayescal.simulate_session(PRS3_FILE, seed=0, poses_file=tmp_path / "poses.csv")
    np.testing.assert_allclose(sim.recording.q, p.q, atol=1e-12)
    for options, match in [({"seed": 0}, r"give n \(--poses N"),
                           ({"seed": 0, "n": 0}, r"n \(--poses\): expected a positive whole number"),
                           ({"seed": 0, "n": 4, "pivot": "0,0,0"}, r"--pivot \(keyword pivot\) goes with --ballbar"),
                           ({"seed": 0, "n": 4, "tolerance_scale": -1.0}, r"tolerance_scale \(--tolerance-scale\)"),
                           ({"seed": 0, "n": 5, "poses_file": tmp_path / "poses.csv"}, r"n \(--poses\) 5 but")]:
        n = options.pop("n", None)
        with pytest.raises(bayescal.InputError, match=match):
            bayescal.simulate_session(PRS3_FILE, n, **options)


def test_compensate_gives_the_grid_and_json_bayescal_compensate_writes(tmp_path):
    from bayescal.compensation import write_grid
    from bayescal.io.answers import json_text

    X, Z = np.meshgrid(np.linspace(-300, 300, 7), np.linspace(-200, 200, 7))
    f = lambda x, z: (1e-4 * x + 2e-4 * z, -1e-4 * x * z / 200)  # noqa: E731
    rows = ["x,z,ex,ez"] + [f"{x},{z},{f(x, z)[0]},{f(x, z)[1]}" for x, z in zip(X.ravel(), Z.ravel())]
    (tmp_path / "e.csv").write_text("\n".join(rows) + "\n")
    xs, zs = np.linspace(-250, 250, 9), np.linspace(-150, 150, 9)
    (tmp_path / "f.csv").write_text("\n".join(["x,z,ex,ez"] + [f"{x},{z},{f(x, z)[0]},{f(x, z)[1]}"
                                                             for x, z in zip(xs, zs)]) + "\n")
    c = bayescal.compensate(errors=tmp_path / "e.csv", x_range=(-300, 300), z_range=(-200, 200), n=4,
                            node_std=0.001, evaluate=tmp_path / "f.csv")
    assert main(["compensate", "--errors", str(tmp_path / "e.csv"), "--x-range", "-300", "300", "--z-range", "-200",
                 "200", "--n", "4", "--node-std", "0.001", "--out", str(tmp_path / "g.csv"), "--evaluate",
                 str(tmp_path / "f.csv"), "--json", str(tmp_path / "a.json")]) == 0
    write_grid(tmp_path / "mine.csv", c.grid)
    assert (tmp_path / "mine.csv").read_text() == (tmp_path / "g.csv").read_text()
    assert json_text(c.evaluation) == (tmp_path / "a.json").read_text()
    with pytest.raises(bayescal.InputError, match=r"errors \(--errors\) builds a grid and grid \(--grid\) reads one"):
        bayescal.compensate(errors=tmp_path / "e.csv", grid=tmp_path / "g.csv")


def test_every_answer_shows_its_report_in_a_notebook(tmp_path):
    """A notebook cell ending in an answer shows the text the command prints (escaped, preformatted)."""
    from html import escape

    answers = [
        bayescal.predict(PRS3_FILE, REC),
        bayescal.grid(bayescal.load(PRS3_FILE, REC), nodes=3),
        bayescal.plan(PRS3_FILE, 6, n_candidates=200, n_random=0),
        bayescal.plan(ROOT / "examples" / "delta" / "machine.toml", 3, measure="height"),
        bayescal.compare(PRS3_FILE, methods="map", trials=2, poses=24, n_eval=10, progress=False),
    ]
    for a in answers:
        html = a._repr_html_()
        assert html.startswith("<pre>") and escape(a.report()) in html, type(a).__name__


@pytest.mark.parametrize("call, match", [
    (lambda s: bayescal.grid(s, methd="map"), "grid: unknown option 'methd' \\(did you mean 'method'\\?\\)"),
    (lambda s: bayescal.diagnose(PRS3_FILE, REC, sed=1), "diagnose: unknown option 'sed' \\(did you mean 'seed'\\?\\)"),
    (lambda s: bayescal.compare(PRS3_FILE, method="ls"), "compare: unknown option 'method' \\(did you mean 'methods'\\?\\)"),
    (lambda s: bayescal.calibrate(s, method="mapp"), "expected one of ls, ridge, tsvd, map, kalman, mcmc"),
])
def test_a_misspelt_option_of_a_verb_is_refused_by_name(call, match):
    from bayescal.errors import InputError

    with pytest.raises(InputError, match=match):
        call(bayescal.load(PRS3_FILE, REC))


def test_a_bayesian_calibration_has_parameters_by_name_as_a_deterministic_one():
    cal = bayescal.calibrate(bayescal.load(PRS3_FILE, REC), method="kalman")
    listed = {p["name"]: p for p in cal.to_dict()["parameters"]}
    assert set(cal.parameters) == set(listed)
    for name, p in cal.parameters.items():
        assert (p.value, p.std, p.unit, p.identified, p.estimated) == tuple(
            listed[name][k] for k in ("value", "std", "unit", "identified", "estimated"))
