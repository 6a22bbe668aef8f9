"""Reports of every kind, made once per session through the command line with small settings."""

from __future__ import annotations

import pytest

from bayescal.cli import main
from tests.conftest import PRS3_FILE, ROOT


def _run(args):
    code = main(args)
    assert code == 0, args


@pytest.fixture(scope="session")
def reports(tmp_path_factory):
    d = tmp_path_factory.mktemp("reports")
    rec = str(ROOT / "examples" / "prs3" / "recording.csv")
    m = str(PRS3_FILE)
    _run(["identify", rec, "--machine", m, "--method", "map", "--report", str(d / "identify.html"), "--json", str(d / "identify.json"), "--quiet"])
    _run(["identify", rec, "--machine", m, "--method", "kalman", "--report", str(d / "kalman.html"),
          "--json", str(d / "kalman.json"), "--quiet"])
    # a few parameters keep the sampler and the one-row-per-parameter traces quick
    few = "chain1.link_length,chain2.link_length,chain3.link_length,chain1.sphere_center.x,chain2.sphere_center.y,tool.point.z"
    _run(["identify", rec, "--machine", m, "--method", "mcmc", "--surrogate", "linear", "--steps", "300", "--free", few, "--report",
          str(d / "mcmc.html"), "--json", str(d / "mcmc.json"), "--quiet"])
    _run(["diagnose", rec, "--machine", m, "--effects", "backlash", "--report", str(d / "diagnose.html"),
          "--json", str(d / "diagnose.json"), "--quiet"])
    _run(["compare", "--machine", m, "--methods", "ls,map", "--trials", "2", "--poses", "20", "--eval-poses", "10",
          "--no-progress", "--report", str(d / "compare.html"), "--json", str(d / "compare.json"), "--quiet"])
    _run(["plan", "--machine", m, "--n", "10", "--candidates", "300", "--random-sets", "3", "--out", str(d / "plan.csv"),
          "--report", str(d / "plan.html"), "--json", str(d / "plan.json"), "--quiet"])
    _run(["grid", rec, "--machine", m, "--nodes", "3", "--report", str(d / "grid.html"), "--json", str(d / "grid.json"), "--quiet"])
    errors = d / "errors.csv"
    errors.write_text("x,z,ex,ez\n" + "".join(
        f"{x},{z},{0.001 * x / 300:.6f},{-0.002 * z / 200:.6f}\n" for x in (-300, 0, 300) for z in (-200, 0, 200)))
    _run(["compensate", "--errors", str(errors), "--x-range", "-300", "300", "--z-range", "-200", "200", "--n", "3",
          "--out", str(d / "bic.csv"), "--report", str(d / "compensate.html")])
    return d
