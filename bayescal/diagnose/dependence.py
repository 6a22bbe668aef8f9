"""Distance-covariance independence test in linear time: exact permutation moments on blocks of poses.

The statistic is the V-statistic of the squared distance covariance
(Szekely, Rizzo and Bakirov 2007) of a channel ``x`` and the per-pose
residual vector ``y``, ``V = mean(A * B)`` with ``A``, ``B`` the
double-centred Euclidean distance matrices of ``x`` and ``y``.  Under
independence the rows of ``x`` are exchangeable against those of ``y``, so
the null distribution is that of ``V`` over random permutations of ``x``.
Its mean, variance and third central moment are computed here exactly,
in O(n^2) and without permuting anything (:func:`permutation_moments`), and
the null is approximated by the Pearson type III (shifted gamma)
distribution with those three moments, so p-values far below any
``1 / n_perm`` are resolved and survive a multiple-testing correction.
The third moment matters: the null is a weighted sum of chi-squares whose
skewness (about 0.9 for a 1-D channel against a 6-D residual) is about three
times that of the gamma distribution with the same mean and variance (about
0.3), and with two moments the false-positive rate on independent data was
0.017-0.020 at alpha = 0.01 and 0.003-0.005 at alpha = 0.001 (4,000 seeded
repetitions each); with three it is 0.008-0.012 and 0.0003-0.0017
(tests/diagnose/test_dependence.py checks it).

Linear cost: recordings of at least ``2 BLOCK`` poses are split (seeded,
at random, not in measurement order) into ``n // BLOCK`` blocks of
``BLOCK..2 BLOCK - 1`` poses; the statistic is the sum of the blocks'
``V`` and, since the blocks are permuted independently, the cumulants of
its null are the sums of the blocks' exact cumulants (the block test of
Zaremba, Gretton and Blaschko 2013, with distance covariance in place of
the MMD).  Cost and memory are then ``O(n BLOCK)`` and ``O(BLOCK^2)``.
Below ``2 BLOCK`` poses the test is the full-data test, and above it the
power is never below that of the full-data test on ``BLOCK`` poses (a
block test's signal-to-noise grows as ``sqrt(n BLOCK)``: halving the block
costs what halving the poses would).

Why not the ``dcor`` package (0.7, installed here): its fast
``O(n log n)`` distance covariance (AVL / mergesort) is for two 1-D
variables only, but the residual is a 3- to 6-vector per pose and the pose
region a 3-vector; its permutation test builds the full ``n x n`` distance
matrices (200 MB each at 5,000 poses, 20 GB at 50,000) and repeats an
``O(n^2)`` pass per permutation, as the previous implementation here did:
that took 24 s of a 31 s diagnosis at 1,000 poses and 11 minutes and 1.5 GB
at 5,000, and 50,000 poses do not fit in memory.  A random-projection test
(Huang and Huo 2022) makes every projection 1-D, but needs tens of
projections times the permutations, or an asymptotic null on top.  The
block test keeps the exact statistic and an exact permutation null per
block (so ``dcor`` is not a dependency; the tests check the statistic
against its definition without double centring).  This test costs about
5 ms per channel at 100 poses and 0.05 s of CPU per channel and 1,000 poses
from 1,000 poses on: all location tests of a 50,000-pose diagnosis took
29 s (benchmarks/README.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from math import factorial

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.distance import cdist
from scipy.stats import pearson3

__all__ = ["BLOCK", "DependenceTest", "ResidualBlocks", "centered_distances", "permutation_moments", "distance_correlation"]

#: Poses per block of the test (blocks hold BLOCK..2 BLOCK - 1 poses).  500 poses keep a block's
#: distance matrices at 2-8 MB and its cost near 50 ms per channel (the exact third moment costs
#: about a dozen passes over the matrices), while below 1,000 poses (every recording the
#: concealed-data study draws: 60-200) the test is the full-data test.
BLOCK = 500


def centered_distances(x: NDArray) -> NDArray:
    """Double-centred Euclidean distance matrix of the rows of ``x`` (n,) or (n, k), shape (n, n).

    ``cdist`` builds the matrix in C without the (n, n, k) difference array.
    """
    x = np.asarray(x, float).reshape(len(x), -1)
    d = cdist(x, x)
    m = d.mean(axis=0)
    d -= m[None, :]
    d -= m[:, None]
    d += m.mean()
    return d


def distance_correlation(x: NDArray, y: NDArray) -> float:
    """Sample distance correlation (V-statistic) of ``x`` (n,) or (n, k) and ``y`` (n,) or (n, k), in [0, 1]."""
    return _dcor(*_v_stats(centered_distances(x), centered_distances(y)))


def _v_stats(A: NDArray, B: NDArray) -> tuple[float, float, float]:
    """``mean(A B)``, ``mean(A A)``, ``mean(B B)``."""
    n2 = A.size
    return float(np.vdot(A, B)) / n2, float(np.vdot(A, A)) / n2, float(np.vdot(B, B)) / n2


def _dcor(vxy: float, vxx: float, vyy: float) -> float:
    if vxx <= 0 or vyy <= 0:
        return 0.0
    return float(np.sqrt(max(vxy, 0.0) / np.sqrt(vxx * vyy)))


# --- exact permutation moments ---------------------------------------------------------------
#
# Gamma = sum_ij a_ij b_{p(i) p(j)} over uniform random permutations p.  Its r-th raw moment is a
# sum over 2r-tuples of indices (i1, j1, ..., ir, jr).  For a tuple whose exact pattern of equal
# entries is the set partition s, the permuted tuple is uniform over the n (n-1) ... (n - |s| + 1)
# tuples of the same pattern, so
#
#     E[Gamma^r] = sum_s G_A(s) G_B(s) / (n)_|s|,   G_M(s) = sum over tuples of exact pattern s of prod_t m_{i_t j_t}.
#
# G is the Moebius inversion, on the lattice of set partitions, of the "at least" sums F(s)
# (tuples equal within each block of s, blocks free to coincide).  F(s) is a sum over the
# vertices of a small multigraph (one vertex per block, one edge per factor) of the product of
# its edge weights; for up to three edges every such graph is a forest (O(n^2) by messages from
# the leaves) or a triangle (trace of M^3, one matrix product).


def _set_partitions(items: tuple[int, ...]) -> list[tuple[frozenset, ...]]:
    if not items:
        return [()]
    first, rest = items[0], items[1:]
    out = []
    for p in _set_partitions(rest):
        out.append((frozenset([first]),) + p)
        for k in range(len(p)):
            out.append(p[:k] + (p[k] | {first},) + p[k + 1:])
    return out


def _coarser(s, t) -> bool:
    return all(any(b <= c for c in t) for b in s)


def _moebius(s, t) -> int:
    """Moebius function of the partition lattice, mu(s, t) for s finer than t."""
    mu = 1
    for c in t:
        m = sum(1 for b in s if b <= c)
        mu *= (-1) ** (m - 1) * factorial(m - 1)
    return mu


def _component_keys(n_vertices: int, edges) -> tuple:
    """Canonical keys of the connected components of a multigraph (loops allowed).

    A tree (loops and parallel edges folded into vertex and edge weights) is keyed as a rooted
    tree, ``(loops at the root, ((multiplicity, child key), ...))``; the only cycle three
    edges can close, a triangle, as ``"triangle"``.
    """
    loops: dict[int, int] = {}
    adj: dict[int, dict[int, int]] = {v: {} for v in range(n_vertices)}
    for u, v in edges:
        if u == v:
            loops[u] = loops.get(u, 0) + 1
        else:
            adj[u][v] = adj[u].get(v, 0) + 1
            adj[v][u] = adj[v].get(u, 0) + 1

    def rooted(v, parent):
        return (loops.get(v, 0), tuple(sorted((k, rooted(c, v)) for c, k in adj[v].items() if c != parent)))

    seen: set[int] = set()
    keys = []
    for root in range(n_vertices):
        if root in seen:
            continue
        comp, stack = [], [root]
        while stack:
            v = stack.pop()
            if v not in seen:
                seen.add(v)
                comp.append(v)
                stack.extend(adj[v])
        n_pairs = sum(len(adj[v]) for v in comp) // 2
        if n_pairs == len(comp) - 1:
            keys.append(rooted(root, None))
        elif len(comp) == 3 and n_pairs == 3 and not any(loops.get(v) for v in comp):
            keys.append("triangle")
        else:  # pragma: no cover - impossible with at most three edges
            raise ValueError(f"graph {edges} is neither a forest nor a triangle")
    return tuple(keys)


@dataclass(frozen=True)
class _Plan:
    """The partitions of the 2 r indices of the r-th moment, compiled once.

    Attributes
    ----------
    sizes : ndarray of int
        Number of blocks of each partition.
    keys : tuple
        The distinct component keys of the partitions' graphs.
    components : ndarray of int, shape (n_partitions, order)
        Per partition, the indices into ``keys`` of its components, padded with ``len(keys)``
        (a factor 1): F is the product of the components' sums.
    mu : ndarray
        Moebius matrix of the partition lattice, ``G = mu @ F``.
    """

    sizes: NDArray
    keys: tuple
    components: NDArray
    mu: NDArray


@lru_cache(maxsize=None)
def _plan(order: int) -> _Plan:
    parts = _set_partitions(tuple(range(2 * order)))
    mu = np.zeros((len(parts), len(parts)))
    for a, s in enumerate(parts):
        for b, t in enumerate(parts):
            if _coarser(s, t):
                mu[a, b] = _moebius(s, t)
    comps = []
    for s in parts:
        lab = {i: k for k, blk in enumerate(s) for i in blk}
        comps.append(_component_keys(len(s), [(lab[2 * t], lab[2 * t + 1]) for t in range(order)]))
    keys = tuple(sorted({k for c in comps for k in c}, key=repr))
    where = {k: i for i, k in enumerate(keys)}
    idx = np.full((len(parts), order), len(keys))
    for a, c in enumerate(comps):
        idx[a, :len(c)] = [where[k] for k in c]
    return _Plan(np.array([len(s) for s in parts]), keys, idx, mu)


class _GraphSums:
    """Sums over vertex labels of products of entries of one symmetric matrix along small multigraphs.

    Rooted subtrees are cached by their key, so the 203 graphs of the third moment cost about a
    dozen matrix-vector products.

    Parameters
    ----------
    M : ndarray, shape (n, n)
        Symmetric.
    x : ndarray, shape (n,), optional
        The 1-D sample ``M`` is the centred distance matrix of, if it is one (``trace(M^3)`` in O(n^2)).
    """

    def __init__(self, M: NDArray, x: NDArray | None = None):
        self.M = M
        self.n = len(M)
        self.d = np.diag(M).copy()
        self.x = x
        self._hadamard: dict[int, NDArray] = {1: M}
        self._msg: dict = {}
        self._triangle: float | None = None

    def _power(self, k: int) -> NDArray:
        if k not in self._hadamard:
            self._hadamard[k] = self._power(k - 1) * self.M
        return self._hadamard[k]

    def triangle(self) -> float:
        """``trace(M^3)``; in O(n^2) when ``M`` is the centred distance matrix of 1-D ``x``."""
        if self._triangle is None:
            if self.x is None:
                self._triangle = float(np.vdot(self.M, self.M @ self.M))
            else:
                # M = H D H (D the distances) has zero column sums, so trace(M^3) = <M, M M> =
                # <M, H D M> = <M, D M>, and D M comes from prefix sums over the sorted x:
                # (D X)_i = x_i (2 C_i - C_n) - (2 E_i - E_n), C and E the cumulative sums of the rows
                # of X and of x X.  The C_n and E_n terms meet the zero column sums of M and drop.
                # 4 passes over the matrix instead of a matrix product (about 3x faster at n = 1000).
                order = np.argsort(self.x, kind="stable")
                xs, Ms = self.x[order], self.M[order]
                C = np.cumsum(Ms, axis=0)
                t = 2.0 * float(xs @ np.einsum("ij,ij->i", Ms, C))
                np.cumsum(xs[:, None] * Ms, axis=0, out=C)
                self._triangle = t - 2.0 * float(np.vdot(Ms, C))
        return self._triangle

    def _message(self, key) -> NDArray:
        """Vector over the root's label: its loop weight times each child's edge-weighted message."""
        if key not in self._msg:
            loops, kids = key
            w = self.d**loops if loops else np.ones(self.n)
            for k, child in kids:
                w = w * (self._power(k) @ self._message(child))
            self._msg[key] = w
        return self._msg[key]

    def value(self, key) -> float:
        """Sum over all labels of one component."""
        return self.triangle() if key == "triangle" else float(self._message(key).sum())


@dataclass(frozen=True)
class _Sums:
    """What the permutation moments need of one symmetric matrix: G for the partitions of each order."""

    n: int
    G: tuple[NDArray, ...]

    @classmethod
    def of(cls, M: NDArray, order: int = 3, x: NDArray | None = None) -> "_Sums":
        """``x``: the 1-D sample ``M`` is the centred distance matrix of, if it is one (faster ``trace(M^3)``)."""
        gs = _GraphSums(np.asarray(M, float), None if x is None else np.asarray(x, float).reshape(-1))
        G = []
        for r in range(1, order + 1):
            plan = _plan(r)
            val = np.array([gs.value(k) for k in plan.keys] + [1.0])
            G.append(plan.mu @ val[plan.components].prod(axis=1))
        return cls(len(M), tuple(G))


@lru_cache(maxsize=64)
def _inverse_falling(n: int, order: int) -> NDArray:
    """``1 / (n)_k`` for each partition of the plan (0 where ``k > n``: no tuple has that pattern, G is 0)."""
    sizes = _plan(order).sizes
    ff = np.array([np.prod(np.arange(n, n - k, -1, dtype=float)) for k in range(int(sizes.max()) + 1)])
    with np.errstate(divide="ignore"):
        inv = np.where(ff > 0, 1.0 / np.where(ff > 0, ff, 1.0), 0.0)
    return inv[sizes]


def _raw_moments(a: _Sums, b: _Sums) -> list[float]:
    return [float(np.sum(ga * gb * _inverse_falling(a.n, r))) for r, (ga, gb) in enumerate(zip(a.G, b.G), start=1)]


def _cumulants(a: _Sums, b: _Sums) -> tuple[float, float, float]:
    """Mean, variance and third central moment of Gamma under permutation."""
    m1, m2, m3 = _raw_moments(a, b)
    var = m2 - m1 * m1
    return m1, max(var, 0.0), m3 - 3 * m1 * m2 + 2 * m1**3


def permutation_moments(A: NDArray, B: NDArray) -> tuple[float, float, float]:
    """Exact mean, variance and third central moment of ``sum_ij a_ij b_{p(i) p(j)}`` over uniform random permutations ``p``.

    Parameters
    ----------
    A, B : ndarray, shape (n, n)
        Symmetric matrices (any: the formulas do not assume centring).

    Returns
    -------
    mean, variance, third_central_moment : float
    """
    return _cumulants(_Sums.of(A), _Sums.of(B))


# --- the block test ---------------------------------------------------------------------------


@dataclass(frozen=True)
class DependenceTest:
    """Result of one test: distance correlation, p-value, and the blocks used.

    Attributes
    ----------
    strength : float
        Distance correlation from the summed block V-statistics (0..1); with one block the
        sample distance correlation of the data.
    p_value : float
        Pearson type III approximation of the permutation null with its exact mean, variance
        and skewness.
    n_blocks : int
    """

    strength: float
    p_value: float
    n_blocks: int


def pearson3_sf(x: float, mean: float, var: float, third: float) -> float:
    """Upper tail at ``x`` of the Pearson type III (shifted gamma) distribution with these moments.

    ``third`` is the third central moment; zero gives the normal tail.
    """
    if var <= 0:
        return 1.0 if x <= mean else 0.0
    sd = np.sqrt(var)
    return float(pearson3.sf((x - mean) / sd, third / sd**3))


class ResidualBlocks:
    """The residual side of the test, computed once and reused for every channel.

    Parameters
    ----------
    y : ndarray, shape (n,) or (n, k)
        Per-pose residual vectors (whitened).
    seed : int
        Seeds the assignment of poses to blocks.
    block : int
        Poses per block (see :data:`BLOCK`).
    """

    def __init__(self, y: NDArray, *, seed: int = 0, block: int = BLOCK):
        y = np.asarray(y, float)
        n = len(y)
        if block < 4:
            raise ValueError(f"block must be at least 4 poses, got {block}")
        n_blocks = max(1, n // block)
        if n_blocks == 1:
            self.index = [np.arange(n)]
        else:
            self.index = [np.sort(b) for b in np.array_split(np.random.default_rng(seed).permutation(n), n_blocks)]
        # the blocks' distance matrices are rebuilt per channel (a few ms each) rather than kept:
        # kept, they would hold 2 MB per 500 poses (200 MB at 50,000 poses)
        self._y, self._sums, self._vyy = [], [], []
        for idx in self.index:
            yb = y[idx]
            B = centered_distances(yb)
            self._y.append(yb)
            self._sums.append(_Sums.of(B, x=yb if yb.ndim == 1 else None))
            self._vyy.append(float(np.vdot(B, B)) / B.size)

    @property
    def n_blocks(self) -> int:
        return len(self.index)

    def test(self, x: NDArray) -> DependenceTest:
        """Distance-covariance test of ``x`` (n,) or (n, k) against the residuals.

        Returns
        -------
        DependenceTest
        """
        x = np.asarray(x, float)
        one_d = x.ndim == 1 or x.shape[1] == 1
        vxy = vxx = vyy = mean = var = third = 0.0
        for idx, yb, sb, byy in zip(self.index, self._y, self._sums, self._vyy):
            xb = x[idx]
            A = centered_distances(xb)
            n2 = A.size
            axx = float(np.vdot(A, A)) / n2
            if axx <= 0 or byy <= 0:
                continue  # constant channel (or residual) in this block: no information, no null mass
            m, v, t = _cumulants(_Sums.of(A, x=xb if one_d else None), sb)
            # cumulants of independent blocks add (the third central moment is the third cumulant)
            vxy += float(np.vdot(A, centered_distances(yb))) / n2
            vxx += axx
            vyy += byy
            mean += m / n2
            var += v / n2**2
            third += t / n2**3
        stat = _dcor(vxy, vxx, vyy)
        if mean <= 0 or var <= 0:
            return DependenceTest(stat, 1.0, self.n_blocks)
        return DependenceTest(stat, pearson3_sf(vxy, mean, var, third), self.n_blocks)
