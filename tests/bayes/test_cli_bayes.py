"""bayescal identify --method map | kalman | mcmc end to end, and the coverage study in quick mode."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.io import write_recording
from bayescal.simulate import simulate_recording
from tests.conftest import PRS3_FILE, ROOT


@pytest.fixture(scope="module")
def rec_file(tmp_path_factory, prs3):
    path = tmp_path_factory.mktemp("rec") / "rec.csv"
    write_recording(path, simulate_recording(prs3, 14, seed=3, dof=3).recording)
    return path


def test_identify_map_and_kalman(tmp_path, rec_file, capsys):
    for method in ("map", "kalman"):
        out = tmp_path / f"{method}.json"
        figures = ["--figures", str(tmp_path)] if method == "kalman" else []
        rc = main(["identify", str(rec_file), "--machine", str(PRS3_FILE), "--method", method, "--json", str(out),
                   *figures])
        assert rc == 0
        d = json.loads(out.read_text())
        assert d["method"] == method
        stds = [p["std"] for p in d["parameters"] if p["identified"]]
        assert stds and all(s is not None and s > 0 for s in stds)
        assert "strong_correlations" in d
    assert (tmp_path / "kalman_history.png").stat().st_size > 1000
    assert "predicted workspace accuracy" in capsys.readouterr().out


@pytest.mark.parametrize("method, option, match", [
    ("kalman", ["--prior-scale", "tolerance"], "--prior-scale goes with --method map"),
    ("mcmc", ["--lam", "1"], "--lam goes with --method ridge (got --method mcmc)"),
    ("kalman", ["--k", "3"], "--k goes with --method tsvd (got --method kalman)"),
    ("mcmc", ["--steps", "5"], "steps (--steps): expected a whole number of at least 20, got 5"),
])
def test_an_option_kalman_and_mcmc_do_not_use_is_refused_not_ignored(rec_file, capsys, method, option, match):
    # --prior-scale, --lam and --k were silently ignored with kalman and mcmc
    assert main(["identify", str(rec_file), "--machine", str(PRS3_FILE), "--method", method, *option]) == 2
    assert match in capsys.readouterr().err


def test_strong_correlations_flagged():
    from bayescal.bayes.summary import strong_correlations

    C = np.array([[1.0, 0.99, 0.0], [0.99, 1.0, -0.96], [0.0, -0.96, 1.0]]) * 4e-6
    pairs = strong_correlations(C, ("a", "b", "c"))
    assert [(a, b) for a, b, _ in pairs] == [("a", "b"), ("b", "c")]
    assert pairs[1][2] == pytest.approx(-0.96)


def test_identify_mcmc_refuses_then_writes(tmp_path, rec_file, capsys):
    out = tmp_path / "m.json"
    args = ["identify", str(rec_file), "--machine", str(PRS3_FILE), "--method", "mcmc", "--surrogate", "linear",
            "--free", "chain1.link_length,chain2.link_length,chain3.link_length", "--json", str(out), "--quiet"]
    assert main(args + ["--steps", "30", "--posterior", str(tmp_path / "no.nc")]) == 1
    d = json.loads(out.read_text())
    assert not d["success"] and "more steps" in d["message"]
    assert all(p["std"] is None for p in d["parameters"])
    assert not (tmp_path / "no.nc").exists()
    capsys.readouterr()
    loud = [a for a in args if a != "--quiet"]
    rc = main(loud + ["--steps", "600", "--walkers", "10", "--posterior", str(tmp_path / "p.nc"), "--figures", str(tmp_path)])
    assert rc == 0
    assert f"wrote {tmp_path / 'p.nc'} (posterior draws, NetCDF)" in capsys.readouterr().err
    assert (tmp_path / "p.nc").stat().st_mode & 0o644 == 0o644  # readable like every other output
    d = json.loads(out.read_text())
    assert d["success"] and len(d["interval_90"]) == 3
    assert (tmp_path / "p.nc").exists() and (tmp_path / "mcmc_trace.png").exists() and (tmp_path / "mcmc_pair.png").exists()


def test_coverage_study_quick(tmp_path):
    r = subprocess.run(
        [sys.executable, str(ROOT / "studies" / "coverage.py"), "--quick", "--out", str(tmp_path)],
        capture_output=True, text=True, cwd=ROOT, timeout=600,
    )
    assert r.returncode == 0, r.stderr
    table = json.loads((tmp_path / "coverage.json").read_text())["table"]
    assert set(table) == {"ls", "map", "map_all", "kalman", "mcmc"}
    assert table["mcmc"]["machines"] + table["mcmc"]["failed"] == 2  # quick: 2 machines sampled
    assert np.isfinite(table["mcmc"]["param_z_rms"])
    for m, t in table.items():
        if m == "mcmc":
            continue
        # 10 machines: the 90% intervals must cover at roughly their nominal rate
        assert 0.8 < t["parameters"] < 0.97, (m, t)
        assert 0.8 < t["tool_points"] < 0.97, (m, t)
    assert (tmp_path / "coverage.png").exists() and (tmp_path / "coverage.md").exists()
    assert np.isfinite(table["map_all"]["param_z_rms"])


def test_coverage_rows_do_not_depend_on_the_number_of_workers():
    import argparse

    sys.path.insert(0, str(ROOT / "studies"))
    import coverage as cov

    args = argparse.Namespace(machine=str(PRS3_FILE), seed=1234, poses=36, dof=6, n_machines=2, n_mcmc=0,
                              mcmc_steps=60, surrogate="linear", workers=1)
    from bayescal.machines.files import load_machine
    from bayescal.simulate import draw_poses

    q = draw_poses(load_machine(PRS3_FILE), 3, np.random.default_rng(0))
    one = cov.run_machines(args, q)
    args.workers = 2
    two = cov.run_machines(args, q)
    for r in one + two:
        r.pop("mcmc_seconds", None)  # wall time, the one thing that differs
    assert one == two and [r["seed"] for r in one] == [1234, 1235]
