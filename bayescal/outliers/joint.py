"""The outlier test of a joint fit (the geometry with a model discrepancy), and the joint fit without the poses it names.

The geometry-only fit judged the poses by a model without the discrepancy,
and a pose the discrepancy explains (the most bent ones) stood out there:
that is physics.  Here every pose is judged against the joint fit (ridge
``lam = 1`` on its design); the poses it flags (a gross error no model
explains) leave the joint fit, which is redone.

The joint fit itself belongs to the calibration
(:mod:`bayescal.identify.calibrate`); it is passed in as two callables, so
that this module and the discrepancy's do not import each other.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from .handling import OutlierHandling
from .stats import ALPHA, exclusion_weights, pose_test_linear, weighted_model

__all__ = ["joint_outlier_handling"]

JUDGED = "judged against the model with its discrepancy"


def joint_outlier_handling(model, theta: NDArray, fit: Any, *,
                           design: Callable[[Any, NDArray, Any], tuple[NDArray, NDArray]],
                           refit: Callable[[Any, NDArray, Any, bool], tuple[NDArray, Any]],
                           robust: str = "auto", alpha: float = ALPHA, lines=None):
    """Judge every pose against a joint fit; refit without the gross ones.

    Parameters
    ----------
    model : Model
        At the noise the joint fit used (full weight on every pose).
    theta : ndarray, shape (P,)
        The joint fit's geometry (mm, rad).
    fit : object
        The joint fit (a :class:`bayescal.discrepancy.DiscrepancyFit`), passed back to the callables.
    design : callable
        ``design(model, theta, fit) -> (A, r)``: the joint fit's whitened, prior-scaled design
        (n_poses * dof, p) and residual rows; may raise InputError (then no test is made).
    refit : callable
        ``refit(model, theta, fit, search) -> (theta, fit)``: the joint fit redone on ``model`` from
        ``theta``, its hyperparameters searched again when ``search`` (poses were left out).
    robust : {"auto", "t", "huber", "off"}
        ``off`` keeps every pose, whatever the test says.
    alpha : float
        Family-wise level of the test.
    lines : ndarray, optional
        CSV line of each pose (named in the answer).

    Returns
    -------
    (OutlierHandling, fit, theta) or None
        The handling, the joint fit and its geometry after the decision; None when the design
        cannot be made (the caller keeps what it had).
    """
    try:
        A, r = design(model, theta, fit)
    except InputError:
        return None
    test = pose_test_linear(A, r, model.dof, lam=1.0, alpha=alpha, lines=lines)
    flagged = test.flagged
    if not flagged.any() or robust == "off" or test.too_many:
        # every pose at full weight: the joint fit again from the robust reference
        theta, fit = refit(model, theta, fit, False)
        A, r = design(model, theta, fit)
        test = pose_test_linear(A, r, model.dof, lam=1.0, alpha=alpha, lines=lines)
        if not test.flagged.any():
            action = f"none flagged, {JUDGED}; every pose kept at full weight"
        else:
            why = "--robust off" if robust == "off" else f"{int(test.flagged.sum())} of {model.n_poses} stand out: structure"
            action = f"kept ({why}), {JUDGED}"
        return OutlierHandling(test=test, mode=robust, action=action), fit, theta
    weights = exclusion_weights(flagged)
    # the hyperparameters again, without the poses no model explains
    theta, fit = refit(weighted_model(model, weights), theta, fit, True)
    A, r = design(model, theta, fit)
    test = pose_test_linear(A, r, model.dof, lam=1.0, weights=weights, alpha=alpha, lines=lines)
    action = f"excluded from the joint fit ({int(np.sum(flagged))} pose(s)), {JUDGED}"
    return OutlierHandling(test=test, mode=robust, action=action, weights=weights), fit, theta
