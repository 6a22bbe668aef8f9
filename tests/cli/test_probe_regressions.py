"""The tracebacks and silent acceptances a probe found (issue 30, item 6-7): each an exit 2 with one line naming the cause."""

from __future__ import annotations

import csv
import io
import os
import shutil
import sys

import pytest

from bayescal.cli import main
from tests.conftest import PRS3_FILE, ROOT

REC = ROOT / "examples" / "prs3" / "recording.csv"
HYB = ROOT / "examples" / "hybrid_table"


def run(capsys, *argv) -> tuple[int, list[str]]:
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    return code, captured.err.strip().splitlines()


def refused(capsys, *argv, match: str | tuple[str, ...]) -> None:
    code, err = run(capsys, *argv)
    assert code == 2 and len(err) == 1, err
    for m in (match,) if isinstance(match, str) else match:
        assert m in err[0], err


@pytest.fixture
def d(tmp_path):
    shutil.copy(REC, tmp_path / "r.csv")
    shutil.copy(PRS3_FILE, tmp_path / "m.toml")
    return tmp_path


# ------------------------------------------------------------------ seeds
SEED_COMMANDS = [
    ["simulate", "--machine", "{d}/m.toml", "--poses", "3", "--out", "{d}/x.csv"],
    ["identify", "{d}/r.csv", "--machine", "{d}/m.toml", "--method", "mcmc"],
    ["diagnose", "{d}/r.csv", "--machine", "{d}/m.toml"],
    ["grid", "{d}/r.csv", "--machine", "{d}/m.toml", "--method", "mcmc"],
    ["plan", "--machine", "{d}/m.toml", "--n", "3", "--out", "{d}/p.csv"],
    ["compare", "--machine", "{d}/m.toml", "--trials", "1"],
]


@pytest.mark.parametrize("seed", ["-1", str(2**32), str(2**70)])
@pytest.mark.parametrize("argv", SEED_COMMANDS, ids=[a[0] for a in SEED_COMMANDS])
def test_seeds_outside_32_bits_are_refused_by_every_command(d, capsys, argv, seed):
    refused(capsys, *[a.format(d=d) for a in argv], "--seed", seed, match=("--seed", "from 0 to 4294967295"))


def test_non_finite_numbers_are_refused(d, capsys):
    refused(capsys, "plan", "--machine", d / "m.toml", "--n", "3", "--measure", "height", "--radius", "nan",
            "--out", d / "p.csv", match="--radius: expected a finite number")
    refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", "--method", "ridge", "--lam", "inf",
            match="--lam: expected a finite number")


# ------------------------------------------------------------------ machine files
@pytest.mark.parametrize("line, match", [
    ("sigma_position = 1e-200", ("measurement.sigma_position", "from 1e-06 to 1000 mm")),
    ("sigma_position = 5e3", ("measurement.sigma_position", "from 1e-06 to 1000 mm")),
])
def test_implausible_sigmas_are_refused_with_the_range(d, capsys, line, match):
    text = (d / "m.toml").read_text()
    (d / "m.toml").write_text("\n".join(line if s.startswith("sigma_position") else s for s in text.splitlines()))
    for method in ("ls", "map"):
        refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", "--method", method, match=match)


@pytest.mark.parametrize("text, match", [
    ("kind = " + "1" * 5000 + "\n", "an integer of more than 4300 digits"),
    ("a = " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply"),
    ("a = {" + "b = {" * 3000 + "}" * 3001 + "\n", "nested too deeply"),
])
def test_hostile_toml_is_refused(d, capsys, text, match):
    (d / "bad.toml").write_text(text)
    refused(capsys, "identify", d / "r.csv", "--machine", d / "bad.toml", match=("bad.toml", match))


# ------------------------------------------------------------------ non-regular and oversized inputs
@pytest.mark.parametrize("where", ["recording", "machine", "module", "poses"])
@pytest.mark.parametrize("kind", ["/dev/zero", "/dev/urandom", "fifo", "folder"])
def test_non_regular_inputs_are_refused_before_reading(d, capsys, where, kind):
    if kind.startswith("/dev/") and not os.path.exists(kind):
        pytest.skip(f"no {kind}")
    bad = {"fifo": d / "fifo", "folder": d / "folder"}.get(kind, kind)
    if kind == "fifo":
        os.mkfifo(bad)
    elif kind == "folder":
        os.mkdir(bad)
    what = {"fifo": "named pipe", "folder": "folder"}.get(kind, "character device")
    if where == "recording":
        refused(capsys, "identify", bad, "--machine", d / "m.toml", match=(str(bad), what))
    elif where == "machine":
        refused(capsys, "identify", d / "r.csv", "--machine", bad, match=(str(bad), what))
    elif where == "poses":
        refused(capsys, "simulate", "--machine", d / "m.toml", "--poses-file", bad, "--seed", "1", "--out", d / "x.csv",
                match=(str(bad), what))
    else:
        for f in ("table.toml", "recording.csv"):
            shutil.copy(HYB / f, d / f)
        (d / "hyb.toml").write_text((HYB / "machine.toml").read_text().replace('"head.toml"', f'"{bad}"'))
        refused(capsys, "identify", d / "recording.csv", "--machine", d / "hyb.toml", match=(str(bad), what))


def test_inputs_above_the_size_limit_are_refused_stating_it(d, capsys, monkeypatch):
    import bayescal.io.safe_paths as sp

    monkeypatch.setattr(sp, "MAX_CSV_BYTES", 1000)
    refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", match=("r.csv", "more than the limit of 1000 bytes"))
    monkeypatch.setattr(sp, "MAX_TOML_BYTES", 100)
    refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", match=("m.toml", "more than the limit of 100 bytes"))


def test_a_recording_on_standard_input_is_read_once(d, capsys, monkeypatch):
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(REC.read_bytes())))
    code, err = run(capsys, "identify", "/dev/stdin", "--machine", d / "m.toml", "--method", "map", "--quiet",
                    "--json", d / "a.json")
    assert code in (0, 1) and not any("empty file" in e for e in err) and (d / "a.json").is_file()


# ------------------------------------------------------------------ sizes
def test_requests_that_cannot_fit_in_memory_are_refused_naming_the_option(d, capsys):
    refused(capsys, "grid", d / "r.csv", "--machine", d / "m.toml", "--nodes", "2000", match=("needs about", "--nodes"))
    refused(capsys, "grid", d / "r.csv", "--machine", d / "m.toml", "--nodes", "1", match=("--nodes", "at least 2"))
    (d / "e.csv").write_text("x,z,ex,ez\n-1,-1,0,0\n1,-1,0,0\n-1,1,0,0\n1,1,0,0\n")
    refused(capsys, "compensate", "--errors", d / "e.csv", "--x-range", "-1", "1", "--z-range", "-1", "1", "--n", "100000",
            match=("needs about", "--n"))
    refused(capsys, "plan", "--machine", d / "m.toml", "--measure", "height", "--spacing", "0.001", "--n", "3",
            "--out", d / "p.csv", match=("needs about", "--spacing"))
    refused(capsys, "simulate", "--machine", d / "m.toml", "--poses", str(10**12), "--seed", "1", "--out", d / "x.csv",
            match=("needs about", "--poses"))
    refused(capsys, "plan", "--machine", d / "m.toml", "--n", "3", "--candidates", str(10**12), "--out", d / "p.csv",
            match=("needs about", "--candidates"))


# ------------------------------------------------------------------ option values
@pytest.mark.parametrize("methods, match", [
    ("ridge:foo=1", "unknown option 'foo' of ridge"), ("ridge:lam=abc", "lam=abc: expected a number from 0 to 1e+12"),
    ("ridge:lam=1e308", "lam=1e+308: expected a number from 0 to 1e+12"),
    ("tsvd:k=-2", "k=-2: expected a positive integer"), ("mcmc:seed=-1", "seed=-1"), ("ls:k=3", "ls takes no options"),
])
def test_compare_method_options_are_refused_up_front(d, capsys, methods, match):
    refused(capsys, "compare", "--machine", d / "m.toml", "--methods", methods, "--trials", "1", "--no-progress",
            match=("--methods", match.replace("ls takes", "it takes")))


@pytest.mark.parametrize("command", ["simulate", "compare"])
def test_a_negative_tolerance_scale_is_refused(d, capsys, command):
    extra = ["--poses", "3", "--seed", "1", "--out", d / "x.csv"] if command == "simulate" else ["--trials", "1"]
    refused(capsys, command, "--machine", d / "m.toml", "--tolerance-scale", "-1", *extra, match="--tolerance-scale")


@pytest.mark.parametrize("option", [["--posterior", "{d}/p.nc"], ["--walkers", "8"], ["--surrogate", "linear"],
                                    ["--variant", "ukf"]])
def test_an_option_of_another_method_is_refused_not_ignored(d, capsys, option):
    refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", "--method", "map",
            *[o.format(d=d) for o in option], match=(option[0], "goes with --method"))


# ------------------------------------------------------------------ compensate
@pytest.mark.parametrize("rows, match", [
    ("0,0,0.01,0.02\n", "1 distinct point"), ("0,0,0,0\n1,0,0,0\n2,0,0,0\n", "on one line"),
])
def test_compensate_refuses_tables_without_an_area(d, capsys, rows, match):
    (d / "e.csv").write_text("x,z,ex,ez\n" + rows)
    refused(capsys, "compensate", "--errors", d / "e.csv", "--x-range", "0", "2", "--z-range", "0", "1", "--n", "3",
            match=("e.csv", match))


def test_compensate_refuses_huge_node_errors_and_points_outside(d, capsys):
    (d / "e.csv").write_text("x,z,ex,ez\n-10,-10,1e300,0\n10,-10,0,0\n-10,10,0,0\n10,10,0,0\n")
    refused(capsys, "compensate", "--errors", d / "e.csv", "--x-range", "-10", "10", "--z-range", "-10", "10", "--n", "2",
            "--out", d / "g.csv", match="ex = 1e+300 mm")
    assert not (d / "g.csv").exists()
    (d / "e.csv").write_text("x,z,ex,ez\n-10,-10,0.01,0\n10,-10,0,0\n-10,10,0,0\n10,10,0,0\n")
    assert run(capsys, "compensate", "--errors", d / "e.csv", "--x-range", "-10", "10", "--z-range", "-10", "10", "--n", "2",
               "--out", d / "g.csv")[0] == 0
    (d / "far.csv").write_text("x,z,ex,ez\n0,0,0.1,0.1\n5000,5000,0.1,0.1\n")
    refused(capsys, "compensate", "--grid", d / "g.csv", "--evaluate", d / "far.csv", match=("far.csv: line 3", "outside the grid"))


# ------------------------------------------------------------------ recordings
def test_an_overflowing_cell_is_named_by_its_own_column(d, capsys):
    rows = list(csv.reader(io.StringIO(REC.read_text())))
    rows[3][rows[0].index("y")] = "1e308"
    with open(d / "r308.csv", "w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    refused(capsys, "identify", d / "r308.csv", "--machine", d / "m.toml", match=("line 4", "column 'y'", "1e+308"))


def test_sigma_columns_outside_the_range_name_line_and_column(d, capsys):
    rows = list(csv.reader(io.StringIO(REC.read_text())))
    rows[0].append("sigma_position")
    for r in rows[1:]:
        r.append("0.005")
    rows[5][-1] = "1e-200"
    with open(d / "rs.csv", "w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    refused(capsys, "identify", d / "rs.csv", "--machine", d / "m.toml", match=("line 6", "sigma_position", "from 1e-06"))


def test_a_ridge_parameter_beyond_the_limit_is_refused(d, capsys):
    # --lam 1e308 was fitted: every std 5e-156 mm, exit 0, "plausible"
    refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", "--method", "ridge", "--lam", "1e308",
            match=("lam", "from 0 to 1e+12"))


@pytest.mark.parametrize("option", ["--json", "--discrepancy-inputs", "--report"])
def test_an_empty_value_is_refused_not_taken_as_absent(d, capsys, option):
    # --json '' ran and wrote nothing; --discrepancy-inputs '' took the default
    extra = ["--method", "map", "--discrepancy", "on"] if option == "--discrepancy-inputs" else []
    refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", *extra, option, "", match=(option, "empty value"))
    refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", *extra, f"{option}=", match=(option, "empty value"))


def test_dash_is_no_output_file(d, capsys):
    # --json - wrote a file named '-'
    refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", "--json", "-", match=("--json -", "not standard output"))
    assert not (d / "-").exists() and not __import__("pathlib").Path("-").exists()


def test_write_urdf_is_checked_against_the_inputs_before_fitting(d, capsys):
    refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", "--write-urdf", d / "r.csv",
            match=("--write-urdf", "is the same file as recording"))


@pytest.mark.parametrize("option", [["--pivot", "1,2,3"], ["--planes", "xz"]])
def test_ballbar_options_without_a_ballbar_are_refused(d, capsys, option):
    # --pivot without --ballbar simulated poses and ignored it
    refused(capsys, "simulate", "--machine", d / "m.toml", "--poses", "3", "--seed", "1", "--out", d / "s.csv", *option,
            match=(option[0], "goes with --ballbar"))
    assert not (d / "s.csv").exists()


def test_a_pose_file_with_more_actuators_is_refused(d, capsys):
    # a q4 column (another machine's plan) was ignored
    (d / "p.csv").write_text("q1,q2,q3,q4\n500,500,500,1\n")
    refused(capsys, "simulate", "--machine", d / "m.toml", "--poses-file", d / "p.csv", "--seed", "1", "--out", d / "s.csv",
            match=("p.csv: line 1, column 'q4'", "beyond the machine's 3 actuators"))


def test_a_grid_range_given_twice_is_refused(d, capsys):
    # --range q1=460:540 --range q1=470:530: the last one won, silently
    refused(capsys, "grid", d / "r.csv", "--machine", d / "m.toml", "--nodes", "3", "--range", "q1=460:540",
            "--range", "q1=470:530", match=("--range q1", "given twice"))


def test_an_effect_to_diagnose_named_twice_is_refused(d, capsys):
    refused(capsys, "diagnose", d / "r.csv", "--machine", d / "m.toml", "--effects", "backlash,backlash",
            match=("--effects", "named twice"))


@pytest.mark.parametrize("option", [["--given", "{d}/r.csv"], ["--centre", "1,2,3"], ["--radius", "5"], ["--spacing", "2"],
                                    ["--sigma", "0.1"], ["--min-distance", "3"]])
def test_relation_options_on_a_plan_of_poses_are_refused(d, capsys, option):
    # a plan of poses ignored them, silently (exit 0)
    refused(capsys, "plan", "--machine", d / "m.toml", "--n", "8", "--candidates", "300", "--out", d / "p.csv",
            *[o.format(d=d) for o in option], match=(option[0], "goes with --measure height or distance"))


def test_pose_options_on_a_plan_of_relations_are_refused(d, capsys):
    delta = ROOT / "examples" / "delta" / "machine.toml"
    refused(capsys, "plan", "--machine", delta, "--measure", "height", "--n", "3", "--no-box", "--out", d / "p.csv",
            match=("--no-box", "only for poses"))


@pytest.mark.parametrize("methods, match", [("tsvd:k=999", "k=999: expected at most 36"), ("ridge:", "nothing after ':'"),
                                            ("ridge:;", "nothing after ':'"), ("ls,,map", "an empty method")])
def test_compare_methods_that_could_only_fail_or_say_nothing_are_refused(d, capsys, methods, match):
    # tsvd:k=999 failed in every trial and compare exited 0; 'ridge:' and 'ls,,map' were taken silently
    refused(capsys, "compare", "--machine", d / "m.toml", "--methods", methods, "--trials", "1", "--no-progress",
            match=("--methods", match))


def test_compare_refuses_negative_retries(d, capsys):
    refused(capsys, "compare", "--machine", d / "m.toml", "--trials", "1", "--retries", "-1", "--no-progress",
            match="--retries")


def test_compare_exits_1_when_a_method_fails_in_every_trial(d, capsys):
    from bayescal.compare import register_method
    from bayescal.compare.methods import METHODS

    from bayescal.errors import IdentificationError

    def broken(model, *, free):
        raise IdentificationError("always")

    register_method("broken_probe", broken, help="fails")
    try:
        code, err = run(capsys, "compare", "--machine", d / "m.toml", "--methods", "ls,broken_probe", "--trials", "2",
                        "--no-progress", "--quiet")
    finally:
        METHODS.pop("broken_probe", None)
    assert code == 1 and "broken_probe failed in every trial" in err[-1], err


# ------------------------------------------------------------------ copied rows (probe 2)
def test_diagnose_refuses_a_recording_of_copied_rows(d, capsys):
    """36 copies of one pose fit exactly (chi-square 0): 'noise explains it' would be a wrong verdict."""
    lines = (d / "r.csv").read_text().splitlines()
    (d / "c.csv").write_text("\n".join([lines[0]] + [lines[1]] * 36) + "\n")
    refused(capsys, "diagnose", d / "c.csv", "--machine", d / "m.toml",
            match=(str(d / "c.csv"), "only 1 distinct", "35 repeat an earlier row", "at least 10 distinct"))


def test_copied_rows_do_not_set_the_map_prior_scale(d):
    """36 copies of one pose are 6 distinct components for 36 parameters: the tolerances, not an 'empirical' scale."""
    from bayescal.bayes.map_identify import default_prior_scale
    from bayescal.io.recording import read_recording
    from bayescal.machines.files import load_machine
    from bayescal.models import model_from_recording

    lines = (d / "r.csv").read_text().splitlines()
    (d / "c.csv").write_text("\n".join([lines[0]] + [lines[1]] * 36) + "\n")
    machine = load_machine(d / "m.toml")
    assert default_prior_scale(model_from_recording(machine, read_recording(d / "r.csv"), check=False))[0] == "empirical"
    scale, note = default_prior_scale(model_from_recording(machine, read_recording(d / "c.csv"), check=False))
    assert scale == "tolerance" and "6 distinct measured components, 35 copied rows not counted" in note


def test_compensate_names_both_lines_of_an_irregular_grid(tmp_path, capsys):
    """Was 'node coordinate np.float64(0.0) differs from np.float64(150.0)', naming only one of the two lines."""
    rows = ["i,j,x,z,ex,ez,std_ex,std_ez"]
    for j, z in enumerate((-200.0, 200.0)):
        for i, x in enumerate((-300.0, 0.0, 300.0)):
            rows.append(f"{i},{j},{150.0 if (i, j) == (1, 0) else x},{z},0.0,0.0,,")
    (tmp_path / "g.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "e.csv").write_text("x,z,ex,ez\n0,0,0,0\n")
    refused(capsys, "compensate", "--grid", tmp_path / "g.csv", "--evaluate", tmp_path / "e.csv",
            match=("g.csv: line 6, column 'x'", "0 mm differs from 150 mm at line 3", "(i = 1)"))


@pytest.mark.parametrize("flag", ["--poses", "--eval-poses"])
def test_compare_names_the_pose_count_option(d, capsys, flag):
    """Was 'n_poses and n_eval: expected positive integers' for either option."""
    refused(capsys, "compare", "--machine", d / "m.toml", "--trials", "2", flag, "0", match=(f"({flag})", "got 0"))


@pytest.mark.parametrize("pivot", ["nan,0,0", "0,inf,0"])
def test_simulate_ballbar_refuses_a_non_finite_pivot(d, capsys, pivot):
    """A NaN pivot was reported as 'the circle does not fit the workspace'."""
    refused(capsys, "simulate", "--machine", d / "m.toml", "--poses", "5", "--seed", "1", "--ballbar", "20",
            "--pivot", pivot, "--out", d / "b.csv", match=("--pivot", "expected three finite numbers"))
    assert not (d / "b.csv").exists()


@pytest.mark.parametrize("extra, flag", [
    (["--max-iter", "0"], "(--max-iter)"),
    (["--method", "mcmc", "--walkers", "2", "--steps", "40", "--surrogate", "linear"], "(--walkers)"),
    (["--method", "mcmc", "--checkpoint", "c.npz", "--checkpoint-every", "0"], "(--checkpoint-every)"),
])
def test_identify_option_errors_name_the_option(d, capsys, monkeypatch, extra, flag):
    """They named only the library's parameter (max_iter, n_walkers, checkpoint_every)."""
    monkeypatch.chdir(d)
    refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", *extra, match=flag)


@pytest.mark.parametrize("command, extra", [
    ("identify", ["--steps", "10"]), ("identify", ["--checkpoint-every", "5"]),
    ("grid", ["--steps", "10"]), ("grid", ["--surrogate", "linear"]), ("grid", ["--method", "kalman", "--steps", "50"]),
])
def test_mcmc_options_with_another_method_are_refused(d, capsys, command, extra):
    """They were accepted and ignored: the run was not what the command line asked for."""
    refused(capsys, command, d / "r.csv", "--machine", d / "m.toml", *extra, match=(f"{extra[-2]} goes with --method mcmc",))


def test_report_must_be_named_html(d, capsys):
    """An HTML page was written under rep.pdf."""
    refused(capsys, "identify", d / "r.csv", "--machine", d / "m.toml", "--report", d / "rep.pdf",
            match=("--report", "rep.pdf", "ending in .html"))
    assert not (d / "rep.pdf").exists()


def test_predict_names_a_constraint_recording_as_such(d, capsys):
    """Was 'line 1: no actuator columns; expected q1, q2, ...' for a Klipper recording of heights."""
    (d / "c.csv").write_text("measure,a_q1,a_q2,a_q3,b_q1,b_q2,b_q3,value\nheight,500,500,500,,,,0.5\n")
    refused(capsys, "predict", d / "c.csv", "--machine", d / "m.toml",
            match=("c.csv: line 1: a constraint recording", "section 6", "recording of measured poses"))
