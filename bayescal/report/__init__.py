"""Self-contained HTML reports of bayescal's results (``--report PATH.html``).

The report is rendered from the result objects a command computed (this
package computes nothing of its own beyond drawing figures): a Jinja2
template (``templates/report.html.j2``, package data) with every figure
embedded as a base64 PNG and inline CSS, so the one file opens in any
browser without network access and can be passed on as it is.

Use :func:`render_report`; the CLI calls it through
:func:`bayescal.cli.outputs.write_report`.
"""

from __future__ import annotations

from datetime import datetime, timezone

from ..errors import InputError

__all__ = ["render_report", "KINDS"]


def _environment():
    import jinja2

    # autoescape: names and messages come from user files and must not become markup
    return jinja2.Environment(
        loader=jinja2.PackageLoader("bayescal.report", "templates"),
        autoescape=jinja2.select_autoescape(["html", "j2"]),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )


def render_report(kind: str, result, *, inputs: dict | None = None, machine=None, **extra) -> str:
    """The HTML text of a report.

    Parameters
    ----------
    kind : {"identify", "diagnose", "compare", "plan", "grid", "compensate"}
    result
        The command's result object (IdentificationResult, FilterResult,
        PosteriorResult, Diagnosis, Comparison, PosePlan, CompensationGrid,
        ToolGrid or compensation.CompensationGrid).
    inputs : dict, optional
        ``{"command": str, "files": [{"option", "path", "sha256", "bytes"}], "versions": {...}}``
        (:func:`bayescal.cli.outputs.run_inputs`).
    machine : Machine, optional
        For the machine and instrument section.
    **extra
        Kind-specific: ``model`` (per-pose residuals of kalman/mcmc), ``choice``
        (regularisation curves), ``identification`` (grid), ``evaluation`` (compensate).
    """
    from .kinds import BUILDERS, inputs_section

    if kind not in BUILDERS:
        raise InputError(f"report kind: expected one of {', '.join(BUILDERS)}, got {kind!r}")
    title, sections = BUILDERS[kind](result, machine=machine, **extra)
    sections = [s for s in sections if s] + [inputs_section(inputs or {}, machine)]
    return _environment().get_template("report.html.j2").render(
        title=title, kind=kind, sections=sections,
        created=datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"),
        version=(inputs or {}).get("versions", {}).get("bayescal", ""),
    )


KINDS = ("identify", "diagnose", "compare", "plan", "grid", "compensate")
