"""Every kind of report renders in headless Chromium: no console message, every image decoded and visible."""

from __future__ import annotations

import re

import pytest

from tests.report.browser import render

KINDS = ("identify", "kalman", "mcmc", "diagnose", "compare", "plan", "grid", "compensate")


@pytest.mark.parametrize("kind", KINDS)
def test_report_renders_in_chromium(reports, tmp_path, kind):
    html = reports / f"{kind}.html"
    text = html.read_text(encoding="utf-8")
    # self-contained: nothing is fetched from anywhere (images are data: URIs, CSS is inline)
    assert not re.search(r'(src|href)="(https?:)?//', text)
    out = render(html, tmp_path, f"report_{kind}")
    assert out.console == [], out.console
    assert out.images, "a report without figures"
    bad = [i for i, im in enumerate(out.images) if not (im["ok"] and im["visible"] and im["w"] > 100 and im["h"] > 100)]
    assert not bad, [out.images[i] for i in bad]
