"""Outlying poses: a per-pose test that accounts for the number of poses, and robust weights (IRLS).

The test (:func:`pose_test`) works on the whitened, tolerance-scaled
linearisation ``A x ~ z`` of a fit (``A = W J S``, rows whitened by the
instrument sigma, see :mod:`bayescal.identify.gauss_newton`), with the
regularisation of the fit (``lam``: 0 for least squares, 1 for MAP, the
ridge value; ``k`` kept directions for TSVD) and optional per-pose weights
``w_i`` of a robust fit (the pose's sigma divided by ``sqrt(w_i)``).

**Statistic.** For pose ``i`` (``d`` rows ``A_i``, residual ``r_i`` at the
fit) the *deleted residual* is the pose's residual against the fit of all
other poses, ``e_i = z_i - A_i x_(i)``.  With ``C = (A^T W A + lam I)^-1``
and ``G_i = A_i C A_i^T`` (so that ``w_i G_i`` is the pose's block of the
hat matrix), the rank-``d`` downdate gives, without refitting,

    e_i = (I - w_i G_i)^-1 r_i,        Cov(e_i) = I + G_i (I - w_i G_i)^-1,
    t_i = e_i^T Cov(e_i)^-1 e_i = r_i^T (I + (1 - w_i) G_i)^-1 (I - w_i G_i)^-1 r_i.

For an unweighted fit (``w_i = 1``) this is the studentised residual
``r_i^T (I - H_ii)^-1 r_i``; for a pose the robust fit has down-weighted to
nothing (``w_i -> 0``) it is ``r_i^T (I + G_i)^-1 r_i``, the residual
against a prediction of variance ``G_i``.  For least squares and for ridge
under its own prior (``x ~ N(0, I / lam)``: MAP with ``lam = 1``) this is
exact in the linear-Gaussian model: ``t_i ~ chi2(d)`` for a pose the model
explains, whatever the other poses are.

* Noise given by ``[measurement]`` (or per-pose sigma columns): ``t_i``
  against ``chi2(d)``.
* Noise not given: the leave-one-out scaled form ``F_i = (t_i / d) /
  s_(i)^2`` with ``s_(i)^2`` the (weighted) residual sum of squares of the
  other poses over its degrees of freedom ``N - tr(H) - d``, against
  ``F(d, N - tr(H) - d)`` (exact for least squares).
* TSVD (``k`` kept directions): the dropped directions stay at nominal, so
  their share of the true errors (a priori ``N(0, I)`` in tolerance units)
  is in every residual; ``A_i V_drop V_drop^T A_i^T`` joins ``Cov(e_i)``.
* ``scale="robust"`` (used by the diagnosis, whose geometric model may miss
  a physical effect that raises every residual): ``t_i / s^2`` against
  ``chi2(d)`` with ``s^2 = max(1, median(t) / median(chi2(d)))``, so that a
  mismatch spread over the poses is not taken for outliers but a pose far
  from the others is.

**Multiple testing.** The per-pose p-values are Sidak-adjusted over the
``n`` poses, ``p_adj = 1 - (1 - p)^n``, and a pose is an outlier when
``p_adj < alpha`` (default 0.01): on a clean recording the chance that
*any* pose is flagged is about ``alpha``, i.e. about ``alpha / n`` false
outliers per pose (far below 1 per 1,000).

**Influence.** Cook's distance of the pose block,
``D_i = (x - x_(i))^T C^-1 (x - x_(i)) / tr(H)``, in units of the noise.

**Robust weights** (:func:`irls_weights`): iteratively reweighted least
squares over per-pose weights from the whitened squared residual norm
``u_i = |r_i|^2`` of each pose (``d`` rows): Student-t,
``w_i = (nu + d) / (nu + u_i / s^2)`` (the EM weights of a multivariate t
likelihood with ``nu`` degrees of freedom), or Huber on the pose norm,
``w_i = min(1, c / sqrt(u_i / s^2))``.  ``s^2 = 1`` when the noise is given,
else estimated with the weights (EM update ``s^2 = sum w u / (n d)`` for t,
``median(u) / median(chi2(d))`` for Huber).

References
----------
R. D. Cook, S. Weisberg, *Residuals and Influence in Regression*, Chapman & Hall 1982, ch. 3-5.
K. L. Lange, R. J. A. Little, J. M. G. Taylor, "Robust statistical modeling using the t
distribution", JASA 84 (1989).
Z. Sidak, "Rectangular confidence regions for the means of multivariate normal
distributions", JASA 62 (1967).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_triangular

from ..constants import DEFAULT_NU, OUTLIER_ALPHA
from ..contract import scale_noise
from ..distributions import chi2_median, chi2_ppf, chi2_sf, f_sf
from ..errors import InputError
from ..measurement import MeasurementModel
from ..progress import report
from ..tallqr import ridge_factor

__all__ = [
    "ALPHA",
    "LOSSES",
    "DEFAULT_NU",
    "MAX_FRACTION",
    "EXCLUDE_FACTOR",
    "PoseTest",
    "exclusion_weights",
    "weighted_model",
    "pose_test_linear",
    "pose_test",
    "irls_weights",
    "recording_lines",
]

#: Family-wise level of the outlier test over all poses of a recording (:data:`bayescal.constants.OUTLIER_ALPHA`;
#: it and DEFAULT_NU, the degrees of freedom of the Student-t loss, are defined there so that the command line
#: offers them as defaults without importing numpy).
ALPHA = OUTLIER_ALPHA
#: Robust losses of :func:`irls_weights`.
LOSSES = ("t", "huber")
#: More flagged poses than this share of a recording: a model mismatch, not outliers.
MAX_FRACTION = 0.1
#: Huber threshold on the whitened pose norm, as a chi quantile of the pose's rows.
HUBER_QUANTILE = 0.95
#: An excluded pose's sigma is multiplied by this (weight ``EXCLUDE_FACTOR**-2`` = 1e-12): out of every fit,
#: but in its place in the measurement order (the order carries the approach direction and the time).
EXCLUDE_FACTOR = 1e6


def exclusion_weights(excluded: NDArray) -> NDArray:
    """Per-pose weights that take the ``excluded`` poses out of a fit: ``EXCLUDE_FACTOR**-2`` there, else 1."""
    return np.where(excluded, EXCLUDE_FACTOR**-2, 1.0)


def weighted_model(model: MeasurementModel, weights: NDArray | None) -> MeasurementModel:
    """``model`` with each pose's sigma divided by ``sqrt(w)`` (the model itself when ``weights`` is None).

    Parameters
    ----------
    model : MeasurementModel
        With the instrument's noise.
    weights : ndarray, shape (n_poses,), optional
        Robust or exclusion weights (dimensionless, > 0).
    """
    if weights is None:
        return model
    return scale_noise(model, 1.0 / np.sqrt(weights))


def recording_lines(n_poses: int, rec=None) -> NDArray:
    """CSV line number of every pose (header = line 1, pose ``i`` on line ``i + 2``).

    A recording that knows its own line numbers (attribute ``lines``) is
    asked; bayescal's reader keeps one row per line with no blank or comment
    lines between them, so pose ``i`` (0-based) is line ``i + 2``.
    """
    lines = getattr(rec, "lines", None) if rec is not None else None
    if lines is not None and len(lines) == n_poses:
        return np.asarray(lines, dtype=int)
    return np.arange(n_poses, dtype=int) + 2


@dataclass(frozen=True)
class PoseTest:
    """The outlier test of every pose of a fit.

    Attributes
    ----------
    statistic : ndarray, shape (n_poses,)
        ``t_i`` (chi-square scale, ``distribution == "chi2"``) or ``F_i``
        (``"F"``), see the module docstring.
    p_value : ndarray, shape (n_poses,)
        Single-pose p-values.
    p_adjusted : ndarray, shape (n_poses,)
        Sidak-adjusted over the poses (family-wise).
    cooks_distance : ndarray, shape (n_poses,)
    leverage : ndarray, shape (n_poses,)
        Trace of the pose's block of the hat matrix (effective parameters it determines).
    weight : ndarray, shape (n_poses,)
        The robust weight of each pose in the fit (ones for an unweighted fit).
    flagged : ndarray of bool, shape (n_poses,)
        ``p_adjusted < alpha``.
    lines : ndarray of int, shape (n_poses,)
        CSV line of every pose.
    distribution : str
        ``"chi2"`` or ``"F"``.
    dof : tuple of float
        Degrees of freedom of the reference distribution.
    alpha : float
    scale : float
        Noise scale ``s^2`` the statistic was divided by (1 when the
        instrument sigma is taken as given).
    """

    statistic: NDArray
    p_value: NDArray
    p_adjusted: NDArray
    cooks_distance: NDArray
    leverage: NDArray
    weight: NDArray
    flagged: NDArray
    lines: NDArray
    distribution: str
    dof: tuple
    alpha: float
    scale: float = 1.0

    @property
    def n_poses(self) -> int:
        return self.statistic.shape[0]

    @property
    def too_many(self) -> bool:
        """More poses flagged than :data:`MAX_FRACTION` of the recording: a model mismatch, not a few outliers."""
        return bool(np.sum(self.flagged) > MAX_FRACTION * self.n_poses)

    @property
    def flagged_index(self) -> NDArray:
        """0-based pose indices of the outliers, most significant first."""
        idx = np.flatnonzero(self.flagged)
        return idx[np.argsort(self.p_value[idx], kind="stable")]

    def outliers(self) -> list[dict]:
        """docs/formats.md section 4: ``[{"line", "statistic", "p_value"}, ...]`` (``p_value`` family-wise), in line order."""
        idx = np.sort(np.flatnonzero(self.flagged))
        return [
            {"line": int(self.lines[i]), "statistic": float(self.statistic[i]), "p_value": float(self.p_adjusted[i]),
             "p_value_single": float(self.p_value[i]), "cooks_distance": float(self.cooks_distance[i]),
             "weight": float(self.weight[i])}
            for i in idx
        ]

    def describe(self) -> str:
        """The test in words, for reports and the JSON answer."""
        ref = f"chi2({self.dof[0]:g})" if self.distribution == "chi2" else f"F({self.dof[0]:g}, {self.dof[1]:.4g})"
        scale = "" if self.scale == 1.0 else f", residuals scaled by s^2 = {self.scale:.3g}"
        return (
            f"studentised deleted residual per pose against {ref}{scale}, Sidak-adjusted over {self.n_poses} poses, "
            f"family-wise alpha = {self.alpha:g}"
        )

    def to_dict(self) -> dict:
        """Every pose's values (for reports and figures)."""
        return {
            "test": self.describe(),
            "distribution": self.distribution,
            "dof": list(self.dof),
            "alpha": self.alpha,
            "scale": self.scale,
            "line": self.lines,
            "statistic": self.statistic,
            "p_value": self.p_value,
            "p_adjusted": self.p_adjusted,
            "cooks_distance": self.cooks_distance,
            "leverage": self.leverage,
            "weight": self.weight,
        }


def _sidak(p: NDArray, n: int) -> NDArray:
    # 1 - (1 - p)^n without cancellation for small p
    return -np.expm1(n * np.log1p(-np.clip(p, 0.0, 1.0 - 1e-16)))


def pose_test_linear(
    A: NDArray,
    r: NDArray,
    dof: int,
    *,
    lam: float = 0.0,
    k: int | None = None,
    weights: NDArray | None = None,
    noise_known: bool = True,
    scale: str = "given",
    alpha: float = ALPHA,
    lines: NDArray | None = None,
    rcond: float = 1e-10,
) -> PoseTest:
    """Test every pose of a linearised, possibly regularised and weighted fit.

    Parameters
    ----------
    A : ndarray, shape (n_poses * dof, p)
        Whitened (by the instrument sigma, not by the robust weights),
        column-scaled Jacobian of the fitted parameters; rows pose by pose.
    r : ndarray, shape (n_poses * dof,)
        Whitened residual ``W (y - h)`` at the fit.
    dof : int
        Rows per pose.
    lam : float
        Ridge parameter of the fit (0: least squares; 1: MAP).
    k : int, optional
        TSVD: the fit kept the ``k`` best-determined directions (``lam`` ignored).
    weights : ndarray, shape (n_poses,), optional
        Robust weights of the fit (default ones).
    noise_known : bool
        Whether the whitening sigma is the instrument's (chi-square test) or a
        default (leave-one-out scaled F test).
    scale : {"given", "robust"}
        ``"robust"``: divide by ``max(1, median(t) / median(chi2(d)))`` (see
        the module docstring); overrides ``noise_known``.
    alpha : float
        Family-wise level.
    lines : ndarray of int, optional
        CSV lines of the poses (default ``i + 2``).
    rcond : float
        Singular values below ``rcond * s_max`` count as zero (least squares).

    Returns
    -------
    PoseTest
    """
    A = np.asarray(A, dtype=float)
    r = np.asarray(r, dtype=float).reshape(-1)
    N, p = A.shape
    if N % dof or r.shape[0] != N:
        raise InputError(f"pose_test_linear: {N} rows and {r.shape[0]} residuals do not make poses of {dof} rows")
    n = N // dof
    if not 0 < alpha < 1:
        raise InputError(f"alpha: expected a level between 0 and 1, got {alpha!r}")
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float).reshape(n)
    if np.any(w < 0) or not np.all(np.isfinite(w)):
        raise InputError("weights: expected finite values >= 0")
    d = _deletion(A, r, dof, w, lam, k, rcond)
    leverage = np.sum(d.wg, axis=1)
    trH = float(np.sum(leverage))
    # Cook: (x - x_(i))^T C^-1 (x - x_(i)) = w^2 sum_j a_j^2 g_j / (1 - w g_j)^2
    cook_num = np.sum(d.a2 * w[:, None] ** 2 * d.g / (1.0 - d.wg) ** 2, axis=1)
    s2, stat, pval, dist, df = _scaled_test(d, w, dof, trH, scale, noise_known)
    padj = _sidak(pval, n)
    cooks = cook_num / (max(trH, 1e-12) * s2)
    return PoseTest(
        statistic=stat, p_value=pval, p_adjusted=padj, cooks_distance=cooks, leverage=leverage, weight=w,
        flagged=padj < alpha, lines=np.arange(n) + 2 if lines is None else np.asarray(lines, dtype=int),
        distribution=dist, dof=df, alpha=float(alpha), scale=float(s2),
    )


@dataclass(frozen=True)
class _Deletion:
    """Each pose's deleted-residual statistic and what the leverage, Cook and scale terms need of it."""

    t: NDArray  # (n,) deleted residual's squared norm in its covariance (unscaled)
    a2: NDArray  # (n, dof) squared residual in the eigenbasis of G_i
    g: NDArray  # (n, dof) eigenvalues of G_i
    wg: NDArray  # (n, dof) w_i g, clipped below 1
    rp: NDArray  # (n, dof) residual per pose


def _deletion(A: NDArray, r: NDArray, dof: int, w: NDArray, lam: float, k: int | None, rcond: float) -> _Deletion:
    """Leave-one-pose-out terms of the (regularised, weighted) linear fit (see :func:`pose_test_linear`)."""
    n = w.size
    sw = np.repeat(np.sqrt(w), dof)
    # C = V diag(1 / (s^2 + lam)) V^T on the kept directions;  G_i = B_i B_i^T with B = A V / sqrt(s^2 + lam).
    # With a ridge every direction is kept, C = (A^T W A + lam I)^-1 = R^-1 R^-T and B = A R^-1 gives the same
    # G_i from a triangular factor, without the SVD's (rows x parameters) orthogonal factor (bayescal.tallqr)
    R = ridge_factor(A, lam, sw) if k is None and lam > 0 else None
    if R is not None:
        B = A @ solve_triangular(R, np.eye(R.shape[0]))
    else:
        _, s, Vt = np.linalg.svd(A * sw[:, None], full_matrices=False)
        if k is not None:
            keep = np.arange(s.size) < int(k)
            lam = 0.0
        else:
            keep = s > rcond * s[0] if lam == 0 else np.ones(s.size, dtype=bool)
        B = (A @ Vt[keep].T) / np.sqrt(s[keep] ** 2 + lam)
    Bp = B.reshape(n, dof, -1)
    G = Bp @ np.swapaxes(Bp, 1, 2)  # (n, d, d)
    g, Q = np.linalg.eigh(G)
    g = np.clip(g, 0.0, None)
    wg = np.clip(w[:, None] * g, 0.0, 1.0 - 1e-9)  # a pose alone determining a direction: leverage 1
    rp = r.reshape(n, dof)
    a2 = np.einsum("nij,ni->nj", Q, rp) ** 2  # squared residual in the eigenbasis of G_i
    t = np.sum(a2 / ((1.0 + (1.0 - w[:, None]) * g) * (1.0 - wg)), axis=1)
    if k is not None and np.any(~keep):
        # TSVD leaves the dropped directions at nominal: their part of the truth, a priori
        # N(0, I) in tolerance units, is in every residual (truncation bias), so it joins the
        # deleted residual's covariance: Cov(e_i) = I + G_i (I - w_i G_i)^-1 + A_i V_drop V_drop^T A_i^T
        Dp = (A @ Vt[~keep].T).reshape(n, dof, -1)
        inv = np.einsum("nij,nj,nkj->nik", Q, 1.0 / (1.0 - wg), Q)
        e = np.einsum("nij,nj->ni", inv, rp)
        cov = np.eye(dof) + np.einsum("nij,nj,nkj->nik", Q, g / (1.0 - wg), Q) + Dp @ np.swapaxes(Dp, 1, 2)
        t = np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[:, :, None])[:, :, 0])
    return _Deletion(t=t, a2=a2, g=g, wg=wg, rp=rp)


def _scaled_test(d: _Deletion, w: NDArray, dof: int, trH: float, scale: str, noise_known: bool):
    """The noise scale, the statistics, their p-values, the distribution's name and its degrees of freedom."""
    t = d.t
    if scale == "robust":
        s2 = max(1.0, float(np.median(t)) / float(chi2_median(dof)))
        stat = t / s2
        pval = chi2_sf(stat, dof)
        dist, df = "chi2", (float(dof),)
    elif scale != "given":
        raise InputError(f"scale: expected 'given' or 'robust', got {scale!r}")
    elif noise_known:
        s2 = 1.0
        stat = t
        pval = chi2_sf(t, dof)
        dist, df = "chi2", (float(dof),)
    else:
        # leave-one-out noise: weighted RSS of the other poses over its degrees of freedom
        N = d.rp.size
        rss = float(np.sum(w * np.sum(d.rp**2, axis=1)))
        drop = w * np.sum(d.a2 / (1.0 - d.wg), axis=1)  # RSS_w - RSS_w(i) = w r^T (I - w G)^-1 r
        dfd = max(N - trH - dof, 1.0)
        s2_i = np.clip(rss - drop, 1e-300, None) / dfd
        stat = (t / dof) / s2_i
        pval = f_sf(stat, dof, dfd)
        s2 = rss / max(N - trH, 1.0)
        dist, df = "F", (float(dof), float(dfd))
    return s2, stat, pval, dist, df


def pose_test(
    model: MeasurementModel,
    theta: NDArray,
    free: NDArray,
    *,
    lam: float = 0.0,
    k: int | None = None,
    weights: NDArray | None = None,
    col_scale: NDArray | None = None,
    noise_known: bool | None = None,
    scale: str = "given",
    alpha: float = ALPHA,
    lines: NDArray | None = None,
) -> PoseTest:
    """Test every pose of a fit of ``model`` at ``theta`` (see the module docstring).

    Parameters
    ----------
    model : MeasurementModel
        The recording's model with its *instrument* noise (not the robust weights).
    theta : ndarray, shape (P,)
        The fitted errors.
    free : ndarray of bool (P,) or of int
        The fitted parameters.
    lam, k, weights, scale, alpha, lines
        As :func:`pose_test_linear`.
    col_scale : ndarray, shape (P,), optional
        Column scaling of the fit (the prior std for MAP); the machine's tolerances by default.
    noise_known : bool, optional
        Default: whether the machine file gives the instrument sigma.
    """
    from ..identify.gauss_newton import whitened_system

    theta = np.asarray(theta, dtype=float)
    free = np.asarray(free)
    idx = np.flatnonzero(free) if free.dtype == bool else free.astype(int)
    S = (model.machine.tolerance if col_scale is None else np.asarray(col_scale, dtype=float))[idx]
    pred = model.predict(theta)
    if not pred.success.all():
        i = int(np.flatnonzero(~pred.success)[0])
        raise InputError(f"outlier test: pose {i + 1} cannot be solved at the fitted geometry ({pred.poses.message[i]})")
    r, J = whitened_system(model, theta, pred)
    known = bool(model.machine.noise.given) if noise_known is None else bool(noise_known)
    if np.array_equal(idx, np.arange(J.shape[1])):
        J *= S  # every column, in the whitened system's own array (a copy is 173 MB at 100,000 poses)
    else:
        J = J[:, idx] * S
    return pose_test_linear(J, r, model.dof, lam=lam, k=k, weights=weights, noise_known=known,
                       scale=scale, alpha=alpha, lines=lines)


def loss_weights(u: NDArray, dof: int, *, loss: str = "t", nu: float = DEFAULT_NU, s2: float = 1.0) -> NDArray:
    """Per-pose IRLS weights from whitened squared residual norms ``u`` (``dof`` rows per pose)."""
    if loss == "t":
        return (nu + dof) / (nu + u / s2)
    if loss == "huber":
        c = float(np.sqrt(chi2_ppf(HUBER_QUANTILE, dof)))
        norm = np.sqrt(u / s2)
        return np.minimum(1.0, c / np.maximum(norm, 1e-300))
    raise InputError(f"loss: expected one of {', '.join(LOSSES)}, got {loss!r}")


def describe_loss(loss: str, nu: float = DEFAULT_NU) -> str:
    return f"Student-t IRLS, nu={nu:g}" if loss == "t" else f"Huber IRLS, c=chi_{{d}}({HUBER_QUANTILE:g})"


@dataclass(frozen=True)
class Irls:
    """The outcome of :func:`irls_weights`: the fit on the weighted model, the weights, the rounds."""

    result: object
    weights: NDArray
    rounds: int
    converged: bool
    scale: float


def irls_weights(
    model: MeasurementModel,
    fit,
    *,
    loss: str = "t",
    nu: float = DEFAULT_NU,
    noise_known: bool | None = None,
    start: object | None = None,
    max_rounds: int = 30,
    tol: float = 1e-3,
) -> Irls:
    """Iteratively reweighted fit: per-pose weights from the loss, the pose's sigma divided by ``sqrt(w)``.

    Parameters
    ----------
    model : MeasurementModel
        With the instrument's per-pose noise (``row_sigma``); the weights
        scale it.
    fit : callable
        ``fit(weighted_model) -> result`` with ``result.theta`` (P,) and
        ``result.success``: any of bayescal's fits.
    loss : {"t", "huber"}
    nu : float
        Student-t degrees of freedom (> 0).
    noise_known : bool, optional
        Default: whether the machine file gives the instrument sigma; if not,
        the noise scale is estimated with the weights.
    start : result, optional
        A fit of the unweighted model to start from (saves one fit).
    max_rounds : int
    tol : float
        Stop when no weight changes by more than this.

    Returns
    -------
    Irls
    """
    if loss not in LOSSES:
        raise InputError(f"loss: expected one of {', '.join(LOSSES)}, got {loss!r}")
    if not nu > 0:
        raise InputError(f"nu: expected a number > 0, got {nu!r}")
    base = np.array(model.row_sigma, dtype=float)
    known = bool(model.machine.noise.given) if noise_known is None else bool(noise_known)
    n, d = base.shape
    w = np.ones(n)
    res = start if start is not None else fit(model)
    s2, converged, rounds = 1.0, False, 0
    for rounds in range(1, max_rounds + 1):
        report(lambda: f"robust weights: round {rounds} of at most {max_rounds}")
        pred = model.predict(res.theta)
        if not pred.success.all():
            break  # a failed fit: keep the last weights
        u = np.sum((model.residual(pred) / base) ** 2, axis=1)
        if not known:
            if loss == "t":
                s2 = max(float(np.sum(w * u) / (n * d)), 1e-300)
            else:
                s2 = max(float(np.median(u)) / float(chi2_median(d)), 1e-300)
        w_new = loss_weights(u, d, loss=loss, nu=nu, s2=s2)
        change = float(np.max(np.abs(w_new - w)))
        w = w_new
        weighted = model.with_pose_sigma(base / np.sqrt(w)[:, None])
        # a fit that can start anywhere (``warm_start``) starts where the last round ended
        res = fit(weighted, theta0=res.theta) if getattr(fit, "warm_start", False) else fit(weighted)
        if change < tol:
            converged = True
            break
    return Irls(result=res, weights=w, rounds=rounds, converged=converged, scale=s2)
