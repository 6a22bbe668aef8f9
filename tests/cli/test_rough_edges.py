"""End-to-end CLI checks of the paths a new user takes first (issue 16, item 4)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bayescal.cli import main
from tests.conftest import PRS3_FILE, ROOT

RAPSM_FILE = ROOT / "examples" / "raspm" / "machine.toml"
REC = ROOT / "examples" / "prs3" / "recording.csv"


def test_compare_accepts_auto_rules_map_and_kalman(tmp_path, capsys):
    out = tmp_path / "cmp.json"
    code = main(["compare", "--machine", str(PRS3_FILE), "--methods", "ridge:lam=auto,tsvd:k=auto,map,kalman",
                 "--trials", "2", "--poses", "20", "--eval-poses", "10", "--no-progress", "--json", str(out)])
    assert code == 0
    ans = json.loads(out.read_text())
    assert ans["labels"] == ["ridge:lam=auto", "tsvd:k=auto", "map", "kalman"]
    for lab in ans["labels"]:
        assert ans["summary"][lab]["failures"] == 0, ans["failure_messages"]
    assert "wrote" in capsys.readouterr().err


@pytest.mark.slow
def test_compare_runs_mcmc(tmp_path):
    out = tmp_path / "cmp.json"
    code = main(["compare", "--machine", str(PRS3_FILE), "--methods", "map,mcmc:steps=60", "--trials", "1",
                 "--poses", "20", "--eval-poses", "10", "--no-progress", "--json", str(out), "--quiet"])
    # 60 steps do not converge: the sampler runs, its trial fails with the reason, and a method that fails in every
    # trial makes the comparison exit 1 (docs/cli.md exit codes), its JSON written all the same
    assert code == 1
    ans = json.loads(out.read_text())
    assert "mcmc:steps=60" in ans["labels"] and ans["summary"]["map"]["n"] == 1
    assert "not converged" in ans["failure_messages"]["mcmc:steps=60"][0]


def test_compare_bad_option_value_is_one_line(capsys):
    assert main(["compare", "--machine", str(PRS3_FILE), "--methods", "ridge:lam=big", "--trials", "1", "--no-progress",
                 "--quiet"]) in (0, 2)
    # a bad value is recorded as a failed trial or refused; never a traceback
    assert "Traceback" not in capsys.readouterr().err


def test_usage_error_is_one_line_with_its_hint(capsys):
    with pytest.raises(SystemExit) as e:
        main(["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "nonsense"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "invalid choice: 'nonsense'" in err[0] and "--help" in err[0]
    assert not any(line.startswith("usage:") for line in err)


def test_outputs_are_announced_and_missing_folders_refused(tmp_path, capsys):
    missing = tmp_path / "no" / "such"
    code = main(["identify", str(REC), "--machine", str(PRS3_FILE), "--json", str(missing / "a.json"), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "--mkdir" in err
    assert not missing.exists()
    code = main(["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "ridge", "--lam", "1", "--mkdir",
                 "--json", str(missing / "a.json"), "--write-machine", str(missing / "cal.toml")])
    assert code == 0
    err = capsys.readouterr().err
    assert f"wrote {missing / 'a.json'}" in err and f"wrote {missing / 'cal.toml'}" in err
    ans = json.loads((missing / "a.json").read_text())
    # the full covariance over the identified parameters, named, with units
    cov = ans["covariance"]
    free = [p for p in ans["parameters"] if p["estimated"]]
    assert cov["names"] == [p["name"] for p in free] and cov["units"] == [p["unit"] for p in free]
    C = np.array(cov["matrix"])
    assert C.shape == (len(free), len(free)) and np.allclose(C, C.T)
    np.testing.assert_allclose(np.sqrt(np.diag(C)), [p["std"] for p in free], rtol=1e-12)
    np.testing.assert_allclose(np.diag(cov["correlation"]), 1.0)


def test_simulate_at_planned_poses(tmp_path, capsys):
    plan, rec = tmp_path / "plan.csv", tmp_path / "rec.csv"
    assert main(["plan", "--machine", str(PRS3_FILE), "--n", "8", "--candidates", "200", "--random-sets", "2",
                 "--out", str(plan), "--quiet"]) == 0
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses-file", str(plan), "--seed", "4", "--out", str(rec)]) == 0
    q_plan = np.loadtxt(plan, delimiter=",", skiprows=1)[:, :3]
    q_rec = np.loadtxt(rec, delimiter=",", skiprows=1)[:, :3]
    np.testing.assert_array_equal(q_rec, q_plan)
    # the recording is a recording: identify runs on it
    assert main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "map", "--quiet"]) == 0
    bad = tmp_path / "bad.csv"
    bad.write_text("q1,q2,pose_id\n500,500,1\n")
    capsys.readouterr()
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses-file", str(bad), "--seed", "1", "--out", str(rec)]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "q3" in err


def test_simulate_refuses_pose_files_it_cannot_honour(tmp_path, capsys):
    # a pose outside q_limits made a recording that identify then refused; with --ballbar the file was ignored
    poses, rec = tmp_path / "poses.csv", tmp_path / "rec.csv"
    poses.write_text("q1,q2,q3,pose_id\n500,500,500,1\n560,500,500,2\n")
    capsys.readouterr()
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses-file", str(poses), "--seed", "1", "--out", str(rec)]) == 2
    err = capsys.readouterr().err
    assert "poses.csv: line 3, column 'q1'" in err and "q_limits" in err and not rec.exists()
    poses.write_text("q1,q2,q3,pose_id\n500,500,500,1\n")
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses-file", str(poses), "--ballbar", "10", "--seed", "1",
                 "--out", str(rec)]) == 2
    assert "--poses-file" in capsys.readouterr().err and not rec.exists()


@pytest.fixture(scope="module")
def raspm_rec(tmp_path_factory):
    rec = tmp_path_factory.mktemp("raspm") / "rec.csv"
    assert main(["simulate", "--machine", str(RAPSM_FILE), "--poses", "40", "--seed", "2", "--out", str(rec), "--quiet"]) == 0
    return rec


def test_grid_on_the_redundant_module_writes_a_bic_grid(tmp_path, raspm_rec, capsys):
    from bayescal.compensation import read_grid

    nc, js = tmp_path / "bic.csv", tmp_path / "g.json"
    code = main(["grid", str(raspm_rec), "--machine", str(RAPSM_FILE), "--nodes", "3", "--range", "x=-200:200",
                 "--range", "z=-450:-300", "--nc", str(nc), "--json", str(js)])
    assert code == 0, capsys.readouterr().err
    g = read_grid(nc)  # the NC-loadable BIC format the compensate command and an NC system read
    np.testing.assert_allclose(g.xs, [-200, 0, 200])
    np.testing.assert_allclose(g.zs, [-450, -375, -300])
    assert np.isfinite(g.std).all() and (g.std > 0).all()
    assert json.loads(js.read_text())["controlled_axes"] == ["x", "z"]


def test_grid_too_wide_names_the_option_that_narrows_it(raspm_rec, capsys):
    code = main(["grid", str(raspm_rec), "--machine", str(RAPSM_FILE), "--nodes", "3", "--range", "x=-5000:5000", "--quiet"])
    assert code == 2
    assert "--range x=LO:HI" in capsys.readouterr().err
    code = main(["grid", str(raspm_rec), "--machine", str(RAPSM_FILE), "--space", "actuator", "--nodes", "3", "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert "--range q1=LO:HI" in err and "--space tool" in err
    code = main(["grid", str(raspm_rec), "--machine", str(RAPSM_FILE), "--range", "w=1:2", "--quiet"])
    assert code == 2 and "x, y, z" in capsys.readouterr().err


def test_tool_space_grid_of_a_non_redundant_machine(tmp_path, prs3):
    """Nodes are where the nominal machine puts the tool point; node values are the identified machine's error there."""
    from bayescal.bayes.tool_grid import NC_COLUMNS

    nc, out = tmp_path / "nc.csv", tmp_path / "grid.csv"
    assert main(["grid", str(REC), "--machine", str(PRS3_FILE), "--space", "tool", "--nodes", "3", "--nc", str(nc),
                 "--out", str(out), "--quiet"]) == 0
    head = nc.read_text().splitlines()[0].split(",")
    assert tuple(head) == NC_COLUMNS
    rows = np.loadtxt(nc, delimiter=",", skiprows=1)
    assert rows.shape == (27, 12)
    g = np.genfromtxt(out, delimiter=",", names=True)
    q = np.column_stack([g["q1"], g["q2"], g["q3"]])
    # nominal forward kinematics of the commanded q reproduces the node (independent of the IK)
    np.testing.assert_allclose(prs3.forward(q).position, np.column_stack([g["x"], g["y"], g["z"]]), atol=1e-6)
    assert (q >= prs3.q_limits[:, 0] - 1e-9).all() and (q <= prs3.q_limits[:, 1] + 1e-9).all()
    # correction = -(error), same nodes in the NC file (order i fastest there, C order over x, y, z here)
    nc_sorted = rows[np.lexsort((rows[:, 2], rows[:, 1], rows[:, 0]))]
    np.testing.assert_allclose(nc_sorted[:, 6:9], -np.column_stack([g["dx"], g["dy"], g["dz"]]), rtol=1e-8, atol=1e-12)


def test_mcmc_resume_gives_the_uninterrupted_result(tmp_path):
    ck = tmp_path / "chain.npz"
    base = ["identify", str(REC), "--machine", str(PRS3_FILE), "--method", "mcmc", "--surrogate", "linear", "--seed", "5",
            "--quiet"]
    full, resumed = tmp_path / "full.json", tmp_path / "resumed.json"
    assert main(base + ["--steps", "300", "--json", str(full)]) == 0
    # "killed" after 150 steps: the checkpoint holds them
    main(base + ["--steps", "150", "--checkpoint", str(ck), "--checkpoint-every", "50"])
    assert ck.is_file()
    assert main(base + ["--steps", "300", "--checkpoint", str(ck), "--resume", "--json", str(resumed)]) == 0
    a, b = json.loads(full.read_text()), json.loads(resumed.read_text())
    a["convergence"].pop("seconds"), b["convergence"].pop("seconds")
    assert a == b
    # another run's checkpoint is refused
    assert main(base[:-3] + ["--seed", "6", "--quiet", "--steps", "300", "--checkpoint", str(ck), "--resume"]) == 2
