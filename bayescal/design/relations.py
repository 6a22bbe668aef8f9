"""Planning constraint measurements: which heights to probe and which distances to measure next.

Candidates are *relations*, not poses: a probe height at a point of a
horizontal grid, or the distance between two grid points (a caliper on a
printed part, a length bar).  Each candidate contributes one row of the
whitened, tolerance-scaled Jacobian ``a = J diag(tol) / sigma``
(:class:`bayescal.constraints.model.ConstraintModel`), and the selection is
the same greedy rank-one update as for poses
(:func:`bayescal.design.select.greedy_select`), started from the information
the user already has: ``M0 = I + A_given^T A_given`` (the tolerance prior
plus the measurements already taken).  With the prior in ``M0`` the log-det
utility is the expected information gain (EIG) of the new rows given the
old; other criteria of :mod:`bayescal.design.criteria` work alike.

The answer says, per parameter, the posterior standard deviation (linearised,
under the tolerance prior) with the given measurements and with the planned
ones added, and which parameters the data (without the prior) determines
before and after (:func:`bayescal.identifiability.analyse_identifiability`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from itertools import combinations

import numpy as np
from numpy.typing import NDArray

from ..constraints.model import ConstraintModel
from ..errors import InputError
from ..identifiability import analyse_identifiability
from ..limits import sigma_problem
from ..io.constraints import ConstraintRecording
from ..machines.base import Machine
from ..constraints.simulate import solve_q_for_points
from .criteria import check_criterion
from .select import greedy_select
from ..notebook import ShowsReport

__all__ = ["RelationPlan", "grid_points", "relation_candidates", "plan_relations", "relation_plan_csv", "MEASURES",
           "relation_output_weight", "relaxed_relations"]

MEASURES = ("height", "distance")


def check_relations_size(machine: Machine, measure: str, radius: float, spacing: float) -> None:
    """Refuse, before any work, a grid of candidates whose arrays would not fit in memory.

    The square of ``2 floor(radius / spacing) + 1`` points per side is
    meshed; heights are one candidate per point within the radius, distances
    one per pair of points (:func:`bayescal.limits.check_memory`).
    """
    from ..limits import check_memory

    if not (np.isfinite(radius) and np.isfinite(spacing) and radius > 0 and spacing > 0):
        raise InputError(f"grid: expected a positive radius and spacing, got {radius} and {spacing} mm")
    k = math.floor(min(radius / spacing, 1e15))  # capped: beyond it any grid is refused, and squares stay finite
    square = (2 * k + 1) ** 2
    points = min(square, np.pi * (k + 1) ** 2)
    rows = points if measure == "height" else points * (points - 1) / 2
    need = 8.0 * (4 * square + rows * (3 * machine.n_params + 2 * machine.n_actuators + 8))
    what = f"{points:,.0f} grid points" + ("" if measure == "height" else f" ({rows:,.0f} pairs)")
    check_memory(need, what, "raise --spacing or lower --radius")


def grid_points(centre: NDArray, radius: float, spacing: float) -> NDArray:
    """Points of a square grid of ``spacing`` within ``radius`` of ``centre`` (horizontal plane), mm."""
    if not (radius > 0 and spacing > 0):
        raise InputError(f"grid: expected a positive radius and spacing, got {radius} and {spacing} mm")
    k = int(np.floor(radius / spacing))
    u = np.arange(-k, k + 1) * spacing
    X, Y = np.meshgrid(u, u, indexing="ij")
    keep = X**2 + Y**2 <= radius**2 * (1 + 1e-12)
    c = np.asarray(centre, dtype=float)
    return np.column_stack([X[keep] + c[0], Y[keep] + c[1], np.full(int(keep.sum()), c[2])])


def relation_candidates(machine: Machine, measure: str, points: NDArray, *, min_distance: float = 0.0) -> ConstraintRecording:
    """Candidate relations at nominal tool ``points``: heights at each, or distances between pairs.

    Parameters
    ----------
    machine : Machine
        Nominal geometry (commanded positions come from it).
    measure : {"height", "distance"}
    points : ndarray, shape (n, 3)
        Tool points, base frame, mm.
    min_distance : float
        Pairs closer than this (mm) are not candidates (a caliper needs a span).

    Returns
    -------
    ConstraintRecording
        ``value`` is the nominal prediction (a placeholder for the measured value).
    """
    if measure not in MEASURES:
        raise InputError(f"measure: expected one of {', '.join(MEASURES)}, got {measure!r}")
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    q = solve_q_for_points(machine, pts)
    N = q.shape[1]
    if measure == "height":
        k = np.arange(len(q), dtype=float)
        return ConstraintRecording(measure=("height",) * len(q), qa=q, qb=np.full_like(q, np.nan), value=pts[:, 2].copy(),
                                   aux={"point_a": k, "point_b": np.full(len(q), np.nan)})
    pairs = np.array([(i, j) for i, j in combinations(range(len(pts)), 2)
                      if np.linalg.norm(pts[i] - pts[j]) >= max(min_distance, 1e-9)], dtype=int).reshape(-1, 2)
    if not len(pairs):
        raise InputError("distance candidates: no pair of grid points is far enough apart; enlarge --radius")
    d = np.linalg.norm(pts[pairs[:, 0]] - pts[pairs[:, 1]], axis=1)
    return ConstraintRecording(measure=("distance",) * len(pairs), qa=q[pairs[:, 0]].reshape(-1, N),
                               qb=q[pairs[:, 1]].reshape(-1, N), value=d,
                               aux={"point_a": pairs[:, 0].astype(float), "point_b": pairs[:, 1].astype(float)})


def _scaled_rows(machine: Machine, rec: ConstraintRecording, sigma: float | None) -> tuple[NDArray, ConstraintModel]:
    model = ConstraintModel.from_recording(machine, rec)
    if any(m == "ballbar" for m in rec.measure):
        raise InputError("planning with ballbar rows is not supported: plan heights or distances")
    pred = model.predict(None)
    if not pred.success.all():
        raise InputError(f"{int((~pred.success).sum())} measurement poses cannot be solved on the nominal machine")
    J = model.jacobian(None, pred).reshape(rec.n_rows, -1)
    s = model.row_sigma[:, 0] if sigma is None else np.full(rec.n_rows, float(sigma))
    return J * machine.tolerance[None, :] / s[:, None], model


def _given_rows(machine: Machine, given: ConstraintRecording) -> NDArray:
    """Whitened, tolerance-scaled rows of the measurements already taken, on the machine's parameters.

    Ballbar rows (docs/formats.md section 6: every command that takes a recording takes this
    one) bring their pivots as nuisance parameters under the pivot prior; their
    information on the machine is the Schur complement of the pivot block, returned
    as equivalent rows ``R`` with ``R^T R = M_mm - M_mp M_pp^-1 M_pm - I``.
    """
    if not any(m == "ballbar" for m in given.measure):
        return _scaled_rows(machine, given, None)[0]
    model = ConstraintModel.from_recording(machine, given)
    pred = model.predict(None)
    if not pred.success.all():
        raise InputError(f"{int((~pred.success).sum())} measurement poses cannot be solved on the nominal machine")
    J = model.jacobian(None, pred).reshape(given.n_rows, -1)
    A = J * model.machine.tolerance[None, :] / model.row_sigma[:, 0][:, None]
    P = machine.n_params
    M = np.eye(A.shape[1]) + A.T @ A
    info = M[:P, :P] - M[:P, P:] @ np.linalg.solve(M[P:, P:], M[P:, :P]) - np.eye(P)
    w, V = np.linalg.eigh((info + info.T) / 2)
    return (V * np.sqrt(np.clip(w, 0.0, None))).T


@dataclass(frozen=True)
class RelationPlan(ShowsReport):
    """Planned heights or distances, and what they add to the measurements already taken.

    Attributes
    ----------
    measure : str
    recording : ConstraintRecording
        The planned rows (``value``: nominal prediction, to be replaced by the measurement).
    points_a, points_b : ndarray, shape (n, 3)
        Nominal tool points of pose a and b (b NaN for heights), mm.
    names, units : tuple of str
    std_prior, std_given, std_planned : ndarray, shape (P,)
        Posterior std (linearised, tolerance prior) before any data, with the
        given data and with the plan added, parameter units.
    fixed_given, fixed_planned : tuple of str
        Parameters the data (without the prior) cannot determine, before and after.
    criterion : str
    utility_given, utility_planned : float
        ``log det`` of the information matrix (EIG-type utility) before and after.
    """

    measure: str
    recording: ConstraintRecording
    points_a: NDArray
    points_b: NDArray
    names: tuple[str, ...]
    units: tuple[str, ...]
    std_prior: NDArray
    std_given: NDArray
    std_planned: NDArray
    fixed_given: tuple[str, ...]
    fixed_planned: tuple[str, ...]
    criterion: str
    utility_given: float
    utility_planned: float

    def report(self) -> str:
        n = self.recording.n_rows
        lines = [
            f"bayescal plan: {n} {self.measure} measurements to take next (criterion {self.criterion}, "
            f"tolerance prior plus the measurements given)",
            f"  expected information gain {0.5 * (self.utility_planned - self.utility_given):.3g} nats",
            f"  not determined by the data before: {', '.join(self.fixed_given) or 'none'}",
            f"  not determined by the data after:  {', '.join(self.fixed_planned) or 'none'}",
            "",
            f"  {'parameter':<28}{'prior std':>12}{'given':>12}{'planned':>12}",
        ]
        for k, name in enumerate(self.names):
            lines.append(f"  {name:<28}{self.std_prior[k]:12.4g}{self.std_given[k]:12.4g}{self.std_planned[k]:12.4g}  {self.units[k]}")
        lines += ["", "  what to measure (nominal tool points, mm):"]
        for i in range(n):
            a = ", ".join(f"{v:.2f}" for v in self.points_a[i])
            if self.measure == "height":
                lines.append(f"  {i + 1:3d}. height at ({a})")
            else:
                b = ", ".join(f"{v:.2f}" for v in self.points_b[i])
                lines.append(f"  {i + 1:3d}. distance ({a}) - ({b}), nominal {self.recording.value[i]:.3f}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "measure": self.measure, "criterion": self.criterion, "n": self.recording.n_rows,
            "qa": self.recording.qa, "qb": self.recording.qb, "nominal_value": self.recording.value,
            "points_a": self.points_a, "points_b": self.points_b,
            "parameters": {n: {"prior_std": float(p), "given_std": float(g), "planned_std": float(q)}
                           for n, p, g, q in zip(self.names, self.std_prior, self.std_given, self.std_planned)},
            "fixed_given": list(self.fixed_given), "fixed_planned": list(self.fixed_planned),
            "expected_information_gain_nats": 0.5 * (self.utility_planned - self.utility_given),
        }


def plan_relations(
    machine: Machine, n: int, *, measure: str = "height", given: ConstraintRecording | None = None,
    centre: NDArray | None = None, radius: float = 50.0, spacing: float | None = None, sigma: float | None = None,
    criterion: str = "EIG", repeats: bool | None = None, min_distance: float = 0.0, method: str | None = None,
    seed: int = 0, n_output: int = 2000,
) -> RelationPlan:
    """Choose ``n`` heights or distances on a horizontal grid that add the most information.

    Parameters
    ----------
    machine : Machine
        Nominal geometry and tolerances (the prior).
    n : int
        Number of relations to plan.
    measure : {"height", "distance"}
    given : ConstraintRecording, optional
        Measurements already taken (their information starts the selection).
    centre : array_like, shape (3,), optional
        Grid centre (tool point), mm; default the tool point at the middle of ``q_limits``.
    radius, spacing : float
        Grid radius and spacing, mm (spacing default ``radius / 4``).
    sigma : float, optional
        One-sigma noise of a planned row, mm; default ``[measurement] sigma_position``.
    criterion : str
        Any of :data:`bayescal.design.criteria.CRITERIA`; log-det ones (EIG, D) work from the prior.
        ``I``: ``sqrt(E[MSE])`` of the tool point over the workspace after MAP
        calibration with the given and the planned rows, ``Q`` from
        ``n_output`` poses drawn uniformly within ``q_limits`` (``seed``).
    repeats : bool, optional
        Allow a relation to be planned twice (default: yes with the relaxed
        method, no with greedy).
    min_distance : float
        Shortest distance candidate, mm.
    method : {"greedy", "relaxed"}, optional
        Default relaxed for I (the Frank-Wolfe relaxed design rounded, see
        :func:`bayescal.design.plan.default_method`), greedy otherwise.
    seed, n_output : int
        Workspace poses for criterion I's output weight.
    """
    criterion, method, repeats = _checked_options(criterion, method, repeats, n, sigma, min_distance)
    check_relations_size(machine, measure, radius, radius / 4 if spacing is None else spacing)
    if centre is None:
        centre = machine.forward(machine.home_q()[None, :]).position[0]
    pts = grid_points(np.asarray(centre, dtype=float), radius, radius / 4 if spacing is None else spacing)
    cands = relation_candidates(machine, measure, pts, min_distance=min_distance)
    s_new = machine.noise.sigma_position if sigma is None else sigma
    A_c, _ = _scaled_rows(machine, cands, s_new)
    P = machine.n_params
    M0 = np.eye(P)
    A_g = np.zeros((0, P))
    if given is not None:
        A_g = _given_rows(machine, given)
        M0 = M0 + A_g.T @ A_g
    Q = relation_output_weight(machine, n_output, np.random.default_rng(seed)) if criterion == "I" else None
    if method == "relaxed":
        idx = relaxed_relations(A_c, Q, n, M0, repeats=repeats)
        M = M0 + A_c[idx].T @ A_c[idx]
    else:
        idx, M = greedy_select(A_c[:, None, :], n, criterion, M0=M0, repeats=repeats, Q=Q)
    planned = replace(cands.subset(idx), sigma=np.full(len(idx), float(s_new)))
    A_all = np.vstack([A_g, A_c[idx]])
    tol = machine.tolerance
    names, units = machine.layout.names, machine.layout.units

    def fixed(A: NDArray) -> tuple[str, ...]:
        return analyse_identifiability(A, machine.layout).fixed if A.shape[0] else tuple(names)

    ld0, ld1 = np.linalg.slogdet(M0)[1], np.linalg.slogdet(M)[1]
    pa = pts[planned.aux["point_a"].astype(int)]
    pb = (pts[planned.aux["point_b"].astype(int)] if measure == "distance" else np.full((planned.n_rows, 3), np.nan))
    return RelationPlan(
        measure=measure, recording=planned, points_a=pa, points_b=pb, names=tuple(names), units=tuple(units),
        std_prior=tol.copy(), std_given=tol * np.sqrt(np.diag(np.linalg.inv(M0))),
        std_planned=tol * np.sqrt(np.diag(np.linalg.inv(M))), fixed_given=fixed(A_g), fixed_planned=fixed(A_all),
        criterion=criterion, utility_given=float(ld0), utility_planned=float(ld1),
    )


def _checked_options(criterion, method, repeats, n, sigma, min_distance) -> tuple[str, str, bool]:
    """:func:`plan_relations`'s criterion, method and repeats resolved, or InputError naming the option."""
    from .plan import METHODS, default_method

    criterion = check_criterion(criterion)
    method = default_method(criterion) if method is None else method
    if method not in METHODS:
        raise InputError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    if method == "relaxed" and criterion != "I":
        raise InputError(f"method 'relaxed': only for criterion I, got {criterion}")
    repeats = (method == "relaxed") if repeats is None else bool(repeats)
    if n < 1:
        raise InputError(f"n: expected a positive number of measurements, got {n}")
    # a noise of 0 or -1 mm, a negative shortest distance: planned without a word
    if sigma is not None and (problem := sigma_problem(sigma, "position")) is not None:
        raise InputError(f"sigma (--sigma): {problem}")
    if not (math.isfinite(min_distance) and min_distance >= 0):
        raise InputError(f"min_distance (--min-distance): expected a length >= 0 in mm, got {min_distance!r}")
    return criterion, method, repeats


def relation_output_weight(machine: Machine, n: int, rng: np.random.Generator) -> NDArray:
    """``Q = mean_e G_e^T G_e`` (P, P) over ``n`` poses uniform within ``q_limits``, ``G_e`` the tolerance-scaled
    tool-point Jacobian (mm per tolerance) of all parameters: criterion I for relations, where the prior covers
    every parameter."""
    from .criteria import output_weight

    q = machine.sample_q(int(n), rng)
    poses = machine.forward(q)
    G = machine.tool_jacobian(q[poses.success], None, machine.forward(q[poses.success]))[:, :3, :]
    G = G[np.all(np.isfinite(G), axis=(1, 2))]
    if not G.shape[0]:
        raise InputError(f"{machine.source}: no pose within q_limits can be solved for criterion I's output weight")
    return output_weight(G * machine.tolerance[None, None, :])


def relaxed_relations(A_c: NDArray, Q: NDArray, n: int, M0: NDArray, *, repeats: bool = True) -> NDArray:
    """Criterion I from the prior-plus-given information ``M0``: the relaxed design rounded, then exchanges.

    ``M0 = I + A_given^T A_given`` is folded in by whitening: with ``M0 = C C^T`` the rows ``a C^-T`` and the
    weight ``C^-1 Q C^-T`` turn ``trace((M0 + A^T A)^-1 Q)`` into the prior-``I`` form the bound and the
    rounding use.
    """
    from .bound import design_mse_bound
    from .rounding import distinct_start, local_search, pool_from_bound, round_weights

    C = np.linalg.cholesky(M0)
    Ci = np.linalg.inv(C)
    B = (A_c @ Ci.T)[:, None, :]
    Qw = Ci @ Q @ Ci.T
    b = design_mse_bound(B, Qw, int(n))
    pool = pool_from_bound(b.weights, B, Qw)
    start = round_weights(b.weights, n) if repeats else distinct_start(b.weights, B, Qw, n, pool)
    return local_search(B, Qw, start, pool, repeats=repeats)


def relation_plan_csv(plan: RelationPlan) -> str:
    """The plan as a constraint-recording CSV with an empty ``value`` column for the user to fill in.

    Aux columns: ``nominal`` (the value the nominal machine predicts, mm) and
    the nominal tool points ``x_a, y_a, z_a`` (and ``x_b, y_b, z_b`` for
    distances), mm, so the user knows where to probe or what to measure.
    The empty ``value`` cells make the file unreadable as a recording until
    every measurement is entered.
    """
    import csv
    import io

    from ..io.constraints import constraints_to_csv

    rec = plan.recording
    aux = {"nominal": rec.value.copy()}
    for k, c in enumerate("xyz"):
        aux[f"{c}_a"] = plan.points_a[:, k]
    if plan.measure == "distance":
        for k, c in enumerate("xyz"):
            aux[f"{c}_b"] = plan.points_b[:, k]
    text = constraints_to_csv(replace(rec, aux=aux))
    rows = list(csv.reader(io.StringIO(text)))
    j = rows[0].index("value")
    for r in rows[1:]:
        r[j] = ""
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(rows)
    return out.getvalue()
