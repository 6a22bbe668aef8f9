"""Every exit-2 path of every command prints exactly one line on stderr (issue 30).

A handful of bad invocations per command, run in-process: usage errors
(argparse's, with the hint folded into the same line), bad files, bad option
values and refused output paths all end in exit 2 and one stderr line.
"""

from __future__ import annotations

import contextlib
import io
import shutil

import pytest

from bayescal.cli import main
from tests.conftest import PRS3_FILE, ROOT


def run(argv) -> tuple[int, str]:
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as e:  # argparse's usage errors
            code = e.code
    return code, err.getvalue()


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    d = tmp_path_factory.mktemp("oneline")
    shutil.copy(ROOT / "examples" / "prs3" / "recording.csv", d / "r.csv")
    shutil.copy(PRS3_FILE, d / "m.toml")
    (d / "bad.csv").write_text("q1,q2\n1,2\n")
    (d / "bad.toml").write_text("[machine\nkind = 1\n")
    (d / "e.csv").write_text("x,z,ex,ez\n-10,-10,0.01,0\n10,-10,0,0.002\n-10,10,0,0\n10,10,0.001,0\n0,0,0,0\n")
    (d / "p.cfg").write_text("[printer]\nkinematics: delta\n[include missing.cfg]\n")
    return d


BAD = {
    "identify": [["{d}/r.csv", "--machine", "{d}/m.toml", "--method", "nonsense"],
                 ["{d}/r.csv", "--machine", "{d}/m.toml", "--nope"],
                 ["{d}/r.csv"],
                 ["{d}/bad.csv", "--machine", "{d}/m.toml"],
                 ["{d}/r.csv", "--machine", "{d}/bad.toml"],
                 ["{d}/r.csv", "--machine", "{d}/m.toml", "--json", "{d}/r.csv"],
                 ["{d}/r.csv", "--machine", "{d}/m.toml", "--max-iter", "abc"]],
    "predict": [["{d}/r.csv"], ["{d}/bad.csv", "--machine", "{d}/m.toml"], ["{d}/r.csv", "--machine", "{d}/nope.toml"],
                ["{d}/r.csv", "--machine", "{d}/m.toml", "--json", "{d}/m.toml"]],
    "simulate": [["--machine", "{d}/m.toml", "--seed", "1"], ["--machine", "{d}/m.toml", "--seed", "-1", "--out", "{d}/s.csv"],
                 ["--machine", "{d}/m.toml", "--seed", "1", "--out", "{d}/m.toml"],
                 ["--machine", "{d}/bad.toml", "--seed", "1", "--out", "{d}/s.csv"],
                 ["--machine", "{d}/m.toml", "--seed", "1", "--poses", "0", "--out", "{d}/s.csv"]],
    "diagnose": [["{d}/r.csv"], ["{d}/bad.csv", "--machine", "{d}/m.toml"],
                 ["{d}/r.csv", "--machine", "{d}/m.toml", "--seed", "2.5"],
                 ["{d}/r.csv", "--machine", "{d}/m.toml", "--figures", "{d}/r.csv"]],
    "compensate": [["--errors", "{d}/nope.csv", "--out", "{d}/g.csv"], ["--errors", "{d}/e.csv", "--n", "-1", "--out", "{d}/g.csv"],
                   ["--errors", "{d}/e.csv", "--out", "{d}/e.csv"], ["--errors", "{d}/bad.csv", "--out", "{d}/g.csv"]],
    "grid": [["{d}/r.csv"], ["{d}/r.csv", "--machine", "{d}/m.toml", "--nodes", "abc"],
             ["{d}/r.csv", "--machine", "{d}/m.toml", "--figure", "{d}/heat.txt"],
             ["{d}/r.csv", "--machine", "{d}/m.toml", "--out", "{d}/r.csv"]],
    "plan": [["--machine", "{d}/m.toml"], ["--machine", "{d}/m.toml", "--n", "x"],
             ["--machine", "{d}/m.toml", "--n", "3", "--criterion", "Z"],
             ["--machine", "{d}/bad.toml", "--n", "3"], ["--machine", "{d}/m.toml", "--n", "3", "--out", "{d}/m.toml"]],
    "compare": [["--machine", "{d}/m.toml", "--methods", "ridge:foo=1"], ["--machine", "{d}/m.toml", "--trials", "-3"],
                ["--machine", "{d}/bad.toml"], ["--methods", "ls"]],
    "klipper": [["{d}/p.cfg"], ["{d}/nope.cfg", "--out", "{d}/k"], ["{d}/p.cfg", "--out", "{d}/k"],
                ["{d}/bad.csv", "--out", "{d}/k"]],
    None: [["nonsense"], ["--nope"]],
}


@pytest.mark.parametrize("command,argv", [(c, a) for c, cases in BAD.items() for a in cases],
                         ids=lambda x: x if isinstance(x, str) else None)
def test_every_refusal_is_one_line(d, command, argv):
    code, text = run(([command] if command else []) + [a.format(d=d) for a in argv])
    assert code == 2, text
    assert "Traceback" not in text
    lines = text.splitlines()
    assert len(lines) == 1 and ": error: " in lines[0], text


def test_usage_error_carries_its_hint_on_the_same_line(d):
    code, text = run(["identify", d / "r.csv", "--machine", d / "m.toml", "--method", "nonsense"])
    assert code == 2
    assert text == ("bayescal identify: error: argument --method: invalid choice: 'nonsense' (choose from 'ls', 'ridge', "
                    "'tsvd', 'map', 'kalman', 'mcmc'); run 'bayescal identify --help' for the options\n")
