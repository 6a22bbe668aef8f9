"""Outliers in identification: test every pose, and refit robustly when the test flags poses.

``robust`` modes (``identify --robust``):

* ``auto`` (default): fit as asked, test every pose
  (:func:`bayescal.outliers.pose_test`); when the test flags any pose, refit
  by Student-t IRLS (``nu = 4``) and test again at the robust fit.  A clean
  recording keeps exactly the fit it had without the option.
* ``t`` / ``huber``: always refit by IRLS with that loss.
* ``off``: fit as asked; flagged poses are reported and kept.

If more than :data:`~bayescal.outliers.MAX_FRACTION` (10 %) of the poses
stand out even in the robust fit, that is a model mismatch (a wrong
instrument frame or unit, unmodelled physics), not a few gross errors: the
unweighted fit is kept, no pose is listed as an outlier, and the answer
says so.

Where the weights come from: the deterministic methods with a fixed
regularisation (ls, ridge with a number, tsvd with a number, map) are
iterated themselves.  Methods whose answer is not one cheap fit (``--lam
auto`` / ``--k auto``, whose rules a gross pose derails; kalman, whose
first poses a gross pose derails; mcmc) get their weights from a robust MAP
pass (MAP under the tolerance prior is well posed whatever the poses); the
method then runs once on the weighted recording, and the poses are tested
at its answer.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..identify.gauss_newton import identify
from ..identify.free import same_free
from ..measurement import MeasurementModel
from .stats import ALPHA, DEFAULT_NU, LOSSES, MAX_FRACTION, PoseTest, describe_loss, irls_weights, pose_test, weighted_model

__all__ = [
    "ROBUST_MODES", "OutlierHandling", "handle_outliers", "identify_with_outliers", "robust_map_weights",
    "robust_map_pass",
    "fit_system", "map_system",
]

ROBUST_MODES = ("auto",) + LOSSES + ("off",)
_NOT_ASSESSED = "not assessed: the fit did not succeed, so its residuals say nothing about single poses"


def fit_system(res) -> dict:
    """The linear system a Gauss-Newton result was solved on: free set, ridge ``lam``, TSVD ``k``."""
    lam = res.lam if res.lam is not None else 0.0
    return {"free": np.asarray(res.free), "lam": float(lam), "k": res.k if res.method == "tsvd" else None}


def map_system(res) -> dict:
    """MAP at the free set of any result (map, kalman, mcmc), under the prior the result was fitted with.

    The tolerance prior (``lam = 1``), times the prior scale ``c`` when the
    result estimated one (``extras["prior_scale"]``, ``identify --method
    map``'s empirical Bayes): the tolerance-scaled system then has
    ``lam = 1 / c^2``.  The pose test must judge the poses by the fit's own
    hat matrix; with ``lam = 1`` it would use a prior the fit did not.
    """
    c = res.extras.get("prior_scale")
    lam = 1.0 if c is None else 1.0 / float(c) ** 2
    return {"free": np.asarray(res.free), "lam": lam, "k": None}


@dataclass(frozen=True)
class OutlierHandling:
    """What the outlier test found and what the fit did with the poses.

    Attributes
    ----------
    test : PoseTest or None
        The test at the answer (with the robust weights, if any); None when
        the fit did not succeed (a failed fit is no yardstick for its poses).
    mode : str
        ``auto``, ``t``, ``huber`` or ``off``.
    action : str
        What the fit did (the answer's ``outlier_handling``).
    weights : ndarray, shape (n_poses,) or None
        Robust weights of the answer (None: none applied).
    screen : PoseTest or None
        The test of the unweighted fit that triggered the refit (``auto``).
    rounds : int
        IRLS rounds.
    structural : bool
        More than :data:`~bayescal.outliers.MAX_FRACTION` of the poses stood
        out even in the robust fit: a model mismatch, not outliers; the
        unweighted fit is kept and no pose is listed as an outlier.
    """

    test: PoseTest | None
    mode: str
    action: str
    weights: NDArray | None = None
    screen: PoseTest | None = None
    rounds: int = 0
    structural: bool = False

    def weighted_model(self, model: MeasurementModel) -> MeasurementModel:
        """``model`` with the robust weights (each pose's sigma divided by ``sqrt(w)``), or itself."""
        return weighted_model(model, self.weights)

    def retested(self, model: MeasurementModel, res, system: dict) -> "OutlierHandling":
        """The same handling, with the test redone at the answer ``res`` of the weighted recording."""
        if not res.success or self.test is None:
            return replace(self, test=None, action=_NOT_ASSESSED)
        t = pose_test(model, res.theta, weights=self.weights, alpha=self.test.alpha, lines=self.test.lines, **system)
        if self.structural:
            return replace(self, test=_unflag(t))
        if t.flagged.any() and self.weights is None and not self.test.flagged.any():
            # the pass that decided the weights flagged none; this answer's test does: say so, not "none flagged"
            return replace(self, test=t, action="kept: flagged by the test at this answer, not by the robust MAP pass "
                                                "that decides the weights; every pose kept at full weight")
        return replace(self, test=t)

    def to_dict(self) -> dict:
        """JSON keys: ``outliers`` (docs/formats.md section 4), ``outlier_handling``, ``outlier_test`` (every pose)."""
        if self.test is None:
            return {"outliers": [], "outlier_handling": self.action, "outlier_test": None}
        return {
            "outliers": self.test.outliers(),
            "outlier_handling": self.action,
            "outlier_test": {**self.test.to_dict(), "mode": self.mode, "irls_rounds": self.rounds,
                             "flagged_before_refit": [] if self.screen is None else [o["line"] for o in self.screen.outliers()]},
        }

    def report(self, *, most_influential: int = 3) -> str:
        t = self.test
        if t is None:
            return f"\n  outliers        {self.action}"
        lines = ["", f"  outliers        {t.describe()}"]
        idx = t.flagged_index
        if idx.size:
            lines.append(f"  {idx.size} pose(s) no model of the machine explains: {self.action}")
            lines.append(f"    {'line':>6} {'statistic':>11} {'p (family)':>11} {'p (single)':>11} {'Cook':>9} {'weight':>8}")
            for i in idx:
                lines.append(
                    f"    {t.lines[i]:>6d} {t.statistic[i]:11.4g} {t.p_adjusted[i]:11.3g} {t.p_value[i]:11.3g} "
                    f"{t.cooks_distance[i]:9.3g} {t.weight[i]:8.3g}"
                )
        elif self.structural:
            lines.append(f"  {self.action}")
        else:
            lines.append(f"  no pose flagged (smallest family-wise p = {float(np.min(t.p_adjusted)):.3g}); {self.action}")
        if self.weights is not None:
            lines.append("    (the chi-square and covariance above are those of the weighted fit; the RMS values use every pose)")
        if self.screen is not None and self.screen.flagged.any():
            lines.append(f"    flagged by the unweighted fit: lines {', '.join(str(o['line']) for o in self.screen.outliers())}")
        top = np.argsort(-t.cooks_distance)[:most_influential]
        lines.append("    most influential poses (Cook's distance): "
                     + ", ".join(f"line {t.lines[i]} ({t.cooks_distance[i]:.3g})" for i in top))
        return "\n".join(lines)


class Refits:
    """The fits of one outlier handling: ``identify`` with the free set resolved once, each refit warm-started.

    Reweighting the poses does not change which directions the rows see, so the identifiability analysis of
    the first fit serves every IRLS round (it was a quarter of the time of a 200-pose robust MAP pass), and
    a round starts where the last ended (``warm_start``: :func:`bayescal.outliers.irls_weights` passes
    ``theta0``), which saves most of its Gauss-Newton iterations.
    """

    def __init__(self, **identify_kw):
        self.kw = identify_kw
        self.first = None
        # TSVD leaves the truncated directions at its start: it starts where the first fit did
        self.warm_start = identify_kw.get("method") != "tsvd"

    def __call__(self, model: MeasurementModel, theta0=None):
        if self.first is None:
            self.first = identify(model, theta0=theta0, **self.kw)
            return self.first
        kw = {**self.kw, "free": same_free(self.first)}
        res = identify(model, theta0=theta0, **kw)
        return replace(res, unidentifiable=self.first.unidentifiable, decided_by_prior=self.first.decided_by_prior)


def _unflag(test: PoseTest) -> PoseTest:
    return replace(test, flagged=np.zeros_like(test.flagged))


def _check(robust: str, loss_nu: float) -> None:
    if robust not in ROBUST_MODES:
        raise InputError(f"robust: expected one of {', '.join(ROBUST_MODES)}, got {robust!r}")
    if not loss_nu > 0:
        raise InputError(f"nu: expected a number > 0, got {loss_nu!r}")


def handle_outliers(
    model: MeasurementModel,
    fit,
    system,
    *,
    robust: str = "auto",
    nu: float = DEFAULT_NU,
    alpha: float = ALPHA,
    lines: NDArray | None = None,
    start=None,
):
    """Fit, test every pose, and refit robustly as ``robust`` says.

    Parameters
    ----------
    model : MeasurementModel
        The recording with its instrument noise.
    fit : callable
        ``fit(model) -> result`` (``theta``, ``free``, ``success``).
    system : callable
        ``system(result) -> dict(free=, lam=, k=)``: the linear system the
        test uses (:func:`fit_system`, :func:`map_system`).
    robust : {"auto", "t", "huber", "off"}
    nu : float
        Student-t degrees of freedom.
    alpha : float
        Family-wise level of the test.
    lines : ndarray of int, optional
        CSV lines of the poses.
    start : result, optional
        The unweighted fit, if already done.

    Returns
    -------
    (result, OutlierHandling)
    """
    _check(robust, nu)
    res0 = fit(model) if start is None else start
    if not res0.success:
        return res0, OutlierHandling(test=None, mode=robust, action=_NOT_ASSESSED)
    test0 = pose_test(model, res0.theta, alpha=alpha, lines=lines, **system(res0))
    if robust == "off":
        action = "kept: no robust refit (--robust off); the fit uses every pose at full weight" if test0.flagged.any() \
            else "none flagged; every pose kept at full weight"
        return res0, OutlierHandling(test=test0, mode=robust, action=action)
    if robust == "auto" and not test0.flagged.any():
        return res0, OutlierHandling(test=test0, mode=robust, action="none flagged; every pose kept at full weight")
    loss = "t" if robust == "auto" else robust
    ir = irls_weights(model, fit, loss=loss, nu=nu, start=res0)
    if not ir.result.success:
        # keep the unweighted answer rather than a failed one, and say so
        action = f"kept: the robust refit ({describe_loss(loss, nu)}) did not succeed ({ir.result.message})"
        return res0, OutlierHandling(test=test0, mode=robust, action=action)
    test1 = pose_test(model, ir.result.theta, weights=ir.weights, alpha=alpha, lines=lines, **system(ir.result))
    if test1.too_many:
        k = int(test1.flagged.sum())
        action = (
            f"none taken as outliers: {k} of {model.n_poses} poses stand out even in the robust fit, more than "
            f"{MAX_FRACTION:.0%}; that is a model mismatch (instrument frame: --frame fit; units; unmodelled physics: "
            "bayescal diagnose), not a few gross errors, so the unweighted fit is kept"
        )
        return res0, OutlierHandling(test=_unflag(test0), mode=robust, action=action, screen=test0, structural=True)
    why = "because the test flagged poses" if robust == "auto" else f"(--robust {robust})"
    rounds = f"{ir.rounds} rounds" + ("" if ir.converged else ", weights not converged")
    action = f"down-weighted ({describe_loss(loss, nu)}, {rounds}) {why}"
    return ir.result, OutlierHandling(test=test1, mode=robust, action=action, weights=ir.weights, screen=test0, rounds=ir.rounds)


def robust_map_weights(model: MeasurementModel, free, *, robust="auto", nu=DEFAULT_NU, alpha=ALPHA, lines=None,
                       max_iter: int = 50) -> OutlierHandling:
    """The handling (weights) of a robust MAP pass, for methods that are not one cheap fit (auto rules, kalman, mcmc)."""
    return robust_map_pass(model, free, robust=robust, nu=nu, alpha=alpha, lines=lines, max_iter=max_iter)[1]


def robust_map_pass(model: MeasurementModel, free, *, robust="auto", nu=DEFAULT_NU, alpha=ALPHA, lines=None,
                    max_iter: int = 50):
    """:func:`robust_map_weights` and the pass's fit: ``(result, OutlierHandling)``.

    Without weights (``handling.weights is None``) the result is the MAP of
    the unweighted ``model`` under the tolerance prior, from the model's
    start: ``identify(model, method="map", free=free, max_iter=max_iter)``.
    """
    fit = Refits(method="map", free=free, max_iter=max_iter)
    res, h = handle_outliers(model, fit, fit_system, robust=robust, nu=nu, alpha=alpha, lines=lines)
    if h.weights is not None:
        h = replace(h, action=h.action.replace("IRLS", "IRLS of a MAP pass"))
    return res, h


def identify_with_outliers(
    model: MeasurementModel,
    *,
    method: str = "map",
    lam: float | None = None,
    k: int | None = None,
    free=None,
    max_iter: int = 50,
    robust: str = "auto",
    nu: float = DEFAULT_NU,
    alpha: float = ALPHA,
    lines: NDArray | None = None,
):
    """:func:`~bayescal.identify.identify` with the outlier test and, as ``robust`` says, IRLS.

    Returns
    -------
    (IdentificationResult, OutlierHandling)
        The result carries the handling's JSON keys in ``extras``.
    """
    fit = Refits(method=method, lam=lam, k=k, free=free, max_iter=max_iter)
    res, h = handle_outliers(model, fit, fit_system, robust=robust, nu=nu, alpha=alpha, lines=lines)
    return replace(res, extras={**res.extras, **h.to_dict()}), h
