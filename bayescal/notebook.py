"""How an answer shows itself in a notebook: its report, as the command prints it.

Every answer of the front door (:mod:`bayescal.api`) has ``report()``, the
text the command prints; :class:`ShowsReport` gives it ``_repr_html_`` so that
a notebook cell ending in the answer shows that text, escaped and in a fixed
font (the columns of its tables line up).  The calibration has a richer table
of its own (:meth:`bayescal.identify.calibrate.Calibration._repr_html_`).
"""

from __future__ import annotations

from html import escape

__all__ = ["ShowsReport"]


class ShowsReport:
    """Mixin: ``_repr_html_`` is ``report()`` as preformatted, escaped text."""

    def _repr_html_(self) -> str:
        return f"<pre>{escape(self.report())}</pre>"
