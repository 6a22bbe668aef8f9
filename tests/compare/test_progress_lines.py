"""A comparison's progress: a line per finished trial, unless a bar is drawn (the fits' own lines would break it)."""

from __future__ import annotations

from bayescal.compare.runner import _collect
from bayescal.progress import report, reporting


class _Bar:
    def __init__(self, disable):
        self.disable, self.n = disable, 0

    def update(self, k):
        self.n += k


def _trials(n):
    for t in range(n):
        report(f"fit of trial {t}")  # what a trial's Gauss-Newton loop reports
        yield {"trial": t, "rms": 0.5}


def test_lines_without_a_drawn_bar_and_none_with_one():
    lines, done = [], {}
    with reporting(lines.append):
        _collect(_trials(2), done, None, _Bar(disable=True), 2)  # stderr not a terminal: tqdm draws nothing
    assert lines == ["fit of trial 0", "1 of 2 trials done", "fit of trial 1", "2 of 2 trials done"]
    assert sorted(done) == [0, 1]
    lines.clear()
    bar = _Bar(disable=False)
    with reporting(lines.append):
        _collect(_trials(3), {}, None, bar, 3)
    assert lines == [] and bar.n == 3
