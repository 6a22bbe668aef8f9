"""Which parameters a fit identifies: a rule or names, less the parameters the user holds fixed, within bounds.

``free`` is ``"auto"``, ``"all"`` or parameter names everywhere in bayescal
(identify, calibrate, compare, grid, the Kalman filter, MCMC).  Holding
parameters fixed by name, as lmfit's ``vary=False`` does, combines with any of
them: :class:`Free` carries both, and :func:`bayescal.identify.gauss_newton.resolve_free`,
the one place a free set is resolved, honours it, so every consumer that
passes ``free`` on gets it.  Bounds (lmfit's ``min`` / ``max``) travel the
same way: :class:`Free` carries them, and :func:`bayescal.identify.gauss_newton.identify`
keeps every step inside them (:func:`bound_arrays`).
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..params import ParamLayout

__all__ = ["Free", "with_fixed", "held_index", "held_names", "same_free", "bounds_of", "bound_arrays", "parse_bounds",
           "check_name"]


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
    bounds : tuple of (str, float, float)
        ``(name, lower, upper)`` in the parameter's unit (the error from nominal, as reported), either side may be
        infinite: the fit's answer stays inside (``ls``, ``ridge``, ``map``: a bounded Gauss-Newton step; ``mcmc``:
        the posterior truncated there).
    """

    base: str | tuple = "auto"
    fix: tuple[str, ...] = ()
    bounds: tuple[tuple[str, float, float], ...] = ()


def with_fixed(free, fix: Sequence[str] | None, bounds=None):
    """``free`` with the names ``fix`` held fixed and ``bounds`` kept (``free`` itself when neither is given).

    Parameters
    ----------
    free : "auto", "all", names, indices or Free
    fix : sequence of str, optional
    bounds : mapping or sequence, optional
        ``{name: (lower, upper)}`` or ``[(name, lower, upper), ...]`` (:func:`parse_bounds`).

    Raises
    ------
    InputError
        ``fix`` is a single string rather than a list of names, or not names; a bound is not a pair of numbers
        with the lower below the upper.
    """
    no_fix = fix is None or (not isinstance(fix, str) and len(fix) == 0)
    box = parse_bounds(bounds)
    if no_fix and not box:
        return free
    if not no_fix and (isinstance(fix, str) or not all(isinstance(f, str) for f in fix)):
        raise InputError(f"fix: expected a list of parameter names, got {fix!r}")
    if isinstance(free, Free):
        return Free(free.base, free.fix + (() if no_fix else tuple(fix)), free.bounds + box)
    base = free if isinstance(free, str) or free is None else tuple(free)
    return Free("auto" if base is None else base, () if no_fix else tuple(fix), box)


def parse_bounds(bounds) -> tuple[tuple[str, float, float], ...]:
    """``bounds`` as ``((name, lower, upper), ...)``, checked (no names resolved yet: :func:`bound_arrays`).

    Accepts ``{name: (lower, upper)}``, ``[(name, lower, upper), ...]`` or None; ``None`` for a side is no bound
    there (as ``-inf`` / ``inf``).

    Raises
    ------
    InputError
        Naming the bound that is not two numbers, has NaN or has its lower side not below its upper side
        (a parameter held at one value is ``fix``).
    """
    if bounds is None:
        return ()
    # a mapping's items are (name, (lower, upper)); a sequence's entries (name, lower, upper)
    items = [(k, *v) if isinstance(v, (tuple, list)) else (k, v) for k, v in bounds.items()] \
        if hasattr(bounds, "items") else list(bounds)
    out = []
    for item in items:
        try:
            name, lo, hi = item
            lo, hi = -np.inf if lo is None else float(lo), np.inf if hi is None else float(hi)
            if not isinstance(name, str):
                raise ValueError
        except (TypeError, ValueError):
            raise InputError(f"bounds (--bound): expected name: (lower, upper) pairs of numbers, got {item!r}") from None
        if np.isnan(lo) or np.isnan(hi):
            raise InputError(f"bounds (--bound): '{name}': expected numbers (or an open side), got ({lo}, {hi})")
        if not lo < hi:
            raise InputError(f"bounds (--bound): '{name}': expected lower < upper, got ({lo}, {hi}); a parameter held "
                             "at one value is fix, not a bound")
        out.append((name, lo, hi))
    return tuple(out)


def bounds_of(free) -> tuple[tuple[str, float, float], ...]:
    """The bounds ``free`` carries (none unless it is a :class:`Free`)."""
    return tuple(free.bounds) if isinstance(free, Free) else ()


def bound_arrays(layout: ParamLayout, bounds) -> tuple[NDArray, NDArray]:
    """Lower and upper bounds of every parameter (P,), ``-inf`` / ``inf`` where none is given.

    Raises
    ------
    InputError
        Naming an unknown parameter (with the closest name) or one bounded twice.
    """
    lo, hi = np.full(len(layout), -np.inf), np.full(len(layout), np.inf)
    seen = set()
    for name, a, b in bounds:
        check_name(layout, name, "bounds")
        if name in seen:
            raise InputError(f"bounds (--bound): '{name}' bounded twice")
        seen.add(name)
        lo[layout.index(name)], hi[layout.index(name)] = a, b
    return lo, hi


def check_name(layout: ParamLayout, name: str, what: str) -> None:
    """InputError naming ``what`` (``fix``, ``bounds``, ``free``) when ``name`` is not a parameter, with the closest."""
    if name not in layout.names:
        # a name written without its prefix (``mass.link3`` for ``effect.gravity_deflection.mass.link3``)
        close = ([n for n in layout.names if n.endswith("." + name)][:1]
                 or difflib.get_close_matches(name, layout.names, n=1))
        hint = f"did you mean '{close[0]}'? " if close else ""
        raise InputError(f"{what}: unknown parameter '{name}'; {hint}expected one of: {', '.join(layout.names)}")


def held_index(layout: ParamLayout, fix: Sequence[str]) -> NDArray:
    """Indices of the names ``fix`` (InputError naming an unknown or repeated one)."""
    out = []
    for name in fix:
        check_name(layout, name, "fix")
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
    held, the refit would count them among the parameters the data cannot identify.  The parameters the fit left
    at a bound are free again, within the same bounds: the refit finds its own active set.
    """
    at_bound = [list(res.names).index(n) for n in res.at_bound]
    idx = np.union1d(np.flatnonzero(res.free), np.array(at_bound, dtype=int)).astype(int)
    held, bounds = tuple(res.held), tuple(res.bounds)
    return Free(tuple(int(j) for j in idx), held, bounds) if held or bounds else idx
