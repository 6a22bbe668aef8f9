"""``compare`` as a user gets it: the defaults, the refusals and the output folder of ``bayescal compare``.

:func:`compare_files` is what the command line runs (and
:func:`bayescal.compare` in a notebook); :func:`write_comparison_folder`
writes what ``--out DIR`` holds besides the saved trials.  Errors name the
keyword and the command line's option.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import InputError, refuse_unknown_options
from ..machines.base import Machine
from .result import Comparison, compare_methods

__all__ = ["compare_files", "write_comparison_folder"]


def compare_files(machine: str | os.PathLike | Machine, *, methods: str = "ls,ridge,tsvd", trials: int = 500,
                  recording: str | os.PathLike | None = None, dof: int | None = None, poses: int | None = None,
                  frame: str = "base", alpha: float = 0.05, out: str | os.PathLike | None = None,
                  **options) -> Comparison:
    """Compare identification methods by Monte Carlo, as ``bayescal compare`` does.

    Parameters
    ----------
    machine : path or Machine
        Nominal machine file with ``[workspace] q_limits`` (docs/formats.md section 1).
    methods : str
        Registry names, comma separated, options after a colon (``"ls,ridge:lam=0.1,tsvd:k=20"``).
    trials : int
        Monte Carlo trials, at least 1.
    recording : path, optional
        Every trial re-measures this recording's poses or relations (sections 2, 6).
    dof : {6, 5, 3}, optional
        What is measured (default 6, or the recording's).
    poses : int, optional
        Poses per trial (default 36); not with ``recording``.
    frame : {"base"}
        Trials are simulated in the base frame; ``"fit"`` is refused (an instrument frame has no prior to
        draw trials from).
    alpha : float
        Family-wise significance level, in (0, 1).
    out : path, optional
        Folder for the saved (resumable) trials; :func:`write_comparison_folder` adds the table, the JSON
        and the figures.
    **options
        Of :func:`bayescal.compare.result.compare_methods`: ``n_eval``, ``seed``, ``free``,
        ``tolerance_scale``, ``metric``, ``workers``, ``dask_workers``, ``scheduler``, ``retries``,
        ``progress``.

    Returns
    -------
    Comparison
        ``report()``, ``to_dict()`` (what ``--json`` writes), ``failed_everywhere``.
    """
    refuse_unknown_options("compare", options, compare_files, compare_methods)
    if frame == "fit":
        raise InputError(
            "--frame fit (keyword frame='fit'): compare draws each trial's true machine from the tolerance prior, and an instrument "
            "frame has none to draw from; the fitted frame changes the calibrated geometry only by the gauge "
            "(docs/real-instruments.md), so compare methods in the base frame")
    if frame != "base":
        raise InputError(f"frame (--frame): expected 'base', got {frame!r}")
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not 0 < alpha < 1:
        raise InputError(f"alpha (--alpha): expected a number between 0 and 1, got {alpha!r}")
    if recording is not None and poses is not None:
        raise InputError(f"poses (--poses): every trial re-measures {recording}'s measurements; drop poses or "
                         "recording")
    if not isinstance(machine, Machine):
        from ..machines.files import load_machine

        machine = load_machine(machine)
    return compare_methods(machine, methods=methods, trials=trials, dof=dof if recording else (dof or 6),
                           n_poses=36 if poses is None else poses, recording=recording, alpha=alpha, out=out,
                           **options)


def write_comparison_folder(cmp: Comparison, out: str | os.PathLike) -> list[Path]:
    """Write ``table.txt``, ``comparison.json`` and the figures into ``out``; the paths written."""
    from ..io import write_json_atomic, write_text_atomic
    from ..plots.compare import plot_comparison

    out = Path(out)
    write_text_atomic(out / "table.txt", cmp.report() + "\n")
    write_json_atomic(out / "comparison.json", cmp.to_dict())
    return [out / "table.txt", out / "comparison.json", *plot_comparison(cmp, out)]
