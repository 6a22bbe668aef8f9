"""``plan_poses``: choose measurement poses by information, and the :class:`PosePlan` answer."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..io import write_text_atomic
from ..machines.base import Machine
from ..measurement import rows_per_pose
from .candidates import CandidateSet, draw_candidates
from .criteria import PRIOR_BASED, CRITERIA, check_criterion, criteria_from_singular_values, eig_value, i_value, utility_kind
from .select import Selection, exchange_refine, greedy_select
from ..notebook import ShowsReport

#: Selection methods: greedy + DETMAX exchange, or (criterion I) the Frank-Wolfe relaxed design rounded
#: and improved by exchanges on a pool (bayescal.design.rounding).
METHODS = ("greedy", "relaxed")

__all__ = ["PosePlan", "plan_poses", "select_from_candidates", "evaluate_selection", "root_expected_mse", "plan_to_csv",
           "write_plan", "METHODS", "default_method", "relaxed_select"]

#: delta of the regularised information matrix delta I + A^T A, relative to the mean
#: per-pose information per parameter (only matters while the selection is rank deficient).
DELTA_REL = 1e-9


@dataclass(frozen=True)
class PosePlan(ShowsReport):
    """A planned measurement session.

    Attributes
    ----------
    machine_name, kind : str
    criterion : str
        What was optimised (see :mod:`bayescal.design.criteria`).
    dof : int
    scaling : str
        Column scaling (``tolerance`` or ``candidates``).
    q : ndarray, shape (n_poses, n_actuators)
        Commanded actuator positions, in measurement order (selection order).
    candidate_index : ndarray of int
        Rows of the usable candidate set.
    values : dict
        Every criterion of the plan (larger is better).
    random_median : dict
        Median of every criterion over ``n_random`` random selections of the
        same size from the same candidates.
    random_beaten : dict
        Fraction of those random selections the plan beats, per criterion.
    kept, fixed : tuple of str
        Parameters the criteria are computed for / not identifiable from any candidate.
    n_candidates, n_rejected : int
    seed : int
    greedy_utility, utility : float
        Selection utility after the greedy pass and after exchange.
    swaps : int
    seconds : float
    """

    machine_name: str
    kind: str
    criterion: str
    dof: int
    scaling: str
    q: NDArray
    candidate_index: NDArray
    values: dict
    random_median: dict
    random_beaten: dict
    kept: tuple[str, ...]
    fixed: tuple[str, ...]
    n_candidates: int
    n_rejected: int
    seed: int
    greedy_utility: float
    utility: float
    swaps: int
    n_random: int
    seconds: float
    extras: dict = field(default_factory=dict)

    @property
    def n_poses(self) -> int:
        return self.q.shape[0]

    def to_dict(self) -> dict:
        return {
            "machine": self.machine_name,
            "kind": self.kind,
            "criterion": self.criterion,
            "dof": self.dof,
            "scaling": self.scaling,
            "n_poses": self.n_poses,
            "seed": self.seed,
            "q": self.q,
            "candidate_index": self.candidate_index,
            "values": self.values,
            "random_median": self.random_median,
            "random_beaten": self.random_beaten,
            "n_random": self.n_random,
            "kept": list(self.kept),
            "fixed": list(self.fixed),
            "n_candidates": self.n_candidates,
            "n_rejected": self.n_rejected,
            "greedy_utility": self.greedy_utility,
            "utility": self.utility,
            "swaps": self.swaps,
            "seconds": self.seconds,
            **self.extras,
        }

    def report(self) -> str:
        lines = [
            f"bayescal pose plan for '{self.machine_name}' ({self.kind})",
            f"  {self.n_poses} poses, {self.dof}-DOF measurement, criterion {self.criterion}, "
            f"column scaling '{self.scaling}', seed {self.seed}",
            f"  candidates      {self.n_candidates} usable ({self.n_rejected} rejected: no forward solution)",
            f"  parameters      {len(self.kept)} identifiable from the candidates"
            + (f"; not identifiable from any pose: {', '.join(self.fixed)}" if self.fixed else ""),
            (f"  selection       Frank-Wolfe relaxed design, rounded, then {self.swaps} exchanges on a pool"
             f"{', repeats allowed' if self.extras.get('repeats') else ''} ({self.seconds:.2f} s)"
             if self.extras.get("method") == "relaxed" else
             f"  selection       greedy then {self.swaps} exchange swaps"
             f"{', repeats allowed' if self.extras.get('repeats') else ''} ({self.seconds:.2f} s)"),
            "",
            f"  {'criterion':<10}{'plan':>14}{'random median':>16}{'beats random':>14}",
        ]
        for c in CRITERIA:
            mark = " *" if c == self.criterion else ""
            lines.append(
                f"  {c + mark:<10}{self.values[c]:14.5g}{self.random_median[c]:16.5g}"
                f"{100 * self.random_beaten[c]:13.0f}%"
            )
        lines.append(f"  (larger is better; random: median of {self.n_random} random sets of {self.n_poses} candidates)")
        if "root_expected_mse_mm" in self.extras:
            lines.append(f"  sqrt(E[MSE]) of the tool point after MAP calibration (linearised): "
                         f"{1e3 * self.extras['root_expected_mse_mm']:.4g} um")
        if "bound_root_mse_mm" in self.extras:
            lines.append(f"  every {self.n_poses}-pose design from these candidates: sqrt(E[MSE]) >= "
                         f"{1e3 * self.extras['bound_root_mse_mm']:.4g} um (Frank-Wolfe bound; the plan is "
                         f"{100 * (self.extras['root_expected_mse_mm'] / self.extras['bound_root_mse_mm'] - 1):.2f} % above it)")
        if "exact_bound_root_mse_mm" in self.extras:
            lines.append(f"  every design of {self.n_poses} whole poses (repeats allowed): sqrt(E[MSE]) >= "
                         f"{1e3 * self.extras['exact_bound_root_mse_mm']:.4g} um (branch and bound on the poses in "
                         f"each of {self.extras['exact_bound_cells']} orthants of the actuator box, "
                         f"{self.extras['exact_bound_nodes']} relaxations; the plan is "
                         f"{100 * (self.extras['root_expected_mse_mm'] / self.extras['exact_bound_root_mse_mm'] - 1):.2f} % above it)")
        if "certified" in self.extras:
            pct = 100 * self.extras["certified_within"]
            found = (f"; {self.extras['certify_replaced']} better design(s) found by the search replaced the plan"
                     if self.extras["certify_replaced"] else "")
            work = f"{self.extras['certify_relaxations']} relaxations{found}"
            lines.append({True: f"  the plan's sqrt(E[MSE]) is within {pct:g} % of every design of {self.n_poses} whole "
                                f"poses (proved, {work})",
                          False: f"  not certified within {pct:g} %: each search found a design more than "
                                 f"{pct:g} % better in sqrt(E[MSE]) ratio ({work})",
                          None: f"  not certified within {pct:g} %: the search stopped at its node budget ({work})"
                          }[self.extras["certified"]])
        return "\n".join(lines)


def evaluate_selection(cands: CandidateSet, index: NDArray) -> dict[str, float]:
    """All criteria of the poses ``index`` of a candidate set (exact, no regularisation).

    I is NaN when the candidate set has no workspace tool-point Jacobian.
    """
    index = np.asarray(index, dtype=int)
    A = cands.blocks[index].reshape(-1, cands.blocks.shape[2])
    vals = criteria_from_singular_values(np.linalg.svd(A, compute_uv=False), A.shape[0])
    vals["EIG"] = eig_value(cands.blocks_prior[index].reshape(-1, cands.blocks_prior.shape[2]))
    Q = cands.output_weight
    Ak = cands.prior_blocks_kept[index]
    vals["I"] = i_value(Ak.reshape(-1, Ak.shape[2]), Q) if Q is not None else float("nan")
    return {c: vals[c] for c in CRITERIA}


def root_expected_mse(cands: CandidateSet, index: NDArray) -> float:
    """``sqrt(E[MSE])`` (mm) of the tool point over the workspace after MAP calibration on poses ``index``.

    ``sqrt(trace(Sigma Q))`` with ``Sigma = (I + A_k^T A_k)^-1`` (criterion I),
    in the linear-Gaussian model: the root of the *expected* mean squared
    error, not the expected (or median) RMS error of one calibration, which
    is smaller (Jensen).  The error of the parameters no pose identifies is
    not included.  ``index`` may repeat poses.
    """
    Q = cands.output_weight
    if Q is None:
        raise InputError("expected output error: the candidate set has no workspace tool-point Jacobian")
    Ak = cands.prior_blocks_kept[np.asarray(index, dtype=int)]
    Ak = Ak.reshape(-1, Ak.shape[2])
    return float(np.sqrt(np.trace(np.linalg.solve(np.eye(Ak.shape[1]) + Ak.T @ Ak, Q))))


def _M0(cands: CandidateSet, criterion: str) -> tuple[NDArray, NDArray]:
    if criterion == "EIG":
        return cands.blocks_prior, np.eye(cands.blocks_prior.shape[2])
    if criterion == "I":
        # MAP identifies the identifiable set under the tolerance prior: tolerance-scaled columns, prior I
        return cands.prior_blocks_kept, np.eye(len(cands.kept_index))
    B = cands.blocks
    L = B.shape[2]
    mean_info = float(np.mean(np.sum(B**2, axis=(1, 2)))) / L
    return B, DELTA_REL * max(mean_info, 1e-300) * np.eye(L)


def default_method(criterion: str) -> str:
    """``relaxed`` for criterion I, ``greedy`` for the others.

    Why: for I, the Frank-Wolfe relaxed design rounded and improved by
    exchanges (:func:`relaxed_select`) gave a lower ``E[MSE]`` than greedy
    plus DETMAX exchange at every number of poses compared (8, 12, 18, 24,
    36) in studies/pose_planning.py: on the 3-PRS 0.01-2.2 % above the
    bound against 0.3-2.8 % for greedy, on the 6R arm 16.6 % against 25.1 %
    at 8 poses and 0.7 % against 1.3 % at 36 (docs/planning.md).
    The other criteria have no relaxation here.
    """
    return "relaxed" if check_criterion(criterion) == "I" else "greedy"


def relaxed_select(cands: CandidateSet, n: int, *, repeats: bool = True, pool_size: int = 256, widen: int | None = None):
    """Criterion I: the Frank-Wolfe relaxed design, rounded, then exchanges (bayescal.design.rounding).

    The exchange pool is the relaxed support, the ``pool_size`` candidates
    with the largest ``d_i`` at the relaxed optimum and every box point
    (``CandidateSet.uniform`` false: the corners, edges and faces of
    ``q_limits``, where the optimal poses of few-pose designs sit).  Two
    starts (the rounded relaxed design and the greedy design on the pool)
    are improved by exchanges on the pool; with at most 12 distinct poses,
    by two-pose exchanges with the relaxed support, the 64 largest ``d_i``
    and (if at most 256) the box points; and then by
    exchanges with every candidate (or, with ``widen``, the pool plus that
    many candidates with the largest ``d_i`` at the design;
    :func:`~bayescal.design.rounding.multistart_search`).

    Returns
    -------
    selection : Selection
        ``utility`` is ``-E[MSE]`` (mm^2) of the design, as for the greedy path.
    bound : DesignMSEBound
        The certified bound on ``E[MSE]`` of every ``n``-pose design, and the relaxed design.
    """
    from .bound import design_mse_bound
    from .rounding import design_mse, multistart_search, pool_from_bound

    B, Q = cands.prior_blocks_kept, cands.output_weight
    if Q is None:
        raise InputError("criterion I: the candidate set has no workspace tool-point Jacobian")
    bound = design_mse_bound(B, Q, int(n))
    pool = pool_from_bound(bound.weights, B, Q, size=pool_size)
    near = pool_from_bound(bound.weights, B, Q, size=64)
    if cands.uniform is not None:
        box = np.flatnonzero(~np.asarray(cands.uniform, dtype=bool))
        pool = np.union1d(pool, box)
        # the two-pose exchanges cost O(n^2) local searches: the box points join them only when few (3-PRS: 81;
        # a 6-axis arm has 2,187)
        near = np.union1d(near, box) if box.size <= 256 else near
    idx, start = multistart_search(B, Q, bound.weights, int(n), pool, repeats=repeats, widen=widen, pair_pool=near)
    u0, u = -design_mse(B, Q, start), -design_mse(B, Q, idx)
    # poses exchanged: the size of the multiset difference between the start and the result
    common = sum(min(a, b) for a, b in zip(*(np.bincount(x, minlength=cands.n) for x in (start, idx))))
    return Selection(index=idx, utility=u, greedy_utility=u0, swaps=int(n - common), history=np.array([u0, u])), bound


def select_from_candidates(
    cands: CandidateSet, n: int, criterion: str, *, exchange: bool = True, shortlist: int = 512,
    max_swaps: int | None = None, repeats: bool = False, method: str = "greedy",
):
    """Select ``n`` poses from a candidate set; returns a :class:`~bayescal.design.select.Selection`.

    ``method="greedy"``: greedy selection then DETMAX exchange (any
    criterion).  ``method="relaxed"`` (criterion I only): :func:`relaxed_select`.
    """
    criterion = check_criterion(criterion)
    if method not in METHODS:
        raise InputError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    if method == "relaxed":
        if criterion != "I":
            raise InputError(f"method 'relaxed': only for criterion I (the relaxation bounds E[MSE]), got {criterion}")
        return relaxed_select(cands, n, repeats=repeats)[0]
    blocks, M0 = _M0(cands, criterion)
    Q = None
    if criterion == "I":
        Q = cands.output_weight
        if Q is None:
            raise InputError("criterion I: the candidate set has no workspace tool-point Jacobian "
                             "(build it with draw_candidates, or pass output_jacobian)")
    idx, _ = greedy_select(blocks, n, criterion, M0=M0, shortlist=shortlist, Q=Q, repeats=repeats)
    return exchange_refine(blocks, idx, criterion, M0=M0, max_iter=max_swaps if exchange else 0, shortlist=shortlist,
                           Q=Q, repeats=repeats)


#: ``exact_bound`` branches on the poses in each of the ``2^m`` orthants of the actuator box.
EXACT_BOUND_MAX_ACTUATORS = 4


def plan_poses(
    machine: Machine, n_poses: int, *, criterion: str = "D", dof: int = 6, n_candidates: int = 20000, seed: int = 0,
    scaling: str = "tolerance", n_random: int = 20, exchange: bool = True, candidates: CandidateSet | None = None,
    repeats: bool | None = None, box: bool = True, method: str | None = None, exact_bound: bool = False,
    certify: float | None = None, certify_nodes: int = 5000,
) -> PosePlan:
    """Plan ``n_poses`` measurement poses that maximise an information criterion.

    Parameters
    ----------
    machine : Machine
        Any kind with ``q_limits``.
    n_poses : int
    criterion : {"D", "A", "E", "O1", "O2", "O3", "O4", "O5", "EIG", "I"}
    dof : {6, 5, 3}
        What the instrument will measure.
    n_candidates : int
        Candidate poses drawn uniformly within ``q_limits``.
    seed : int
        Seeds the candidates and the random selections: same seed, same plan.
    scaling : {"tolerance", "candidates"}
        Column scaling (see :mod:`bayescal.design.candidates`).
    n_random : int
        Random selections the plan is compared against.
    exchange : bool
        Run the exchange refinement after the greedy pass.
    candidates : CandidateSet, optional
        Use these instead of drawing (``n_candidates`` is then ignored).
    repeats : bool, optional
        Allow a pose to be planned more than once (measured again).  Default: yes with the relaxed method (the optimal
        design measure puts weight on a few extreme poses; forbidding repeats cost up to 3 % in ``sqrt(E[MSE])`` at 36
        poses on the 3-PRS), no with greedy.
    method : {"greedy", "relaxed"}, optional
        Default :func:`default_method` (relaxed for I, greedy otherwise).
    box : bool
        Add the corners, edges and faces of the actuator box to the candidates
        (:func:`bayescal.design.candidates.box_points`).
    exact_bound : bool
        Criterion I only: also certify a lower bound on ``sqrt(E[MSE])`` of every design of ``n_poses`` whole poses
        (:func:`bayescal.design.exact_bound.exact_design_bound`, orthant cells), tighter than the relaxed bound at few
        poses; seconds to minutes with 3 actuators, and its cost grows with ``2^m`` cells.
    certify : float, optional
        Criterion I only: prove that the plan's ``sqrt(E[MSE])`` is at most ``1 + certify`` times that of every design
        of ``n_poses`` whole poses from the candidates (e.g. 0.01: within 1 % of the best), by branch and bound
        (:func:`bayescal.design.exact_decision.exact_design_below`, cells in fractions of each actuator's stroke).  If
        the search finds such a design, it becomes the plan and the question is asked again (up to
        :data:`CERTIFY_ROUNDS` times).  The answer is in ``extras`` (``certified``: true, false when the rounds ran
        out, null when the node budget did).
    certify_nodes : int
        Relaxations allowed per search (``certify``).

    Returns
    -------
    PosePlan
    """
    t0 = time.perf_counter()
    criterion, method, repeats = _checked_options(machine, n_poses, criterion, dof, method, repeats, exact_bound)
    rng = np.random.default_rng(seed)
    cands = candidates if candidates is not None else draw_candidates(machine, n_candidates, dof=dof, rng=rng, scaling=scaling,
                                                                       box=box)
    _check_candidates(cands, n_poses, dof, criterion, method, repeats, exact_bound, certify)
    sel, bound, exact, certificate = _select(machine, cands, int(n_poses), criterion, method, repeats, exchange,
                                             exact_bound, certify, certify_nodes)
    values = evaluate_selection(cands, sel.index)
    med, beaten = _against_random(cands, values, int(n_poses), n_random, rng)
    return _pose_plan(machine, cands, sel, values, (med, beaten), criterion=criterion, dof=dof, seed=seed,
                      n_random=n_random, seconds=time.perf_counter() - t0,
                      extras=_plan_extras(cands, sel, criterion, method, repeats, bound, exact, certificate))


def _pose_plan(machine: Machine, cands: CandidateSet, sel, values: dict, random: tuple, *, criterion: str, dof: int,
               seed: int, n_random: int, seconds: float, extras: dict) -> PosePlan:
    """The plan of the selection ``sel`` from ``cands``, with its criteria ``values`` and the random comparison."""
    med, beaten = random
    return PosePlan(
        machine_name=machine.name, kind=machine.kind, criterion=criterion, dof=dof, scaling=cands.scaling,
        q=cands.q[sel.index], candidate_index=sel.index, values=values, random_median=med, random_beaten=beaten,
        kept=cands.kept, fixed=cands.fixed, n_candidates=cands.n, n_rejected=cands.n_rejected, seed=int(seed),
        greedy_utility=sel.greedy_utility, utility=sel.utility, swaps=sel.swaps, n_random=int(n_random),
        seconds=seconds, extras=extras,
    )


def _checked_options(machine: Machine, n_poses, criterion: str, dof: int, method: str | None, repeats: bool | None,
                     exact_bound: bool) -> tuple[str, str, bool]:
    """The criterion, the method and whether poses may repeat, checked before any candidate is drawn."""
    criterion = check_criterion(criterion)
    rows_per_pose(dof)
    if int(n_poses) != n_poses or n_poses < 1:
        raise InputError(f"n_poses: expected a positive integer, got {n_poses!r}")
    method = default_method(criterion) if method is None else method
    repeats = (method == "relaxed") if repeats is None else bool(repeats)
    if exact_bound and machine.n_actuators > EXACT_BOUND_MAX_ACTUATORS:
        # refused before drawing candidates: 2^m orthant cells; on the 6R arm (relaxed optimum on about 200
        # candidates) even the orthants of three of its joints (8 cells) had not reached one complete count
        # vector after 4 minutes (stopped there)
        raise InputError(f"exact_bound: the search over the 2^m orthants of the actuator box is practical up to "
                         f"{EXACT_BOUND_MAX_ACTUATORS} actuators; this machine has {machine.n_actuators}")
    return criterion, method, repeats


def _check_candidates(cands: CandidateSet, n_poses, dof: int, criterion: str, method: str, repeats: bool,
                      exact_bound: bool, certify: float | None) -> None:
    """Refuse a plan the candidates cannot give, or a bound or certificate the criterion and method do not allow."""
    if n_poses > cands.n and not repeats:
        raise InputError(f"n_poses: {n_poses} asked for, but only {cands.n} usable candidates; draw more candidates")
    L = cands.blocks.shape[2]
    if n_poses * dof < L and criterion not in PRIOR_BASED:
        raise InputError(
            f"n_poses: {n_poses} poses x {dof} components < {L} identifiable parameters; criterion {criterion} "
            f"needs at least {-(-L // dof)} poses (or use EIG or I, which include the tolerance prior)"
        )
    if exact_bound and not (method == "relaxed" and criterion == "I" and cands.output_weight is not None):
        raise InputError("exact_bound: only for criterion I with the relaxed selection (the bound is on E[MSE]), "
                         f"got criterion {criterion}, method {method}")
    if certify is not None and not (method == "relaxed" and criterion == "I" and cands.output_weight is not None):
        raise InputError("certify: only for criterion I with the relaxed selection (it compares E[MSE]), "
                         f"got criterion {criterion}, method {method}")
    if certify is not None and not (0 < certify < 1):
        raise InputError(f"certify: expected a fraction in (0, 1) (0.01 for 1 %), got {certify}")
    if certify is not None and not repeats:
        raise InputError("certify: the search covers designs with repeated poses; plan with repeats allowed")


def _select(machine: Machine, cands: CandidateSet, n: int, criterion: str, method: str, repeats: bool, exchange: bool,
            exact_bound: bool, certify: float | None, certify_nodes: int):
    """The selection, the relaxed bound, the exact bound and the certificate (None where not asked or not relaxed I)."""
    bound = exact = certificate = None
    if method == "relaxed" and criterion == "I":
        sel, bound = relaxed_select(cands, n, repeats=repeats)
        if certify is not None:
            sel, certificate = certify_selection(cands, machine.q_limits, sel, certify, certify_nodes)
        if exact_bound:
            from .exact_bound import exact_design_bound, orthant_cells

            exact = exact_design_bound(cands.prior_blocks_kept, cands.output_weight, n,
                                       orthant_cells(cands.q, machine.q_limits))
    else:
        sel = select_from_candidates(cands, n, criterion, exchange=exchange, repeats=repeats, method=method)
    return sel, bound, exact, certificate


def _against_random(cands: CandidateSet, values: dict, n: int, n_random, rng) -> tuple[dict, dict]:
    """Per criterion: the median over ``n_random`` random selections of ``n`` poses, and the fraction the plan beats.

    The random selections repeat poses only when they must: a plan with repeats of more poses than candidates.
    """
    rand = np.array([list(evaluate_selection(cands, rng.choice(cands.n, n, replace=n > cands.n)).values())
                     for _ in range(int(n_random))]) if n_random > 0 else np.full((1, len(CRITERIA)), np.nan)
    med = {c: float(np.median(rand[:, i])) for i, c in enumerate(CRITERIA)}
    beaten = {c: float(np.mean(values[c] > rand[:, i])) for i, c in enumerate(CRITERIA)}
    return med, beaten


def _plan_extras(cands: CandidateSet, sel: Selection, criterion: str, method: str, repeats: bool, bound, exact,
                 certificate: dict | None) -> dict:
    """The plan's ``extras``: how it was chosen and the expected MSE, bounds and certificate where there are."""
    return {"utility_kind": utility_kind(criterion), "method": method, "repeats": repeats,
            **({"root_expected_mse_mm": root_expected_mse(cands, sel.index)}
               if cands.output_blocks is not None else {}),
            **({"bound_root_mse_mm": bound.lower_root_mse} if bound is not None else {}),
            **({"exact_bound_root_mse_mm": exact.lower_root_mse, "exact_bound_nodes": exact.nodes,
                "exact_bound_cells": exact.cells} if exact is not None else {}),
            **(certificate or {})}


#: Searches ``certify`` runs at most: each design it finds replaces the plan and is questioned again.
CERTIFY_ROUNDS = 5


def certify_selection(cands: CandidateSet, q_limits: NDArray, sel: Selection, within: float,
                      max_nodes: int) -> tuple[Selection, dict]:
    """Prove ``sel`` within a factor ``1 + within`` of every exact design in ``sqrt(E[MSE])``, or replace it.

    Each round asks :func:`~bayescal.design.exact_decision.exact_design_below`
    for a design with ``E[MSE]`` below ``E[MSE](sel) / (1 + within)^2``; a
    design found is improved by single exchanges over all candidates
    (:func:`~bayescal.design.rounding.local_search`, repeats allowed), becomes
    ``sel`` and is asked about again.

    Returns the (possibly replaced) selection and the ``extras`` entries
    ``certified`` (True: proved; False: every round found a better design;
    None: a search ran out of nodes), ``certified_within``,
    ``certify_relaxations`` (all rounds) and ``certify_replaced`` (designs
    adopted).
    """
    from .exact_decision import exact_design_below, stroke_fractions
    from .rounding import design_mse, local_search

    coords = stroke_fractions(cands.q, q_limits)
    B, Q = cands.prior_blocks_kept, cands.output_weight
    relaxations = replaced = 0
    answer = False
    for _ in range(CERTIFY_ROUNDS):
        f = design_mse(B, Q, sel.index)
        dec = exact_design_below(B, Q, len(sel.index), f / (1 + within) ** 2, coords, max_nodes=max_nodes)
        relaxations += dec.nodes
        if dec.below is not True:
            answer = None if dec.below is None else True
            break
        replaced += 1
        # the search stops at the first design below the threshold, not at a good one: exchanges polish it
        index = local_search(B, Q, np.asarray(dec.design, dtype=int), np.arange(B.shape[0]), repeats=True,
                             max_moves=50 * len(sel.index))  # until no exchange improves (the cap is a safeguard)
        u = -design_mse(B, Q, index)
        sel = Selection(index=np.sort(index), utility=u, greedy_utility=sel.greedy_utility,
                        swaps=sel.swaps, history=np.append(sel.history, u))
    return sel, {"certified": answer, "certified_within": float(within), "certify_relaxations": int(relaxations),
                 "certify_replaced": int(replaced)}


def plan_to_csv(plan: PosePlan) -> str:
    """The plan as CSV: ``q1..qN`` (commanded, machine units) and ``pose_id`` (1-based, measurement order)."""
    m = plan.q.shape[1]
    lines = [",".join([f"q{j + 1}" for j in range(m)] + ["pose_id"])]
    for i, row in enumerate(plan.q):
        lines.append(",".join([repr(float(v)) for v in row] + [str(i + 1)]))
    return "\n".join(lines) + "\n"


def write_plan(path, plan: PosePlan):
    """Write :func:`plan_to_csv` atomically."""
    return write_text_atomic(path, plan_to_csv(plan))
