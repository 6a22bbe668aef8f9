"""MCMC posteriors of the identifiable geometric errors (emcee), checked with arviz.

The posterior of the identifiable errors ``x`` (the others at the prior
mean) is

    log p(x | y) = sum_i log N(y_i | h_i(x), R) + log N(x | mu, diag(s^2)) + const,

with one likelihood term per pose ``i``.  It is sampled with
:class:`emcee.EnsembleSampler`:

* vectorised: the walkers' parameter vectors are stacked into ONE call of
  the measurement model's ``predict`` (``n_walkers * n_poses`` rows);
* started from the MAP estimate and its Laplace approximation, bent along
  the directions the prior decides (:mod:`bayescal.bayes.bent_laplace`; so
  burn-in is short);
* with a mixture of moves (see :mod:`bayescal.bayes.moves`): an
  independence Metropolis-Hastings move proposing from a multivariate t
  around the MAP with the Laplace covariance, pushed through that bent map,
  with the map's Gaussian mixed in (0.9 Gaussian + 0.1 t) where draws of
  the t show the posterior's tails are no heavier than the Gaussian's
  (:func:`~bayescal.bayes.moves.choose_proposal`) (0.9; nearly independent
  draws when the posterior is close to Gaussian or curved only along
  prior-decided directions, in any dimension) and the
  differential-evolution moves ``DEMove`` (0.07) and the corrected DE
  snooker move (0.03), which keep the chain moving where the Laplace
  approximation is poor.  The integrated autocorrelation time is about 1.4
  steps on the 3-PRS example (3.1 with the t alone), against about 125
  with DE + snooker alone and several hundred with emcee's default stretch
  move (see ``benchmarks/mcmc_ess.py``).

Convergence is judged on the chain after burn-in with arviz's rank-normalised
R-hat and bulk/tail effective sample sizes (walkers as chains), and emcee's
integrated autocorrelation time (:mod:`bayescal.bayes.autocorr`: its estimator,
vectorised; the chain must be at least ``tau_factor`` times longer).  With
``ess`` a run stops as soon as these pass with that ESS
(:mod:`bayescal.bayes.stopping`).  A posterior that fails any check is not reported:
``success`` is False and the message says how many more steps to run.

The samples are kept as an arviz :class:`xarray.DataTree` with groups

* ``posterior``: ``theta`` (chain, draw, param) in mm or rad;
* ``log_likelihood``: ``y`` (chain, draw, pose), one value per pose, so
  :func:`arviz.loo` is leave-one-pose-out and :func:`arviz.compare` works;
* ``sample_stats``: ``lp`` (chain, draw), the log posterior;
* ``observed_data``: ``y_measured`` (pose, component);
* ``constant_data``: ``q`` (pose, actuator), ``sigma`` (component),
  ``prior_mean`` and ``prior_std`` (param).
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import arviz as az
import emcee
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from .autocorr import integrated_time
from .bent_laplace import BentLaplace, bent_laplace, log_posterior_gradient
from .linear import linearisation_error, linearise
from .moves import choose_proposal, default_moves
from .priors import GaussianPrior, map_estimate, prior_from_machine
from .stopping import EssStop, checked_ess
from ..identify.free import bound_arrays, bounds_of
from ..identify.result import bounds_dict, covariance_dict, decided_by_prior_lines
from ..measurement import MeasurementModel
from ..stats import posterior_effective_params
from .summary import PosteriorMembers, parameter_list, parameter_table, strong_correlations

__all__ = ["PosteriorResult", "sample_posterior", "log_posterior_function", "write_posterior"]

#: Default convergence thresholds (see the module docstring).
#: R-hat over emcee walkers is pessimistic: the walkers of an ensemble are not
#: independent chains (every move uses the others), so 1.01, the threshold for
#: independent chains, is not reached in practical run lengths even when the
#: autocorrelation-time check (the primary one) passes.
MAX_RHAT = 1.05
MIN_ESS = 400.0
TAU_FACTOR = 50.0


@dataclass(frozen=True, eq=False)
class PosteriorResult(PosteriorMembers):
    """A sampled posterior and its convergence checks.

    Attributes
    ----------
    names, units : tuple of str
        All parameters of the machine.
    free : ndarray of bool, shape (P,)
        The sampled (identifiable) parameters.
    theta : ndarray, shape (P,)
        Posterior mean (sampled parameters; the others where the MAP held
        them: the prior mean, or a model's ``theta_start`` such as a machine
        file's effect values), or the MAP start when the posterior is refused.
    theta_map : ndarray, shape (P,)
    mean : ndarray, shape (n_free,)
    covariance : ndarray, shape (n_free, n_free)
    quantiles : ndarray, shape (3, n_free)
        5 %, 50 % and 95 % posterior quantiles.
    rhat, ess_bulk, ess_tail, tau : ndarray, shape (n_free,)
        Per parameter: rank-normalised R-hat, bulk and tail effective sample
        size (arviz), integrated autocorrelation time in steps (emcee's estimator).
    n_walkers, n_steps, burn : int
    acceptance : float
        Mean acceptance fraction.
    success : bool
        True only if every convergence check passed.
    message : str
    more_steps : int
        When not converged: about how many more steps are needed.
    tree : xarray.DataTree
        The samples after burn-in (see the module docstring for the groups).
    seconds : float
        Sampling wall time.
    """

    machine_name: str
    kind: str
    names: tuple[str, ...]
    units: tuple[str, ...]
    free: NDArray
    theta: NDArray
    theta_map: NDArray
    mean: NDArray
    covariance: NDArray
    quantiles: NDArray
    rhat: NDArray
    ess_bulk: NDArray
    ess_tail: NDArray
    tau: NDArray
    n_walkers: int
    n_steps: int
    burn: int
    acceptance: float
    success: bool
    message: str
    more_steps: int
    rms_before: dict
    rms_after: dict
    dof: int
    n_poses: int
    tree: object = field(repr=False)
    seconds: float = float("nan")
    fixed: tuple[str, ...] = ()
    unidentifiable: tuple[str, ...] = ()
    #: Combinations the data do not separate that the prior decides (``free="auto"``: sampled, not fixed).
    decided_by_prior: tuple[str, ...] = ()
    #: Parameters the user held where the MAP held them (``fix``), whatever the data see.
    held: tuple[str, ...] = ()
    #: ``(name, lower, upper)``: the posterior sampled is truncated there (``bounds``).
    bounds: tuple = ()
    #: None: a parameter the posterior is truncated for is sampled, not put on its bound.
    at_bound: tuple[str, ...] = ()
    #: The Laplace approximation the walkers started on and the independence move proposed from (bent_laplace.py).
    bend: BentLaplace | None = field(default=None, repr=False)
    #: Importance-sampling ESS fractions of the straight and the bent proposal (``{"draws", "straight",
    #: "bent"}``), by which the bend was kept or dropped; None when no bend was fitted or tried.
    proposal_check: dict | None = field(default=None, repr=False)
    #: Which parameters the data determine alone (the MAP's, :attr:`IdentificationResult.determined`).
    determined: NDArray | None = field(default=None, repr=False)
    #: The bulk and tail ESS the run had to reach (``min_ess``, raised to ``ess`` where a run stops there).
    min_ess: float = MIN_ESS

    method = "mcmc"
    #: ``dof`` is the tool's already (body sensors' tilt rows apart)
    tool_dof = None

    @property
    def extras(self) -> dict:
        """Further JSON keys of the answer: none (the sampler's prior is the tolerances as they are)."""
        return {}

    @property
    def prior_effective_params(self) -> float | None:
        """``n - tr(P_prior^-1 P_post)`` of the tolerance prior and the sampled covariance (None if refused)."""
        if not self.success:
            return None
        try:
            sd = np.asarray(self.tree["constant_data"]["prior_std"].values, dtype=float)
            return posterior_effective_params(np.diag(sd**2), np.asarray(self.covariance, dtype=float))
        except (AttributeError, KeyError, IndexError, TypeError, ValueError, np.linalg.LinAlgError):
            return None

    @property
    def bent_directions(self) -> int:
        """Prior-decided directions the independence proposal was bent along (0: straight)."""
        return 0 if self.bend is None else self.bend.bent

    @property
    def free_names(self) -> tuple[str, ...]:
        return tuple(n for n, f in zip(self.names, self.free) if f)

    @property
    def std(self) -> NDArray:
        """Posterior std per parameter; NaN where not sampled or the posterior was refused."""
        out = np.full(self.theta.shape, np.nan)
        if self.success:
            out[self.free] = np.sqrt(np.diag(self.covariance))
        return out

    @property
    def samples(self) -> NDArray:
        """All draws after burn-in, shape (n_walkers * n_kept, n_free)."""
        th = self.tree["posterior"]["theta"].values
        return th.reshape(-1, th.shape[-1])

    def to_dict(self) -> dict:
        ok = self.success
        out = {
            "machine": self.machine_name,
            "kind": self.kind,
            "method": "mcmc",
            "success": ok,
            "message": self.message,
            "parameters": parameter_list(self.names, self.units, self.theta, self.std, self.free, self.determined),
            "rms_before": self.rms_before,
            "rms_after": self.rms_after,
            "dof": self.dof,
            "n_poses": self.n_poses,
            "covariance_kind": "posterior sample covariance (emcee)" if ok else "none: posterior not converged",
            "fixed": list(self.fixed),
            "held": list(self.held),
            **bounds_dict(self.bounds, ()),
            "unidentifiable": list(self.unidentifiable),
            "decided_by_prior": list(self.decided_by_prior),
            "convergence": {
                "n_walkers": self.n_walkers,
                "n_steps": self.n_steps,
                "burn": self.burn,
                "acceptance": self.acceptance,
                "max_rhat": float(np.max(self.rhat)),
                "min_ess_bulk": float(np.min(self.ess_bulk)),
                "min_ess_tail": float(np.min(self.ess_tail)),
                "min_ess": self.min_ess,
                "max_tau_steps": float(np.max(self.tau)),
                "more_steps": self.more_steps,
                "seconds": self.seconds,
                "proposal_bent_directions": self.bent_directions,
                "proposal_check": self.proposal_check,
            },
        }
        if ok:
            out["interval_90"] = [
                {"name": n, "q05": float(a), "q50": float(b), "q95": float(c)}
                for n, a, b, c in zip(self.free_names, *self.quantiles)
            ]
            out["covariance"] = covariance_dict(self.names, self.units, self.free, self.covariance)
            out["strong_correlations"] = [
                {"a": a, "b": b, "correlation": c} for a, b, c in strong_correlations(self.covariance, self.free_names)
            ]
        return out

    def _check_note(self) -> str:
        c = self.proposal_check
        if c is None:
            return ""
        if c.get("bent") is None:
            notes = [f"importance efficiency {c['straight']:.2f}"]
        else:
            kept = "kept" if self.bent_directions else "dropped"
            notes = [f"bend {kept}: importance efficiency {c['bent']:.2f} bent, {c['straight']:.2f} straight"]
        gw = c.get("gaussian_weight")
        if gw is not None and c.get("largest_weight_t") is not None:
            what = f"proposal {gw:g} Gaussian + {1 - gw:g} t" if gw else "proposal t alone"
            notes.append(f"{what}: largest weight {np.exp(c['largest_weight_mixture']):.3g} mixed, "
                         f"{np.exp(c['largest_weight_t']):.3g} t")
        return f" ({'; '.join(notes)}; {c['draws']} draws)"

    def report(self) -> str:
        status = "converged" if self.success else "NOT CONVERGED: posterior not reported"
        lines = [
            f"bayescal posterior of '{self.machine_name}' ({self.kind})",
            f"  method          mcmc (emcee, Laplace-t independence + DE + snooker moves): {status}",
            f"  sampler         {self.n_walkers} walkers x {self.n_steps} steps ({self.burn} burn-in), "
            f"acceptance {self.acceptance:.2f}, {self.seconds:.1f} s; proposal bent along {self.bent_directions} "
            f"prior-decided direction(s)" + self._check_note(),
            f"  convergence     max R-hat {np.max(self.rhat):.4f} (<= {MAX_RHAT}), min ESS bulk "
            f"{np.min(self.ess_bulk):.0f} / tail {np.min(self.ess_tail):.0f} (>= {self.min_ess:.0f}), "
            f"max autocorrelation time {np.max(self.tau):.0f} steps",
        ]
        if self.message:
            lines.append(f"  message         {self.message}")
        lines += [
            f"  measurement     {self.dof}-DOF, {self.n_poses} poses, {int(self.free.sum())} parameters sampled",
            f"  RMS position    {self.rms_before['position']:.6f} mm before, {self.rms_after['position']:.6f} mm after",
        ]
        if not self.success:
            return "\n".join(lines)
        rows = parameter_list(self.names, self.units, self.theta, self.std, self.free, self.determined)
        lines += parameter_table(
            rows, strong_correlations(self.covariance, self.free_names),
            {"q05": self.quantiles[0], "q95": self.quantiles[2], "R-hat": self.rhat},
        )
        if self.held:
            lines += ["", f"  held at the prior mean (fix): {', '.join(self.held)}"]
        if self.bounds:
            lines += ["", "  the posterior truncated to: " + ", ".join(
                f"{n} in [{a:g}, {b:g}]" for n, a, b in self.bounds)]
        if self.fixed:
            lines += ["", f"  not identifiable from these poses, held at the prior mean: {', '.join(self.fixed)}"]
        lines += decided_by_prior_lines(self.decided_by_prior)
        return "\n".join(lines)


def log_posterior_function(model, prior: GaussianPrior, idx: NDArray, *, guess=None, base: ArrayLike | None = None):
    """Vectorised ``X (n_walkers, n_free) -> (n_walkers, 1 + n_poses)``: log posterior, then per-pose log-likelihood.

    All walkers go through one ``model.predict`` call (stacked theta).
    Poses that cannot be solved give ``-inf``.  The parameters outside
    ``idx`` are held at ``base`` (default the prior mean; the sampler holds
    them where its MAP did, :func:`sample_posterior`).  ``guess`` warm-starts
    the forward kinematics: solved poses (tiled over the walkers), or a
    callable ``thetas (W, P) -> ToolPoses`` of ``W * n_poses`` rows (a
    machine's ``tangent_guesses``).
    """
    n_poses, dof = model.n_poses, model.dof
    sig = model.row_sigma
    y = model.y_measured
    base = prior.mean.copy() if base is None else np.array(base, dtype=float)
    pri = prior.subset(idx)
    const = -np.sum(np.log(sig), axis=1) - 0.5 * dof * np.log(2 * np.pi)  # per pose

    def log_prob(X: NDArray) -> NDArray:
        X = np.atleast_2d(X)
        W = X.shape[0]
        th = np.tile(base, (W, 1))
        th[:, idx] = X
        pred = model.predict(np.repeat(th, n_poses, axis=0), guess=guess(th) if callable(guess) else guess)
        r = ((pred.y.reshape(W, n_poses, dof) - y[None]) / sig).astype(float)
        ll = -0.5 * np.sum(r**2, axis=2) + const[None, :]
        ll[~pred.success.reshape(W, n_poses)] = -np.inf
        lp = ll.sum(axis=1) + pri.logpdf(X)
        lp[~np.isfinite(lp)] = -np.inf
        return np.column_stack([lp, ll])

    return log_prob


def _tree(model, prior, idx, names, chain, lp, ll) -> object:
    """The arviz DataTree of draws ``chain`` (steps, walkers, n_free) with pointwise log-likelihood."""
    return az.from_dict(
        {
            "posterior": {"theta": np.swapaxes(chain, 0, 1)},
            "log_likelihood": {"y": np.swapaxes(ll, 0, 1)},
            "sample_stats": {"lp": lp.T},
            "observed_data": {"y_measured": model.y_measured},
            "constant_data": {
                "q": np.asarray(model.q),
                "sigma": model.sigma,
                "pose_sigma": np.asarray(model.row_sigma),
                "prior_mean": prior.mean[idx],
                "prior_std": prior.std[idx],
            },
        },
        dims={
            "theta": ["param"],
            "y": ["pose"],
            "y_measured": ["pose", "component"],
            "q": ["pose", "actuator"],
            "sigma": ["component"],
            "pose_sigma": ["pose", "component"],
            "prior_mean": ["param"],
            "prior_std": ["param"],
        },
        coords={"param": list(names), "pose": np.arange(model.n_poses), "component": np.arange(model.dof)},
    )


def sample_posterior(
    model, *, prior: GaussianPrior | None = None, free: ArrayLike | str | None = None, n_walkers: int | None = None,
    n_steps: int = 1000, burn: int | None = None, seed: int = 0, progress: bool = False, max_rhat: float = MAX_RHAT,
    min_ess: float = MIN_ESS, tau_factor: float = TAU_FACTOR, moves=None, surrogate: str = "none",
    checkpoint: str | os.PathLike | None = None, checkpoint_every: int = 100, resume: bool = False,
    theta0: ArrayLike | None = None, ess: float | None = None,
) -> PosteriorResult:
    """Sample the posterior of the identifiable errors with emcee and check convergence.

    Parameters
    ----------
    model : MeasurementModel or LinearisedModel
        With measured values.
    prior : GaussianPrior, optional
        Default: the machine's tolerance prior.
    free : "auto", "all", names or Free, optional
        Sampled parameters; the identifiable set by default.  A :class:`~bayescal.identify.free.Free` with bounds:
        the posterior truncated there.
    n_walkers : int, optional
        Default ``2 * n_free + 2``.
    n_steps : int
        Steps per walker, including burn-in.
    burn : int, optional
        Steps discarded; default ``n_steps // 5`` (the start is already near the mode).
    seed : int
    progress : bool
        Show a tqdm progress bar.
    max_rhat : float
        Largest rank-normalised R-hat over the walkers (see the module docstring).
    min_ess : float
        Smallest bulk and tail effective sample size.
    tau_factor : float
        Chain length after burn-in, in integrated autocorrelation times, at least.
    moves : emcee moves, optional
        Default :func:`bayescal.bayes.moves.default_moves` with the MAP and its Laplace covariance: independence MH
        0.9, ``DEMove`` 0.07, corrected snooker 0.03.
    surrogate : {"none", "linear"}
        ``"linear"`` samples the model linearised at the MAP (much faster); the largest linearisation error over 200
        posterior draws, in units of the instrument sigma, is then checked (must be < 0.1) and reported.
    checkpoint : path-like, optional
        Save the chain and the random state here (.npz, atomically) every ``checkpoint_every`` steps and at the end
        (:mod:`bayescal.bayes.checkpoint`).
    resume : bool
        Continue the chain saved in ``checkpoint`` up to ``n_steps``: the same draws as an uninterrupted run with the
        same arguments.
    theta0 : array_like, shape (P,), optional
        Where the MAP search starts (:func:`~bayescal.bayes.priors.map_estimate`); the prior mean by default.
    ess : float, optional
        Stop once every check passes with bulk and tail ESS of at least this (``min_ess`` raised to it), checked as
        the chain grows by a tenth (:class:`~bayescal.bayes.stopping.EssStop`), ``n_steps`` the most steps; the
        draws are the first ones of the run that does not stop.  Default: run ``n_steps``.

    Returns
    -------
    PosteriorResult
        ``success`` False (and no posterior std) unless every check passes.
    """
    ess, min_ess = _check_run_options(surrogate, checkpoint, checkpoint_every, resume, ess, min_ess)  # before the MAP
    prior, start = _map_start(model, prior, free, theta0)
    idx = np.flatnonzero(start.free)
    exact, model = model, (linearise(model, start.theta) if surrogate == "linear" else model)
    n_walkers, burn_default, burn = _chain_size(idx.size, n_walkers, n_steps, burn)
    rng = np.random.default_rng(seed)
    map_pred = model.predict(start.theta)
    # the parameters not sampled stay where the MAP held them (its start: the model's theta_start, e.g. a
    # machine file's effect values, else the prior mean), the same values the answer reports
    log_prob = log_posterior_function(model, prior, idx, guess=_warm_starts(model, start.theta, map_pred), base=start.theta)
    moves, bend, proposal_check = _proposal(model, prior, idx, start, map_pred, log_prob, moves, n_walkers, seed)
    p0 = _starting_points(model.machine, prior, idx, start, bend, log_prob, n_walkers, rng)
    stop = _ess_stop(ess, n_walkers, burn_default, burn, max_rhat, min_ess, tau_factor)
    sampler, seconds = _run_chain(model, idx, start, log_prob, moves, p0, n_steps=n_steps, seed=seed, progress=progress,
                                  surrogate=surrogate, checkpoint=checkpoint, checkpoint_every=checkpoint_every,
                                  resume=resume, stop=stop)
    burn = sampler.iteration // 5 if burn_default else burn  # a run stopped early burns a fifth of what it ran
    res = _summarise(model, prior, idx, start, sampler, burn, seconds, max_rhat, min_ess, tau_factor,
                     burn_grows=burn_default, known=None if stop is None else stop.known, bend=bend,
                     proposal_check=proposal_check)
    if surrogate == "linear":
        res = _surrogate_checked(res, exact, prior, idx, start, rng)
    return res


def _warm_starts(model, theta: NDArray, pred):
    """The forward kinematics' start for the walkers: the MAP's poses, or first-order guesses near them.

    A plain measurement model on a machine that offers ``tangent_guesses``
    (the 3-PRS) starts every walker's solve a Newton step closer than the
    MAP's poses; any other model, or a MAP pose that did not solve, keeps the
    MAP's poses.
    """
    tangent = getattr(model.machine, "tangent_guesses", None)
    if tangent is None or not isinstance(model, MeasurementModel) or not np.all(pred.poses.success):
        return pred.poses
    return tangent(model.q, theta, pred.poses)


def _check_run_options(surrogate: str, checkpoint, checkpoint_every: int, resume: bool, ess,
                       min_ess: float) -> tuple[float | None, float]:
    """Refuse the surrogate, checkpoint and ESS options that cannot work, before anything is computed.

    A fresh run over an existing checkpoint, ``resume`` without a checkpoint
    or with none there, ``checkpoint_every`` below 1 step, an ``ess`` that is
    not a positive number.  Returns ``ess`` (a float or None) and ``min_ess``
    raised to it.
    """
    ess = checked_ess(ess)
    min_ess = float(min_ess) if ess is None else max(float(min_ess), ess)
    if surrogate not in ("none", "linear"):
        raise InputError(f"surrogate: expected 'none' or 'linear', got {surrogate!r}")
    if resume and checkpoint is None:
        raise InputError("resume: give the checkpoint to resume from")
    if checkpoint is None:
        return ess, min_ess
    if checkpoint_every < 1:
        raise InputError(f"checkpoint_every (--checkpoint-every): expected a positive number of steps, got {checkpoint_every}")
    if not resume and os.path.lexists(checkpoint):
        # a fresh chain saved over it would lose the chain it holds (hours of sampling, --resume forgotten)
        raise InputError(f"--checkpoint {checkpoint}: a file is there already; a fresh run would replace it. "
                         "Expected --resume to continue its chain, or another path (remove the file to start afresh)")
    if resume and not os.path.exists(checkpoint):
        # as load_checkpoint says it, but before the MAP and the proposal check rather than after them
        raise InputError(f"--resume: {checkpoint}: no checkpoint there (run once with --checkpoint {checkpoint})")
    return ess, min_ess


def _map_start(model, prior: GaussianPrior | None, free, theta0):
    """The prior (the machine's tolerance prior by default) and the MAP the chain starts from, or a clear refusal."""
    if model.y_measured is None:
        raise InputError("sample_posterior: the measurement model has no measured values")
    prior = prior_from_machine(model.machine) if prior is None else prior
    bounds = bounds_of(free)
    if bounds:
        # the target is the posterior truncated to the bounds (the prior's); the chain starts at the bounded MAP
        prior = prior.within(*bound_arrays(model.machine.layout, bounds))
    start = map_estimate(model, prior=prior, free=free, theta0=theta0)
    if start.covariance is None:
        raise InputError(f"sample_posterior: the MAP start failed ({start.message})")
    return prior, _laplace_on_bounds(model, prior, start)


def _laplace_on_bounds(model, prior: GaussianPrior, start):
    """The bounded MAP with the parameters it put on a bound sampled too: the Laplace covariance over all of them.

    At a bound the MAP's covariance is conditional on the bound; the sampler explores the posterior truncated
    there, so its walkers and independence proposals start from ``(J^T R^-1 J + P0^-1)^-1`` over every sampled
    parameter at that point (draws beyond a bound are mirrored or rejected).
    """
    if not start.at_bound:
        return start
    from ..identify.gauss_newton import posterior_covariance, whitened_system
    from ..identify.solvers import filtered_solve

    free = start.free.copy()
    free[[start.names.index(n) for n in start.at_bound]] = True
    idx = np.flatnonzero(free)
    r, J = whitened_system(model, start.theta, model.predict(start.theta), columns=idx)
    # the MAP's Laplace covariance under the tolerance prior (lam = 1), as identify computes it
    cov, _ = posterior_covariance(filtered_solve(J * prior.std[idx], r, "ridge", lam=1.0), "map", lam=1.0)
    return dataclasses.replace(start, free=free, covariance=cov * np.outer(prior.std[idx], prior.std[idx]),
                               at_bound=())


def _chain_size(n: int, n_walkers: int | None, n_steps: int, burn: int | None) -> tuple[int, bool, int]:
    """The walkers, whether the burn-in is the default, and the burn-in, checked (memory included)."""
    n_walkers = 2 * n + 2 if n_walkers is None else int(n_walkers)
    if n_walkers < max(2 * n, n + 2) or n_walkers % 2:
        # emcee's red-blue moves refuse fewer walkers than twice the dimensions (a RuntimeError otherwise)
        raise InputError(f"n_walkers (--walkers): expected an even number >= {max(2 * n, n + 2)} (twice the {n} sampled "
                         f"parameters), got {n_walkers}")
    from ..limits import check_memory

    # the chain and its log-probabilities, held by emcee and copied into the summary and the posterior tree
    check_memory(4.0 * 8 * n_steps * n_walkers * (n + 2), f"a chain of {n_steps:,} steps x {n_walkers} walkers x {n} "
                 "parameters", "lower --steps or --walkers")
    burn_default = burn is None
    burn = n_steps // 5 if burn is None else int(burn)
    if not 0 <= burn < n_steps:
        raise InputError(f"burn: expected 0 <= burn < n_steps = {n_steps}, got {burn}")
    return n_walkers, burn_default, burn


def _proposal(model, prior, idx, start, map_pred, log_prob, moves, n_walkers: int, seed: int):
    """The moves, the Laplace approximation the walkers start on, and the check that kept or dropped its bend."""
    if moves is None:
        # the Laplace approximation bent along what the prior decides (bent_laplace.py): the walkers start on
        # it and the independence move proposes from it, if it matches the posterior better than the straight
        # one.  A valley that is not quadratic (an effect's mass times its compliances) can make the bend's
        # extrapolation far worse than no bend: importance weights of draws from both decide (one call each).
        bend = bent_laplace(log_posterior_gradient(model, prior, idx, guess=map_pred.poses, base=start.theta), start.theta[idx],
                            start.covariance, prior.std[idx])
        # the same draws say whether the proposal's Gaussian may be mixed in (choose_proposal): accepted about
        # twice as often where the posterior is nearly Gaussian, not used where its tails are heavier
        check = np.random.RandomState(np.random.SeedSequence([seed, 7]).generate_state(1)[0])
        bend, proposal_check = choose_proposal(lambda X: log_prob(X)[:, 0], start.theta[idx], start.covariance,
                                               bend, max(4 * n_walkers, 200), check)
        moves = default_moves(start.theta[idx], start.covariance, bend=bend,
                              gaussian_weight=proposal_check["gaussian_weight"])
    else:  # the caller's moves: the walkers start on the plain Laplace approximation
        bend = BentLaplace.linear(start.theta[idx], np.linalg.cholesky(start.covariance))
        proposal_check = None
    return moves, bend, proposal_check


def _starting_points(machine, prior, idx, start, bend, log_prob, n_walkers: int, rng) -> NDArray:
    """The walkers' starting points drawn from ``bend``, each with a positive posterior density."""
    n = idx.size
    p0 = bend.to_x(rng.standard_normal((n_walkers, n)))
    if start.bounds:
        # the user's bounds: the Laplace draws mirrored into them (half of a draw's coordinate on a bound falls
        # beyond it, and redrawing many such coordinates at once rarely lands inside)
        sub = prior.subset(idx)
        p0 = mirrored(p0, sub.lower, sub.upper)
    # a start outside the support (below a physical bound of the prior, a pose that does not assemble) would
    # stay stuck there: draw it again
    bad = ~np.isfinite(log_prob(p0)[:, 0])
    for _ in range(20):
        if not bad.any():
            break
        p0[bad] = bend.to_x(rng.standard_normal((int(bad.sum()), n)))
        bad = ~np.isfinite(log_prob(p0)[:, 0])
    if bad.any():
        names = [machine.layout.names[i] for i in idx]
        low = prior.subset(idx).lower
        below = [f"{nm} = {v:.4g} (bound {b:g})" for nm, v, b in zip(names, start.theta[idx], low)] if low is not None else []
        below = [t for t, v, b in zip(below, start.theta[idx], low if low is not None else []) if v < b]
        why = (f"the MAP lies below the prior's bound: {', '.join(below)}" if below else
               "the MAP's Laplace approximation puts them where poses do not assemble or the prior is zero")
        raise InputError(f"sample_posterior: {int(bad.sum())} of {n_walkers} starting points keep a zero posterior density "
                         f"after 20 redraws; {why}" + ("" if start.success else f" (the MAP did not converge: {start.message})"))
    return p0


def mirrored(x: NDArray, lo: NDArray, hi: NDArray) -> NDArray:
    """``x`` (..., n) reflected at the bounds ``lo`` and ``hi`` (n,) into ``[lo, hi]`` (infinite sides: no reflection)."""
    lo = np.broadcast_to(lo, x.shape)
    hi = np.broadcast_to(hi, x.shape)
    both = np.isfinite(lo) & np.isfinite(hi)
    width = np.where(both, hi - lo, 1.0)
    y = np.mod(np.where(both, x - np.where(both, lo, 0.0), 0.0), 2 * width)
    inside_both = np.where(both, lo, 0.0) + np.where(y > width, 2 * width - y, y)
    out = np.where(np.isfinite(lo) & (x < lo), 2 * lo - x, x)
    out = np.where(np.isfinite(hi) & (out > hi), 2 * hi - out, out)
    return np.where(both, inside_both, out)


def _run_chain(model, idx, start, log_prob, moves, p0, *, n_steps, seed, progress, surrogate, checkpoint,
               checkpoint_every, resume, stop: EssStop | None = None):
    """The emcee sampler run (or resumed from ``checkpoint``) up to ``n_steps`` or ``stop``, and its wall time in s."""
    n_walkers, n = p0.shape
    fingerprint = None  # the options were checked up front (_check_run_options)
    if checkpoint is not None:
        from .checkpoint import load_checkpoint, run_fingerprint, save_checkpoint

        names = tuple(model.machine.layout.names[i] for i in idx)
        fingerprint = run_fingerprint(model, names, seed=seed, n_walkers=n_walkers, surrogate=surrogate,
                                      held=start.theta[~start.free], bounds=start.bounds)
    backend = load_checkpoint(checkpoint, fingerprint) if resume else None
    if backend is not None and backend.iteration > n_steps:
        raise InputError(f"--resume: {checkpoint} holds {backend.iteration} steps, more than n_steps = {n_steps}")
    sampler = emcee.EnsembleSampler(n_walkers, n, log_prob, vectorize=True, moves=moves, backend=backend)
    if backend is None:
        sampler.random_state = np.random.RandomState(seed).get_state()  # emcee seeds from numpy's legacy state
    t0 = time.perf_counter()
    # with a stop rule the chain grows one check at a time: emcee reserves its storage for the steps asked of one
    # call, so a generous cap costs no memory it does not use; a resumed chain is checked where an uninterrupted
    # run would have been
    check = None if stop is None else stop.check_from(sampler.iteration)
    bar = _progress_bar(progress and stop is not None, sampler.iteration, n_steps)
    first = True
    while check is None or not (sampler.iteration == check and stop(sampler)):
        if check is not None and sampler.iteration == check:
            check = stop.next_check(check)
        end = n_steps if check is None else min(check, n_steps)
        if sampler.iteration >= end:
            break
        # a resumed or continued chain goes on from the backend's last state, random state included; emcee's check
        # of the starting walkers only where the run starts, as one call would make it
        start_state = p0 if sampler.iteration == 0 else sampler.backend.get_last_sample()
        for _ in sampler.sample(start_state, iterations=end - sampler.iteration, progress=progress and bar is None,
                                skip_initial_state_check=not first):
            if checkpoint is not None and sampler.iteration % checkpoint_every == 0:
                save_checkpoint(checkpoint, sampler.backend, fingerprint)
            if bar is not None:
                bar.update(1)
        first = False
    if bar is not None:
        bar.total = bar.n  # stopped at its ESS: the bar ends full, not at a fraction of the cap
        bar.refresh()
        bar.close()
    if checkpoint is not None:
        save_checkpoint(checkpoint, sampler.backend, fingerprint)
    return sampler, time.perf_counter() - t0


def _progress_bar(wanted: bool, done: int, n_steps: int):
    """A tqdm bar over the steps of a run that stops at its ESS (emcee's would restart at every check), or None."""
    if not wanted:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=n_steps, initial=done, unit="step", desc="sampling (stops at its ESS)")


def _surrogate_checked(res: PosteriorResult, exact, prior, idx, start, rng) -> PosteriorResult:
    """The linear surrogate's posterior checked against the exact model on 200 draws; RMS from the exact model."""
    draws = res.samples[rng.choice(res.samples.shape[0], size=min(200, res.samples.shape[0]), replace=False)]
    full = np.tile(start.theta, (draws.shape[0], 1))
    full[:, idx] = draws
    err = linearisation_error(exact, start.theta, full)
    note = f"linear surrogate at the MAP: largest linearisation error {err:.3g} sigma over 200 draws"
    ok = err < 0.1
    if not ok:
        note += " (>= 0.1: sample the full model instead)"
    msg = "; ".join(m for m in (res.message, note) if m)
    before = exact.residual(exact.predict(_reference(exact, prior)))
    after = exact.residual(exact.predict(res.theta))
    return dataclasses.replace(
        res, success=res.success and ok, message=msg, rms_before=exact.rms(before), rms_after=exact.rms(after),
        theta=res.theta if ok else start.theta,
    )


def _reference(model, prior) -> NDArray:
    """What "before" means: the machine file as given (a model's ``theta_start``: its stored effect values), else the prior mean."""
    ref = model.theta_start
    return prior.mean if ref is None else np.asarray(ref, dtype=float)


def _summarise(model, prior, idx, start, sampler, burn, seconds, max_rhat, min_ess, tau_factor, *,
               burn_grows: bool = False, known: dict | None = None, **extra) -> PosteriorResult:
    """The result of the chain ``sampler`` holds after ``burn``; ``extra`` are further fields of the result.

    ``known`` maps ``(steps, burn)`` to the R-hat and ESS a stop check computed for that chain already.
    """
    machine = model.machine
    names = tuple(machine.layout.names[i] for i in idx)
    chain = sampler.get_chain(discard=burn)
    lp = sampler.get_log_prob(discard=burn)
    ll = sampler.get_blobs(discard=burn)
    n_steps, n_walkers, n = sampler.iteration, chain.shape[1], idx.size
    kept = chain.shape[0]
    tau = _autocorr_time(sampler, burn)
    tree = _tree(model, prior, idx, names, chain, lp, ll)
    rhat, ess_b, ess_t = (known or {}).get((n_steps, burn)) or _diagnostics(tree)
    flat = chain.reshape(-1, n)
    mean = flat.mean(axis=0)
    cov = np.atleast_2d(np.cov(flat, rowvar=False))
    quant = np.quantile(flat, [0.05, 0.5, 0.95], axis=0)
    success, message, more = _convergence(tau, ess_b, ess_t, rhat, kept, n_steps, max_rhat, min_ess, tau_factor,
                                          burn_grows)
    theta = start.theta.copy()
    if success:
        theta[idx] = mean
    before = model.residual(model.predict(_reference(model, prior)))
    pred = model.predict(theta)
    after = model.residual(pred) if pred.success.all() else np.full_like(before, np.nan)
    return PosteriorResult(
        machine_name=machine.name,
        kind=machine.kind,
        names=machine.layout.names,
        units=machine.layout.units,
        free=start.free.copy(),
        theta=theta,
        theta_map=start.theta,
        mean=mean,
        covariance=cov,
        quantiles=quant,
        rhat=rhat,
        ess_bulk=ess_b,
        ess_tail=ess_t,
        tau=tau,
        n_walkers=n_walkers,
        n_steps=n_steps,
        burn=burn,
        acceptance=float(np.mean(sampler.acceptance_fraction)),
        success=success,
        message=message,
        more_steps=more,
        rms_before=model.rms(before),
        rms_after=model.rms(after),
        dof=model.tool_dof,  # the tool's DOF (body sensors' tilt rows apart)
        n_poses=model.n_poses,
        tree=tree,
        seconds=seconds,
        fixed=start.fixed,
        held=start.held,
        bounds=start.bounds,
        determined=getattr(start, "determined", None),
        unidentifiable=start.unidentifiable,
        decided_by_prior=start.decided_by_prior,
        min_ess=float(min_ess),
        **extra,
    )


def _diagnostics(tree) -> tuple[NDArray, NDArray, NDArray]:
    """Rank-normalised R-hat and bulk and tail ESS per parameter of ``tree``'s ``theta`` (arviz; walkers as chains)."""
    return (az.rhat(tree)["theta"].values, az.ess(tree, method="bulk")["theta"].values,
            az.ess(tree, method="tail")["theta"].values)


def _ess_stop(ess: float | None, n_walkers: int, burn_default: bool, burn: int, max_rhat: float, min_ess: float,
              tau_factor: float) -> EssStop | None:
    """The rule that stops a run at ``ess`` (:mod:`bayescal.bayes.stopping`) by the checks :func:`_summarise` applies.

    None when no ``ess`` is asked for: the run takes its ``n_steps``.
    """
    if ess is None:
        return None

    known: dict = {}

    def passes(sampler, b: int) -> bool:
        chain = sampler.get_chain(discard=b)
        tree = az.from_dict({"posterior": {"theta": np.swapaxes(chain, 0, 1)}}, dims={"theta": ["param"]})
        rhat, ess_b, ess_t = known[(sampler.iteration, b)] = _diagnostics(tree)  # the summary's, if the run stops
        return _convergence(_autocorr_time(sampler, b), ess_b, ess_t, rhat, chain.shape[0], sampler.iteration,
                            max_rhat, min_ess, tau_factor, False)[0]

    return EssStop(ess=min_ess, n_walkers=n_walkers, tau_factor=tau_factor,
                   burn=(lambda steps: steps // 5) if burn_default else (lambda steps: burn), passes=passes,
                   tau=_autocorr_time, known=known)


def _autocorr_time(sampler, burn: int) -> NDArray:
    """emcee's integrated autocorrelation time per parameter in steps, vectorised (:mod:`bayescal.bayes.autocorr`).

    A chain too short to trust it is not warned about here: :func:`_convergence` reports it in the result.
    """
    return integrated_time(sampler.get_chain(discard=burn))


def _convergence(tau, ess_b, ess_t, rhat, kept: int, n_steps: int, max_rhat: float, min_ess: float,
                 tau_factor: float, burn_grows: bool) -> tuple[bool, str, int]:
    """Whether every convergence check passed, the message saying which did not, and about how many more steps."""
    problems, more = [], 0
    if not np.all(np.isfinite(tau)) or kept < tau_factor * np.max(tau):
        need = tau_factor * np.nanmax(tau) if np.all(np.isfinite(tau)) else 2 * kept
        more = max(more, int(np.ceil(need - kept)))
        problems.append(f"chain {kept} steps < {tau_factor:g} x autocorrelation time {np.nanmax(tau):.0f}")
    if np.min(ess_b) < min_ess or np.min(ess_t) < min_ess:
        e = min(np.min(ess_b), np.min(ess_t))
        more = max(more, int(np.ceil(kept * (min_ess / max(e, 1.0) - 1))))
        problems.append(f"ESS {e:.0f} < {min_ess:g}")
    if np.max(rhat) > max_rhat:
        more = max(more, kept)  # R-hat falls roughly with 1/sqrt(length): try twice as long
        problems.append(f"R-hat {np.max(rhat):.3f} > {max_rhat}")
    success = not problems
    if more and burn_grows:
        # ``more`` is for the kept chain; with the default burn-in (a fifth of n_steps) a longer run also
        # discards more, so the advice is the n_steps whose kept part is ``kept + more``
        more = int(np.ceil((kept + more) / 0.8)) + 1 - n_steps
    message = "" if success else (
        f"not converged ({'; '.join(problems)}): run about {more} more steps (n_steps >= {n_steps + more})"
    )
    return success, message, more


def write_posterior(result: PosteriorResult, path: str | os.PathLike, *, thin: int | None = None) -> Path:
    """Write the posterior DataTree to NetCDF-4 atomically; refuses an unconverged posterior.

    Parameters
    ----------
    result : PosteriorResult
    path : path-like
    thin : int, optional
        Keep every ``thin``-th draw of each walker.  Default: a quarter of the
        largest autocorrelation time, which loses little effective sample
        size and keeps the file small (all draws of a 33-parameter run are
        a few hundred MB).  ``thin=1`` keeps everything.

    Notes
    -----
    Uses the netCDF4 engine (h5netcdf would need h5py, which is not a dependency).
    """
    if not result.success:
        raise InputError(f"{path}: not writing a posterior that has not converged ({result.message})")
    thin = max(1, int(np.max(result.tau) // 4)) if thin is None else int(thin)
    if thin < 1:
        raise InputError(f"thin: expected an integer >= 1, got {thin}")
    tree = result.tree if thin == 1 else result.tree.isel(draw=slice(None, None, thin))
    from ..io.answers import write_with_atomic

    # a temporary file with a unique name beside path, then a rename; a link or device at path is refused
    return write_with_atomic(path, to_path=lambda tmp: tree.to_netcdf(tmp, engine="netcdf4"))
