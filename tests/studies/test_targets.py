"""studies/targets.py: the one PASS/MISS wording and exit rule, and the studies' target text unchanged by it."""

import re

import numpy as np

from tests.studies.conftest import STUDIES, load_study


def test_verdict_and_exit_code():
    t = load_study("targets")
    assert [t.verdict(x) for x in (True, False, None, np.True_, np.False_)] == ["PASS", "MISS", "NOT TESTED", "PASS", "MISS"]
    assert t.exit_code([True, np.True_, None]) == 0
    assert t.exit_code([True, None, np.False_]) == 1  # a numpy False is a miss (``is False`` would not see it)
    assert t.exit_code([]) == 0


def test_no_study_spells_its_own_pass_miss():
    # every study words its targets through studies/targets.py
    own = re.compile(r"""['"]PASS['"]\s*(if|,|})|True:\s*['"]PASS""")
    offenders = [p.name for p in STUDIES.glob("*.py") if p.name != "targets.py" and own.search(p.read_text())]
    assert not offenders, offenders


def test_target_text_of_the_studies_is_unchanged():
    dc = load_study("diagnose_concealed")
    checks = [("named right", True, "9 of 10"), ("no false alarm", False, "2 of 10"), ("small effects", None, "0 cases")]
    assert dc.targets_text(checks) == (
        "PASS       named right: 9 of 10\nMISS       no false alarm: 2 of 10\nNOT TESTED small effects: 0 cases\n"
    )
    co = load_study("coverage_offprior", siblings=True)
    base = dict(part="prs3", dof=6, parameters=(0.86, 0.93), tool_points=(0.9, 0.94), truths=[1, 2])
    lines = co.check_lines([{**base, "ok": True, "targeted": True, "method": "ls"},
                            {**base, "ok": False, "targeted": True, "method": "map_eb"},
                            {**base, "ok": False, "targeted": False, "method": "map"}])
    assert [line[:18] for line in lines] == ["PASS              ", "MISS              ", "ref (out of range)"]
    assert lines[0] == ("PASS               prs3    6-DOF ls          parameters 86.0-93.0 %, tool points 90.0-94.0 % "
                        "over 2 truths (target 85-95 %)")
