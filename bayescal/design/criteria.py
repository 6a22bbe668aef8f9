"""Optimality criteria and observability indices of an identification Jacobian.

Every criterion is a function of the whitened, column-scaled identification
Jacobian ``A`` (``n_rows x L``: ``n_rows = n_poses * dof`` measured
components, ``L`` identified parameters), with singular values
``s_1 >= ... >= s_L`` and information matrix ``M = A^T A`` (eigenvalues
``s_i^2``).  All are reported so that **larger is better**:

==========  ==========================================  =============================
name        value                                       source
==========  ==========================================  =============================
``D``       ``det(M)^(1/L) = (s_1 ... s_L)^(2/L)``      D-optimality (Kiefer 1959)
``A``       ``L / trace(M^-1) = L / sum s_i^-2``        A-optimality (reported as efficiency)
``E``       ``lambda_min(M) = s_L^2``                   E-optimality
``O1``      ``(s_1 ... s_L)^(1/L) / sqrt(m)``           Borm & Menq 1991
``O2``      ``s_L / s_1``                               Driels & Pathre 1990
``O3``      ``s_L``                                     Nahvi, Hollerbach & Hayward 1994
``O4``      ``s_L^2 / s_1``                             Nahvi & Hollerbach 1996
``O5``      ``1 / (1/s_1 + ... + 1/s_L)``               Sun & Hollerbach 2008
``EIG``     ``0.5 log det(I + A_tol^T A_tol)``          Bayesian expected information gain
``I``       ``sqrt(trace(Q) / trace(Sigma Q))``         I-optimality (output error)
==========  ==========================================  =============================

``m`` in O1 is the number of measured components (rows of ``A``).  O1..O4
follow Nahvi & Hollerbach (1996); the O5 formula (after Sun & Hollerbach,
ICRA 2008) could not be checked against the paper's text: see
docs/planning.md, "Checking O1..O5 against the literature".  The O
indices use singular values of the Jacobian itself, not of ``J^T J``.  EIG
is the mutual information (nats) between the parameters and a linear-Gaussian
measurement under the tolerance prior ``theta ~ N(0, diag(tol^2))``; it is
computed on the tolerance-scaled Jacobian ``A_tol`` of all parameters
(the prior keeps it finite where ``A_tol`` is rank deficient).

``I`` is I-optimality (integrated prediction variance) of the tool point
under the tolerance prior, on the tolerance-scaled Jacobian ``A_k`` of the
identifiable parameters (the columns MAP identification estimates):
``Sigma = (I + A_k^T A_k)^-1`` is the posterior covariance (scaled units),
``G_e`` (3 x L, mm per scaled unit) the tool-point Jacobian at workspace pose
``e``, and ``Q = mean_e G_e^T G_e`` over workspace poses drawn within
``q_limits``.  ``trace(Sigma Q) = mean_e trace(G_e Sigma G_e^T)`` is the
expected mean squared tool-point error (mm^2) after calibration, and
``trace(Q)`` the same before (``Sigma = I``, the prior); ``I`` is the ratio of
the RMS errors, before over after (dimensionless, larger is better).

For selection, each criterion has a *utility* evaluated on a (slightly
regularised) information matrix ``M_delta = delta I + A^T A``:
``log det`` for D and O1 (O1 ranks pose sets of equal size as D does),
``-trace(M^-1)`` for A, ``log det`` with ``delta = 1`` (the prior) for EIG,
``-trace(M^-1 Q)`` with ``M = I + A_k^T A_k`` for I,
and the index itself computed from ``eigvalsh(M_delta)`` for the spectral
criteria E and O2..O5.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..constants import CRITERIA
from ..errors import InputError

__all__ = [
    "CRITERIA", "SPECTRAL", "check_criterion", "criterion_value", "criteria_from_singular_values", "i_value",
    "output_weight", "utility",
]

# CRITERIA, all criteria in the order reports list them, is defined in bayescal.constants (the command line offers
# them without importing numpy) and exported from here as before.
#: Criteria computed with the tolerance prior (defined for any number of poses).
PRIOR_BASED = ("EIG", "I")
#: Criteria that are functions of extreme singular values (no rank-k update formula).
SPECTRAL = ("E", "O2", "O3", "O4", "O5")


def check_criterion(name: str) -> str:
    """The canonical criterion name; InputError listing the known ones otherwise."""
    key = str(name).upper()
    if key not in CRITERIA:
        raise InputError(f"criterion: expected one of {', '.join(CRITERIA)}, got {name!r}")
    return key


def criteria_from_singular_values(s: NDArray, n_rows: int) -> dict[str, float]:
    """D, A, E and O1..O5 from the singular values of a Jacobian (not of ``J^T J``).

    Parameters
    ----------
    s : ndarray, shape (L,)
        Singular values of the whitened, column-scaled Jacobian (any order).
    n_rows : int
        Number of rows ``m`` of that Jacobian (measured components), for O1.

    Returns
    -------
    dict
        Criterion name to value; zero (never negative) for a rank-deficient
        Jacobian, where the parameters are not identifiable.
    """
    s = np.sort(np.asarray(s, dtype=float))[::-1]
    L = s.size
    if L == 0:
        raise InputError("criteria: no parameters (empty set of singular values)")
    tiny = np.finfo(float).eps * max(s[0], 1e-300) * max(n_rows, L)
    if s[-1] <= tiny:
        return {"D": 0.0, "A": 0.0, "E": 0.0, "O1": 0.0, "O2": 0.0, "O3": 0.0, "O4": 0.0, "O5": 0.0}
    log_geo = float(np.mean(np.log(s)))  # log of (s_1 ... s_L)^(1/L), without overflow
    return {
        "D": float(np.exp(2.0 * log_geo)),
        "A": float(L / np.sum(s**-2.0)),
        "E": float(s[-1] ** 2),
        "O1": float(np.exp(log_geo) / np.sqrt(n_rows)),
        "O2": float(s[-1] / s[0]),
        "O3": float(s[-1]),
        "O4": float(s[-1] ** 2 / s[0]),
        "O5": float(1.0 / np.sum(1.0 / s)),
    }


def eig_value(A_tol: NDArray) -> float:
    """Expected information gain ``0.5 log det(I + A^T A)`` (nats) of a tolerance-scaled Jacobian."""
    s = np.linalg.svd(np.asarray(A_tol, dtype=float), compute_uv=False)
    return float(0.5 * np.sum(np.log1p(s**2)))


def output_weight(G: NDArray) -> NDArray:
    """``Q = mean_e G_e^T G_e`` (L, L) of tool-point Jacobians ``G`` (n_e, 3, L), mm^2 per scaled unit^2."""
    G = np.asarray(G, dtype=float)
    return np.einsum("eri,erj->ij", G, G, optimize=True) / G.shape[0]


def i_value(A_k: NDArray, Q: NDArray) -> float:
    """I-optimality value ``sqrt(trace(Q) / trace(Sigma Q))``, ``Sigma = (I + A_k^T A_k)^-1``.

    Parameters
    ----------
    A_k : ndarray, shape (n_rows, L)
        Whitened, tolerance-scaled Jacobian of the identifiable parameters.
    Q : ndarray, shape (L, L)
        Output weight (:func:`output_weight`), mm^2 per scaled unit^2.

    Returns
    -------
    float
        Expected RMS tool-point error before calibration over that after
        (linearised, Gaussian prior from the tolerances); 1 without data.
    """
    A_k = np.asarray(A_k, dtype=float)
    M = np.eye(A_k.shape[1]) + A_k.T @ A_k
    return float(np.sqrt(np.trace(Q) / np.trace(np.linalg.solve(M, Q))))


def criterion_value(name: str, A: NDArray, *, A_tol: NDArray | None = None, Q: NDArray | None = None) -> float:
    """One criterion of a stacked Jacobian ``A`` (n_rows, L).

    EIG needs ``A_tol`` (n_rows, P), the tolerance-scaled Jacobian of all
    parameters; I needs ``Q`` (L, L) and takes ``A`` tolerance-scaled.
    """
    name = check_criterion(name)
    if name == "I":
        if Q is None:
            raise InputError("criterion I: needs the output weight Q of the tool-point Jacobian over the workspace")
        return i_value(A, Q)
    if name == "EIG":
        if A_tol is None:
            raise InputError("criterion EIG: needs the tolerance-scaled Jacobian of all parameters (A_tol)")
        return eig_value(A_tol)
    A = np.asarray(A, dtype=float)
    return criteria_from_singular_values(np.linalg.svd(A, compute_uv=False), A.shape[0])[name]


# ------------------------------------------------------------------ utilities
def _spectral_utility(name: str, lam: NDArray) -> NDArray:
    """Spectral criterion from eigenvalues ``lam`` (..., L) of a PD information matrix."""
    s = np.sqrt(np.clip(lam, 0.0, None))
    s_min, s_max = s.min(axis=-1), s.max(axis=-1)
    if name == "E":
        return s_min**2
    if name == "O2":
        return s_min / s_max
    if name == "O3":
        return s_min
    if name == "O4":
        return s_min**2 / s_max
    if name == "O5":
        with np.errstate(divide="ignore"):
            return 1.0 / np.sum(1.0 / s, axis=-1)
    raise InputError(f"criterion {name!r} is not spectral")


def utility_kind(name: str) -> str:
    """How a criterion is optimised: ``logdet``, ``trace_inv``, ``weighted_trace`` or ``spectral``."""
    name = check_criterion(name)
    if name in ("D", "O1", "EIG"):
        return "logdet"
    if name == "A":
        return "trace_inv"
    if name == "I":
        return "weighted_trace"
    return "spectral"


def utility(name: str, M: NDArray, *, Q: NDArray | None = None) -> NDArray:
    """Selection utility of information matrices ``M`` (..., L, L), larger is better.

    ``log det M`` (D, O1, EIG), ``-trace(M^-1)`` (A), ``-trace(M^-1 Q)``
    (I; ``Q`` required), or the spectral index computed from
    ``eigvalsh(M)`` (E, O2..O5).  Non-positive-definite matrices get
    ``-inf``.
    """
    name = check_criterion(name)
    kind = utility_kind(name)
    M = np.asarray(M, dtype=float)
    if kind == "weighted_trace":
        if Q is None:
            raise InputError("criterion I: needs the output weight Q")
        lam = np.linalg.eigvalsh(M)
        ok = lam.min(axis=-1) > 0
        # solve on the positive-definite ones only; the others get -inf
        Ms = np.where(ok[..., None, None], M, np.eye(M.shape[-1]))
        tr = np.trace(np.linalg.solve(Ms, np.broadcast_to(Q, Ms.shape)), axis1=-2, axis2=-1)
        return np.where(ok, -tr, -np.inf)
    if kind == "logdet":
        sign, ld = np.linalg.slogdet(M)
        return np.where(sign > 0, ld, -np.inf)
    if kind == "trace_inv":
        lam = np.linalg.eigvalsh(M)
        with np.errstate(divide="ignore"):
            return np.where(lam.min(axis=-1) > 0, -np.sum(1.0 / lam, axis=-1), -np.inf)
    return _spectral_utility(name, np.linalg.eigvalsh(M))
