"""The identify help's description: wrapped like the rest of it, each sentence in its own paragraph."""

from bayescal.cli.identify import HELP


def _paragraphs():
    return [" ".join(p.split()) for p in HELP.split("\n\n")]


def test_description_lines_fit_a_terminal():
    # RawDescriptionHelpFormatter prints the text as written: a joined line runs past 80 columns
    long = [line for line in HELP.splitlines() if len(line) > 80]
    assert not long, long


def test_rule_report_sentence_belongs_to_the_auto_paragraph():
    paras = _paragraphs()
    (auto,) = [p for p in paras if p.startswith("--lam auto / --k auto")]
    (map_,) = [p for p in paras if p.startswith("--method map")]
    assert "every other rule picks" in auto and "<- used" in auto
    assert "every other rule picks" not in map_
    assert "--prior-scale tolerance|empirical chooses explicitly" in map_ and "prior scale: ..." in map_
