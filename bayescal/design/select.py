"""Greedy selection of pose blocks with rank-k updates, then DETMAX-style exchange.

Each candidate pose contributes a block ``B`` of ``k = dof`` rows of the
whitened, column-scaled Jacobian, so adding it changes the information
matrix by a rank-k term: ``M + B^T B``.  With ``G = B M^-1`` (k x L) and
``H = I_k + G B^T`` (k x k),

* matrix determinant lemma: ``log det(M + B^T B) - log det M = log det H``;
* Woodbury: ``trace((M + B^T B)^-1) = trace(M^-1) - trace(H^-1 G G^T)``,
  and with a weight ``Q`` (I-optimality)
  ``trace((M + B^T B)^-1 Q) = trace(M^-1 Q) - trace(H^-1 G Q G^T)``;

so the gain of every candidate costs ``O(k L^2)`` (one product with
``M^-1``) instead of a fresh ``O(L^3)`` factorisation.  ``M^-1`` is
refreshed from the accumulated matrix (Cholesky) once per accepted pose,
which keeps round-off from accumulating over the Woodbury updates.

Spectral criteria (E, O2..O5) depend on extreme eigenvalues, which have no
closed-form rank-k update; they are evaluated exactly (``eigvalsh`` of
``M + B^T B``) on a shortlist of the candidates with the largest D-gain,
and, for these and for A, until the selected rows make the data part of
``M`` full rank (where every spectral index is zero and ``trace(M^-1)`` is
dominated by ``1/delta``) the greedy pass uses the D utility.
I (``-trace(M^-1 Q)``) starts from the prior ``M0 = I``, where it is finite
from the first pose, and needs no such phase.

Exchange: Mitchell's DETMAX with excursions of length one.  Add the best
candidate, then remove the pose whose removal costs least; accept the swap
only if the utility strictly increases, stop otherwise.  The utility never
decreases, and the loop ends because the selection set is finite.

References
----------
T. J. Mitchell, "An algorithm for the construction of D-optimal experimental
designs", Technometrics 16 (1974) 203-210.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from .criteria import check_criterion, utility, utility_kind

__all__ = ["Selection", "candidate_gains", "greedy_select", "exchange_refine", "brute_force_greedy"]


@dataclass(frozen=True)
class Selection:
    """Indices chosen from a candidate set and the utility history.

    Attributes
    ----------
    index : ndarray of int, shape (n,)
        Selected candidates, in selection order (exchange keeps positions).
    utility : float
        Final selection utility (see :func:`bayescal.design.criteria.utility`).
    greedy_utility : float
        Utility right after the greedy pass.
    swaps : int
        Exchanges accepted.
    history : ndarray
        Utility after the greedy pass and after each accepted swap (non-decreasing).
    """

    index: NDArray
    utility: float
    greedy_utility: float
    swaps: int
    history: NDArray


def _inverse(M: NDArray) -> NDArray:
    # Cholesky-based inverse: M is symmetric positive definite (delta I or prior I + data)
    c = np.linalg.cholesky(M)
    ci = np.linalg.solve(c, np.eye(M.shape[0]))
    return ci.T @ ci


def candidate_gains(
    blocks: NDArray, M: NDArray, criterion: str, *, Minv: NDArray | None = None, shortlist: int = 512,
    exclude: NDArray | None = None, Q: NDArray | None = None,
) -> NDArray:
    """Utility of ``M + B_i^T B_i`` minus utility of ``M`` for every candidate block.

    Parameters
    ----------
    blocks : ndarray, shape (N, k, L)
        Candidate blocks of the whitened, scaled Jacobian.
    M : ndarray, shape (L, L)
        Current (positive-definite) information matrix.
    criterion : str
    Minv : ndarray, shape (L, L), optional
        ``M^-1`` if already known.
    shortlist : int
        Spectral criteria: candidates (largest D-gain first) evaluated exactly.
    exclude : ndarray of int, optional
        Candidates to give ``-inf`` (already selected).
    Q : ndarray, shape (L, L), optional
        Output weight of criterion I (required for it).

    Returns
    -------
    ndarray, shape (N,)
        Gains (``-inf`` where excluded or, for spectral criteria, outside the shortlist).
    """
    criterion = check_criterion(criterion)
    kind = utility_kind(criterion)
    Minv = _inverse(M) if Minv is None else Minv
    N, k, L = blocks.shape
    # G = B M^-1 as one (N k x L) @ (L x L) GEMM: O(k L^2) per candidate, faster than N small products
    G = (blocks.reshape(-1, L) @ Minv).reshape(N, k, L)
    H = np.eye(k) + np.einsum("nkl,njl->nkj", G, blocks, optimize=True)  # (N, k, k)
    if kind in ("trace_inv", "weighted_trace"):
        if kind == "weighted_trace":
            if Q is None:
                raise InputError("criterion I: needs the output weight Q")
            GQ = (G.reshape(-1, L) @ Q).reshape(N, k, L)  # one more GEMM: O(k L^2) per candidate
        else:
            GQ = G
        GG = np.einsum("nkl,njl->nkj", GQ, G, optimize=True)
        gains = np.trace(np.linalg.solve(H, GG), axis1=1, axis2=2)
    else:
        sign, gains = np.linalg.slogdet(H)
    gains = np.array(gains, dtype=float)
    if exclude is not None and len(exclude):
        gains[np.asarray(exclude)] = -np.inf
    if kind == "spectral":
        order = np.argsort(-gains, kind="stable")[: max(1, min(shortlist, gains.size))]
        order = order[np.isfinite(gains[order])]
        out = np.full(gains.shape, -np.inf)
        Mc = M[None] + np.swapaxes(blocks[order], 1, 2) @ blocks[order]
        out[order] = utility(criterion, Mc) - float(utility(criterion, M))
        return out
    return gains


def _data_full_rank(M: NDArray, M0: NDArray) -> bool:
    lam = np.linalg.eigvalsh(M - M0)
    return lam[0] > 1e-10 * max(lam[-1], 1e-300)


def greedy_select(
    blocks: NDArray, n: int, criterion: str, *, M0: NDArray, shortlist: int = 512, lazy: bool = True,
    chunk: int = 256, Q: NDArray | None = None, repeats: bool = False,
) -> tuple[NDArray, NDArray]:
    """Greedy addition of ``n`` candidate blocks maximising the criterion's utility.

    Parameters
    ----------
    blocks : ndarray, shape (N, k, L)
    n : int
    criterion : str
    M0 : ndarray, shape (L, L)
        Starting information (``delta I``, or the prior ``I`` for EIG).
    shortlist : int
        Spectral criteria: candidates evaluated exactly per step.
    lazy : bool
        For log-det utilities (D, O1, EIG, and the rank-building phase of
        the others), lazy evaluation (Minoux's accelerated greedy): ``log
        det(M0 + sum B^T B)`` is submodular, so a candidate's gain can only
        shrink as poses are added and its last computed gain is an upper
        bound.  Candidates are re-evaluated in chunks, best bound first,
        until the best exact gain beats every remaining bound.  The
        selection is the same as re-evaluating every candidate.
    chunk : int
        Candidates re-evaluated at a time in the lazy pass.
    Q : ndarray, shape (L, L), optional
        Output weight of criterion I (required for it).
    repeats : bool
        Allow a candidate to be chosen more than once (measured again).
        Repeating the most informative poses can beat any set of distinct
        poses (the optimal design measure puts weight on a few support
        points); the lazy bounds stay valid, since a repeated block's gain
        also only shrinks.

    Returns
    -------
    index : ndarray of int, shape (n,)
        Selected candidates in order.
    M : ndarray, shape (L, L)
        Final information matrix (including ``M0``).
    """
    criterion = check_criterion(criterion)
    N = blocks.shape[0]
    if not 1 <= n <= (np.inf if repeats else N):
        raise InputError(f"n: expected 1 to {N} poses (the number of usable candidates), got {n}")
    M = np.array(M0, dtype=float)
    selected: list[int] = []

    def excluded() -> NDArray:
        return np.array([] if repeats else selected, dtype=int)

    rank_first = utility_kind(criterion) in ("spectral", "trace_inv")
    bound: NDArray | None = None  # upper bounds of the log-det gains (lazy greedy)
    for _ in range(n):
        use = criterion
        if rank_first and not (selected and _data_full_rank(M, M0)):
            # spectral indices of rank-deficient data are all zero and trace(M^-1) is dominated by
            # 1/delta of the unobserved directions: build rank with the D utility first
            use = "D"
        if utility_kind(use) != "logdet" or not lazy:
            bound = None
            gains = candidate_gains(blocks, M, use, shortlist=shortlist, exclude=excluded(), Q=Q)
            j = int(np.argmax(gains))
        elif bound is None:
            gains = candidate_gains(blocks, M, use, exclude=excluded())
            bound = gains.copy()
            j = int(np.argmax(gains))
        else:
            j = _lazy_pick(blocks, M, use, bound, excluded(), chunk)
        if bound is not None and not repeats:
            bound[j] = -np.inf
        selected.append(j)
        M = M + blocks[j].T @ blocks[j]
    return np.array(selected, dtype=int), M


def exchange_refine(
    blocks: NDArray, selected: NDArray, criterion: str, *, M0: NDArray, max_iter: int | None = None,
    shortlist: int = 512, Q: NDArray | None = None, repeats: bool = False,
) -> Selection:
    """DETMAX exchange (excursion length one) from a starting selection; never lowers the utility.

    With ``repeats`` a candidate already in the selection may be added again.
    """
    criterion = check_criterion(criterion)
    S = [int(i) for i in selected]
    M = M0 + np.einsum("nki,nkj->ij", blocks[S], blocks[S])
    cur = float(utility(criterion, M, Q=Q))
    history = [cur]
    max_iter = 2 * len(S) if max_iter is None else int(max_iter)
    swaps = 0
    for _ in range(max_iter):
        gains = candidate_gains(blocks, M, criterion, shortlist=shortlist,
                                exclude=np.array([] if repeats else S, dtype=int), Q=Q)
        c = int(np.argmax(gains))
        if not np.isfinite(gains[c]):
            break
        M_plus = M + blocks[c].T @ blocks[c]
        members = S + [c]
        BB = np.swapaxes(blocks[members], 1, 2) @ blocks[members]
        u = utility(criterion, M_plus[None] - BB, Q=Q)
        i = int(np.argmax(u))
        if members[i] == c or not u[i] > cur + 1e-12 * abs(cur):  # removing a copy of c changes nothing
            break
        S[i] = c
        M = M_plus - BB[i]
        cur = float(u[i])
        history.append(cur)
        swaps += 1
    return Selection(index=np.array(S, dtype=int), utility=cur, greedy_utility=history[0], swaps=swaps,
                     history=np.array(history))


def brute_force_greedy(
    blocks: NDArray, n: int, criterion: str, *, M0: NDArray, Q: NDArray | None = None, repeats: bool = False,
) -> NDArray:
    """Greedy selection recomputing the utility of every candidate from scratch (reference, slow).

    The independent path the rank-k updates are tested and benchmarked
    against: ``utility(M + B_i^T B_i)`` by a fresh factorisation per candidate.
    For spectral criteria it evaluates all candidates (no shortlist).
    """
    criterion = check_criterion(criterion)
    M = np.array(M0, dtype=float)
    selected: list[int] = []
    rank_first = utility_kind(criterion) in ("spectral", "trace_inv")
    for _ in range(n):
        use = criterion
        if rank_first and not (selected and _data_full_rank(M, M0)):
            use = "D"
        best, best_u = -1, -np.inf
        for i in range(blocks.shape[0]):
            if i in selected and not repeats:
                continue
            u = float(utility(use, M + blocks[i].T @ blocks[i], Q=Q))
            if u > best_u:
                best, best_u = i, u
        selected.append(best)
        M = M + blocks[best].T @ blocks[best]
    return np.array(selected, dtype=int)


def _lazy_pick(blocks: NDArray, M: NDArray, use: str, bound: NDArray, excluded: NDArray, chunk: int) -> int:
    """The lazy greedy step: re-evaluate the largest upper bounds (in growing chunks) until the best is fresh.

    ``bound`` (upper bounds of the log-det gains) is updated in place with the gains re-evaluated.
    """
    Minv = _inverse(M)
    fresh = np.zeros(blocks.shape[0], dtype=bool)
    fresh[excluded] = True
    # candidates by decreasing bound, sorted once per step: re-evaluated gains only shrink,
    # so the order of the not yet re-evaluated ones stays valid
    order = np.argsort(-bound, kind="stable")
    order = order[~fresh[order]]
    pos, size = 0, chunk
    while True:
        todo = order[pos:pos + size]
        pos += todo.size
        size *= 2  # geometric chunks: at most about twice the work of evaluating everything
        if todo.size:
            bound[todo] = candidate_gains(blocks[todo], M, use, Minv=Minv)
            fresh[todo] = True
        best_fresh = np.where(fresh, bound, -np.inf)
        best_fresh[excluded] = -np.inf
        j = int(np.argmax(best_fresh))
        if pos >= order.size or best_fresh[j] >= bound[order[pos]]:
            return j
