"""Recursive identification: a Kalman filter over the recording, one update per measured pose.

The state is the vector of identifiable geometric errors ``x`` (the others
stay at the prior mean).  It starts at the prior ``N(mu, diag(s^2))`` and,
pose by pose in measurement order,

* predict: ``x <- x`` (a random walk ``x <- x + w``, ``w ~ N(0, Q)``, when
  the parameters may drift, e.g. with temperature);
* update with pose ``i``: ``z_i = y_i`` (dof rows), ``h_i(x)`` from the
  measurement model restricted to that pose, noise ``R = diag(sigma^2)``.

Two variants, both from filterpy:

* ``"ekf"``: :class:`filterpy.kalman.ExtendedKalmanFilter`, relinearised at
  every update with the model's analytic Jacobian at the current mean;
* ``"ukf"``: :class:`filterpy.kalman.UnscentedKalmanFilter` with
  :class:`~filterpy.kalman.MerweScaledSigmaPoints`; the ``2n + 1`` sigma
  points are evaluated in ONE vectorised call of the model's ``predict``
  (stacked theta), for strongly nonlinear cases.

With ``Q = 0`` and a linear model the result equals the batch MAP solution
``(P0^-1 + A^T R^-1 A)^-1 (P0^-1 x0 + A^T R^-1 z)``; with a nonlinear
model the EKF is one Gauss-Newton pass in information form.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..identify import resolve_free
from ..identify.gauss_newton import determined_at
from ..identify.free import held_names
from .accuracy import evaluation_poses, tool_point_jacobian, workspace_accuracy
from .priors import GaussianPrior, prior_from_machine
from ..identify.result import covariance_dict, decided_by_prior_lines
from ..stats import posterior_effective_params
from .summary import PosteriorMembers, parameter_list, parameter_table, strong_correlations

__all__ = ["FilterResult", "kalman_filter", "MAX_PROCESS_NOISE"]

#: Largest process noise, as a fraction of the prior std per pose step: at 100 the filter forgets every pose
#: at the next, so more is no filter; 1e300 overflowed the state covariance.
MAX_PROCESS_NOISE = 100.0


@dataclass(frozen=True)
class FilterResult(PosteriorMembers):
    """The whole history of a recursive identification.

    Attributes
    ----------
    machine_name, kind : str
    variant : str
        ``"ekf"`` or ``"ukf"``.
    names, units : tuple of str
        All parameters of the machine.
    free : ndarray of bool, shape (P,)
        The filter's state (identifiable set).
    theta : ndarray, shape (P,)
        Final estimate (others at the prior mean).
    means : ndarray, shape (n_poses + 1, n_free)
        State mean before any pose (row 0, the prior) and after each pose.
    covariances : ndarray, shape (n_poses + 1, n_free, n_free)
    workspace_accuracy : ndarray, shape (n_poses + 1,)
        RMS over evaluation poses of the predicted 3-D tool-point std, mm,
        from the state covariance after each pose (linearised at the final
        estimate; the fixed parameters' uncertainty is not included).
    nis : ndarray, shape (n_poses,)
        Normalised innovation squared per pose (about ``dof`` on average
        when the filter is consistent).
    process_noise : ndarray, shape (n_free,)
        Random-walk std per pose step (zeros: static parameters).
    rms_before, rms_after : dict
        Residual RMS of the recording against the prior mean and the final estimate.
    """

    machine_name: str
    kind: str
    variant: str
    names: tuple[str, ...]
    units: tuple[str, ...]
    free: NDArray
    theta: NDArray
    means: NDArray
    covariances: NDArray
    workspace_accuracy: NDArray
    nis: NDArray
    process_noise: NDArray
    rms_before: dict
    rms_after: dict
    dof: int
    success: bool = True
    message: str = ""
    fixed: tuple[str, ...] = ()
    unidentifiable: tuple[str, ...] = ()
    #: Parameters the user held at the prior mean (``fix``), whatever the data see.
    held: tuple[str, ...] = ()
    #: A Gaussian answer keeps no bounds (:func:`bayescal.identify.probabilistic.calibrate_bayes` refuses them).
    bounds: tuple = ()
    at_bound: tuple[str, ...] = ()
    #: Combinations the data do not separate that the prior decides (``free="auto"``: estimated, not fixed).
    decided_by_prior: tuple[str, ...] = ()
    extras: dict = field(default_factory=dict)
    #: Which parameters the data determine alone (:func:`bayescal.identify.gauss_newton.data_determined`).
    determined: NDArray | None = None
    #: the tool's rows per pose (None: ``dof``); ``dof`` adds the body sensors' tilt rows
    tool_dof: int | None = None

    method = "kalman"

    @property
    def n_poses(self) -> int:
        return self.means.shape[0] - 1

    @property
    def prior_effective_params(self) -> float | None:
        """``n - tr(P_prior^-1 P_post)`` of the state before the first pose and after the last (None if singular)."""
        try:
            prior, post = np.asarray(self.covariances[0], dtype=float), np.asarray(self.covariances[-1], dtype=float)
            return posterior_effective_params(prior, post)
        except (AttributeError, KeyError, IndexError, TypeError, ValueError, np.linalg.LinAlgError):
            return None

    @property
    def covariance(self) -> NDArray:
        """Final state covariance (n_free, n_free)."""
        return self.covariances[-1]

    @property
    def stds(self) -> NDArray:
        """Std of each state parameter after each pose, shape (n_poses + 1, n_free)."""
        return np.sqrt(np.clip(np.einsum("kii->ki", self.covariances), 0.0, None))

    @property
    def std(self) -> NDArray:
        out = np.full(self.theta.shape, np.nan)
        out[self.free] = self.stds[-1]
        return out

    @property
    def free_names(self) -> tuple[str, ...]:
        return tuple(n for n, f in zip(self.names, self.free) if f)

    def poses_needed(self, within: float = 0.1) -> int:
        """First pose count after which the workspace accuracy is within ``within`` (relative) of the final one."""
        a = self.workspace_accuracy
        return int(np.flatnonzero(a <= a[-1] * (1 + within))[0])

    def to_dict(self) -> dict:
        return {
            "machine": self.machine_name,
            "kind": self.kind,
            "method": "kalman",
            "variant": self.variant,
            "success": self.success,
            "message": self.message,
            "parameters": parameter_list(self.names, self.units, self.theta, self.std, self.free, self.determined),
            "rms_before": self.rms_before,
            "rms_after": self.rms_after,
            "dof": self.dof if self.tool_dof is None else self.tool_dof,
            "n_poses": self.n_poses,
            "covariance_kind": "Kalman filter state covariance",
            "covariance": covariance_dict(self.names, self.units, self.free, self.covariance),
            "fixed": list(self.fixed),
            "held": list(self.held),
            "unidentifiable": list(self.unidentifiable),
            "decided_by_prior": list(self.decided_by_prior),
            "strong_correlations": [
                {"a": a, "b": b, "correlation": c} for a, b, c in strong_correlations(self.covariance, self.free_names)
            ],
            "history": {
                "std": self.stds,
                "workspace_accuracy_mm": self.workspace_accuracy,
                "nis": self.nis,
            },
            "poses_needed": self.poses_needed(),
            "process_noise": self.process_noise,
            **self.extras,
        }

    def report(self) -> str:
        n = self.n_poses
        a = self.workspace_accuracy
        lines = [
            f"bayescal recursive identification of '{self.machine_name}' ({self.kind})",
            f"  method          kalman ({self.variant.upper()}), one update per pose: {'done' if self.success else 'FAILED'}",
        ]
        if self.message:
            lines.append(f"  message         {self.message}")
        lines += [
            f"  measurement     {self.dof if self.tool_dof is None else self.tool_dof}-DOF"
            f"{'' if self.tool_dof in (None, self.dof) else f' + {(self.dof - self.tool_dof) // 2} body sensor(s)'}, {n} poses, {int(self.free.sum())} parameters in the state",
            f"  process noise   {'none (static parameters)' if not np.any(self.process_noise) else 'random walk, max std per pose %.3g' % self.process_noise.max()}",
            f"  RMS position    {self.rms_before['position']:.6f} mm before, {self.rms_after['position']:.6f} mm after",
            f"  consistency     mean normalised innovation squared {np.mean(self.nis):.3g} (expected {self.dof})",
            "",
            "  predicted workspace accuracy (RMS tool-point std over evaluation poses) after each pose:",
        ]
        steps = sorted(set([0, 1, 2, 5, 10, 15, 20, 30, 40, 60, 80, 100, 150, 200, n]) & set(range(n + 1)))
        lines += [f"    after {k:4d} poses: {a[k]:.5f} mm" for k in steps]
        k = self.poses_needed()
        lines.append(f"  within 10% of the final accuracy after {k} poses: measuring more than that buys little")
        pairs = strong_correlations(self.covariance, self.free_names)
        lines += parameter_table(parameter_list(self.names, self.units, self.theta, self.std, self.free, self.determined), pairs)
        if self.held:
            lines += ["", f"  held at the prior mean (fix): {', '.join(self.held)}"]
        if self.fixed:
            lines += ["", f"  not identifiable from these poses, held at the prior mean: {', '.join(self.fixed)}"]
        lines += decided_by_prior_lines(self.decided_by_prior)
        return "\n".join(lines)


def kalman_filter(
    model,
    *,
    variant: str = "ekf",
    prior: GaussianPrior | None = None,
    free: ArrayLike | str | None = None,
    process_noise: ArrayLike | float = 0.0,
    eval_q: ArrayLike | None = None,
    n_eval: int = 50,
    seed: int = 0,
    alpha: float = 0.5,
) -> FilterResult:
    """Run an extended or unscented Kalman filter over the poses of ``model`` in order.

    Parameters
    ----------
    model : MeasurementModel or LinearisedModel
        With measured values; poses are processed in their stored order.
    variant : {"ekf", "ukf"}
    prior : GaussianPrior, optional
        Initial state; the machine's tolerance prior by default.
    free : "auto", "all" or names, optional
        The state: the identifiable set by default.
    process_noise : float or array_like, shape (n_free,)
        Random-walk std per pose step as a fraction of the prior std
        (scalar or per state parameter); 0 for static parameters.
    eval_q : array_like, shape (n_eval, n_actuators), optional
        Poses for the predicted workspace accuracy; drawn within
        ``q_limits`` (seeded) by default, the recording's poses without limits.
    alpha : float
        Spread of the UKF sigma points (Merwe's alpha; beta = 2, kappa = 0).

    Returns
    -------
    FilterResult
    """
    if variant not in ("ekf", "ukf"):
        raise InputError(f"variant: expected 'ekf' or 'ukf', got {variant!r}")
    if model.y_measured is None:
        raise InputError("kalman_filter: the measurement model has no measured values")
    machine = model.machine
    prior = prior_from_machine(machine) if prior is None else prior
    idx, ida = resolve_free(model, free, prior.mean, prior=True)  # the filter starts from the prior
    qn = _process_noise(process_noise, idx.size) * prior.std[idx]
    run = _run_filter(model, variant, prior, idx, qn, alpha)
    theta = _full_theta(prior.mean.copy(), idx, run.means[-1])
    means, covs = np.array(run.means), np.array(run.covariances)
    free_mask = np.zeros(machine.n_params, dtype=bool)
    free_mask[idx] = True
    q_eval = evaluation_poses(machine, n_eval, seed=seed, fallback=model.q) if eval_q is None else np.asarray(eval_q)
    G = tool_point_jacobian(machine, q_eval, theta, idx)
    before = model.residual(model.predict(prior.mean))
    pred = model.predict(theta)
    after = model.residual(pred) if pred.success.all() else np.full_like(before, np.nan)
    return FilterResult(
        machine_name=machine.name,
        kind=machine.kind,
        variant=variant,
        names=machine.layout.names,
        units=machine.layout.units,
        free=free_mask,
        theta=theta,
        means=means,
        covariances=covs,
        workspace_accuracy=workspace_accuracy(G, covs),
        nis=run.nis,
        process_noise=qn,
        rms_before=model.rms(before),
        rms_after=model.rms(after),
        dof=model.dof,
        tool_dof=model.tool_dof,
        success=run.success,
        message=run.message,
        fixed=tuple(nm for nm, fr in zip(machine.layout.names, free_mask) if not fr and nm not in held_names(free)),
        held=held_names(free),
        unidentifiable=() if ida is None else ida.combinations,
        decided_by_prior=() if ida is None else ida.decided_by_prior,
        determined=determined_at(model, theta, free_mask, pred),
    )


def _process_noise(process_noise, n: int) -> NDArray:
    """The random-walk std per pose step as a fraction of the prior std, one per state parameter (checked)."""
    frac = np.broadcast_to(np.asarray(process_noise, dtype=float), (n,))
    if np.any(frac < 0) or not np.all(np.isfinite(frac)) or np.any(frac > MAX_PROCESS_NOISE):
        # 1e300 overflowed the state covariance (a ValueError from inside the update, not a refusal)
        raise InputError(f"process_noise: expected finite values from 0 to {MAX_PROCESS_NOISE:g} (the random-walk std "
                         f"per pose step as a fraction of the prior std), got {process_noise!r}")
    return frac


def _full_theta(base: NDArray, idx: NDArray, x: ArrayLike) -> NDArray:
    """All parameters: ``base`` with the state ``x`` at ``idx`` (a copy)."""
    th = base.copy()
    th[idx] = np.ravel(x)
    return th


@dataclass(frozen=True)
class _FilterRun:
    """The filter's pass over the poses: the state after 0, 1, ... poses and the innovations' consistency."""

    means: list  # n_done + 1 arrays (n_free,): the prior mean, then after each pose
    covariances: list  # n_done + 1 arrays (n_free, n_free)
    nis: NDArray  # (n_done,) normalised innovation squared per pose
    success: bool
    message: str


def _new_filter(variant: str, x0: NDArray, P0: NDArray, R: NDArray, Q: NDArray, dof: int, alpha: float):
    """A filterpy EKF or UKF (Merwe sigma points) at the prior ``N(x0, P0)``, static or random-walk state."""
    n = x0.size
    if variant == "ekf":
        f = ExtendedKalmanFilter(dim_x=n, dim_z=dof)
        f.x = x0.reshape(n, 1).copy()
    else:
        points = MerweScaledSigmaPoints(n, alpha=alpha, beta=2.0, kappa=0.0)
        f = UnscentedKalmanFilter(dim_x=n, dim_z=dof, dt=1.0, hx=None, fx=lambda x, dt: x, points=points)
        f.x = x0.copy()
    f.P, f.R, f.Q = P0.copy(), R, Q
    return f


def _run_filter(model, variant: str, prior: GaussianPrior, idx: NDArray, qn: NDArray, alpha: float) -> _FilterRun:
    """One predict and update per pose in stored order; stops (``success`` False) at a pose it cannot update with."""
    row_sigma = model.row_sigma
    base = prior.mean.copy()
    means = [prior.mean[idx].copy()]
    covs = [np.diag(prior.std[idx] ** 2)]
    nis = np.empty(model.n_poses)
    message, success = "", True
    f = _new_filter(variant, means[0], covs[0], np.diag(row_sigma[0] ** 2), np.diag(qn**2), model.dof, alpha)
    for i in range(model.n_poses):
        sub = model.subset([i])
        f.R = np.diag(row_sigma[i] ** 2)  # per-pose noise (recording columns or robust weights)
        try:
            if variant == "ekf":
                _ekf_update(f, sub, i, base, idx, model.dof)
            else:
                _ukf_update(f, sub, i, base, idx)
        except (InputError, np.linalg.LinAlgError) as exc:
            success, message = False, f"stopped at pose {i + 1}: {exc}"
            nis = nis[:i]
            break
        innov = np.ravel(f.y)
        nis[i] = float(innov @ np.linalg.solve(f.S, innov))
        means.append(np.ravel(f.x).copy())
        P = np.asarray(f.P)
        covs.append(0.5 * (P + P.T))
    return _FilterRun(means, covs, nis, success, message)


def _ekf_update(f, sub, i: int, base: NDArray, idx: NDArray, dof: int) -> None:
    """The EKF's step to pose ``i`` (one-pose model ``sub``, ``dof`` rows): predict (after the first), update."""
    z = sub.y_measured[0]
    if i > 0:
        f.predict()
    cache = {}

    def jac(x):
        th = _full_theta(base, idx, x)
        pred = sub.predict(th)
        if not pred.success.all():
            raise InputError(f"pose {i + 1}: {pred.poses.message[0]} at the current estimate")
        cache["h"] = pred.y[0].reshape(dof, 1)
        return sub.jacobian(th, pred)[0][:, idx]

    # HJacobian runs first in filterpy's update, at the same x as Hx
    f.update(z.reshape(dof, 1), HJacobian=jac, Hx=lambda x: cache["h"])


def _ukf_update(f, sub, i: int, base: NDArray, idx: NDArray) -> None:
    """The UKF's step to pose ``i`` (the one-pose model ``sub``): predict, then update."""
    z = sub.y_measured[0]
    f.predict()
    thetas = np.tile(base, (f.sigmas_f.shape[0], 1))
    thetas[:, idx] = f.sigmas_f
    pred = sub.predict(thetas)  # one vectorised call for all sigma points
    if not pred.success.all():
        raise InputError(f"pose {i + 1}: a sigma point cannot be solved (try a smaller alpha)")
    it = iter(pred.y)
    f.update(z, hx=lambda x: next(it))
