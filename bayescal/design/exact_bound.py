"""A certified lower bound on E[MSE] over *exact* n-pose designs (criterion I, linearised): branch and bound on cell counts.

Why.  The Frank-Wolfe bound of :mod:`bayescal.design.bound` holds for every
design because it relaxes the counts ``m_i`` to real weights.  At a few
poses the relaxed optimum puts fractional weights (0.7, 1.5, ...) on a few
box corners, which no design of whole poses can copy, and the gap between
the best exact design and that bound can exceed any fixed margin.  Whether
a plan's distance to the relaxed bound is the planner's fault or the
problem's needs a bound for exact designs.

How.  Partition the candidates into cells (by default the orthants of the
actuator box, :func:`orthant_cells`).  In every exact design the number of
poses ``t_c`` in cell ``c`` is a whole number and ``sum_c t_c = n``.  For a
fixed vector ``t`` the relaxation

    min f(w) = trace(Q (I + sum_i w_i B_i^T B_i)^-1)   s.t.  w >= 0,  sum_{i in c} w_i = t_c

is convex, so its minimum bounds every exact design with those cell counts,
and the minimum over all vectors ``t`` bounds every exact design.  Within a
cell the relaxation may still spread weight, but it can no longer move
weight between corners of the box: that is where the integrality gap of
the plain relaxation comes from.  Each relaxation is solved by pairwise
Frank-Wolfe steps on the product of simplices, and its value is taken from
the duality gap (valid at any iterate, as in :mod:`.bound`)::

    f(v) >= f(w) - sum_c (t_c max_{i in c} d_i - sum_{i in c} w_i d_i),   d_i = trace(B_i Sigma Q Sigma B_i^T).

The vectors ``t`` are searched depth first: fixing ``t_0, ..., t_k`` and
pooling the remaining cells into one with the remaining poses is again a
relaxation of all its completions, so a branch whose bound is not below
the best complete vector found is cut.  The result is the least bound over
all complete vectors: a certified lower bound on ``E[MSE]`` of every exact
design of ``n`` poses from the candidates, repeats allowed.  With one cell
per candidate it is the exact optimum (tested by enumeration).

Cost: one relaxation per node of the search, each a few passes over all
candidates; on the 3-PRS (20,081 candidates, 32-33 parameters, 8 orthants)
at 8-10 poses 56-145 nodes and 12-40 CPU s (docs/planning.md).  The
number of cell-count vectors grows as ``C(n + K - 1, K - 1)`` with ``K``
cells, so machines with many actuators need coarser cells.

Why our own solver: the relaxation has tens of thousands of weights but
each linear minimisation is one argmax per cell, and the bound needs the
duality gap, which general-purpose solvers do not report (as for
:mod:`.bound`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import brentq

from ..errors import InputError
from .bound import _RootOfLowerMse

__all__ = ["ExactDesignBound", "exact_design_bound", "orthant_cells", "cell_relaxation"]


@dataclass(frozen=True)
class ExactDesignBound(_RootOfLowerMse):
    """Lower bound on ``E[MSE]`` (mm^2) of every exact ``n``-pose design from a candidate set.

    Attributes
    ----------
    n_poses : int
    lower_mse : float
        Certified lower bound on ``E[MSE] = trace(Sigma Q)`` (mm^2) of every
        design of ``n_poses`` whole poses from the candidates, repeats allowed.
    cell_counts : tuple of int
        The cell-count vector whose relaxation gave ``lower_mse``, indexed
        by the caller's cell labels (0 for labels without candidates).
    nodes : int
        Relaxations solved (nodes of the search).
    cells : int
        Number of cells that hold candidates.
    """

    n_poses: int
    lower_mse: float
    cell_counts: tuple
    nodes: int
    cells: int

    def to_dict(self) -> dict:
        return {"n_poses": self.n_poses, "lower_mse_mm2": self.lower_mse, "lower_root_mse_mm": self.lower_root_mse,
                "cell_counts": list(self.cell_counts), "nodes": self.nodes, "cells": self.cells}


def orthant_cells(q: NDArray, q_limits: NDArray) -> NDArray:
    """Cell of each candidate: the orthant of the actuator box around its centre.

    Parameters
    ----------
    q : ndarray, shape (N, m)
        Candidate actuator vectors (mm or rad, as ``q_limits``).
    q_limits : ndarray, shape (m, 2)
        Lower and upper limit per actuator.

    Returns
    -------
    ndarray of int, shape (N,)
        ``sum_j 2^j [q_j > centre_j]``, in ``0 .. 2^m - 1``.
    """
    q = np.asarray(q, dtype=float)
    lim = np.asarray(q_limits, dtype=float)
    if q.ndim != 2 or lim.shape != (q.shape[1], 2):
        raise InputError(f"q_limits: expected shape ({q.shape[-1]}, 2) for candidates of shape {q.shape}, "
                         f"got {lim.shape}")
    above = q > 0.5 * (lim[:, 0] + lim[:, 1])
    return (above.astype(np.int64) << np.arange(q.shape[1])).sum(axis=1)


def _d(BB: NDArray, SQS: NDArray) -> NDArray:
    return BB.reshape(BB.shape[0], -1) @ SQS.reshape(-1)


def _group_gap(d: NDArray, w: NDArray, groups: NDArray, totals: NDArray) -> float:
    gmax = np.full(totals.size, -np.inf)
    np.maximum.at(gmax, groups, d)
    used = totals > 0
    return float(np.sum(totals[used] * gmax[used]) - w @ d)


def _pairwise(BB: NDArray, groups: NDArray, Q: NDArray, M0: NDArray, w: NDArray, steps: int, rtol: float) -> NDArray:
    """Pairwise Frank-Wolfe steps within cells on the active candidates (weight from the worst live to the best)."""
    w = w.copy()
    M = M0 + np.tensordot(w, BB, 1)
    labels = [np.flatnonzero(groups == g) for g in np.unique(groups)]
    for _ in range(steps):
        S = np.linalg.inv(M)
        d = _d(BB, S @ Q @ S)
        f = float(np.trace(S @ Q))
        best, gap = (0.0, -1, -1), 0.0
        for idx in labels:
            live = idx[w[idx] > 0]
            if live.size == 0:
                continue
            b = int(idx[np.argmax(d[idx])])
            a = int(live[np.argmin(d[live])])
            gap += float(w[idx].sum() * d[b] - w[idx] @ d[idx])
            if d[b] - d[a] > best[0]:
                best = (float(d[b] - d[a]), a, b)
        if best[1] < 0 or gap <= rtol * f:
            break
        _, a, b = best
        D = BB[b] - BB[a]

        def slope(t: float) -> float:  # f'(t) along M + t D; convex in t, f'(0) = d_a - d_b < 0
            St = np.linalg.inv(M + t * D)
            return -float(np.trace(St @ D @ St @ Q))

        if slope(0.0) >= 0:  # the pair's difference is rounding: no descent left along it
            break
        t = w[a] if slope(w[a]) <= 0 else brentq(slope, 0.0, w[a], xtol=1e-13 * max(w[a], 1.0))
        w[a] -= t
        w[b] += t
        if w[a] <= 1e-14:
            w[a] = 0.0
        M = M + t * D
    return w


def cell_relaxation(
    BB: NDArray, Q: NDArray, groups: NDArray, totals: NDArray, *, stop_above: float = np.inf,
    stop_below: float = -np.inf, rtol: float = 1e-7, start: NDArray | None = None,
    outer: int = 300, inner: int = 300, add: int = 8,
) -> tuple[float, float, NDArray]:
    """Certified lower bound of ``min f(w)`` with the weight of each cell fixed.

    Parameters
    ----------
    BB : ndarray, shape (N, L, L)
        ``B_i^T B_i`` of every candidate (whitened, tolerance-scaled).
    Q : ndarray, shape (L, L)
        Output weight (mm^2 per scaled unit^2).
    groups : ndarray of int, shape (N,)
        Cell of each candidate, ``0 .. G - 1``.
    totals : ndarray, shape (G,)
        Weight (poses) of each cell, ``>= 0``.
    stop_above : float
        Stop as soon as the certified bound exceeds this (mm^2).
    stop_below : float
        Stop as soon as ``f`` of an iterate is below this (mm^2): the
        minimum is then below it too (all a branch and bound needs to know
        to split a node).
    rtol : float
        Stop when the duality gap is below ``rtol * f``.
    start : ndarray, shape (N,), optional
        Weights to start from; each cell's are rescaled to its total (a cell
        without weight starts on its most informative candidate).

    Returns
    -------
    lower : float
        Certified lower bound (mm^2); ``inf`` when a cell with poses has no candidate.
    f : float
        ``E[MSE]`` of the last relaxed iterate (mm^2), ``>= lower``.
    w : ndarray, shape (N,)
        That iterate.
    """
    N, L, _ = BB.shape
    groups = np.asarray(groups, dtype=np.int64)
    totals = np.asarray(totals, dtype=float)
    G = totals.size
    if groups.shape != (N,) or groups.min() < 0 or groups.max() >= G:
        raise InputError(f"groups: expected {N} cell labels in 0..{G - 1}")
    if np.any(totals < 0):
        raise InputError(f"totals: expected weights >= 0, got {totals}")
    count = np.bincount(groups, minlength=G)
    if np.any((totals > 0) & (count == 0)):
        return np.inf, np.inf, np.zeros(N)
    M0 = np.eye(L)
    S = np.linalg.inv(M0)
    d = _d(BB, S @ Q @ S)
    w = _start_weights(d, groups, totals, start)
    lower, f = -np.inf, np.inf
    for _ in range(int(outer)):
        S = np.linalg.inv(M0 + np.tensordot(w, BB, 1))
        f = float(np.trace(S @ Q))
        d = _d(BB, S @ Q @ S)
        gap = _group_gap(d, w, groups, totals)
        lower = max(lower, f - gap)
        if lower > stop_above or f < stop_below or gap <= rtol * f:
            break
        new = []
        for g in np.flatnonzero(totals > 0):
            idx = np.flatnonzero(groups == g)
            top = idx[np.argsort(-d[idx], kind="stable")[: int(add)]]
            top = top[w[top] == 0]
            if top.size:  # a small Frank-Wolfe step onto the new vertices of this cell
                w[idx] *= 1 - 1e-3
                w[top] = 1e-3 * totals[g] / top.size
                new.append(top)
        active = np.union1d(np.flatnonzero(w > 0), np.concatenate(new) if new else np.zeros(0, np.int64))
        w[active] = _pairwise(BB[active], groups[active], Q, M0, w[active], int(inner), 0.1 * rtol)
    return float(lower), f, w


def _start_weights(d: NDArray, groups: NDArray, totals: NDArray, start: NDArray | None) -> NDArray:
    """Where :func:`cell_relaxation` starts: a parent's optimum rescaled to each cell's total, else its best candidate."""
    w = np.zeros(d.size)
    for g in np.flatnonzero(totals > 0):
        idx = np.flatnonzero(groups == g)
        s = 0.0 if start is None else float(np.sum(start[idx]))
        if s > 0:  # a parent's relaxed optimum, rescaled: a child of a search node starts next to it
            w[idx] = np.maximum(start[idx], 0.0) * (totals[g] / s)
        else:  # the cell's weight on its most informative candidate
            w[idx[np.argmax(d[idx])]] = totals[g]
    return w


def checked_design_problem(blocks: NDArray, Q: NDArray, n: int) -> tuple[NDArray, NDArray]:
    """``blocks`` (N, k, L) and ``Q`` (L, L) as float arrays, and ``n`` a positive whole number, or InputError."""
    blocks = np.asarray(blocks, dtype=float)
    Q = np.asarray(Q, dtype=float)
    if blocks.ndim != 3:
        raise InputError(f"blocks: expected shape (N, k, L), got {blocks.shape}")
    L = blocks.shape[2]
    if int(n) != n or n < 1:
        raise InputError(f"n: expected a positive whole number of poses, got {n}")
    if Q.shape != (L, L):
        raise InputError(f"Q: expected shape ({L}, {L}), got {Q.shape}")
    return blocks, Q


def exact_design_bound(
    blocks: NDArray, Q: NDArray, n: int, cells: NDArray, *, rtol: float = 1e-7, progress=None,
) -> ExactDesignBound:
    """Lower bound on ``E[MSE]`` of every exact ``n``-pose design (criterion I, linearised), by branch and bound.

    Parameters
    ----------
    blocks : ndarray, shape (N, k, L)
        Whitened, tolerance-scaled Jacobian blocks (``CandidateSet.prior_blocks_kept``).
    Q : ndarray, shape (L, L)
        Output weight (``CandidateSet.output_weight``), mm^2 per scaled unit^2.
    n : int
        Number of poses.
    cells : ndarray of int, shape (N,)
        Cell of each candidate (e.g. :func:`orthant_cells`); labels ``0 .. K - 1``.
    rtol : float
        Relative duality gap at which a complete cell-count vector's
        relaxation is taken as solved (its certified bound is used either way).
    progress : callable, optional
        Called with a line of text for every improved complete vector.

    Returns
    -------
    ExactDesignBound
    """
    blocks, Q = checked_design_problem(blocks, Q, n)
    N = blocks.shape[0]
    cells = np.asarray(cells)
    if not rtol >= 0:
        raise InputError(f"rtol: expected >= 0, got {rtol}")
    if cells.shape != (N,) or not np.issubdtype(cells.dtype, np.integer) or cells.min() < 0:
        raise InputError(f"cells: expected {N} non-negative integer labels, got shape {cells.shape}")
    # only the non-empty cells take poses; relabel them 0 .. K-1 (and report counts by the caller's labels)
    labels, cells = np.unique(cells, return_inverse=True)

    def by_label(counts) -> tuple:
        out = np.zeros(int(labels.max()) + 1, dtype=int)
        out[labels] = counts
        return tuple(int(c) for c in out)

    K = int(cells.max()) + 1
    BB = np.einsum("nki,nkj->nij", blocks, blocks)
    best = [np.inf, ()]
    nodes = [0]

    def visit(prefix: list[int], start: NDArray | None) -> None:
        j = len(prefix)
        rest = int(n) - sum(prefix)
        leaf = j == K - 1
        groups = cells if leaf else np.minimum(cells, j)  # cells j.. pooled into one with the remaining poses
        nodes[0] += 1
        # an inner node only has to be cut (bound above the best) or split (some iterate below it)
        lower, _, w = cell_relaxation(BB, Q, groups, np.array(prefix + [rest], dtype=float), stop_above=best[0],
                                      stop_below=-np.inf if leaf or best[0] == np.inf else best[0], rtol=rtol,
                                      start=start)
        if lower >= best[0]:
            return
        if leaf:
            best[0], best[1] = lower, by_label(prefix + [rest])
            if progress is not None:
                progress(f"cells {best[1]}: every design >= {lower:.6g} mm^2 ({nodes[0]} nodes)")
            return
        wj = float(w[cells == j].sum())
        for c in sorted(range(rest + 1), key=lambda c: abs(c - wj)):  # nearest the relaxed weight first
            visit(prefix + [c], w)

    visit([], None)
    return ExactDesignBound(n_poses=int(n), lower_mse=float(best[0]), cell_counts=best[1], nodes=nodes[0], cells=K)
