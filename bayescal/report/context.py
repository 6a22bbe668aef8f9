"""Building blocks of a report's context: sections, tables, cells, figures as data URIs, versions.

A report is a list of sections; a section has paragraphs, tables, figures
and optionally preformatted text.  Numbers are shown rounded and carried
exactly in a ``data-value`` attribute (``repr`` of the float), so the
report can be checked against the JSON answer to the last bit.
"""

from __future__ import annotations

import base64
import importlib.metadata
import math
import platform
import tempfile
from pathlib import Path
from typing import Callable

__all__ = ["cell", "table", "section", "figure", "versions", "fmt"]

#: Distributions whose versions a report states.
DEPENDENCIES = ("numpy", "scipy", "matplotlib", "emcee", "arviz", "filterpy", "jinja2")


def fmt(value, spec: str = ".6g") -> str:
    """A number for reading (``-`` for None / NaN)."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float)):
        f = float(value)
        if not math.isfinite(f):
            return "-"
        return format(value, spec) if not isinstance(value, int) else str(value)
    return str(value)


def cell(value, spec: str = ".6g", *, cls: str = "", text: str | None = None) -> dict:
    """A table cell: shown as ``text`` (or ``value`` formatted), with the exact number in ``data-value``."""
    exact = None
    if isinstance(value, (int, float)) and not isinstance(value, bool) and value is not None and math.isfinite(float(value)):
        exact = repr(float(value))
    return {"text": fmt(value, spec) if text is None else text, "value": exact, "cls": cls}


def table(columns, rows, *, caption: str = "", id: str = "", row_classes=None) -> dict:
    """A table: ``rows`` of cells (dicts from :func:`cell`, or plain values)."""
    out = []
    for i, r in enumerate(rows):
        cells = [c if isinstance(c, dict) else cell(c) for c in r]
        out.append({"cells": cells, "cls": row_classes[i] if row_classes else ""})
    return {"columns": list(columns), "rows": out, "caption": caption, "id": id}


def section(title: str, *, id: str = "", text=(), tables=(), figures=(), pre: str | None = None, cls: str = "") -> dict:
    return {"title": title, "id": id or title.lower().replace(" ", "-"), "text": [t for t in text if t],
            "tables": [t for t in tables if t], "figures": [f for f in figures if f], "pre": pre, "cls": cls}


def png_uri(path: str | Path) -> str:
    """A PNG file as a ``data:`` URI (the report must open without network or side files)."""
    return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


def figure(draw: Callable[[Path], object], caption: str) -> dict | None:
    """Draw a figure with ``draw(path)`` (one of bayescal.plots) into a temporary PNG and embed it.

    ``draw`` may return a path or a list of paths (several figures);
    returns a figure dict, a list of them, or None when nothing was drawn.
    """
    with tempfile.TemporaryDirectory(prefix="bayescal-report-") as tmp:
        made = draw(Path(tmp) / "figure.png")
        paths = made if isinstance(made, (list, tuple)) else [made]
        figs = [{"uri": png_uri(p), "caption": caption if len(paths) == 1 else f"{caption}: {Path(p).stem.replace('_', ' ')}",
                 "alt": caption} for p in paths if p is not None and Path(p).is_file()]
    if not figs:
        return None
    return figs[0] if len(figs) == 1 else figs


def versions() -> dict:
    """bayescal, Python and the dependencies' versions."""
    from .. import __version__

    out = {"bayescal": __version__, "python": platform.python_version()}
    for dist in DEPENDENCIES:
        try:
            out[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out
