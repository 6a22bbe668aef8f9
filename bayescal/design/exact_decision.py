"""Is there an exact n-pose design below a given E[MSE]? Branch and bound on cells that split where the weight lies.

Why.  :func:`.exact_bound.exact_design_bound` bounds every design of ``n``
whole poses by fixing the number of poses per orthant of the actuator box.
Within an orthant the relaxation still spreads a pose's weight over
several candidates, so where the best exact design and the relaxed optimum
differ by a few tenths of a percent the orthant bound can stay below a
target that no design reaches (3-PRS, 5-DOF, 10 poses: orthant bound
1.0062 times the relaxed bound, best design found 1.0104, target 1.01).
This module answers the yes/no question the target asks.

How.  A node of the search is a partition of the candidates into cells
with a whole number of poses in each.  Its relaxation (weights ``w >= 0``
with each cell's sum fixed, :func:`.exact_bound.cell_relaxation`) bounds
``E[MSE]`` of every exact design with those counts, from the Frank-Wolfe
duality gap.  Then:

* the certified bound is at or above the threshold: no design with those
  counts is below it, the node is closed;
* the design that puts each cell's poses on the candidate holding most of
  its relaxed weight is below the threshold: that design answers *yes*;
* otherwise one cell is split in two and the node branches over every
  division of its poses between the halves (``t + 1`` children).  The cell
  is the one whose relaxed weight is most spread in the candidates'
  coordinates, and it is cut, across the coordinate of largest weighted
  variance, at the weighted mean, so that the weight that was fractional
  lands on both sides and has to become whole.  A cell whose weight sits on
  one candidate (but whose bound is not yet decisive) is halved across its
  widest coordinate.

Every exact design lies in exactly one child, so when all nodes are closed
*no* design of ``n`` poses from the candidates (repeats allowed) has
``E[MSE]`` below the threshold.  A cell of identical candidates (equal
blocks) is never split; a node whose cells with poses each hold one pose
is an exact design and is decided by its own value.  Candidates the
coordinates cannot tell apart are split by their order in the cell, so
the coordinates decide only how fast the answer comes, never the answer.
A node is closed only when its bound clears the threshold by a relative
``1e-9`` (the bound's rounding).  Small problems are checked against
exhaustive enumeration (tests/design/test_exact_decision.py).

Cost: one relaxation per node.  On the 3-PRS (20,081 candidates, 32
parameters) the 10-pose, 5-DOF question at 1 % above the relaxed bound
closes in under 200 nodes, about 40 s (docs/planning.md); the search is
depth first and stops at ``max_nodes`` with no answer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from .exact_bound import cell_relaxation, checked_design_problem

__all__ = ["ExactDesignDecision", "exact_design_below", "stroke_fractions"]


def stroke_fractions(q: NDArray, q_limits: NDArray) -> NDArray:
    """Each actuator's position as a fraction of its stroke (0 at the lower limit, 1 at the upper): coordinates
    in which every actuator's range counts alike, for splitting cells.

    Parameters
    ----------
    q : ndarray, shape (N, m)
        Actuator positions (mm or rad, as ``q_limits``).
    q_limits : ndarray, shape (m, 2)
        Lower and upper limit per actuator.

    Returns
    -------
    ndarray, shape (N, m)
        Dimensionless.
    """
    q = np.asarray(q, dtype=float)
    lim = np.asarray(q_limits, dtype=float)
    if q.ndim != 2 or lim.shape != (q.shape[1], 2) or not np.all(lim[:, 1] > lim[:, 0]):
        raise InputError(f"q_limits: expected shape ({q.shape[-1]}, 2) with upper > lower for positions of shape "
                         f"{q.shape}, got {lim.tolist()}")
    return (q - lim[:, 0]) / (lim[:, 1] - lim[:, 0])


@dataclass(frozen=True)
class ExactDesignDecision:
    """Whether some exact ``n``-pose design from the candidates has ``E[MSE]`` below a threshold.

    Attributes
    ----------
    n_poses : int
    threshold_mse : float
        The threshold on ``E[MSE] = trace(Sigma Q)`` (mm^2).
    below : bool or None
        ``True``: :attr:`design` is below the threshold.  ``False``: proved
        that no design of ``n_poses`` whole poses from the candidates,
        repeats allowed, is below it.  ``None``: the search stopped at its
        node budget without an answer.
    design : tuple of int or None
        Candidate indices (repeats counted) of a design below the threshold.
    design_mse : float
        ``E[MSE]`` (mm^2) of :attr:`design` (``nan`` without one).
    nodes : int
        Relaxations solved.
    closed : int
        Nodes closed by their certified bound.
    max_depth : int
        Deepest node visited (number of cell splits).
    """

    n_poses: int
    threshold_mse: float
    below: bool | None
    design: tuple | None
    design_mse: float
    nodes: int
    closed: int
    max_depth: int

    def to_dict(self) -> dict:
        """JSON-ready fields (``below`` is ``null`` when undecided)."""
        return {"n_poses": self.n_poses, "threshold_mse_mm2": self.threshold_mse, "below": self.below,
                "design": None if self.design is None else list(self.design),
                "design_mse_mm2": None if not np.isfinite(self.design_mse) else self.design_mse,
                "nodes": self.nodes, "closed": self.closed, "max_depth": self.max_depth}


def _design_mse(BB: NDArray, Q: NDArray, design: NDArray) -> float:
    M = np.eye(Q.shape[0]) + BB[design].sum(axis=0)
    return float(np.trace(np.linalg.solve(M, Q)))


def _split(idx: NDArray, coords: NDArray, w: NDArray, BB: NDArray) -> tuple[NDArray, NDArray] | None:
    """Two non-empty halves of the cell ``idx``, or None if all its candidates are the same pose.

    At the weighted mean across the most spread coordinate; else at the
    middle of the widest coordinate; else (candidates with equal
    coordinates, which need not be equal poses) by position in the cell.
    """
    X, ww = coords[idx], w[idx]
    total = float(ww.sum())
    if total > 0:
        mu = ww @ X / total
        var = ww @ (X - mu) ** 2 / total
        for dim in np.argsort(-var, kind="stable"):
            if var[dim] <= 0:
                break
            left = X[:, dim] < mu[dim]
            if 0 < left.sum() < idx.size:
                return idx[left], idx[~left]
    lo, hi = X.min(axis=0), X.max(axis=0)
    dim = int(np.argmax(hi - lo))
    if hi[dim] > lo[dim]:
        left = X[:, dim] < 0.5 * (lo[dim] + hi[dim])
        if 0 < left.sum() < idx.size:  # (adjacent floats can put every candidate on one side)
            return idx[left], idx[~left]
    if idx.size > 1 and not np.all(BB[idx] == BB[idx[0]]):
        return idx[: idx.size // 2], idx[idx.size // 2:]
    return None  # one pose (or copies of it): its relaxation is exact


def _spread(idx: NDArray, coords: NDArray, w: NDArray) -> float:
    """Weighted variance of the cell's relaxed weight in the coordinates, times its weight (0 on one candidate)."""
    ww = w[idx]
    total = float(ww.sum())
    if total <= 0:
        return 0.0
    X = coords[idx]
    mu = ww @ X / total
    return float(ww @ ((X - mu) ** 2).sum(axis=1))


def exact_design_below(
    blocks: NDArray, Q: NDArray, n: int, threshold_mse: float, coords: NDArray, *, max_nodes: int = 5000,
    progress=None,
) -> ExactDesignDecision:
    """Decide whether some design of ``n`` whole poses has ``E[MSE]`` below a threshold (criterion I, linearised).

    Parameters
    ----------
    blocks, Q, n
        As for :func:`bayescal.design.exact_bound.exact_design_bound`.
    threshold_mse : float
        Threshold on ``E[MSE]`` (mm^2), e.g. ``1.01**2`` times the relaxed
        bound to ask whether any design is within 1 % of it in
        ``sqrt(E[MSE])``.
    coords : ndarray, shape (N, m)
        Coordinates of the candidates in which cells are split, best in
        comparable units (e.g. each actuator's position as a fraction of its
        stroke).  Any coordinates give a valid answer; they only decide how
        fast it comes.
    max_nodes : int
        Relaxations allowed before giving up (``below=None``).
    progress : callable, optional
        Called with a line of text every 50 nodes.

    Returns
    -------
    ExactDesignDecision
    """
    blocks, Q = checked_design_problem(blocks, Q, n)
    coords = _checked_search(coords, blocks.shape[0], threshold_mse, max_nodes)
    N = blocks.shape[0]
    n = int(n)
    BB = np.einsum("nki,nkj->nij", blocks, blocks)
    stats = {"nodes": 0, "closed": 0, "depth": 0}

    def decision(below, design=None, mse=np.nan) -> ExactDesignDecision:
        return ExactDesignDecision(n_poses=n, threshold_mse=float(threshold_mse), below=below,
                                   design=None if design is None else tuple(int(i) for i in sorted(design)),
                                   design_mse=float(mse), nodes=stats["nodes"], closed=stats["closed"],
                                   max_depth=stats["depth"])

    # a node is closed only with a little room above the threshold: its bound carries rounding (~1e-13)
    closing = float(threshold_mse) * (1 + 1e-9)
    # depth first on an explicit stack of (cells, counts, parent's relaxed weights, depth)
    stack = [([np.arange(N)], [n], None, 0)]
    while stack:
        if stats["nodes"] >= int(max_nodes):
            return decision(None)
        cells, counts, start, depth = stack.pop()
        stats["nodes"] += 1
        stats["depth"] = max(stats["depth"], depth)
        if progress is not None and stats["nodes"] % 50 == 0:
            progress(f"{stats['nodes']} nodes, {stats['closed']} closed, depth {depth}, {len(stack)} waiting")
        groups = np.empty(N, dtype=np.int64)
        for g, idx in enumerate(cells):
            groups[idx] = g
        lower, _, w = cell_relaxation(BB, Q, groups, np.array(counts, dtype=float), stop_above=closing,
                                      stop_below=threshold_mse, start=start)
        if lower >= closing:
            stats["closed"] += 1
            continue
        # each cell's poses on its heaviest candidate: an exact design, often the answer once the cells are small
        rounded = np.concatenate([np.repeat(idx[np.argmax(w[idx])], t) for idx, t in zip(cells, counts) if t > 0])
        f_rounded = _design_mse(BB, Q, rounded)
        if f_rounded < threshold_mse:
            return decision(True, rounded, f_rounded)
        g, parts = _cell_to_split(cells, counts, coords, w, BB)
        if parts is None:
            # every cell with poses is one pose: the node is the exact design ``rounded``, already above the threshold
            stats["closed"] += 1
            continue
        a, b = parts
        t = counts[g]
        wa = float(w[a].sum())
        # pushed so that the division nearest the relaxed weight is popped first
        for c in sorted(range(t + 1), key=lambda c: abs(c - wa), reverse=True):
            stack.append((cells[:g] + [a, b] + cells[g + 1:], counts[:g] + [c, t - c] + counts[g + 1:], w, depth + 1))
    return decision(False)


def _checked_search(coords, N: int, threshold_mse: float, max_nodes) -> NDArray:
    """The candidates' coordinates as floats, or InputError naming what :func:`exact_design_below` refuses."""
    coords = np.asarray(coords, dtype=float)
    if not (np.isfinite(threshold_mse) and threshold_mse > 0):
        raise InputError(f"threshold_mse: expected a positive finite E[MSE] in mm^2, got {threshold_mse}")
    if coords.ndim != 2 or coords.shape[0] != N or not np.all(np.isfinite(coords)):
        raise InputError(f"coords: expected finite coordinates of shape ({N}, m), got {coords.shape}")
    if int(max_nodes) < 1:
        raise InputError(f"max_nodes: expected >= 1, got {max_nodes}")
    return coords


def _cell_to_split(cells, counts, coords: NDArray, w: NDArray, BB: NDArray):
    """The cell with poses to divide next (the widest spread of relaxed weight first) and its two parts.

    ``(None, None)`` when every cell with poses is one candidate.
    """
    live = [g for g, t in enumerate(counts) if t > 0]
    spread = [_spread(cells[g], coords, w) for g in live]
    order = sorted(range(len(live)), key=lambda i: (-spread[i], -cells[live[i]].size))
    for i in order:
        parts = _split(cells[live[i]], coords, w, BB)
        if parts is not None:
            return live[i], parts
    return None, None
