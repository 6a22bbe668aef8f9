"""The answer of an identification: named parameters with uncertainty, fit statistics, history."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = ["IdentificationResult", "ParameterEstimate", "covariance_dict", "decided_by_prior_lines"]

STRONG_CORRELATION = 0.95
POORLY_DETERMINED = 10.0  # std above this many tolerances: the value is not a physical error


def covariance_dict(names, units, free, covariance) -> dict | None:
    """The JSON block of a covariance over the identified parameters (docs/formats.md section 3).

    ``{"names": [...], "units": [...], "matrix": [[...]], "correlation": [[...]], "unit": ...}``:
    entry (i, j) of ``matrix`` is in unit_i x unit_j (mm, rad); ``correlation`` is dimensionless.
    None without a covariance.
    """
    if covariance is None:
        return None
    C = np.atleast_2d(np.asarray(covariance, dtype=float))
    free = np.asarray(free, dtype=bool)
    d = np.sqrt(np.clip(np.diag(C), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        R = C / np.outer(d, d)
    return {
        "names": [n for n, f in zip(names, free) if f],
        "units": [u for u, f in zip(units, free) if f],
        "matrix": C,
        "correlation": R,
        "unit": "entry (i, j) in units[i] x units[j]; correlation dimensionless",
    }


@dataclass(frozen=True)
class ParameterEstimate:
    """One identified error (actual minus nominal).

    ``estimated``: the method gave it a value (it was free); ``identified``:
    the data determine it alone, without the prior (its direction lies in
    the row space of the identification matrix).  A free parameter of a
    gauge, or one no row sees, is estimated but not identified: its value
    and std are the prior's.
    """

    name: str
    value: float
    std: float | None
    unit: str
    identified: bool
    estimated: bool = True


@dataclass(frozen=True)
class IdentificationResult:
    """What an identification found.

    Attributes
    ----------
    machine_name, kind : str
    method : str
        ``ls``, ``ridge``, ``tsvd`` (or a method added later).
    lam, k : float or int or None
        The regularisation actually used.
    names, units : tuple of str
        All parameters of the machine.
    theta : ndarray, shape (P,)
        Identified errors; fixed parameters stay at their start value.
    free : ndarray of bool, shape (P,)
        Which parameters were identified.
    covariance : ndarray, shape (n_free, n_free) or None
        Of the identified parameters (see ``covariance_kind``).
    covariance_kind : str
        How ``covariance`` was obtained.
    rms_before, rms_after : dict
        ``{"position": mm, "angle": rad or None}`` against nominal and calibrated model.
    residuals_before, residuals_after : ndarray, shape (n_poses, dof)
        ``y - h`` in mm and rad.
    singular_values : ndarray
        Of the whitened, tolerance-scaled identification matrix at the solution.
    filter_factors : ndarray
    rank : int
        Numerical rank of that matrix.
    iterations : int
    history : ndarray, shape (iterations + 1, P)
        ``theta`` after each Gauss-Newton iteration (row 0: the start).
    cost_history : ndarray, shape (iterations + 1,)
        Whitened sum of squared residuals after each iteration.
    success : bool
    message : str
    fixed : tuple of str
        Parameters the data cannot identify, held at nominal, and ``unidentifiable`` explains why.
    held : tuple of str
        Parameters the user held at nominal (``fix``), whatever the data see.
    at_bound : tuple of str
        Parameters the answer put on one of their ``bounds``: not estimated there (no std; the others' covariance
        is conditional on them staying on the bound).
    bounds : tuple of (str, float, float)
        The bounds the fit kept, ``(name, lower, upper)`` in the parameter's unit.
    unidentifiable : tuple of str
    decided_by_prior : tuple of str
        Combinations the data do not separate that the prior decided (map,
        ridge, tsvd with ``free="auto"``: estimated, not fixed), in words.
    dof : int
        Rows per pose: the tool's 6, 5 or 3, plus two tilt rows per body sensor.
    tool_dof : int, optional
        The tool's rows per pose (6, 5 or 3); None: ``dof`` (no body sensors).
    n_poses : int
    chi2 : float
        Whitened sum of squared residuals after calibration.
    noise_given : bool
        Whether the instrument sigma came from the machine file; if not, the
        covariance was scaled by the reduced chi-square.
    condition_number : float
        Of the whitened, tolerance-scaled matrix on the subspace the data
        determine (largest over smallest singular value above the structural
        threshold), so gauges do not show as 1e16.
    determined : ndarray of bool, shape (P,), optional
        Which free parameters the data determine alone (no prior needed:
        :func:`bayescal.identify.gauss_newton.data_determined`); None: all
        free ones (methods without a prior identify an identifiable set).
    """

    machine_name: str
    kind: str
    method: str
    lam: float | None
    k: int | None
    names: tuple[str, ...]
    units: tuple[str, ...]
    theta: NDArray
    free: NDArray
    covariance: NDArray | None
    covariance_kind: str
    rms_before: dict
    rms_after: dict
    residuals_before: NDArray
    residuals_after: NDArray
    singular_values: NDArray
    filter_factors: NDArray
    rank: int
    iterations: int
    history: NDArray
    cost_history: NDArray
    success: bool
    message: str
    fixed: tuple[str, ...] = ()
    unidentifiable: tuple[str, ...] = ()
    decided_by_prior: tuple[str, ...] = ()
    held: tuple[str, ...] = ()
    at_bound: tuple[str, ...] = ()
    bounds: tuple = ()
    dof: int = 6
    n_poses: int = 0
    chi2: float = float("nan")
    noise_given: bool = True
    extras: dict = field(default_factory=dict)
    tolerance: NDArray | None = None
    determined: NDArray | None = None
    condition_number: float = float("nan")
    tool_dof: int | None = None

    @property
    def tilt_rows(self) -> int:
        """Body sensors' tilt rows per pose (two per sensor; 0 without sensors)."""
        return 0 if self.tool_dof is None else self.dof - self.tool_dof

    @property
    def measurement_label(self) -> str:
        """``3-DOF`` or, with body sensors, ``3-DOF + 2 body sensors``."""
        k = self.tilt_rows // 2
        base = f"{self.dof - self.tilt_rows}-DOF"
        return base if not k else f"{base} + {k} body sensor{'s' if k > 1 else ''}"

    def poorly_determined(self, factor: float = POORLY_DETERMINED) -> tuple[str, ...]:
        """Identified parameters whose std exceeds ``factor`` times their tolerance.

        Their values are not physical errors but whatever the ill-conditioned
        directions absorbed; ridge, MAP or TSVD keep them near nominal.
        """
        if self.tolerance is None:
            return ()
        std = self.std
        return tuple(n for n, s, t, f in zip(self.names, std, self.tolerance, self.free) if f and np.isfinite(s) and s > factor * t)

    # ------------------------------------------------------------------ access
    @property
    def std(self) -> NDArray:
        """Standard deviation per parameter (NaN where not identified or not defined)."""
        out = np.full(self.theta.shape, np.nan)
        if self.covariance is not None:
            out[self.free] = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return out

    @property
    def identified(self) -> NDArray:
        """Which parameters the data determine alone, shape (P,) bool (see ``determined``)."""
        if self.determined is None:
            return np.asarray(self.free, dtype=bool)
        return np.asarray(self.free, dtype=bool) & np.asarray(self.determined, dtype=bool)

    @property
    def effective_params(self) -> float:
        """Effective number of fitted parameters: the filter factors summed (the trace of the hat matrix)."""
        return float(np.sum(self.filter_factors)) if np.size(self.filter_factors) else float(np.sum(self.free))

    @property
    def prior_effective_params(self) -> float | None:
        """Ridge, TSVD and MAP: the filter factors summed (the hat matrix's trace under the prior); else None.

        None for least squares (no prior: every free parameter counts) and when the factors are not finite.
        """
        if self.method not in ("ridge", "tsvd", "map") or self.filter_factors is None:
            return None
        f = np.asarray(self.filter_factors, dtype=float)
        return float(f.sum()) if f.size and np.all(np.isfinite(f)) else None

    @property
    def dof_fit(self) -> float:
        """Residual degrees of freedom: measured components less :attr:`effective_params` (at least 1)."""
        return max(self.n_poses * self.dof - self.effective_params, 1.0)

    @property
    def reduced_chi2(self) -> float:
        """Chi-square per residual degree of freedom (about 1 when the stated noise fits)."""
        return self.chi2 / self.dof_fit

    @property
    def parameters(self) -> tuple[ParameterEstimate, ...]:
        std = self.std
        ident = self.identified
        return tuple(
            ParameterEstimate(n, float(v), None if not np.isfinite(s) else float(s), u, bool(i), bool(f))
            for n, v, s, u, i, f in zip(self.names, self.theta, std, self.units, ident, self.free)
        )

    @property
    def free_names(self) -> tuple[str, ...]:
        return tuple(n for n, f in zip(self.names, self.free) if f)

    def correlations(self, threshold: float = STRONG_CORRELATION) -> list[tuple[str, str, float]]:
        """Pairs of identified parameters with ``|correlation| >= threshold``, strongest first."""
        if self.covariance is None:
            return []
        d = np.sqrt(np.clip(np.diag(self.covariance), 1e-300, None))
        C = self.covariance / np.outer(d, d)
        names = self.free_names
        iu = np.triu_indices(len(names), 1)
        pairs = [(names[i], names[j], float(C[i, j])) for i, j in zip(*iu) if abs(C[i, j]) >= threshold]
        return sorted(pairs, key=lambda p: -abs(p[2]))

    # ----------------------------------------------------------------- output
    def to_dict(self) -> dict:
        """The JSON answer of ``bayescal identify`` (docs/formats.md section 3), plus details."""
        return {
            "machine": self.machine_name,
            "kind": self.kind,
            "method": self.method,
            "lam": self.lam,
            "k": self.k,
            "success": self.success,
            "message": self.message,
            "parameters": [
                {"name": p.name, "value": p.value, "std": p.std, "unit": p.unit, "identified": p.identified,
                 "estimated": p.estimated}
                for p in self.parameters
            ],
            "rms_before": self.rms_before,
            "rms_after": self.rms_after,
            "dof": self.dof - self.tilt_rows,
            **({"tilt_rows_per_pose": self.tilt_rows} if self.tilt_rows else {}),
            "n_poses": self.n_poses,
            "iterations": self.iterations,
            "chi2": self.chi2,
            "rank": self.rank,
            "condition_number": self.condition_number,
            "n_identified": int(self.identified.sum()),
            "n_estimated": int(np.sum(self.free)),
            "effective_params": self.effective_params,
            "dof_fit": self.dof_fit,
            "reduced_chi2": self.reduced_chi2,
            "singular_values": self.singular_values,
            "covariance_kind": self.covariance_kind,
            "covariance": covariance_dict(self.names, self.units, self.free, self.covariance),
            "fixed": list(self.fixed),
            "held": list(self.held),
            **bounds_dict(self.bounds, self.at_bound),
            "unidentifiable": list(self.unidentifiable),
            "decided_by_prior": list(self.decided_by_prior),
            "strong_correlations": [{"a": a, "b": b, "correlation": c} for a, b, c in self.correlations()],
            "cost_history": self.cost_history,
            **self.extras,
        }

    def report(self, *, max_combinations: int = 10) -> str:
        """A readable report: fit statistics, parameters with std and unit, warnings."""
        reg = f" (lambda = {self.lam:.4g})" if self.lam is not None else f" (k = {self.k})" if self.k is not None else ""
        status = "converged" if self.success else "FAILED"
        nfree = int(self.free.sum())
        nident = int(self.identified.sum())
        rows = self.n_poses * self.dof
        lines = [
            f"bayescal identification of '{self.machine_name}' ({self.kind})",
            f"  method          {self.method}{reg}: {status} after {self.iterations} iterations",
        ]
        if self.message:
            lines.append(f"  message         {self.message}")
        # least squares (and ridge with lam = 0) has no prior to decide what the data leave open
        prior = not (self.method == "ls" or (self.method == "ridge" and not self.lam))
        counted = (f"{nident} parameters identified by the data" if nident == nfree else
                   f"{nfree} parameters estimated: {nident} identified by the data, {nfree - nident} "
                   + ("decided by the prior" if prior else "not separated by the data"))
        if nident < self.rank < nfree and not prior:
            counted += f" (the data determine {self.rank} combinations)"
        elif nident < self.rank < nfree:
            # a parameter counts as identified only when the data determine it alone; with a fitted frame every
            # parameter may share a gauge, while the data still determine `rank` combinations of them
            counted += f" in part (the data determine {self.rank} combinations)"
        lines += [
            f"  measurement     {self.measurement_label}, {self.n_poses} poses, {rows} residuals, {counted}",
            f"  chi-square      {self.chi2:.4g} (reduced {self.reduced_chi2:.4g} on {self.dof_fit:.1f} degrees of freedom, "
            f"{self.effective_params:.1f} effective parameters); "
            f"noise sigma {'from the machine file' if self.noise_given else 'default, covariance scaled by reduced chi-square'}",
            f"  RMS position    {self.rms_before['position']:.6f} mm before, {self.rms_after['position']:.6f} mm after",
        ]
        if self.rms_before.get("angle") is not None:
            lines.append(
                f"  RMS angle       {self.rms_before['angle']:.3e} rad before, {self.rms_after['angle']:.3e} rad after"
            )
        if self.rms_before.get("tilt") is not None:
            lines.append(
                f"  RMS tilt        {self.rms_before['tilt']:.3e} rad before, {self.rms_after['tilt']:.3e} rad after "
                "(body sensors)"
            )
        if self.rank:
            lines.append(f"  identification matrix: rank {self.rank} of {nfree}, condition number {self.condition_number:.3g} "
                         "on the subspace the data determine")
        lines.append(f"  covariance      {self.covariance_kind}")
        poor = set(self.poorly_determined())
        lines += ["", f"  {'parameter':<36}{'value':>14}{'std':>12}  unit"]
        for p in self.parameters:
            if not p.estimated:
                continue
            std = f"{p.std:12.3e}" if p.std is not None else f"{'-':>12}"
            flag = " !" if p.name in poor else "" if p.identified else " (prior)"
            lines.append(f"  {p.name:<36}{p.value:14.6g}{std}  {p.unit}{flag}")
        if poor:
            lines += [
                "",
                f"  ! {len(poor)} parameters have a std above {POORLY_DETERMINED:g} times their tolerance: the data do not "
                "determine them, and their values are not physical errors. Consider --method ridge --lam auto "
                "or --method tsvd --k auto.",
            ]
        corr = self.correlations()
        if corr:
            lines += ["", f"  strongly correlated pairs (|r| >= {STRONG_CORRELATION}):"]
            lines += [f"    {a} ~ {b}: {c:+.3f}" for a, b, c in corr[:15]]
            if len(corr) > 15:
                lines.append(f"    ... and {len(corr) - 15} more")
        if self.held:
            lines += ["", f"  held at nominal (fix): {', '.join(self.held)}"]
        lines += bound_lines(self.names, self.units, self.theta, self.bounds, self.at_bound)
        if self.fixed:
            lines += ["", f"  not identifiable from these poses, fixed at nominal: {', '.join(self.fixed)}"]
            lines += [f"    - {c}" for c in self.unidentifiable[:max_combinations]]
        lines += decided_by_prior_lines(
            self.decided_by_prior, " (estimated near nominal in proportion to the tolerances; --method ls fixes them instead)",
            max_combinations)
        return "\n".join(lines)


def decided_by_prior_lines(combinations, how: str = "", max_combinations: int = 0) -> list[str]:
    """Report lines naming the combinations the data do not separate and the prior decides (none: no lines).

    ``how`` follows "decided by the prior" (how the method treats them); the first ``max_combinations``
    combinations are then listed in full.
    """
    if not combinations:
        return []
    names = ", ".join(c.split(":", 1)[0] for c in combinations)
    return ["", f"  not separated by these poses, decided by the prior{how}: {names}"] + [
        f"    - {c}" for c in combinations[:max_combinations]]


def bounds_dict(bounds, at_bound) -> dict:
    """The answer's ``bounds`` (``{name: [lower, upper]}``, ``null`` for an open side) and ``at_bound`` ({} if none)."""
    if not bounds:
        return {}
    side = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731 (JSON has no infinity)
    return {"bounds": {n: [side(a), side(b)] for n, a, b in bounds}, "at_bound": list(at_bound)}


def bound_lines(names, units, theta, bounds, at_bound) -> list[str]:
    """Report lines: each parameter the answer put on a bound, with the bound, and what its std means."""
    if not at_bound:
        return ["", f"  bounds kept, none reached: {', '.join(b[0] for b in bounds)}"] if bounds else []
    lines = ["", "  on a bound (no std; the others' covariance is conditional on these staying there):"]
    for name in at_bound:
        j = list(names).index(name)
        lo, hi = next((a, b) for n, a, b in bounds if n == name)
        side = "lower" if theta[j] == lo else "upper"
        lines.append(f"    {name:<34}{theta[j]:14.6g}  {units[j]}  ({side} bound)")
    return lines
