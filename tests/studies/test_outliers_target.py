"""studies/outliers_target.py on one small seed: every gross pose named, none clean, and its PASS/MISS exit code."""

from tests.studies.conftest import load_study


def _study():
    return load_study("outliers_target")


def _rows(text):
    """{method: (clean, plain, robust, ratio, missed, false)} from the study's printed table."""
    rows = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 7 and parts[0] in ("map", "map_tol", "ridge_auto", "tsvd_auto", "kalman"):
            rows[parts[0]] = tuple(float(v) for v in parts[1:])
    return rows


def test_command_map_and_lam_auto_meet_the_target_on_one_seed(capsys):
    code = _study().main(["--seeds", "1", "--poses", "60", "--methods", "map,ridge_auto"])
    out = capsys.readouterr().out
    rows = _rows(out)
    assert set(rows) == {"map", "ridge_auto"}
    for clean, plain, robust, ratio, missed, false in rows.values():
        assert missed == 0 and false == 0
        assert abs(ratio - robust / clean) < 0.02  # the ratio printed is the one of the printed errors
        assert robust < plain  # the gross pose costs the unweighted fit, the robust one recovers
    assert out.count("PASS") == 6 and "MISS" not in out
    assert code == 0


def test_a_missed_target_is_printed_and_exits_1(capsys):
    mod = _study()
    mod.MAX_RATIO = 0.5  # unattainable: the robust fit on corrupted data is never twice as good as the clean fit
    code = mod.main(["--seeds", "1", "--poses", "60", "--methods", "kalman"])
    out = capsys.readouterr().out
    assert "MISS  kalman: robust / clean" in out
    assert code == 1
