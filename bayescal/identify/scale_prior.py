"""A hyperprior on the prior scale: how far the machine file's tolerances may be off.

The rules for lambda (:mod:`bayescal.identify.choose`) work in tolerance-scaled
coordinates, where the prior on the errors is ``x ~ N(0, c^2 I)``: ``c = 1``
says the tolerances are right, ``c = 0.5`` that the machine is twice as good
as they say, ``c = 4`` four times as bad.  With rows whitened by the
instrument sigma ``sigma``, the ridge parameter is ``lam = sigma^2 / c^2``.

The data say how large ``c`` is through the evidence ``p(z | c)``.  That
likelihood does not vanish as ``c -> 0`` (it tends to the likelihood of pure
noise), so a hyperprior flat in ``log c`` gives the posterior a tail toward
``c = 0`` whose mass is set by where the candidate grid happens to end.
The tolerances are information: a :class:`ScaleHyperprior` states how far
they may be off, a proper density on ``log c``, and the posterior over
``lam`` is evidence times hyperprior (:func:`bayescal.identify.choose.lambda_posterior`).

Written here (a few lines of numpy) because the densities are elementary and
must be evaluated on a grid of ``log c`` with the normalising constant left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError

__all__ = ["ScaleHyperprior", "DEFAULT_HYPERPRIOR", "FLAT_HYPERPRIOR"]

KINDS = ("flat", "lognormal", "loguniform", "halfcauchy")


@dataclass(frozen=True)
class ScaleHyperprior:
    """A density on the prior scale ``c`` (errors over tolerances, dimensionless), evaluated in ``log c``.

    Attributes
    ----------
    kind : {"flat", "lognormal", "loguniform", "halfcauchy"}
        ``flat``: constant in ``log c`` (improper; the old behaviour, the
        grid's ends bound it).  ``lognormal``: ``log c ~ N(log centre,
        width^2)``.  ``loguniform``: ``log c`` uniform on ``[log low, log
        high]``.  ``halfcauchy``: ``c`` half-Cauchy with scale ``centre``
        (Gelman 2006's weakly informative prior for a hierarchical scale;
        in ``log c`` the density is ``sech(log c - log centre) / pi``,
        symmetric, with exponential tails).
    centre : float
        ``lognormal`` and ``halfcauchy``: the median of ``c``.
    width : float
        ``lognormal``: standard deviation of ``log c`` (natural log).
    low, high : float
        The support of ``c``: ``loguniform`` needs both; the other kinds are
        truncated to ``[low, high]`` (default unbounded: ``0`` and ``inf``).
    """

    kind: str = "lognormal"
    centre: float = 1.0
    width: float = float(np.log(2.0))
    low: float = 0.0
    high: float = float("inf")

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise InputError(f"hyperprior kind: expected one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.kind in ("lognormal", "halfcauchy") and not self.centre > 0:
            raise InputError(f"hyperprior centre: expected > 0, got {self.centre}")
        if self.kind == "lognormal" and not self.width > 0:
            raise InputError(f"hyperprior width: expected > 0, got {self.width}")
        if not 0 <= self.low < self.high or (self.kind == "loguniform" and not (self.low > 0 and np.isfinite(self.high))):
            raise InputError(f"hyperprior range: expected 0 <= low < high (loguniform: 0 < low < high < inf), "
                             f"got {self.low}, {self.high}")

    def log_density(self, log_c: ArrayLike) -> NDArray:
        """Log density of ``log c`` at ``log_c`` (natural log), up to a constant; ``-inf`` outside the support."""
        u = np.asarray(log_c, dtype=float)
        with np.errstate(divide="ignore"):
            inside = (u >= np.log(self.low)) & (u <= np.log(self.high))
        if self.kind in ("flat", "loguniform"):
            body = np.zeros_like(u)
        elif self.kind == "lognormal":
            body = -0.5 * ((u - np.log(self.centre)) / self.width) ** 2
        else:  # half-Cauchy on c: p(c) ~ 1 / (1 + (c/a)^2), times dc/dlog c = c: -log cosh(log c - log a) + const
            v = np.abs(u - np.log(self.centre))
            body = -(v + np.log1p(np.exp(-2.0 * v)))
        return np.where(inside, body, -np.inf)

    def describe(self) -> str:
        """One line for reports, e.g. ``log-normal on c, median 1, sd of ln c 0.693, c in [0.3, 6]``."""
        if self.kind == "loguniform":
            return f"log-uniform on c in [{self.low:g}, {self.high:g}]"
        text = {"flat": "flat in log c", "lognormal": f"log-normal on c, median {self.centre:g}, sd of ln c {self.width:.3g}",
                "halfcauchy": f"half-Cauchy on c, scale {self.centre:g}"}[self.kind]
        if self.low > 0 or np.isfinite(self.high):
            text += f", c in [{self.low:g}, {self.high:g}]"
        return text


#: No hyperprior: flat in ``log c`` over the candidate grid (what the rules did before).
FLAT_HYPERPRIOR = ScaleHyperprior(kind="flat")

#: The hyperprior the ``success`` rule uses by default: the machine's errors
#: are the tolerances' size within a factor 2 (one standard deviation of
#: ``ln c``, median 1: the tolerances are taken at their word), and certainly
#: between 0.3 and 6 times them (beyond that the machine file's tolerances
#: carry no information and the user should fix them).  Why this one
#: (studies/choice_rules.py, docs/regularisation.md): flat in ``log c`` leaves
#: the posterior a tail toward ``c = 0`` as long as the grid, which costs up to
#: 4 points of success at ``c <= 1``; the median at 1 recovers most of it at
#: ``c = 1``, the bounds keep the pull toward 1 from costing machines twice as
#: good as their tolerances, and at ``c = 2, 4`` the data outweigh it.  The
#: same statement for every machine and measurement, not fitted per case.
DEFAULT_HYPERPRIOR = ScaleHyperprior(kind="lognormal", centre=1.0, width=float(np.log(2.0)), low=0.3, high=6.0)
