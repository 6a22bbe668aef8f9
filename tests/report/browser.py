"""Render an HTML file in headless Chromium: console messages, image decoding, a screenshot.

No browser-driver package: Chromium's own command line does it.  A copy of
the page gets a small script that, on ``load``, writes for every image
whether it decoded (``complete`` and ``naturalWidth > 0``) and is laid out
visibly (non-zero box) into a ``<pre id="bayescal-check">``; ``--dump-dom``
prints the DOM after the page settled (``--virtual-time-budget``).  Console
messages (including failed resource loads) come on stderr with
``--enable-logging=stderr``; every remote host is mapped to nowhere, so a
report that needed the network would fail visibly.

Where Chromium is missing the tests skip, except in CI (``CI=true`` or
``BAYESCAL_REQUIRE_BROWSER=1``), where they fail.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"

_CHECK = """<script>
window.addEventListener('load', function () {
  var out = Array.prototype.map.call(document.images, function (im) {
    var r = im.getBoundingClientRect();
    return {ok: im.complete && im.naturalWidth > 0, w: im.naturalWidth, h: im.naturalHeight,
            visible: r.width > 0 && r.height > 0 && getComputedStyle(im).visibility !== 'hidden'};
  });
  var pre = document.createElement('pre');
  pre.id = 'bayescal-check';
  pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
});
</script>"""


def chromium() -> str:
    """The Chromium executable, or skip (fail in CI)."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        exe = shutil.which(name)
        if exe:
            return exe
    if os.environ.get("CI", "").lower() == "true" or os.environ.get("BAYESCAL_REQUIRE_BROWSER"):
        pytest.fail("Chromium is required in CI (apt-get install chromium) but was not found")
    pytest.skip("Chromium not installed (apt-get install chromium)")


@dataclass
class Rendered:
    images: list[dict]
    console: list[str]
    screenshot: Path


def _flags(profile: Path) -> list[str]:
    return [
        "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run", "--hide-scrollbars",
        f"--user-data-dir={profile}", "--host-resolver-rules=MAP * ~NOTFOUND",
    ]


def render(html: Path, tmp: Path, name: str) -> Rendered:
    """Render ``html``; return the image checks, console lines and a screenshot (also copied to tests/artifacts)."""
    exe = chromium()
    checked = tmp / f"{name}.checked.html"
    text = html.read_text(encoding="utf-8")
    checked.write_text(text.replace("</body>", _CHECK + "\n</body>"), encoding="utf-8")
    run = subprocess.run(
        [exe, *_flags(tmp / "profile-dom"), "--enable-logging=stderr", "--v=0", "--virtual-time-budget=10000",
         "--dump-dom", checked.as_uri()],
        capture_output=True, text=True, timeout=180,
    )
    m = re.search(r'<pre id="bayescal-check">(.*?)</pre>', run.stdout, re.S)
    assert m, f"chromium did not finish rendering {html} (exit {run.returncode}): {run.stderr[-2000:]}"
    images = json.loads(m.group(1).replace("&quot;", '"'))
    console = [ln for ln in run.stderr.splitlines() if "CONSOLE" in ln or "ERR_" in ln]
    shot = tmp / f"{name}.png"
    subprocess.run(
        [exe, *_flags(tmp / "profile-shot"), "--window-size=1200,3000", f"--screenshot={shot}", html.as_uri()],
        capture_output=True, text=True, timeout=180,
    )
    assert shot.is_file() and shot.stat().st_size > 10_000, f"no screenshot of {html}"
    ARTIFACTS.mkdir(exist_ok=True)
    shutil.copy(shot, ARTIFACTS / shot.name)
    print(f"screenshot: {ARTIFACTS / shot.name}")
    return Rendered(images, console, shot)
