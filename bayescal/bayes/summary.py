"""Shared output of the probabilistic methods: the parameter list of docs/formats.md section 3 and correlation flags."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..identify.result import STRONG_CORRELATION, ParameterEstimate

__all__ = ["parameter_list", "strong_correlations", "parameter_table", "STRONG_CORRELATION", "PosteriorMembers"]


class PosteriorMembers:
    """The members of the result contract (:class:`bayescal.contract.Result`) a filter or a sampler answers alike.

    Neither keeps residual rows (a consumer predicts them from the model at ``theta``), neither is a
    regularised linear solve (no filter factors), and their prior's tolerances are the model's machine's.
    """

    residuals_before = None
    residuals_after = None
    filter_factors = None
    tolerance = None

    @property
    def effective_params(self) -> float:
        """The free parameters counted (no filter factors)."""
        return float(np.sum(self.free))

    def poorly_determined(self, factor: float = 10.0) -> tuple[str, ...]:
        """None named: the posterior's spread is the prior's where the data are silent, never beyond it."""
        return ()

    @property
    def parameters(self) -> tuple[ParameterEstimate, ...]:
        """Every parameter with value, std, unit, identified and estimated, as the JSON's ``parameters`` list."""
        return tuple(ParameterEstimate(p["name"], p["value"], p["std"], p["unit"], p["identified"], p["estimated"])
                     for p in parameter_list(self.names, self.units, self.theta, self.std, self.free, self.determined))


def parameter_list(names, units, theta: NDArray, std: NDArray, free: NDArray, determined: NDArray | None = None) -> list[dict]:
    """``[{"name", "value", "std", "unit", "identified", "estimated"}]`` with ``std`` None where undefined.

    ``estimated``: the method gave the parameter a value (free); ``identified``: the data determine it alone
    (``determined``, :func:`bayescal.identify.gauss_newton.data_determined`; all free ones when not given).
    """
    det = np.ones(len(names), dtype=bool) if determined is None else np.asarray(determined, dtype=bool)
    return [
        {"name": n, "value": float(v), "std": float(s) if np.isfinite(s) else None, "unit": u,
         "identified": bool(f and d), "estimated": bool(f)}
        for n, v, s, u, f, d in zip(names, theta, std, units, free, det)
    ]


def strong_correlations(cov: NDArray, names, threshold: float = STRONG_CORRELATION) -> list[tuple[str, str, float]]:
    """Pairs with ``|correlation| >= threshold``, strongest first."""
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    C = cov / np.outer(d, d)
    iu = np.triu_indices(len(names), 1)
    pairs = [(names[i], names[j], float(C[i, j])) for i, j in zip(*iu) if abs(C[i, j]) >= threshold]
    return sorted(pairs, key=lambda p: -abs(p[2]))


def parameter_table(rows: list[dict], pairs: list[tuple[str, str, float]], extra_cols: dict | None = None) -> list[str]:
    """Report lines: identified parameters with value, std, unit (and extra columns), then correlated pairs."""
    extra_cols = extra_cols or {}
    head = f"  {'parameter':<36}{'value':>14}{'std':>12}" + "".join(f"{k:>12}" for k in extra_cols) + "  unit"
    lines = ["", head]
    j = 0
    for r in rows:
        if not r.get("estimated", r["identified"]):
            continue
        std = f"{r['std']:12.3e}" if r["std"] is not None else f"{'-':>12}"
        extra = "".join(f"{v[j]:12.4g}" for v in extra_cols.values())
        lines.append(f"  {r['name']:<36}{r['value']:14.6g}{std}{extra}  {r['unit']}")
        j += 1
    if pairs:
        lines += ["", f"  strongly correlated pairs (|r| >= {STRONG_CORRELATION}):"]
        lines += [f"    {a} ~ {b}: {c:+.3f}" for a, b, c in pairs[:15]]
        if len(pairs) > 15:
            lines.append(f"    ... and {len(pairs) - 15} more")
    return lines
