"""Effective samples per second: bayescal's MCMC against emcee with its default settings, same posterior, same run.

The posterior is the one ``bayescal identify --method mcmc`` samples by
default: the EXACT-kinematics posterior of the identifiable geometric
errors (the log posterior evaluated with the full nonlinear forward
kinematics, one batched Newton solve per step), under the machine file's
tolerance prior.  Three recordings of the bundled 3-PRS
(``examples/prs3/machine.toml``):

* ``6-DOF example``: the bundled recording (36 poses, 6-DOF);
* ``5-DOF``: 36 poses simulated with ``bayescal simulate --dof 5`` (seed 5);
* ``effect fitted``: 60 poses simulated with a concealed joint compliance
  (``--effect joint_compliance:0.5 --aux payload_kg``, seed 3, 6-DOF);
  ``bayescal.diagnose.diagnose`` fits the effect jointly with the geometry
  and the fitted ``[effect.joint_compliance]`` table
  (:func:`bayescal.diagnose.calibrated.calibrated_machine`) is put on the
  nominal machine, so the measurement model applies the fitted effect at
  every pose, as ``identify`` does with such a machine file;
* ``positioner``: the bundled REAL recording of the two-axis positioner
  (``examples/positioner``, 205 poses, 6-DOF, instrument frame fitted) with
  ``free="auto"``: 30 parameters, 16 of them decided by the prior, whose
  posterior valley is curved (:mod:`bayescal.bayes.bent_laplace`);
* ``effect-joint``: 60 poses simulated with a concealed backlash
  (``--effect backlash:8``, seed 3, 6-DOF), diagnosed, and the backlash
  parameters sampled *with* the geometry
  (:class:`bayescal.effects.joint_model.EffectModel`, what
  ``identify --fit-effects`` samples; the prior truncated at zero backlash).

Per recording, on the same target density, from the same start (walkers
drawn from the MAP and its Laplace covariance; bayescal's defaults from its
bent version, part of what is measured) and with the same number of walkers (``2 n + 2``, ``n``
sampled parameters):

* bayescal: :func:`bayescal.bayes.mcmc.sample_posterior` with its defaults
  (vectorised log-probability, one model call per step for all walkers;
  Laplace-t independence MH 0.9 + DE 0.07 + corrected snooker 0.03; the
  independence move's acceptance makes the chain exact for the nonlinear
  posterior, the Laplace approximation only sets how fast it mixes);
* baseline: ``emcee.EnsembleSampler(n_walkers, n_dim, log_prob)`` with its
  defaults (stretch move, a = 2, one log-probability call per walker);
* second baseline: bayescal's sampler with the straight Laplace-t
  independence proposal (the default before the bent map), to measure what
  bending the proposal along the prior-decided directions gains;
* ``--vectorised-stretch`` adds emcee's stretch move with the vectorised
  call, to separate the gain of vectorising from that of the moves.

ESS is arviz's bulk ESS (walkers as chains) of each parameter, and the
figure is its MINIMUM over the parameters (the tail ESS minimum is printed
too); the first fifth of each chain is burn-in.  Growth: the same ESS on
the first half of the kept draws, so ``growth`` = ESS(all) / ESS(half) is
about 2 when the ESS estimate grows in proportion to the run, as it should
for a converged chain.  The baseline's stretch move has autocorrelation
times of hundreds of steps in 30+ dimensions, so its short-run ESS is, if
anything, overestimated (its growth is then far from 2) and the ratio
understated.  Nothing is asserted about times; the script prints the
ratios and exits 0.

Run: ``python benchmarks/mcmc_ess.py [--steps 1000] [--base-steps 500] [--cases 6dof,5dof,effect,positioner,effect-joint]``
(about 25 minutes on one free core; ``--linearised`` samples the models
linearised at the MAP instead, the figure of earlier versions of this file).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small matrices: threads only add overhead

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import arviz as az  # noqa: E402
import emcee  # noqa: E402

from bayescal.bayes import linearise, map_estimate, prior_from_machine  # noqa: E402
from bayescal.bayes.mcmc import log_posterior_function, sample_posterior  # noqa: E402
from bayescal.bayes.moves import default_moves  # noqa: E402
from bayescal.io import read_recording  # noqa: E402
from bayescal.machines.files import load_machine  # noqa: E402
from bayescal.measurement import MeasurementModel  # noqa: E402

MACHINE = ROOT / "examples" / "prs3" / "machine.toml"
CASES = ("6dof", "5dof", "effect", "positioner", "effect-joint")


def ess(chain: np.ndarray, method: str = "bulk") -> float:
    """Minimum over parameters of arviz's ESS of ``chain`` (steps, walkers, n)."""
    with warnings.catch_warnings():  # a short chain has more walkers than draws: arviz warns, the ESS is still defined
        warnings.simplefilter("ignore", UserWarning)
        dt = az.from_dict({"posterior": {"theta": np.swapaxes(chain, 0, 1)}}, dims={"theta": ["param"]})
    return float(az.ess(dt, method=method)["theta"].values.min())


def _simulate(out: Path, *args: str) -> Path:
    if not out.exists():
        cmd = [sys.executable, "-m", "bayescal", "simulate", "--machine", str(MACHINE), "--out", str(out), "--quiet", *args]
        subprocess.run(cmd, check=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    return out


def build_case(name: str, out: Path):
    """(description, measurement model, free set) of one benchmark recording."""
    machine = load_machine(MACHINE)
    if name == "6dof":
        rec = read_recording(ROOT / "examples" / "prs3" / "recording.csv")
        return "bundled example, 36 poses, 6-DOF", MeasurementModel.from_recording(machine, rec), None
    if name == "5dof":
        rec = read_recording(_simulate(out / "mcmc_rec5.csv", "--poses", "36", "--seed", "5", "--dof", "5"))
        return "simulated, 36 poses, 5-DOF", MeasurementModel.from_recording(machine, rec), None
    if name == "positioner":
        from bayescal.instrument import prepare_model

        ex = ROOT / "examples" / "positioner"
        _, model, _ = prepare_model(load_machine(ex / "machine.toml"), read_recording(ex / "recording.csv"),
                                    frame="fit")
        return "real two-axis positioner, 205 poses, 6-DOF, frame fitted, free = auto", model, "auto"
    if name == "effect":
        from bayescal.diagnose import diagnose
        from bayescal.diagnose.calibrated import calibrated_machine

        path = _simulate(out / "mcmc_rec_compliance.csv", "--poses", "60", "--seed", "3",
                         "--effect", "joint_compliance:0.5", "--aux", "payload_kg")
        rec = read_recording(path)
        d = diagnose(machine, rec, effects=["joint_compliance"], seed=1)
        cal = calibrated_machine(machine, d)
        if not cal.effects:
            raise SystemExit(f"the diagnosis selected no effect (verdict {d.verdict}); cannot benchmark the effect case")
        with_effect = machine.with_effects(cal.machine.effects)
        values = ", ".join(f"{k} = {v:.3g} {u}".rstrip() for e in cal.machine.effects
                           for (k, v), u in zip(e.values, e.units))
        desc = f"simulated, 60 poses, 6-DOF, fitted joint_compliance ({values})"
        return desc, MeasurementModel.from_recording(with_effect, rec), None
    if name == "effect-joint":
        from bayescal.diagnose import diagnose
        from bayescal.diagnose.calibrated import calibrated_machine
        from bayescal.effects.joint_model import effect_model

        path = _simulate(out / "mcmc_rec_backlash.csv", "--poses", "60", "--seed", "3", "--effect", "backlash:8")
        rec = read_recording(path)
        cal = calibrated_machine(machine, diagnose(machine, rec, effects=["backlash"], seed=1))
        if not cal.effects:
            raise SystemExit("the diagnosis selected no effect; cannot benchmark the joint effect case")
        desc = "simulated, 60 poses, 6-DOF, backlash diagnosed and sampled with the geometry (identify --fit-effects)"
        return desc, effect_model(machine.with_effects(cal.machine.effects), rec), None
    raise SystemExit(f"unknown case {name!r}; expected some of {', '.join(CASES)}")


def run_case(name, out, steps, base_steps, seed, linearised, vectorised_stretch) -> dict:
    desc, exact, free = build_case(name, out)
    machine = exact.machine
    start = map_estimate(exact, free=free)
    model = linearise(exact, start.theta) if linearised else exact
    idx = np.flatnonzero(start.free)
    n = idx.size
    walkers = 2 * n + 2
    rows = []

    ours = sample_posterior(model, free=free, n_steps=steps, n_walkers=walkers, seed=seed)
    chain = ours.tree["posterior"]["theta"].values.swapaxes(0, 1)  # (kept, walkers, n)
    rows.append(("bayescal defaults (vectorised, bent Laplace-t IMH + DE + snooker)", ours.seconds, chain,
                 float(ours.acceptance), steps))
    straight = sample_posterior(model, free=free, n_steps=steps, n_walkers=walkers, seed=seed,
                                moves=default_moves(start.theta[idx], start.covariance))
    rows.append(("bayescal, straight Laplace-t IMH + DE + snooker", straight.seconds,
                 straight.tree["posterior"]["theta"].values.swapaxes(0, 1), float(straight.acceptance), steps))

    lp = log_posterior_function(model, prior_from_machine(machine), idx, guess=model.predict(start.theta).poses)
    rng = np.random.default_rng(seed)
    p0 = rng.multivariate_normal(start.theta[idx], start.covariance, size=walkers)
    for _ in range(20):  # a start of zero density (below an effect's physical bound) would never move: redraw it
        bad = ~np.isfinite(lp(p0)[:, 0])
        if not bad.any():
            break
        p0[bad] = rng.multivariate_normal(start.theta[idx], start.covariance, size=int(bad.sum()))
    contestants = [("emcee defaults (stretch, one call per walker)", False)]
    if vectorised_stretch:
        contestants.append(("emcee stretch, vectorised call", True))
    for label, vec in contestants:
        if vec:
            s = emcee.EnsembleSampler(walkers, n, lambda X: lp(X)[:, 0], vectorize=True)
        else:
            s = emcee.EnsembleSampler(walkers, n, lambda x: lp(x[None])[0, 0])  # emcee's defaults
        s.random_state = np.random.RandomState(seed).get_state()
        k = base_steps if not vec else steps
        t0 = time.perf_counter()
        s.run_mcmc(p0, k)
        rows.append((label, time.perf_counter() - t0, s.get_chain(discard=k // 5), float(np.mean(s.acceptance_fraction)), k))

    table = []
    for label, sec, ch, acc, k in rows:
        half = ch[: ch.shape[0] // 2]
        e_all, e_half = ess(ch), ess(half)
        table.append({"sampler": label, "steps": k, "seconds": sec, "acceptance": acc, "ess_bulk": e_all,
                      "ess_tail": ess(ch, "tail"), "growth": e_all / max(e_half, 1e-9), "ess_per_s": e_all / sec})
    return {"case": name, "description": desc, "n": n, "walkers": walkers, "success": ours.success,
            "message": ours.message, "posterior": "linearised at the MAP" if linearised else "exact kinematics",
            "rows": table}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=1000, help="bayescal steps per walker (the CLI default, 1000)")
    ap.add_argument("--base-steps", type=int, default=500, help="emcee default sampler's steps per walker (default 500)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, from {', '.join(CASES)}")
    ap.add_argument("--linearised", action="store_true", help="sample the models linearised at the MAP instead")
    ap.add_argument("--vectorised-stretch", action="store_true", help="add emcee's stretch move with the vectorised call")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out"), help="folder for the simulated recordings")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0]
    print(f"load average at start: {load:.1f}; ESS = minimum over parameters of arviz's bulk ESS (walkers as chains)")
    ratios = []
    for name in args.cases.split(","):
        r = run_case(name.strip(), out, args.steps, args.base_steps, args.seed, args.linearised, args.vectorised_stretch)
        print(f"\n{r['case']}: {r['description']}; posterior: {r['posterior']}; {r['n']} parameters, {r['walkers']} walkers"
              + ("" if r["success"] else f"  [bayescal's convergence checks: {r['message']}]"))
        print(f"  {'sampler':<68}{'steps':>6}{'seconds':>9}{'accept':>8}{'min bulk ESS':>14}{'min tail ESS':>14}"
              f"{'growth':>8}{'ESS/s':>10}")
        for row in r["rows"]:
            print(f"  {row['sampler']:<68}{row['steps']:6d}{row['seconds']:9.1f}{row['acceptance']:8.2f}"
                  f"{row['ess_bulk']:14.0f}{row['ess_tail']:14.0f}{row['growth']:8.2f}{row['ess_per_s']:10.2f}")
        ratio = r["rows"][0]["ess_per_s"] / r["rows"][2]["ess_per_s"]
        bent = r["rows"][0]["ess_per_s"] / r["rows"][1]["ess_per_s"]
        ratios.append((name, ratio, bent))
        print(f"  ratio of ESS/s, bayescal / emcee defaults: {ratio:.0f}x (target >= 10x); "
              f"bent / straight proposal: {bent:.2f}x")
    print("\nsummary (bayescal / emcee defaults; bent / straight): "
          + "; ".join(f"{c} {x:.0f}x, {b:.2f}x" for c, x, b in ratios))
    return 0


if __name__ == "__main__":
    sys.exit(main())
