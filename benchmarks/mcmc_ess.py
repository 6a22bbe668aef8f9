"""Effective samples per second: bayescal's MCMC against emcee with its default settings, same posterior, same run.

Posterior: the identifiable errors of the bundled 3-PRS example recording
(33 parameters), the model linearised at the MAP (``--full`` for the exact
kinematics, much slower).  Both samplers start from the same walkers (drawn
from the MAP and its Laplace covariance) and run the same number of steps:

* bayescal: :func:`bayescal.bayes.mcmc.sample_posterior` with its defaults
  (vectorised log-probability, one model call per move for all walkers;
  Laplace-t independence MH 0.9 + DE 0.07 + corrected snooker 0.03);
* for reference, the same with the DE 0.8 + snooker 0.2 moves only (the
  default before the independence move);
* baseline: ``emcee.EnsembleSampler(n_walkers, n_dim, log_prob)`` with its
  defaults (stretch move, one call per walker).

ESS is arviz's bulk ESS (walkers as chains), the minimum over parameters;
with the stretch move's long autocorrelation the baseline's ESS from a
short run is, if anything, overestimated.

Run: ``python benchmarks/mcmc_ess.py [--steps 4000] [--full]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import arviz as az  # noqa: E402
import emcee  # noqa: E402

from bayescal.bayes import linearise, map_estimate, prior_from_machine  # noqa: E402
from bayescal.bayes.mcmc import log_posterior_function, sample_posterior  # noqa: E402
from bayescal.bayes.moves import default_moves  # noqa: E402
from bayescal.io import read_recording  # noqa: E402
from bayescal.machines import load_machine  # noqa: E402
from bayescal.measurement import MeasurementModel  # noqa: E402


def min_ess(chain: np.ndarray) -> float:
    dt = az.from_dict({"posterior": {"theta": np.swapaxes(chain, 0, 1)}}, dims={"theta": ["param"]})
    return float(az.ess(dt, method="bulk")["theta"].values.min())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--full", action="store_true", help="exact kinematics instead of the linearised model")
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args(argv)
    machine = load_machine(ROOT / "examples" / "prs3" / "machine.toml")
    exact = MeasurementModel.from_recording(machine, read_recording(ROOT / "examples" / "prs3" / "recording.csv"))
    start = map_estimate(exact)
    model = exact if args.full else linearise(exact, start.theta)
    idx = np.flatnonzero(start.free)
    n = idx.size
    walkers = 2 * n + 2
    burn = args.steps // 5

    ours = sample_posterior(model, n_steps=args.steps, n_walkers=walkers, burn=burn, seed=args.seed)
    ess_ours = float(np.min(ours.ess_bulk))
    de = sample_posterior(model, n_steps=args.steps, n_walkers=walkers, burn=burn, seed=args.seed,
                          moves=default_moves())
    ess_de = float(np.min(de.ess_bulk))

    lp = log_posterior_function(model, prior_from_machine(machine), idx, guess=model.predict(start.theta).poses)
    rng = np.random.default_rng(args.seed)
    p0 = rng.multivariate_normal(start.theta[idx], start.covariance, size=walkers)
    base = emcee.EnsembleSampler(walkers, n, lambda x: lp(x[None])[0, 0])  # emcee defaults: stretch move, not vectorised
    t0 = time.perf_counter()
    base.run_mcmc(p0, args.steps)
    t_base = time.perf_counter() - t0
    ess_base = min_ess(base.get_chain(discard=burn))

    r_ours, r_base = ess_ours / ours.seconds, ess_base / t_base
    print(f"posterior: {n} parameters, {walkers} walkers, {args.steps} steps ({burn} burn-in), "
          f"{'exact kinematics' if args.full else 'linearised at the MAP'}")
    print(f"{'sampler':<48}{'seconds':>9}{'min bulk ESS':>14}{'ESS/s':>10}")
    print(f"{'bayescal (vectorised, Laplace-t + DE + snooker)':<48}{ours.seconds:9.1f}{ess_ours:14.0f}{r_ours:10.1f}")
    print(f"{'bayescal, DE + snooker only':<48}{de.seconds:9.1f}{ess_de:14.0f}{ess_de / de.seconds:10.1f}")
    print(f"{'emcee defaults (stretch, per walker)':<48}{t_base:9.1f}{ess_base:14.0f}{r_base:10.1f}")
    print(f"ratio of effective samples per second: {r_ours / r_base:.1f}x (target >= 10x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
