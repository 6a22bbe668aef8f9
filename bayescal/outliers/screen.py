"""Gross errors are not physics: name the outlying poses and take them out of the diagnosis.

A tracker beam break or a mistyped value makes one pose disagree with every
model of the machine.  Left in, it is a "structured mismatch" the location
tests pin on a pose region and no effect explains ("unexplained").  The
screen runs before anything else: the geometric MAP fit (tolerance prior,
every parameter free, as the diagnosis fits it), the per-pose test of
:func:`bayescal.outliers.pose_test` with the *robust* noise scale
(``s^2 = max(1, median(t) / median(chi2(d)))``: a missing physical effect
raises the residuals of every pose and with them the scale, so it is not
taken for outliers, while a pose far from the rest is), Sidak-adjusted over
the poses.  Flagged poses are excluded by weight: their sigma is multiplied
by :data:`EXCLUDE_FACTOR`, so that they carry no weight in any fit but keep
their place in the measurement order (the order carries the approach
direction and the time the effects read); they are never held-out test
poses of the cross-validation.  The screen is repeated at the refit
without them (at most :data:`MAX_ROUNDS` times) so that one gross pose
cannot hide another, and excluded poses are tested again by their residual
against the fit of the others: one that a gross pose only dragged out of
line (swamping) is released.

Before any effect is fitted the poses are tested against the geometry with
every candidate effect, linearised at the geometric fit
(:func:`retest_with_candidates`): the poses a physical effect explains are
released before the fits that would otherwise be made twice.  A diagnosis
asks them right after the screen's first round (:func:`first_round`), at
that round's fit: where they release every pose it flagged, the later rounds
never run (:func:`complete_screen` runs them when they are wanted).  When the
diagnosis selects effects, the poses are tested again against the final
model (:func:`retest_with_effects`); if that names other poses, the
diagnosis is run once more with those excluded (a warm-up's first poses are
physics, not outliers, and a gross pose the geometric misfit hid is found);
when it selects none, the geometric screen was the right one and a screen
from the candidates gives way to it.
The screen keeps every round's geometric fit (:attr:`OutlierScreen.fits`):
a retest that names the poses of one of its rounds hands that fit on as the
rerun's first.

If more than :data:`MAX_FRACTION` of the poses would be flagged, the most
outlying of them alone is taken out and the screen looks again (at most
:data:`MAX_STEPS` times): one gross pose can drag the fit so far that a
tenth of the others stand out with it. If the many remain, the mismatch is
not a few bad poses but structure: nothing is excluded and the diagnosis
proceeds on every pose (the answer says so).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ..effects.model import COARSE_START_POSES, fit_map, joint_system
from ..errors import InputError, KinematicsError
from ..measurement import MeasurementModel
from ..tallqr import ridge_solution
from .stats import (
    ALPHA,
    EXCLUDE_FACTOR,
    MAX_FRACTION,
    PoseTest,
    exclusion_weights,
    pose_test,
    pose_test_linear,
    weighted_model,
)

__all__ = ["OutlierScreen", "screen_outliers", "first_round", "complete_screen", "retest_with_candidates",
           "retest_with_effects", "retest_with_discrepancy", "EXCLUDE_FACTOR", "MAX_FRACTION"]

MAX_ROUNDS = 3
#: Poses taken out one at a time when too many stand out at once (a gross pose swamping the fit).
MAX_STEPS = 3
_EXCLUDED = "excluded from every fit, the location tests and the cross-validation (kept in the measurement order)"


@dataclass(frozen=True)
class OutlierScreen:
    """Outlying poses of a recording, and what the diagnosis did with them.

    Attributes
    ----------
    test : PoseTest
        The last round's test (robust scale).
    excluded : ndarray of bool, shape (n_poses,)
        Poses taken out of the fits.
    action : str
        What was done (the answer's ``outlier_handling``).
    fit : EffectFit or None
        The geometric MAP fit of the weighted model (the diagnosis's first
        fit), when the screen ended on it or had fitted it in an earlier round
        (a retest that names the poses of an earlier round); None otherwise.
    fits : tuple of (ndarray of bool, EffectFit)
        Every geometric fit the screen made, with the poses it excluded:
        a rerun whose retest names one of these sets starts from that fit
        (it is the fit the rerun would make, bit for bit).
    replaced : OutlierScreen or None
        The geometric screen this one replaced (:func:`retest_with_candidates`): where a diagnosis that
        selects no effect returns, its final model being the geometry alone.  None for any other screen.
        It may be the screen's first round alone (``complete`` False): :func:`complete_screen` finishes it.
    complete : bool
        False for the first round alone (:func:`first_round`): its test's flagged poses are not excluded yet,
        and the later rounds are still to run (:func:`complete_screen`).
    """

    test: PoseTest
    excluded: NDArray
    action: str
    fit: object = None
    fits: tuple = ()
    replaced: object = None
    complete: bool = True

    def fit_for(self, excluded: NDArray):
        """The geometric fit this screen made with exactly ``excluded`` poses out, or None."""
        for mask, fit in self.fits:
            if np.array_equal(mask, excluded):
                return fit
        return None

    @property
    def weights(self) -> NDArray:
        """Per-pose weights of the fits: ``EXCLUDE_FACTOR**-2`` for an excluded pose, else 1."""
        return exclusion_weights(self.excluded)

    def weighted_model(self, model: MeasurementModel) -> MeasurementModel:
        """``model`` with the excluded poses' sigma multiplied by :data:`EXCLUDE_FACTOR`."""
        return weighted_model(model, self.weights if self.excluded.any() else None)

    def outliers(self) -> list[dict]:
        """docs/formats.md section 4 entries of the excluded poses (line order)."""
        t = self.test
        return [
            {"line": int(t.lines[i]), "statistic": float(t.statistic[i]), "p_value": float(t.p_adjusted[i]),
             "p_value_single": float(t.p_value[i])}
            for i in np.flatnonzero(self.excluded)
        ]

    def to_dict(self) -> dict:
        test = {**self.test.to_dict(), "excluded": self.excluded}
        return {"outliers": self.outliers(), "outlier_handling": self.action, "outlier_test": test}

    def report(self) -> str:
        out = self.outliers()
        if not out:
            return f"outliers: none ({self.action})"
        rows = "; ".join(f"line {o['line']} (statistic {o['statistic']:.4g}, p = {o['p_value']:.3g})" for o in out)
        return f"outliers: {len(out)} pose(s) no model explains, {self.action}: {rows}"


#: Poses from which a round of the screen starts its fit from the round before's converged one (a few poses out
#: of many move the optimum little: at 100,000 poses the second round's fit took 2 iterations, 5.0 s of CPU,
#: against 6.4 s from the nominal geometry); below, every round's fit starts from the nominal geometry, as it
#: always did.  The large-recording threshold of the effect fits (:data:`bayescal.effects.model.COARSE_START_POSES`).
WARM_ROUNDS_POSES = COARSE_START_POSES


def screen_outliers(model: MeasurementModel, *, lines: NDArray | None = None, alpha: float = ALPHA,
                    first: OutlierScreen | None = None) -> OutlierScreen:
    """Find gross-error poses before the diagnosis (see the module docstring).

    Parameters
    ----------
    model : MeasurementModel
        The recording with its instrument noise.
    lines : ndarray of int, optional
        CSV line of every pose (default ``i + 2``).
    alpha : float
        Family-wise level over the poses.
    first : OutlierScreen, optional
        The first round, made already by :func:`first_round` on the same ``model``, ``lines`` and ``alpha``:
        the screen goes on from it (the answer is the one without it, bit for bit).

    Returns
    -------
    OutlierScreen
    """
    n = model.n_poses
    if first is not None and first.excluded.size != n:
        raise InputError(f"first: a first round of {first.excluded.size} poses; expected one of this recording's {n} "
                         "(first_round on the same model)")
    excluded = np.zeros(n, dtype=bool)
    test = fit = None
    stepped = 0
    fits = []  # every round's fit with the poses it left out (OutlierScreen.fits)
    for _ in range(MAX_ROUNDS + MAX_STEPS):
        if first is not None and not fits:
            fit, test = first.fit, first.test
        else:
            start = fits[-1][1].theta if fits and n >= WARM_ROUNDS_POSES and fits[-1][1].success else None
            fit, test = _round(model, excluded, start, lines, alpha)
        fits.append((excluded.copy(), fit))
        # an excluded pose is tested by its residual against the fit of the others, so it stays out only
        # while that still flags it: a gross reading that dragged the first fit makes innocent poses
        # stand out there (swamping; a few parameters seen by few rows, as distances on a delta), and
        # they are released once it is out
        new = test.flagged.copy()
        if test.too_many:
            # Too many to be a few bad poses, or one gross pose (0.5 mm among 5 um readings) that
            # dragged the fit so far that a tenth of the others stand out with it. Take out the
            # most outlying flagged pose alone and look again (sequential deletion); if the many
            # remain, it is structure and nothing is excluded.
            cand = np.flatnonzero(new & ~excluded)
            if stepped < MAX_STEPS and cand.size:
                excluded = excluded.copy()
                excluded[cand[np.argmax(test.statistic[cand])]] = True
                stepped += 1
                fit = None
                continue
            none = OutlierScreen(test, np.zeros(n, dtype=bool), "", fits=tuple(fits))
            return replace(none, fit=none.fit_for(none.excluded),
                           action=f"none excluded: {int(new.sum())} of {n} poses stand out, more than "
                           f"{MAX_FRACTION:.0%}; that is structure, not a few bad poses")
        if np.array_equal(new, excluded):
            break
        excluded, fit = new, None
    if excluded.any():
        action = _EXCLUDED
    else:
        action = "no pose flagged; every pose used"
    return OutlierScreen(test=test, excluded=excluded, action=action, fit=fit, fits=tuple(fits))


def _round(model: MeasurementModel, excluded: NDArray, start, lines, alpha: float):
    """One round of the screen: the geometric MAP fit with ``excluded`` poses out (from ``start``) and its test."""
    weights = exclusion_weights(excluded)
    fit = fit_map(weighted_model(model, weights if excluded.any() else None), theta0=start)
    free = np.ones(model.n_params, dtype=bool)
    test = pose_test(model, fit.theta, free, lam=1.0, weights=weights, scale="robust", alpha=alpha, lines=lines)
    return fit, test


def first_round(model: MeasurementModel, *, lines: NDArray | None = None, alpha: float = ALPHA) -> OutlierScreen:
    """The screen's first round alone: the geometric fit of every pose and its test, nothing excluded yet.

    A diagnosis asks the candidate effects about the poses this round flags before the screen's later
    rounds refit without them (docs/outliers.md, "In the diagnosis"): where the candidates explain them
    all, those rounds are never needed.  :func:`complete_screen` finishes it into :func:`screen_outliers`'s
    answer.

    Parameters
    ----------
    model : MeasurementModel
        The recording with its instrument noise.
    lines : ndarray of int, optional
        CSV line of every pose (default ``i + 2``).
    alpha : float
        Family-wise level over the poses.

    Returns
    -------
    OutlierScreen
        ``excluded`` all False, ``complete`` False (``test.flagged`` holds the poses the round flagged), ``fit``
        the round's fit.
    """
    none = np.zeros(model.n_poses, dtype=bool)
    fit, test = _round(model, none, None, lines, alpha)
    return OutlierScreen(test=test, excluded=none, action="first round of the screen", fit=fit,
                         fits=((none.copy(), fit),), complete=False)


def complete_screen(model: MeasurementModel, screen: OutlierScreen, *, alpha: float = ALPHA) -> OutlierScreen:
    """The complete screen: ``screen`` itself when complete, else a first round finished by the later rounds.

    Parameters
    ----------
    model : MeasurementModel
        The recording :func:`first_round` screened (with its instrument noise).
    screen : OutlierScreen
        A complete screen, or a first round (``complete`` False).
    alpha : float
        Family-wise level over the poses (the first round's).

    Returns
    -------
    OutlierScreen
        :func:`screen_outliers`'s answer on ``model`` (bit for bit), the CSV lines those of the first round.

    Raises
    ------
    InputError
        ``screen`` screened a recording with another number of poses than ``model``.
    """
    if screen.complete:
        return screen
    return screen_outliers(model, lines=screen.test.lines, alpha=alpha, first=screen)


def retest_with_candidates(model: MeasurementModel, effects, theta: NDArray, screen: OutlierScreen, *,
                           alpha: float = ALPHA, keep_same: bool = False) -> OutlierScreen | None:
    """Test every pose against the geometry with every candidate effect, linearised at the geometric fit.

    The screen judged the poses by the geometric model alone, and the
    diagnosis judges them again against its final model
    (:func:`retest_with_effects`), running once more when that names other
    poses: at 100,000 poses that second pass cost 44 s of CPU (its fits), for
    one pose the geometric misfit's tail had flagged.  Judged first against
    the richest model the diagnosis considers, before any effect is fitted,
    a pose a physical effect explains is released while releasing it costs
    only the screen's features again.  The design is the joint fit's at the
    geometric fit and every candidate's start values (prior ``N(0, 1)`` per
    prior std about that point, ridge ``lam = 1``), the residual that of its
    linear fit there: a Gauss-Newton step whose prior is centred at that
    point (the joint fit's step would also pull the geometry and the effects
    towards their prior means; at the geometric MAP that pull is of the order
    of the prior's share of the fit, small where the poses outnumber the
    parameters).  The final model still
    judges the poses: this spares the second pass only where the two agree.

    Parameters
    ----------
    model : MeasurementModel
        The recording with its instrument noise (not the exclusion weights).
    effects : list of (Effect, Features)
        The candidate effects.
    theta : ndarray, shape (P,)
        The geometric fit (mm, rad).
    screen : OutlierScreen
        The geometric screen, or its first round alone (:func:`first_round`; nothing excluded yet).
    keep_same : bool
        Return the new screen even when it names the screen's poses.

    Returns
    -------
    OutlierScreen or None
        The screen to diagnose with (its :attr:`~OutlierScreen.replaced` is ``screen``), or None when it
        names the same poses (unless ``keep_same``), when too many stand out, or when a candidate cannot be
        evaluated, or differentiated, at its start values.
    """
    if not effects:
        return None
    eta = np.array([p.start_value for e, f in effects for p in e.params(model.machine, f)], dtype=float)
    try:
        A, r = joint_system(model, effects, theta, eta)
    except (KinematicsError, InputError):
        return None
    if not (np.isfinite(A).all() and np.isfinite(r).all()):  # a candidate without a derivative at its start
        return None
    # the residual of the linearised fit (every candidate with the geometry, ridge about this point, the screen's
    # weights): the test's deletion formulas take the residual at the fit, not at its start
    sw = np.repeat(np.sqrt(screen.weights), model.dof)
    r = r - A @ ridge_solution(A, r, 1.0, sw)
    names = ", ".join(e.name for e, _ in effects)
    return _retest(model, A, r, screen, alpha=alpha,
                   judged=f"judged against the geometry with every candidate effect ({names}) linearised at the "
                   "geometric fit", released="the geometric model's misfit alone had flagged some", replaced=screen,
                   keep_same=keep_same)


def retest_with_effects(
    model: MeasurementModel,
    effects,
    fit,
    screen: OutlierScreen,
    *,
    alpha: float = ALPHA,
    keep_same: bool = False,
) -> OutlierScreen | None:
    """Test every pose against the diagnosis's final model (geometry and the selected effects).

    The screen judges the poses by the geometric model alone, whose misfit on
    a recording with physics has tails (the first poses of a warm-up, the
    heaviest payloads) that can pass for outliers, and whose inflated scale
    can hide a gross pose.  Against the final model the yardstick is right:
    this returns the screen the diagnosis should have used, or None when it
    is the one it used.

    Parameters
    ----------
    model : MeasurementModel
        The recording with its instrument noise (not the exclusion weights).
    effects : list of (Effect, Features)
        The selected effects.
    fit : EffectFit
        The final joint fit (on the weighted model).
    screen : OutlierScreen
        The screen the diagnosis used.
    keep_same : bool
        Return the new screen (this test, its action) even when it names the screen's poses.
    """
    if not effects:
        return None
    # the joint fit's own system (geometry, then each effect through dq, dx and the bending of sensor bodies)
    A, r = joint_system(model, effects, fit.theta, fit.eta)
    return _retest(model, A, r, screen, alpha=alpha,
                   judged="judged against the geometry with " + ", ".join(e.name for e, _ in effects),
                   released="the geometric model's misfit alone had flagged some", keep_same=keep_same)


def retest_with_discrepancy(model: MeasurementModel, theta, fitted, screen: OutlierScreen, *,
                            alpha: float = ALPHA) -> OutlierScreen | None:
    """Test every pose against the final model with its discrepancy; the screen to use, or None if unchanged.

    A pose whose residual the discrepancy explains (the most bent poses of a
    machine that bends) is physics, not a gross error: against the geometry
    alone it stood out, against the model with the discrepancy it does not,
    and it is released.  The design is the joint fit's: the geometry's
    columns scaled by its prior std, the discrepancy's features (prior
    ``N(0, I)``), ridge ``lam = 1``.

    Parameters
    ----------
    model : MeasurementModel
        The final model's recording (effects applied) with its instrument noise, not the exclusion weights.
    theta : ndarray, shape (P,)
        The geometry of the joint fit.
    fitted : DiscrepancyFit
    screen : OutlierScreen
    """
    from ..discrepancy.fit import joint_design

    try:
        A, r = joint_design(model, theta, fitted, np.asarray(model.machine.tolerance)[fitted.free])
    except InputError:
        return None
    return _retest(model, A, r, screen, alpha=alpha, judged="judged against the final model with its discrepancy",
                   released="the model without it had flagged some: physics, not gross errors")


def _retest(model: MeasurementModel, A: NDArray, r: NDArray, screen: OutlierScreen, *, alpha: float, judged: str,
            released: str, replaced: OutlierScreen | None = None, keep_same: bool = False) -> OutlierScreen | None:
    """The screen's test redone on a final model's linear system ``A x ~ r``; the new screen, or None if unchanged
    (with ``keep_same``, the new screen whatever it names; None still when too many stand out).

    ``A`` (rows, parameters) is whitened and scaled by the prior std, ``r`` the whitened residual; ridge
    ``lam = 1`` (the prior), the screen's exclusion weights, the robust scale.  More flagged poses than
    :data:`MAX_FRACTION` is structure the final model misses, not outliers: the screen stands.
    """
    test = pose_test_linear(A, r, model.dof, lam=1.0, weights=screen.weights, scale="robust", alpha=alpha,
                            lines=screen.test.lines)
    flagged = test.flagged
    if test.too_many or (np.array_equal(flagged, screen.excluded) and not keep_same):
        return None
    if flagged.any():
        action = f"{_EXCLUDED}; {judged}"
    else:
        action = f"no pose flagged, {judged} ({released}); every pose used"
    # the geometric fit with these poses out, when the screen made it: the rerun's first fit, as it would make it
    return OutlierScreen(test=test, excluded=flagged.copy(), action=action, fit=screen.fit_for(flagged),
                         fits=screen.fits, replaced=replaced)
