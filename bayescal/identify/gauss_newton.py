"""Iterated (Gauss-Newton) identification with LS, ridge or TSVD steps.

Each iteration linearises ``h`` at the current ``theta`` and solves the
linearised problem for the *total* deviation from nominal,

    A phi ~ z,   A = W J S,   z = W (y - h(theta)) + A phi_current,

where ``W`` whitens the rows (divides by the instrument sigma) and ``S``
scales the columns by the parameter tolerances (``theta = S phi``).  With
LS this is plain Gauss-Newton.  With ridge the fixed point minimises
``|W (y - h)|^2 + lam |phi|^2``: Tikhonov regularisation towards nominal,
the MAP estimate under the tolerance prior when ``lam = 1``.  With TSVD the
solution is restricted to the ``k`` best-determined directions ``V_k`` of
``A`` at the start geometry, and Gauss-Newton runs on the coordinates in
that fixed subspace.  (The seed applies its filters to the increment
instead; on the total deviation the regularised solution does not depend on
the number of iterations, and a fixed TSVD subspace cannot flip between
nearly equal singular values from one iteration to the next.)

Ridge and MAP take a step only where it does not raise the cost their fixed
point minimises, ``|W (y - h)|^2 + lam |phi - c|^2`` with ``c`` the prior
mean (halved otherwise): a model whose prediction is a product of
unknowns (an effect's compliance times a link mass,
:mod:`bayescal.effects.joint_model`) makes full steps overshoot, and
accepting every one cycled without converging.  LS and TSVD take every
step that can be evaluated (docs/architecture.md says why).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..constants import DETERMINISTIC_METHODS
from ..contract import whiten
from ..errors import ConvergenceWarning, InputError, KinematicsError
from ..limits import check_fit_memory, check_lam
from ..identifiability import STRUCTURAL_RTOL, analyse_identifiability, priority_order
from ..iteration import Proposal, Refused, StepControl, gauss_newton
from ..measurement import MeasurementModel
from .free import Free, bound_arrays, bounds_of, check_name, held_index, held_names
from .result import IdentificationResult
from .solvers import LS_RCOND, filtered_solve

__all__ = ["identify", "resolve_free", "whitened_system", "posterior_covariance", "data_determined", "determined_at"]


def whitened_system(model: MeasurementModel, theta: NDArray, prediction, columns: NDArray | None = None
                    ) -> tuple[NDArray, NDArray]:
    """Whitened residual ``W (y - h)`` (N,) and Jacobian ``W J`` (N, P) at ``theta``.

    ``columns`` (increasing indices): only those columns of ``W J`` (N, len(columns)), the same values
    and layout as the whole one's ``J[:, columns]``; a model that can compute them alone
    (:meth:`MeasurementModel.jacobian_columns`) does.
    """
    r = whiten(model, model.residual(prediction)).reshape(-1)
    if columns is None:
        J = whiten(model, model.jacobian(theta, prediction)).reshape(-1, model.n_params)
    else:
        own = getattr(model, "jacobian_columns", None)
        Jc = own(theta, prediction, columns) if own is not None else model.jacobian(theta, prediction)[:, :, columns]
        # laid out as the whole one's J[:, columns] is (numpy's fancy indexing gives Fortran order): the SVD and
        # the products of a solve take other paths, with other round-off, on the other layout
        J = np.array(whiten(model, Jc).reshape(-1, len(columns)), order="F")
    return r, J


def resolve_free(model: MeasurementModel, free, theta0: NDArray, *, prior: bool = False, system=None):
    """Indices of the parameters to identify, and the identifiability analysis if automatic.

    Parameters
    ----------
    model : MeasurementModel
    free : "auto", "all", None (= "auto"), a sequence of names or indices, or a :class:`~bayescal.identify.free.Free`
        (one of those less the names it holds fixed: with "auto" the identifiable set is chosen among the rest)
    theta0 : ndarray, shape (P,)
        Where the identifiability is analysed.
    prior : bool
        Whether the estimator has a prior that decides the directions the
        data do not see (MAP, ridge with ``lam > 0``, TSVD in the
        tolerance-scaled metric, the Kalman filter).  With ``prior`` and
        ``"auto"`` only the parameters the measurement does not see at all
        are fixed; the others are estimated and the prior decides their
        confounded combinations (:meth:`Identifiability.with_prior` says
        why).  Without, ``"auto"`` fixes enough parameters at ``theta0``
        for least squares to be well posed, nuisance parameters (ballbar
        pivots, a fitted instrument frame) kept in preference.
    system : (Prediction, ndarray, ndarray), optional
        ``model.predict(theta0)`` and its :func:`whitened_system`, when the
        caller has them (``identify`` starts from the same point).

    Returns
    -------
    (ndarray of int, Identifiability or None)
    """
    layout = model.machine.layout
    held = np.zeros(0, dtype=int)
    if isinstance(free, Free):
        held, free = held_index(layout, free.fix), free.base
    if free is None or (isinstance(free, str) and free == "auto"):
        if system is not None:
            J = system[2]
        else:
            pred = model.predict(theta0)
            _, J = whitened_system(model, theta0, pred) if model.y_measured is not None else (None, None)
        if J is None:
            J = whiten(model, model.jacobian(theta0, pred)).reshape(-1, model.n_params)
        geometry = model.machine.geometry_part[1]
        nuisance = np.setdiff1d(np.arange(len(layout)), geometry)
        order = priority_order(model.machine.tolerance, layout.units, nuisance=nuisance)
        # parameters held fixed are no candidates: the identifiable set is chosen among the others
        ida = analyse_identifiability(J, layout, candidates=order[~np.isin(order, held)])
        if prior:
            ida = ida.with_prior(layout.names)
        ida = ida.holding(held, layout.names)
        if ida.kept_index.size == 0:
            raise InputError("free: no parameter left to identify (every parameter the measurement sees is fixed)")
        return ida.kept_index, ida
    if isinstance(free, str) and free == "all":
        idx = np.setdiff1d(np.arange(len(layout)), held)
    else:
        for f in free:
            if isinstance(f, str):
                check_name(layout, f, "free")
        idx = np.array([layout.index(f) if isinstance(f, str) else int(f) for f in free], dtype=int)
        if np.unique(idx).size != idx.size:
            raise InputError("free: parameters listed twice")
        if np.isin(idx, held).any():
            both = [layout.names[j] for j in idx[np.isin(idx, held)]]
            raise InputError(f"fix: {', '.join(both)} also listed in free; expected each parameter in one of them")
    if idx.size == 0:
        raise InputError("free: expected at least one parameter to identify")
    return np.sort(idx), None


def posterior_covariance(final, method: str, *, lam: float | None, noise_var: float = 1.0,
                         ratio: bool = False) -> tuple[NDArray, str]:
    """Covariance of the scaled parameters ``phi = theta / S`` of one linearised solve, and how it was built.

    The thin SVD ``A = U diag(s) V^T`` of the whitened, tolerance-scaled
    matrix spans only the directions the rows see; with fewer measured
    components than parameters (or a gauge) the rest of parameter space is
    ``I - V V^T``.  A method with a prior must keep the prior's variance
    there: dropping it made one pose of the 3-PRS report a sphere-centre std
    of 0.0007 mm against 0.05 mm for the Kalman filter on the same pose.

    * map, ridge (``lam > 0``): the Gaussian posterior ``(A^T A / c + lam I)^-1``
      ``= V diag(1 / (s^2 / c + lam)) V^T + (I - V V^T) / lam``, with ``c``
      the noise variance factor (1 for a stated noise);
    * tsvd: ``c V_k diag(1 / s^2) V_k^T`` in the kept directions plus the
      tolerance prior ``I - V_k V_k^T`` in the truncated ones, which TSVD
      leaves at nominal (their truth is a tolerance-sized unknown);
    * ls, ridge with ``lam = 0``: ``c V diag(1 / s^2) V^T`` (well posed by
      construction: the free set is identifiable).

    Parameters
    ----------
    final : SvdSolve
        The solve at the answer (``V`` of shape (n_free, r)).
    method : {"ls", "ridge", "tsvd", "map"}
    lam : float or None
        Prior precision in tolerance units (1 for map).
    noise_var : float
        Factor on the instrument variance (the reduced chi-square when the
        noise is estimated).
    ratio : bool
        ``lam`` is a noise-to-prior variance ratio (the noise not stated: the
        sigmas are weights and the empirical prior scale sets ``lam``), so the
        whole posterior scales with ``noise_var``: ``c (A^T A + lam I)^-1``.
        Otherwise ``lam`` is the prior precision in tolerance units.

    Returns
    -------
    (ndarray, shape (n_free, n_free), str)
    """
    V, s = final.V, final.s
    n = V.shape[0]
    outside = np.eye(n) - V @ V.T  # projector on what the rows do not see (zero when they see everything)
    if method in ("map", "ridge") and lam and ratio:
        cov = noise_var * ((V / (s**2 + lam)) @ V.T + outside / lam)
        kind = ("Laplace posterior c (A^T A + lam I)^-1 (noise and prior scale estimated together)" if method == "map"
                else "Laplace (ridge as MAP: c (A^T A + lam I)^-1)")
    elif method in ("map", "ridge") and lam:
        cov = (V / (s**2 / noise_var + lam)) @ V.T + outside / lam
        kind = ("Laplace posterior (A^T A + I)^-1 under the tolerance prior" if method == "map"
                else "Laplace (ridge as MAP: (A^T A + lam I)^-1)")
    elif method == "tsvd":
        cov = noise_var * final.covariance() + outside
        kind = "linearised in the kept directions, the tolerance prior in the truncated ones"
    else:
        cov = noise_var * final.covariance()
        kind = "linearised (A^T A)^-1"
    return 0.5 * (cov + cov.T), kind


def _condition(s: NDArray, rtol: float = STRUCTURAL_RTOL) -> float:
    """Largest over smallest singular value above ``rtol`` of the largest (inf when none)."""
    if not s.size or s[0] <= 0:
        return float("inf")
    kept = s[s > rtol * s[0]]
    return float(kept[0] / kept[-1])


def determined_at(model, theta: NDArray, free: NDArray, prediction=None) -> NDArray | None:
    """Which parameters (P,) the data determine alone at ``theta``: free and in the row space (None if not solvable)."""
    pred = model.predict(theta) if prediction is None else prediction
    if not np.all(pred.success):
        return None
    free = np.asarray(free, dtype=bool)
    J = whiten(model, model.jacobian(theta, pred)).reshape(-1, model.n_params)[:, free]
    out = np.zeros(free.size, dtype=bool)
    out[free] = data_determined(J)[0]
    return out


def data_determined(A: NDArray, rtol: float = STRUCTURAL_RTOL, *, svd=None) -> tuple[NDArray, NDArray]:
    """Which columns of ``A`` the rows determine alone, and the singular values of ``A``.

    Column ``i`` is determined when the unit vector ``e_i`` lies in the row
    space of ``A`` (singular values above ``rtol`` times the largest): no
    direction the data do not see moves it.  A parameter of a gauge, or one
    no row sees, is not; under a prior its value is the prior's.

    Parameters
    ----------
    A : ndarray, shape (n_rows, n)
        Whitened identification matrix (column scaling does not change the answer).
    rtol : float
    svd : (ndarray, ndarray), optional
        ``(s, V)`` of ``numpy.linalg.svd(A, full_matrices=False)`` (``V = Vt.T``), when already computed.

    Returns
    -------
    (ndarray of bool, shape (n,), ndarray of float, descending singular values)
    """
    A = np.asarray(A, dtype=float)
    if A.size == 0:
        return np.zeros(A.shape[1], dtype=bool), np.zeros(0)
    if svd is not None:
        s, Vt = svd[0], svd[1].T
    else:
        _, s, Vt = np.linalg.svd(A, full_matrices=False)
    keep = s > rtol * s[0] if s.size and s[0] > 0 else np.zeros(s.size, dtype=bool)
    Vr = Vt[keep].T
    outside = 1.0 - np.sum(Vr**2, axis=1)  # squared length of e_i outside the row space
    return outside < 1e-6, s


def identify(
    model: MeasurementModel,
    *,
    method: str = "ls",
    lam: float | None = None,
    k: int | None = None,
    free: ArrayLike | str | None = None,
    theta0: ArrayLike | None = None,
    scale: ArrayLike | None = None,
    prior_mean: ArrayLike | None = None,
    max_iter: int = 50,
    xtol: float = 1e-8,
) -> IdentificationResult:
    """Identify geometric errors from a measurement model with measured values.

    Parameters
    ----------
    model : MeasurementModel
        With ``y_measured`` (e.g. from :meth:`MeasurementModel.from_recording`).
    method : {"ls", "ridge", "tsvd", "map"}
        Least squares, ridge estimation or truncated SVD (see the module docstring); ``"map"`` is ridge with
        ``lam = 1`` (and the columns scaled by the prior standard deviations ``scale``): the maximum a posteriori
        estimate under the Gaussian prior ``N(prior_mean, diag(scale^2))``, see :mod:`bayescal.bayes.priors`.
    lam : float, optional
        Ridge parameter, dimensionless (relative to the whitened, tolerance-scaled matrix); ``lam = 1`` is the
        MAP estimate under the tolerance prior.  Required for ridge.
    k : int, optional
        Number of singular values TSVD keeps.  Required for tsvd.
    free : sequence of str or int, "auto", "all", None or Free
        Parameters to identify.  ``None``/"auto": for LS (and ridge with ``lam = 0``) the identifiable set found by
        :func:`bayescal.identifiability.analyse_identifiability`, the others staying at ``theta0``; for map, ridge
        and tsvd every parameter the measurement sees, the prior (tolerance scaling) deciding what the data do
        not separate (:func:`resolve_free` with ``prior=True``).  A :class:`~bayescal.identify.free.Free` also
        holds names fixed and carries bounds: the start is moved into them, every step stays inside, and a
        parameter that ends on one is named in ``at_bound``, the others' covariance conditional on it there.
    theta0 : array_like, shape (P,), optional
        Start (and value of fixed parameters); by default the model's ``theta_start`` where it has one
        (:mod:`bayescal.effects.joint_model`), else zeros (nominal).
    scale : array_like, shape (P,), optional
        Column scaling, in parameter units; defaults to the machine's tolerances.  For ridge and MAP this is
        the prior standard deviation.
    prior_mean : array_like, shape (P,), optional
        Where ridge and MAP shrink to (the prior mean); by default the machine's ``prior_mean`` where a view
        states one (effect parameters), else nominal (zeros).
    max_iter : int
        Gauss-Newton iterations at most.
    xtol : float
        Convergence when the largest change of ``theta / scale`` is below this.

    Returns
    -------
    IdentificationResult
        ``success`` is False (with a warning and a message) when LS meets an
        ill-posed matrix, the iteration diverges, or a pose cannot be solved.
    """
    P = model.machine.n_params
    solver, lam = _check_options(model, method, lam, max_iter)
    if prior_mean is None:
        prior_mean = model.machine.prior_mean  # a view's parameters centred elsewhere (effects); None: zero
    box = _box(model, method, free)
    asked = (lam, theta0, scale, prior_mean, max_iter, xtol)  # a refit holding parameters on their bounds asks again
    theta, S_all = _start(model, theta0, scale, box)
    # the start's prediction and linearisation serve the automatic free set and the first step
    pred = _start_prediction(model, theta)
    r, J = whitened_system(model, theta, pred)
    # a prior (ridge, map) or a truncation in the tolerance-scaled metric (tsvd) decides the directions
    # the data do not see, so "auto" leaves them to it instead of fixing parameters (resolve_free)
    idx, ida = resolve_free(model, free, theta, prior=(solver == "ridge" and lam > 0) or solver == "tsvd",
                            system=(pred, r, J))
    _check_size(model, method, solver, lam, k, idx.size)
    S = S_all[idx]
    c, basis = _centre_and_basis(method, k, J, idx, S, prior_mean, P)
    # "before" is the start as asked (nominal), also where the bounds moved the start into the box
    res_before = model.residual(pred) if box is None else _residual_before(model, asked[1], pred)
    it = _iterate(model, method, solver, lam, k, theta, pred, r, J, idx, S, c, basis, max_iter, xtol,
                  box=None if box is None else (box[0][idx], box[1][idx]))
    if box is None:
        return _result(model, method, solver, lam, k, it, idx, S, c, basis, ida, res_before, held_names(free))
    return _bounded_answer(model, method, solver, lam, k, it, idx, S, c, basis, ida, res_before, free, box, asked)


def _bounded_answer(model, method, solver, lam, k, it, idx, S, c, basis, ida, res_before, free, box, asked):
    """:func:`identify`'s answer when bounds were given: the parameters on one out of the estimated set."""
    it, keep, at_bound = _on_bounds(it, idx, S, box)
    res = _result(model, method, solver, lam, k, it, idx[keep], S[keep], c[keep], basis, ida, res_before,
                  held_names(free), at_bound=tuple(model.machine.layout.names[j] for j in at_bound))
    return _held_on_bounds(model, method, k, free, replace(res, bounds=bounds_of(free)), box, ida is not None, asked)


def _residual_before(model, theta0, pred) -> NDArray:
    """Residuals at the start as asked (``theta0``, else the model's own start), before the bounds moved it.

    Falls back to the start inside the bounds (``pred``) when a pose does not solve there.
    """
    theta, _ = _start(model, theta0, None)
    before = model.predict(theta)
    return model.residual(before if before.success.all() else pred)


def _held_on_bounds(model, method: str, k, free, res: IdentificationResult, box, auto: bool, asked):
    """The bounded answer with the parameters on a bound named there, the free set chosen again without them.

    A parameter on its bound is not estimated: with ``free="auto"`` the identifiable set and the combinations
    the prior decides are those of the fit holding it there (a gauge the bound settles is no longer one, and
    least squares may now identify what the bounded parameter hid), so that fit is made, from the start asked,
    holding them (the same point where the set does not change).  A parameter not estimated at all that the
    bounds moved from nominal is named on its bound too, not "fixed at nominal".
    """
    names = model.machine.layout.names
    lo, hi = box
    off = tuple(n for j, n in enumerate(names) if not res.free[j] and n not in res.held and n not in res.at_bound
                and (res.theta[j] == lo[j] or res.theta[j] == hi[j]))
    if not (res.at_bound and auto):
        return replace(res, at_bound=res.at_bound + off, fixed=tuple(n for n in res.fixed if n not in off),
                       unidentifiable=tuple(u for u in res.unidentifiable if u.split(":")[0] not in off))
    on = res.at_bound
    lam, theta0, scale, prior_mean, max_iter, xtol = asked
    hold = Free(free.base, free.fix + on, tuple(b for b in free.bounds if b[0] not in on))
    # from the start asked, not from this answer: least squares' values far from nominal (hundreds of tolerances
    # where the data barely see a direction) are no place to linearise a new free set
    start = _start(model, theta0, None)[0]
    start[[names.index(n) for n in on]] = res.theta[[names.index(n) for n in on]]
    again = identify(model, method=method, lam=lam, k=k, free=hold, theta0=start, scale=scale,
                     prior_mean=prior_mean, max_iter=max_iter, xtol=xtol)
    return replace(again, held=tuple(n for n in again.held if n not in on), at_bound=on + again.at_bound,
                   bounds=res.bounds, rms_before=res.rms_before, residuals_before=res.residuals_before,
                   iterations=res.iterations + again.iterations, history=np.vstack([res.history, again.history[1:]]),
                   cost_history=np.concatenate([res.cost_history, again.cost_history[1:]]))


def _box(model, method: str, free) -> tuple[NDArray, NDArray] | None:
    """The bounds ``free`` carries as (lower, upper) arrays (P,), checked; None without any."""
    bounds = bounds_of(free)
    if not bounds:
        return None
    if method == "tsvd":
        raise InputError("bounds (--bound): tsvd keeps the solution in its k best-determined directions and cannot "
                         "also keep parameters inside bounds; expected method ls, ridge or map (or mcmc)")
    layout = model.machine.layout
    both = sorted(set(held_names(free)) & {b[0] for b in bounds})
    if both:
        raise InputError(f"bounds (--bound): {', '.join(both)} also held fixed (fix, --fix); expected each in one "
                         "of them")
    return bound_arrays(layout, bounds)


def _on_bounds(it: "_Iterated", idx: NDArray, S: NDArray, box) -> tuple["_Iterated", NDArray, NDArray]:
    """The iteration's end with the free parameters on a bound put exactly there, the free ones left, those on one.

    A parameter on a bound is not estimated at the answer: its std and the others' covariance are those
    conditional on it staying there (what a Laplace approximation at a constrained maximum gives).
    """
    lo, hi = box[0][idx], box[1][idx]
    x = it.theta[idx]
    # within 1e-9 tolerances: the bounded solve lands on the bound to round-off of the scaling
    on_lo, on_hi = np.abs(x - lo) <= 1e-9 * S, np.abs(x - hi) <= 1e-9 * S
    theta = it.theta.copy()
    theta[idx] = np.where(on_lo, lo, np.where(on_hi, hi, x))
    keep = ~(on_lo | on_hi)
    return replace(it, theta=theta, J=it.J[:, keep]), keep, idx[~keep]


def _within(sol, c: NDArray, S: NDArray, box, lam: float) -> NDArray:
    """The solve's point ``c + x`` (scaled), or where the bounded solve puts it when that point leaves ``box``."""
    x = c + sol.x
    if box is None or not np.any((x * S < box[0]) | (x * S > box[1])):
        return x
    return c + _bounded_solve(sol, lam, box[0] / S - c, box[1] / S - c)


def _bounded_solve(sol, lam: float, lo: NDArray, hi: NDArray) -> NDArray:
    """``argmin |A y - z|^2 + lam |y|^2`` over ``lo <= y <= hi``, from the SVD of ``A`` the unbounded solve took.

    ``|A y - z|^2 = |diag(s) V^T y - U^T z|^2 + const``: the bounded problem is solved on that small system
    (n_free rows, plus ``sqrt(lam) I`` for a prior) by bounded-variable least squares (Stark and Parker 1995,
    ``scipy.optimize.lsq_linear``), which returns the exact constrained minimiser of this convex problem.
    """
    from scipy.optimize import lsq_linear

    M, b = sol.s[:, None] * sol.V.T, sol.Utz
    if lam:
        M = np.vstack([M, np.sqrt(lam) * np.eye(M.shape[1])])
        b = np.concatenate([b, np.zeros(M.shape[1])])
    return lsq_linear(M, b, bounds=(lo, hi), method="bvls", tol=1e-12).x


def _start_prediction(model, theta: NDArray):
    """The model's prediction at the start; InputError naming the first pose that does not solve there."""
    pred = model.predict(theta)
    if not pred.success.all():
        i = int(np.flatnonzero(~pred.success)[0])
        raise InputError(f"pose {i + 1} (q = {model.q[i].tolist()}): {pred.poses.message[i]} at the start geometry")
    return pred


def _centre_and_basis(method: str, k, J: NDArray, idx: NDArray, S: NDArray, prior_mean, P: int):
    """The prior mean in scaled coordinates ``c`` (ridge/MAP solve for phi = c + x) and TSVD's fixed subspace.

    ``basis`` is V_k in scaled coordinates (None for the other methods).
    """
    c = np.zeros(idx.size) if prior_mean is None else np.asarray(prior_mean, dtype=float).reshape(P)[idx] / S
    basis = None
    if method == "tsvd":
        basis = np.linalg.svd(J[:, idx] * S, full_matrices=False)[2][: int(k)].T
    return c, basis


def _start(model, theta0, scale, box=None) -> tuple[NDArray, NDArray]:
    """The start ``theta`` (P,), inside ``box``, and the column scaling (P,) of :func:`identify`, checked; refused when
    too large."""
    machine = model.machine
    P = machine.n_params
    if theta0 is None:
        # a model may say where its search must start (effect parameters that enter as products: off zero)
        theta0 = model.theta_start
    theta = np.zeros(P) if theta0 is None else np.array(theta0, dtype=float)
    if theta.shape != (P,):
        raise InputError(f"theta0: expected shape ({P},), got {theta.shape}")
    # the Jacobian, its whitened and scaled copies and the SVD's factors (bayescal.limits.FIT_COPIES)
    check_fit_memory(model.n_poses * model.dof, P)
    S_all = machine.tolerance if scale is None else np.asarray(scale, dtype=float).reshape(P)
    if np.any(S_all <= 0):
        raise InputError("scale: expected positive values")
    return (theta if box is None else np.clip(theta, *box)), S_all


def _check_options(model, method: str, lam, max_iter) -> tuple[str, float | None]:
    """The solver a method uses and its lambda, or InputError naming the argument."""
    if model.y_measured is None:
        raise InputError("identify: the measurement model has no measured values")
    if method not in DETERMINISTIC_METHODS:
        raise InputError(f"method: expected 'ls', 'ridge', 'tsvd' or 'map', got {method!r}")
    if method == "map":
        if lam is not None and lam != 1:
            raise InputError(f"lam: map is ridge with lam = 1 (the prior fixes the weight), got {lam!r}")
        lam = 1.0
    # a string or a bool is no lam (np.isfinite raised TypeError on '1' and took True for 1); the range is the one
    # the command line, calibrate and compare accept (limits.LAM_RANGE; an automatic rule searches no further)
    if method == "ridge":
        check_lam(lam)
    if int(max_iter) != max_iter or max_iter < 1:
        raise InputError(f"max_iter (--max-iter): expected a whole number >= 1, got {max_iter!r}")
    return ("ridge" if method == "map" else method), lam


def _check_size(model, method: str, solver: str, lam, k, n_free: int) -> None:
    """InputError when the rows cannot determine ``n_free`` parameters, or ``k`` is out of range."""
    n_rows = model.n_poses * model.dof
    # a prior (map, ridge with lam > 0) makes fewer rows than parameters well posed, and so does
    # TSVD's truncation to k <= n_rows directions (the others stay at the start, in the scaled metric)
    if n_rows < n_free and not (solver == "ridge" and lam > 0) and method != "tsvd":
        raise InputError(
            f"{model.n_poses} poses give {n_rows} measured components for {n_free} parameters; "
            f"expected at least {n_free // model.dof + 1} poses"
        )
    k_max = min(n_free, n_rows)
    if method == "tsvd" and (k is None or int(k) != k or not 1 <= k <= k_max):
        raise InputError(f"k: tsvd needs an integer from 1 to {k_max} (identified parameters, measured components), "
                         f"got {k!r}")


def _result(model, method, solver, lam, k, it: "_Iterated", idx, S, c, basis, ida, res_before,
            held=(), at_bound=()) -> IdentificationResult:
    """The answer at the iteration's end: covariance and singular values from the final linearisation."""
    machine = model.machine
    P = machine.n_params
    theta, pred, r, J = it.theta, it.pred, it.r, it.J
    # final linearisation at the solution, for singular values and covariance (J: the free columns)
    A = J * S
    if basis is None:
        final = filtered_solve(A, r + A @ (theta[idx] / S - c), solver, lam=lam, k=k)
    else:
        sub = filtered_solve(A @ basis, r, "ls")
        final = type(sub)(x=sub.x, s=sub.s, f=sub.f, V=basis @ sub.V, Utz=sub.Utz)
    noise_given = machine.noise.given
    n_rows = model.n_poses * model.dof
    dof_fit = max(n_rows - float(final.f.sum()), 1.0)
    chi2 = float(r @ r)
    # without a stated noise the sigmas are weights: the noise variance is estimated from the fit
    noise_var = 1.0 if noise_given else chi2 / dof_fit
    cov_phi, kind = posterior_covariance(final, method, lam=lam, noise_var=noise_var, ratio=not noise_given)
    cov = cov_phi * np.outer(S, S)
    # the final ridge/LS solve took the SVD of this very A: no second factorisation
    determined, s_data = data_determined(A, svd=(final.s, final.V) if basis is None else None)
    determined_all = np.zeros(P, dtype=bool)
    determined_all[idx] = determined
    if not it.success and it.ill_posed:
        cov = None
    if not it.success:
        warnings.warn(it.message, ConvergenceWarning, stacklevel=3)  # at identify's caller
    res_after = model.residual(pred)
    free_mask = np.zeros(P, dtype=bool)
    free_mask[idx] = True
    return IdentificationResult(
        machine_name=machine.name,
        kind=machine.kind,
        method=method,
        lam=None if method not in ("ridge", "map") else float(lam),
        k=None if method != "tsvd" else int(k),
        names=machine.layout.names,
        units=machine.layout.units,
        theta=theta,
        free=free_mask,
        covariance=cov,
        covariance_kind=kind if noise_given else kind + ", scaled by reduced chi-square",
        rms_before=model.rms(res_before),
        rms_after=model.rms(res_after),
        residuals_before=res_before,
        residuals_after=res_after,
        singular_values=final.s,
        filter_factors=final.f,
        rank=int(np.sum(s_data > STRUCTURAL_RTOL * s_data[0])) if s_data.size and s_data[0] > 0 else 0,
        determined=determined_all,
        condition_number=_condition(s_data),
        iterations=len(it.history) - 1,
        history=np.array(it.history),
        cost_history=np.array(it.costs),
        success=it.success,
        message=it.message,
        fixed=tuple(n for n, f in zip(machine.layout.names, free_mask)
                    if not f and n not in held and n not in at_bound),
        held=tuple(held),
        at_bound=tuple(at_bound),
        unidentifiable=() if ida is None else ida.combinations,
        decided_by_prior=() if ida is None else ida.decided_by_prior,
        dof=model.dof,
        tool_dof=model.tool_dof,
        n_poses=model.n_poses,
        chi2=chi2,
        noise_given=noise_given,
        tolerance=machine.tolerance.copy(),
    )


@dataclass
class _Iterated:
    """Where the Gauss-Newton iteration stopped, and why."""

    theta: NDArray
    pred: object
    r: NDArray
    J: NDArray  # the whitened Jacobian's free columns (N, len(idx))
    history: list
    costs: list
    success: bool
    message: str
    ill_posed: bool


def _iterate(model, method, solver, lam, k, theta, pred, r, J, idx, S, c, basis, max_iter, xtol,
             box=None) -> _Iterated:
    """Gauss-Newton steps of ``method`` in the scaled coordinates ``phi = theta[idx] / S`` until convergence.

    LS and TSVD take every step that can be solved in full, so that the iteration and its fixed point are the filtered
    solve's; a full step of an ill-conditioned problem can leave the assembly (a pose with no solution), and only then
    is it halved (:func:`bayescal.iteration.gauss_newton`). Ridge and MAP (``lam > 0``) measure each step by the cost
    their fixed point minimises, the chi-square plus ``lam |phi - c|^2``, and halve a step that raises it: their fixed
    point is unchanged, and a model bilinear in its unknowns (a bending compliance times a link mass) no longer cycles
    around it (the chi-square alone may rise where the prior pulls, so it cannot be the test).  The stop tests and
    ``cost_history`` stay on the chi-square: where full steps lower the penalised cost, the iteration is the one
    before, to the last bit.

    With ``box`` (the free parameters' lower and upper bounds) a step whose solve leaves the box is solved again with
    the bounds (:func:`_bounded_solve`); a step that stays inside is the unbounded one, bit for bit, and halving keeps
    a step inside (the box is convex and the start inside it).
    """
    machine = model.machine
    phi0 = theta[idx] / S
    last = {}  # the last solve, for the divergence message's condition number
    prior = solver == "ridge" and bool(lam)  # the cost the fixed point minimises has the prior's term

    def penalised(theta_new, state, chi2) -> float:
        d = theta_new[idx] / S - c
        return chi2 + lam * float(d @ d)

    def evaluate(theta_new, state):
        pred_new = model.predict(theta_new, guess=state[0].poses)
        if not pred_new.success.all():
            i = int(np.flatnonzero(~pred_new.success)[0])
            why = pred_new.poses.message[i]
            raise KinematicsError(f"pose {i + 1} cannot be solved at the updated geometry ({why})")
        # only the free columns: the others are never used, and a serial arm's are whole blocks not computed
        r_new, J_new = whitened_system(model, theta_new, pred_new, columns=idx)
        return float(r_new @ r_new), (pred_new, r_new, J_new)

    def propose(theta, state):
        r, J = state[1], state[2]
        A = J * S
        phi = theta[idx] / S
        if basis is None:
            sol = filtered_solve(A, r + A @ (phi - c), solver, lam=lam, k=k)
            sol = type(sol)(x=_within(sol, c, S, box, lam if prior else 0.0), s=sol.s, f=sol.f, V=sol.V, Utz=sol.Utz)
        else:
            # least squares for the coordinates c of phi = phi0 + V_k c
            sub = filtered_solve(A @ basis, r + A @ (phi - phi0), "ls")
            sol = type(sub)(x=phi0 + basis @ sub.x, s=sub.s, f=sub.f, V=basis @ sub.V, Utz=sub.Utz)
        last["s"] = sol.s
        if method == "ls" and sol.s[-1] <= LS_RCOND * sol.s[0]:
            worst = np.argsort(-np.abs(sol.V[:, -1]))[:4]
            names = ", ".join(machine.layout.names[idx[j]] for j in worst)
            raise Refused(
                f"least squares is ill-posed: the identification matrix is rank deficient "
                f"(smallest/largest singular value {sol.s[-1] / sol.s[0]:.1e}); the measurement does not "
                f"separate {names}. Use ridge or tsvd, or let bayescal reduce the parameter set "
                "(free='auto', --free auto)"
            )
        # the full step lands on the solve's point itself; a halving moves S (x - phi) of the way (no round-off
        # of theta + (target - theta) in either)
        target, step = theta.copy(), np.zeros(theta.size)
        target[idx], step[idx] = S * sol.x, S * (sol.x - phi)
        return Proposal(step=step, target=target)

    scale = np.full(theta.size, np.inf)  # fixed parameters never move
    scale[idx] = S
    control = StepControl(descent=prior, bound=1e6, merit=penalised if prior else None)
    out = gauss_newton(theta, (float(r @ r), (pred, r, J[:, idx])), evaluate, propose, control=control,
                       scale=scale, max_iter=max_iter, xtol=xtol, unit="tolerances", failures=(KinematicsError,))
    message = out.message
    if out.reason == "diverged":
        s = last["s"]
        message += (f"; the problem is too ill-conditioned for {method} (condition number "
                    f"{s[0] / max(s[-1], 1e-300):.1e}). Use ridge or tsvd")
    pred, r, J = out.state
    return _Iterated(out.x, pred, r, J, out.history, out.costs, out.success, message, out.reason == "refused")
