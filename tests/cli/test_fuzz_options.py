"""Fuzzing option values of the commands: every run ends in exit 0, 1 or 2, and 2 with one error line (issue 30, item 4).

In-process calls of ``bayescal.cli.main`` (no subprocesses), derandomised
hypothesis cases, each within hypothesis' deadline.  Values come from hostile
sets (negative, zero, huge, NaN, not numbers) and a few ordinary ones, so that
the commands that do run stay small.
"""

from __future__ import annotations

import contextlib
import io
import shutil
from datetime import timedelta

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bayescal.cli import main
from tests.conftest import PRS3_FILE, ROOT

CLI = settings(max_examples=15, deadline=timedelta(seconds=20), derandomize=True,
               suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

INTS = st.sampled_from(["-1", "0", "1", "2", "3", "-99999999999999999999", "4294967296", str(2**63), str(10**30), "1.5",
                        "abc", "", "0x10", "1e3"])
FLOATS = st.sampled_from(["-1", "0", "1e-300", "0.5", "1", "2", "nan", "inf", "-inf", "1e300", "abc", "", "1e400", "-0"])
TEXT = st.sampled_from(["", "x", "a,b", ",", "q1", "all", "auto", "..", "/", "\u0661", "--json"])


def check(argv: list[str]) -> int:
    """Run one command; assert the exit code and the one error line, never a traceback."""
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as e:  # argparse's usage errors
            code = e.code
    text = err.getvalue()
    assert "Traceback" not in text, text
    assert code in (0, 1, 2), (code, text)
    if code == 2:
        lines = text.strip().splitlines()
        errors = [ln for ln in lines if ": error: " in ln]
        # exactly one line: the error (argparse's usage errors carry their hint on the same line)
        assert len(lines) == 1 and len(errors) == 1, text
    return code


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    shutil.copy(ROOT / "examples" / "prs3" / "recording.csv", d / "r.csv")
    shutil.copy(PRS3_FILE, d / "m.toml")
    (d / "e.csv").write_text("x,z,ex,ez\n-10,-10,0.01,0\n10,-10,0,0.002\n-10,10,0,0\n10,10,0.001,0\n0,0,0,0\n")
    return d


@CLI
@given(st.fixed_dictionaries({}, optional={
    "--poses": INTS, "--seed": INTS, "--tolerance-scale": FLOATS, "--dof": INTS, "--effect": st.sampled_from(
        ["backlash", "backlash:30", "backlash:-1", "backlash:nan", "nope", "thermal_expansion:1e300", ":", "backlash:"]),
    "--aux": TEXT, "--ballbar": FLOATS, "--pivot": st.sampled_from(["0,0,0", "1,2", "nan,0,0", "a,b,c"]),
    "--planes": st.sampled_from(["xy", "xz,yz", "xx", ""])}))
def test_simulate_options(d, opts):
    argv = ["simulate", "--machine", d / "m.toml", "--out", d / "s.csv", "--quiet"]
    opts.setdefault("--seed", "1")
    opts.setdefault("--poses", "3")
    for k, v in opts.items():
        argv += [k, v]
    check(argv)


@CLI
@given(st.fixed_dictionaries({"--n": INTS}, optional={"--x-range": st.tuples(FLOATS, FLOATS),
                                                      "--z-range": st.tuples(FLOATS, FLOATS), "--node-std": FLOATS}))
def test_compensate_options(d, opts):
    argv = ["compensate", "--errors", d / "e.csv", "--out", d / "g.csv"]
    opts.setdefault("--x-range", ("-10", "10"))
    opts.setdefault("--z-range", ("-10", "10"))
    for k, v in opts.items():
        argv += [k, *v] if isinstance(v, tuple) else [k, v]
    check(argv)


@CLI
@given(st.fixed_dictionaries({}, optional={
    "--lam": FLOATS, "--max-iter": INTS, "--dof": INTS, "--free": TEXT, "--nu": FLOATS, "--outlier-alpha": FLOATS,
    "--robust": st.sampled_from(["auto", "off", "t", "x"]), "--frame": st.sampled_from(["base", "fit", "x"]),
    "--seed": INTS, "--walkers": INTS, "--posterior": st.just("p.nc"), "--k": INTS}))
def test_identify_options(d, opts):
    argv = ["identify", d / "r.csv", "--machine", d / "m.toml", "--method", "ridge", "--quiet", "--json", d / "a.json"]
    opts.setdefault("--lam", "1")
    opts.setdefault("--max-iter", "3")  # ordinary runs stay short
    for k, v in opts.items():
        argv += [k, d / v if k == "--posterior" else v]
    check(argv)


@CLI
@given(st.fixed_dictionaries({"--measure": st.sampled_from(["height", "distance"])}, optional={
    "--n": INTS, "--radius": FLOATS, "--spacing": FLOATS, "--sigma": FLOATS, "--min-distance": FLOATS,
    "--centre": st.sampled_from(["0,0,0", "0,0", "nan,0,0", "1e300,0,0", "x"]), "--seed": INTS,
    "--criterion": st.sampled_from(["EIG", "D", "I", "nope"])}))
def test_plan_relation_options(d, opts):
    argv = ["plan", "--machine", d / "m.toml", "--out", d / "p.csv", "--quiet"]
    opts.setdefault("--n", "2")
    opts.setdefault("--spacing", "25")
    for k, v in opts.items():
        argv += [k, v]
    check(argv)


@CLI
@given(st.fixed_dictionaries({"--methods": st.sampled_from(
    ["ridge:foo=1", "ridge:lam=abc", "tsvd:k=0", "ls:k=3", "mcmc:steps=5", "mcmc:ess=0", "mcmc:ess=abc", "kalman:variant=x", "nope", ",", "ridge:rule=gcv",
     "ridge:lam=nan", "tsvd:k=2.5", "ridge;lam=1", "ridge:lam"])}, optional={
    "--trials": INTS, "--poses": INTS, "--eval-poses": INTS, "--alpha": FLOATS, "--tolerance-scale": FLOATS,
    "--seed": INTS}))
def test_compare_options_refused_before_any_trial(d, opts):
    argv = ["compare", "--machine", d / "m.toml", "--no-progress", "--quiet"]
    for k, v in opts.items():
        argv += [k, v]
    # every --methods value above is refused, whatever the other options: before a trial runs
    assert check(argv) == 2


@CLI
@given(st.sampled_from(["json", "report", "write-machine", "write-klipper"]),
       st.sampled_from(["/dev/null", "{d}/r.csv", "{d}/m.toml", "{d}", "{d}/nope/a", "{d}/link", "{d}/fifo", ""]))
def test_output_paths(d, option, target):
    import os

    if not (d / "fifo").exists():
        os.mkfifo(d / "fifo")
        (d / "victim").write_text("keep")
        (d / "link").symlink_to(d / "victim")
    code = check(["identify", d / "r.csv", "--machine", d / "m.toml", "--method", "ridge", "--lam", "1", "--max-iter", "2",
                  "--quiet", f"--{option}", target.format(d=d)])
    assert (d / "victim").read_text() == "keep"
    assert (d / "r.csv").read_bytes() == (ROOT / "examples" / "prs3" / "recording.csv").read_bytes()
    assert (d / "m.toml").read_bytes() == PRS3_FILE.read_bytes()
    if target not in ("",):
        assert code == 2


@CLI
@given(st.fixed_dictionaries({}, optional={
    "--nodes": INTS, "--seed": INTS, "--range": st.sampled_from(["q1=450:550", "q1=550:450", "x=0:1", "q9=0:1", "q1=nan:1",
                                                                 "q1", "=:", "q1=1e300:1e301"]),
    "--aux": st.sampled_from(["payload_kg=5", "temp_C=nan", "nope=1", "payload_kg", "=", "payload_kg=1e400"]),
    "--space": st.sampled_from(["auto", "tool", "actuator", "x"]), "--free": TEXT,
    "--method": st.sampled_from(["map", "kalman", "ls"]), "--steps": INTS}))
def test_grid_options(d, opts):
    argv = ["grid", d / "r.csv", "--machine", d / "m.toml", "--quiet", "--out", d / "g.csv"]
    opts.setdefault("--nodes", "2")
    for k, v in opts.items():
        argv += [k, v]
    check(argv)


@CLI
@given(st.fixed_dictionaries({}, optional={
    "--dof": st.sampled_from(["6", "5", "3", "4", "x"]), "--frame": st.sampled_from(["base", "fit", "x"]),
    "--json": st.sampled_from(["p.json", "r.csv", "m.toml", ""])}))
def test_predict_options(d, opts):
    argv = ["predict", d / "r.csv", "--machine", d / "m.toml", "--quiet"]
    for k, v in opts.items():
        argv += [k, d / v if k == "--json" and v else v]
    check(argv)
    assert (d / "r.csv").read_bytes() == (ROOT / "examples" / "prs3" / "recording.csv").read_bytes()
    assert (d / "m.toml").read_bytes() == PRS3_FILE.read_bytes()
