"""Which parameters a fit identifies: a rule or names, less the parameters the user holds fixed.

``free`` is ``"auto"``, ``"all"`` or parameter names everywhere in bayescal
(identify, calibrate, compare, grid, the Kalman filter, MCMC).  Holding
parameters fixed by name, as lmfit's ``vary=False`` does, combines with any of
them: :class:`Free` carries both, and :func:`bayescal.identify.gauss_newton.resolve_free`,
the one place a free set is resolved, honours it, so every consumer that
passes ``free`` on gets it.
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..params import ParamLayout

__all__ = ["Free", "with_fixed", "held_index", "held_names", "same_free"]


@dataclass(frozen=True)
class Free:
    """Parameters to identify: ``base`` (``"auto"``, ``"all"`` or names) less ``fix``.

    Attributes
    ----------
    base : str or tuple of str
        ``"auto"``, ``"all"`` or parameter names.
    fix : tuple of str
        Parameter names held at their starting value (nominal, or the prior
        mean): not identified (no std in the result; zero variance in a written ``[calibration]``).  With ``"auto"``
        the identifiable set is chosen among the others.
    """

    base: str | tuple = "auto"
    fix: tuple[str, ...] = ()


def with_fixed(free, fix: Sequence[str] | None):
    """``free`` with the names ``fix`` held fixed (``free`` itself when nothing is fixed).

    Raises
    ------
    InputError
        ``fix`` is a single string rather than a list of names, or not names.
    """
    if fix is None or (not isinstance(fix, str) and len(fix) == 0):
        return free
    if isinstance(fix, str) or not all(isinstance(f, str) for f in fix):
        raise InputError(f"fix: expected a list of parameter names, got {fix!r}")
    base = free if isinstance(free, str) or free is None else tuple(free)
    return Free("auto" if base is None else base, tuple(fix))


def held_index(layout: ParamLayout, fix: Sequence[str]) -> NDArray:
    """Indices of the names ``fix`` (InputError naming an unknown or repeated one)."""
    out = []
    for name in fix:
        if name not in layout.names:
            close = difflib.get_close_matches(name, layout.names, n=1)
            hint = f"did you mean '{close[0]}'? " if close else ""
            raise InputError(f"fix: unknown parameter '{name}'; {hint}expected one of: {', '.join(layout.names)}")
        if layout.index(name) in out:
            raise InputError(f"fix: '{name}' listed twice")
        out.append(layout.index(name))
    return np.array(sorted(out), dtype=int)


def held_names(free) -> tuple[str, ...]:
    """The names ``free`` holds fixed (none unless it is a :class:`Free`)."""
    return tuple(free.fix) if isinstance(free, Free) else ()


def same_free(res):
    """The ``free`` that refits exactly ``res``'s free set, its held parameters still named as held.

    A refit at the same set (outlier weights, a rescaled prior) passes indices; without the names the user
    held, the refit would count them among the parameters the data cannot identify.
    """
    idx = np.flatnonzero(res.free)
    held = tuple(getattr(res, "held", ()))
    return Free(tuple(int(j) for j in idx), held) if held else idx
