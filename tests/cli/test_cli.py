import json

import numpy as np
import pytest

from bayescal.cli import COMMANDS, main
from tests.conftest import PRS3_FILE


def test_simulate_identify_end_to_end(tmp_path, capsys):
    rec = tmp_path / "rec.csv"
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses", "40", "--seed", "5", "--out", str(rec)]) == 0
    truth = json.loads((tmp_path / "rec.truth.json").read_text())
    out_json, cal = tmp_path / "a.json", tmp_path / "cal.toml"
    code = main([
        "identify", str(rec), "--machine", str(PRS3_FILE), "--method", "ridge", "--lam", "1",
        "--json", str(out_json), "--write-machine", str(cal),
    ])
    assert code == 0
    report = capsys.readouterr().out
    assert "RMS position" in report and "chain1.link_length" in report
    ans = json.loads(out_json.read_text())
    assert ans["method"] == "ridge" and ans["machine"] == "spindle head A"
    assert ans["rms_after"]["position"] < 0.2 * ans["rms_before"]["position"]
    assert len(ans["parameters"]) == len(truth["parameters"])
    # the calibrated machine file alone predicts the true machine on fresh poses
    from bayescal.machines.files import load_machine

    nominal, calibrated, true = load_machine(PRS3_FILE), load_machine(cal), load_machine(tmp_path / "rec.truth.toml")
    q = nominal.sample_q(200, np.random.default_rng(0))
    err_cal = np.linalg.norm(calibrated.forward(q).position - true.forward(q).position, axis=1)
    err_nom = np.linalg.norm(nominal.forward(q).position - true.forward(q).position, axis=1)
    sigma = nominal.noise.sigma_position
    assert np.sqrt(np.mean(err_cal**2)) < 3 * sigma < np.sqrt(np.mean(err_nom**2))


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("q1,q2,q3,x,y,z\n500,,500,0,0,0\n")
    assert main(["identify", str(bad), "--machine", str(PRS3_FILE)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.csv" in err[0] and "q2" in err[0] and "line 2" in err[0]


def test_ls_ill_posed_exit_1(tmp_path, capsys):
    rec = tmp_path / "rec5.csv"
    main(["simulate", "--machine", str(PRS3_FILE), "--poses", "30", "--seed", "2", "--dof", "5", "--out", str(rec), "--quiet"])
    assert main(["identify", str(rec), "--machine", str(PRS3_FILE), "--method", "ls", "--free", "all"]) == 1
    assert "ill-posed" in capsys.readouterr().out


def test_help_teaches_with_examples(capsys):
    with pytest.raises(SystemExit) as e:
        main(["identify", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "examples:" in out and "--write-machine" in out


def test_unwritable_output_is_one_line_and_exit_2(tmp_path, capsys):
    blocker = tmp_path / "afile"
    blocker.write_text("")
    code = main([
        "simulate", "--machine", str(PRS3_FILE), "--poses", "3", "--seed", "1", "--out", str(blocker / "rec.csv"), "--quiet",
    ])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "afile" in err[0] and "Traceback" not in err[0]



def test_closed_pipe_ends_quietly(monkeypatch, capsys):
    """`bayescal identify ... | head`: the reader went away; no traceback, no error line, exit 141."""
    import os
    import sys

    class ClosedPipe:
        def __init__(self):
            self.fd = os.open(os.devnull, os.O_WRONLY)

        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            pass

        def fileno(self):
            return self.fd

    from tests.conftest import ROOT

    monkeypatch.setattr(sys, "stdout", ClosedPipe())
    code = main(["identify", str(ROOT / "examples" / "prs3" / "recording.csv"), "--machine", str(PRS3_FILE)])
    assert code == 141
    assert capsys.readouterr().err == ""


def test_closed_pipe_does_not_cost_the_answers(monkeypatch, tmp_path):
    """`bayescal identify ... --json a.json --write-machine m.toml | head`: the files are still written."""
    import os
    import sys

    from bayescal.machines.files import load_machine
    from tests.conftest import ROOT

    class ClosedPipe:
        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            pass

        def fileno(self):
            return os.open(os.devnull, os.O_WRONLY)

    monkeypatch.setattr(sys, "stdout", ClosedPipe())
    ans, cal = tmp_path / "a.json", tmp_path / "cal.toml"
    code = main([
        "identify", str(ROOT / "examples" / "prs3" / "recording.csv"), "--machine", str(PRS3_FILE),
        "--method", "ridge", "--lam", "1", "--json", str(ans), "--write-machine", str(cal),
    ])
    assert code == 141
    assert json.loads(ans.read_text())["method"] == "ridge"
    assert load_machine(cal).name == "spindle head A"


@pytest.mark.parametrize("command", ["identify", "diagnose"])
def test_pose_the_machine_cannot_assemble_names_file_and_line(tmp_path, capsys, command):
    machine = tmp_path / "m.toml"
    machine.write_text(PRS3_FILE.read_text().split("[workspace]")[0])  # no q_limits: any q passes the reader
    lines = ["q1,q2,q3,x,y,z"] + [f"{500 + i},500,500,0,0,30" for i in range(11)]
    lines[3] = "500,500,2500,0,0,30"  # line 4: links 400 mm long cannot span this
    rec = tmp_path / "rec.csv"
    rec.write_text("\n".join(lines) + "\n")
    assert main([command, str(rec), "--machine", str(machine)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{rec}: line 4:" in err[0] and "cannot assemble" in err[0]


def test_every_computing_command_takes_json(tmp_path, capsys):
    """docs/formats.md section 3: every command that computes something can write its answer with --json PATH."""
    from bayescal.cli import COMMANDS, build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for name in COMMANDS:
        assert "--json" in sub.choices[name]._option_string_actions, name
    ans = tmp_path / "truth.json"
    assert main(["simulate", "--machine", str(PRS3_FILE), "--poses", "3", "--seed", "1",
                 "--out", str(tmp_path / "r.csv"), "--json", str(ans), "--quiet"]) == 0
    assert len(json.loads(ans.read_text())["parameters"]) == 36 and (tmp_path / "truth.toml").exists()


def test_top_level_help_imports_no_command_and_no_numpy():
    """`bayescal --help` lists every command with its one-line help without importing the commands' modules
    (each pulls in numpy and the library; issue 32); the one-liners are those the commands register."""
    import subprocess
    import sys

    from bayescal.cli import COMMANDS, SUMMARIES, build_parser

    code = ("import sys\nfrom bayescal.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "print('LOADED', sorted(m for m in sys.modules if m == 'numpy' or m.startswith('bayescal.cli.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "LOADED []"
    for name in COMMANDS:
        assert f"{name}" in out and SUMMARIES[name] in " ".join(out.split())
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert {c.dest: c.help for c in sub._choices_actions} == SUMMARIES


#: What a command's parser may import of the package: the command line's own modules, the option names
#: (bayescal.constants), the errors and the package itself (no library module, which would bring numpy).
_PARSER_MODULES = ("bayescal", "bayescal._lazy", "bayescal.errors", "bayescal.constants")


@pytest.mark.parametrize("command", COMMANDS)
def test_command_help_and_usage_errors_import_neither_numpy_nor_the_library(command):
    """`bayescal COMMAND --help` and a usage error build the command's parser only (issue 31): the choices and
    defaults it shows come from bayescal.constants, and the library (numpy, scipy, ...) is imported by the
    command's run. An import set, not a timing: the help took 0.6-1.3 s of CPU with them, about 0.05 s without."""
    import subprocess
    import sys

    code = (
        "import contextlib, io, sys\nfrom bayescal.cli import build_parser, main\n"
        f"build_parser(({command!r},))\n"
        f"for argv in ([{command!r}, '--help'], [{command!r}, '--no-such-option'], [{command!r}, '--json']):\n"
        "    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):\n"
        "        try:\n            main(argv)\n        except SystemExit:\n            pass\n"
        "heavy = ('numpy', 'scipy', 'matplotlib', 'emcee', 'arviz', 'filterpy', 'dask')\n"
        "print('HEAVY', sorted(m for m in sys.modules if m.split('.')[0] in heavy and '.' not in m))\n"
        f"print('LIBRARY', sorted(m for m in sys.modules if m.startswith('bayescal') and m not in {_PARSER_MODULES!r}"
        " and not m.startswith('bayescal.cli')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    lines = out.strip().splitlines()
    assert lines[-2:] == ["HEAVY []", "LIBRARY []"], out


def test_the_parsers_names_are_the_librarys():
    """The names the parsers offer (bayescal.constants) are the ones the library acts on, defined once."""
    from bayescal import constants
    from bayescal.bayes.priors import PRIOR_SCALES
    from bayescal.compare import METHODS, METRICS
    from bayescal.design import CRITERIA, SCALINGS
    from bayescal.effects import EFFECTS
    from bayescal.identify.choose import DEFAULT_RULE, RULE_NAMES
    from bayescal.outliers import ALPHA, DEFAULT_NU

    assert (PRIOR_SCALES, RULE_NAMES, DEFAULT_RULE, CRITERIA, SCALINGS, METRICS) == (
        constants.PRIOR_SCALES, constants.RULE_NAMES, constants.DEFAULT_RULE, constants.CRITERIA, constants.SCALINGS,
        constants.METRICS)
    assert (ALPHA, DEFAULT_NU) == (constants.OUTLIER_ALPHA, constants.DEFAULT_NU)
    assert tuple(EFFECTS) == constants.EFFECT_NAMES and all(cls.name == name for name, cls in EFFECTS.items())
    # compare --help lists these: the registry's own methods (all of them, as a fresh process has it), described by
    # the same words
    assert {name: METHODS[name].help for name in constants.COMPARE_METHODS} == constants.COMPARE_METHODS
    import subprocess
    import sys

    code = "from bayescal.compare import METHODS\nprint(' '.join(METHODS))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == list(constants.COMPARE_METHODS)


def test_values_that_start_with_a_minus_sign_are_values():
    # argparse took --pivot -10,0,80 and --x-range -3e2 3e2 for options: "expected one argument" (exit 2)
    from bayescal.cli import build_parser

    a = build_parser(("simulate",)).parse_args(["simulate", "--machine", "m.toml", "--seed", "1", "--out", "o.csv",
                                                "--ballbar", "10", "--pivot", "-10,0,80"])
    assert a.pivot == "-10,0,80"
    c = build_parser(("compensate",)).parse_args(["compensate", "--x-range", "-3e2", "3e2", "--z-range", "-.5", "1e-3"])
    assert c.x_range == [-300.0, 300.0] and c.z_range == [-0.5, 0.001]
    p = build_parser(("plan",)).parse_args(["plan", "--machine", "m.toml", "--n", "3", "--out", "p.csv",
                                            "--measure", "height", "--centre", "-5,0,0.2"])
    assert list(p.centre) == [-5.0, 0.0, 0.2]
    with pytest.raises(SystemExit):  # an unknown option is still one
        build_parser(("plan",)).parse_args(["plan", "--machine", "m.toml", "--n", "3", "--out", "p.csv", "-x"])


def test_a_misspelt_option_names_its_command_and_the_option_meant(capsys):
    from pathlib import Path

    ex = Path(__file__).resolve().parents[2] / "examples" / "prs3"
    with pytest.raises(SystemExit) as e:
        main(["identify", str(ex / "recording.csv"), "--machine", str(ex / "machine.toml"), "--methd", "map"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("bayescal identify: error: unrecognized arguments: --methd map")
    assert "(did you mean --method?)" in err and "run 'bayescal identify --help'" in err
