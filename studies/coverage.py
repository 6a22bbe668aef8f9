"""Coverage of the nominal 90% intervals of every identification method, over machines drawn from the prior.

For each simulated machine (true errors drawn from the tolerance prior, all
parameters, including the ones the measurement cannot identify) a recording
with the instrument noise of the example machine is simulated and
identified with

* ``ls``: Gauss-Newton least squares on the identifiable set, covariance (A^T A)^-1;
* ``map``: MAP on the identifiable set (= ridge lam = 1), Laplace covariance;
* ``map_all``: MAP on all parameters (the prior decides the null space);
* ``kalman``: the EKF over the poses (identifiable set), final covariance;
* ``mcmc``: the emcee posterior (identifiable set, exact kinematics by
  default, ``--surrogate linear`` for the model linearised at the MAP),
  5-95% quantiles.  A refused (unconverged) posterior counts as a failure.

Quantities whose coverage is counted:

1. identifiable parameters.  Only combinations outside the null space are
   determined, so for the methods on the identifiable set the truth they
   estimate is the *projected* truth: ``theta_eq = theta[idx] + K theta[fixed]``
   with ``K = pinv(J_idx) J_fixed`` (whitened Jacobian at nominal), the
   reduced-model parameters that reproduce the true machine.  For
   ``map_all`` it is the truth itself (its posterior covers the null space
   with the prior).
2. tool points at fresh poses (not in the recording): the true
   ``p(q, theta)`` against ``p(q, theta_hat) +- 1.645 sqrt(diag(G C G^T))``,
   per axis.

Every machine is seeded by its index (``seed + i``), so the tables are the
same for any number of worker processes (``--workers``).

Run: ``python studies/coverage.py [--quick] [--n-machines 200] [--n-mcmc N] [--workers 2] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bayescal.bayes.accuracy import tool_point_draws  # noqa: E402
from bayescal.bayes.mcmc import sample_posterior  # noqa: E402
from bayescal.io import write_json_atomic, write_text_atomic  # noqa: E402
from bayescal.machines.files import load_machine  # noqa: E402
from bayescal.measurement import MeasurementModel  # noqa: E402
from bayescal.simulate import draw_poses, simulate_recording  # noqa: E402
from coverage_common import Z90, fit_methods, parameter_target, z_scores  # noqa: E402

METHODS = ("ls", "map", "map_all", "kalman", "mcmc")


def one_machine(
    machine, seed: int, n_poses: int, dof: int, q_fresh: np.ndarray, do_mcmc: bool, mcmc_steps: int,
    surrogate: str = "none",
) -> dict:
    """Inside-the-interval indicators (and z scores) per method and quantity for one simulated machine."""
    sim = simulate_recording(machine, n_poses, seed=seed, dof=dof)
    model = MeasurementModel.from_recording(machine, sim.recording)
    truth = sim.theta_true
    p_true = machine.forward(q_fresh, truth).position
    out: dict = {"seed": seed}
    fits = fit_methods(model, ("ls", "map", "map_all", "kalman"), q_fresh)
    if do_mcmc:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fits["mcmc"] = sample_posterior(model, n_steps=mcmc_steps, surrogate=surrogate, seed=seed)
    for name, res in fits.items():
        if not res.success:
            out[name] = {"failed": res.message}
            continue
        if name == "mcmc":
            out["mcmc_seconds"] = res.seconds
        idx = np.flatnonzero(res.free)
        target = parameter_target(model, truth, res.free, all_params=name == "map_all")
        if name == "mcmc":
            lo, hi = res.quantiles[0], res.quantiles[2]
            inside_p = (target >= lo) & (target <= hi)
            z_p = (target - res.mean) / np.sqrt(np.diag(res.covariance))
            # tool points: push thinned posterior draws through the kinematics (one vectorised call)
            draws = res.samples[:: max(1, res.samples.shape[0] // 300)]
            pos = tool_point_draws(machine, q_fresh, res.theta, idx, draws)
            qlo, qhi = np.quantile(pos, [0.05, 0.95], axis=0)
            inside_t = (p_true >= qlo) & (p_true <= qhi)
            z_t = (p_true - pos.mean(axis=0)) / pos.std(axis=0, ddof=1)
        else:
            z_p, z_t = z_scores(machine, res, target, q_fresh, p_true)
            inside_p = np.abs(z_p) <= Z90
            inside_t = np.abs(z_t) <= Z90
        out[name] = {
            "param_inside": inside_p.astype(float).tolist(),
            "param_z": z_p.tolist(),
            "tool_inside": inside_t.astype(float).ravel().tolist(),
            "tool_z": z_t.ravel().tolist(),
        }
    return out


def summarise(rows: list[dict]) -> dict:
    table = {}
    for m in METHODS:
        got = [r[m] for r in rows if m in r and "failed" not in r[m]]
        tried = sum(1 for r in rows if m in r)
        reasons = sorted({r[m]["failed"].split(":")[0] for r in rows if m in r and "failed" in r[m]})
        if not got:
            continue
        pi = np.concatenate([g["param_inside"] for g in got])
        ti = np.concatenate([g["tool_inside"] for g in got])
        pz = np.concatenate([g["param_z"] for g in got])
        tz = np.concatenate([g["tool_z"] for g in got])
        # per-machine fractions give a standard error that respects within-machine correlation
        per_p = np.array([np.mean(g["param_inside"]) for g in got])
        per_t = np.array([np.mean(g["tool_inside"]) for g in got])
        table[m] = {
            "machines": len(got),
            "failed": tried - len(got),
            "failure_kinds": reasons,
            "parameters": float(pi.mean()),
            "parameters_se": float(per_p.std(ddof=1) / np.sqrt(len(got))) if len(got) > 1 else float("nan"),
            "tool_points": float(ti.mean()),
            "tool_points_se": float(per_t.std(ddof=1) / np.sqrt(len(got))) if len(got) > 1 else float("nan"),
            "param_z_rms": float(np.sqrt(np.mean(pz**2))),
            "tool_z_rms": float(np.sqrt(np.mean(tz**2))),
        }
    return table


def markdown(table: dict, args, seconds: float) -> str:
    mc = "exact kinematics" if args.surrogate == "none" else f"{args.surrogate} surrogate"
    lines = [
        f"Coverage of nominal 90% intervals ({args.n_machines} machines drawn from the prior, "
        f"{args.poses} poses, {args.dof}-DOF, seed {args.seed}; mcmc on {args.n_mcmc} ({mc}, "
        f"{args.mcmc_steps} steps); "
        + (f"{seconds:.0f} s with {args.workers} worker(s))" if np.isfinite(seconds) else "rebuilt from the rows of a run)"),
        "",
        "| method | machines | parameters | tool points (fresh poses) | RMS z params | RMS z tool |",
        "|---|---|---|---|---|---|",
    ]
    for m, t in table.items():
        lines.append(
            f"| {m} | {t['machines']}{' (+%d failed)' % t['failed'] if t['failed'] else ''} | "
            f"{t['parameters']:.3f} +- {t['parameters_se']:.3f} | {t['tool_points']:.3f} +- {t['tool_points_se']:.3f} | "
            f"{t['param_z_rms']:.2f} | {t['tool_z_rms']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def _run_one(job: tuple) -> dict:
    """One machine in a worker process (top level, so a spawned process can import it)."""
    machine_path, *rest = job
    return one_machine(load_machine(machine_path), *rest)


def run_machines(args, q_fresh: np.ndarray, log_path: Path | None = None) -> list[dict]:
    """All machines, in index order, in this process or ``args.workers`` processes (same rows either way)."""
    jobs = [
        (args.machine, args.seed + i, args.poses, args.dof, q_fresh, i < args.n_mcmc, args.mcmc_steps, args.surrogate)
        for i in range(args.n_machines)
    ]
    t0 = time.perf_counter()
    log = open(log_path, "w") if log_path is not None else None  # progress log, one JSON row per machine
    rows = []
    try:
        if args.workers > 1:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            ex = ProcessPoolExecutor(max_workers=args.workers, mp_context=multiprocessing.get_context("spawn"))
            results = ex.map(_run_one, jobs)
        else:
            ex, results = None, map(_run_one, jobs)
        for row in results:
            rows.append(row)
            if log is not None:
                log.write(json.dumps(row) + "\n")
                log.flush()
            if len(rows) % 10 == 0:
                print(f"  {len(rows)}/{args.n_machines} machines, {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        if ex is not None:
            ex.shutdown()
    finally:
        if log is not None:
            log.close()
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="10 machines, 30 poses, MCMC (linear surrogate) on 2 of them (for the test suite)")
    ap.add_argument("--n-machines", type=int, default=200)
    ap.add_argument("--n-mcmc", type=int, default=None, help="machines also sampled with MCMC (default: all)")
    ap.add_argument("--mcmc-steps", type=int, default=240,
                    help="steps per walker (default 240: about 70 autocorrelation times with the default moves)")
    ap.add_argument("--surrogate", choices=("none", "linear"), default="none",
                    help="MCMC model: exact kinematics (default) or linearised at the MAP")
    ap.add_argument("--poses", type=int, default=36)
    ap.add_argument("--dof", type=int, default=6)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--workers", type=int, default=1, help="worker processes (the answer does not depend on it)")
    ap.add_argument("--machine", default=str(ROOT / "examples" / "prs3" / "machine.toml"))
    ap.add_argument("--out", default=str(ROOT / "studies" / "out" / "coverage"))
    ap.add_argument("--from-rows", metavar="ROWS.jsonl",
                    help="only rebuild the tables and figure from the per-machine rows of a run (for example an "
                         "interrupted one: its rows are the first machines, in order); the other options must be "
                         "those of that run")
    args = ap.parse_args(argv)
    if args.quick:
        args.n_machines, args.n_mcmc, args.poses, args.surrogate = 10, 2, 30, "linear"
    if args.n_mcmc is None:
        args.n_mcmc = args.n_machines
    machine = load_machine(args.machine)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    q_fresh = draw_poses(machine, 20, np.random.default_rng(args.seed - 1))
    t0 = time.perf_counter()
    if args.from_rows:
        rows = [json.loads(line) for line in Path(args.from_rows).read_text().splitlines() if line.strip()]
        if [r["seed"] for r in rows] != [args.seed + i for i in range(len(rows))]:
            raise SystemExit(f"{args.from_rows}: rows are not machines seed {args.seed}, {args.seed + 1}, ... in order")
        args.n_machines, args.n_mcmc = len(rows), min(args.n_mcmc, len(rows))
        seconds = float("nan")
    else:
        rows = run_machines(args, q_fresh, out / "rows.jsonl")
        seconds = time.perf_counter() - t0
    table = summarise(rows)
    write_json_atomic(out / "coverage.json", {"table": table, "args": vars(args), "seconds": seconds})
    md = markdown(table, args, seconds)
    write_text_atomic(out / "coverage.md", md)
    from bayescal.plots.bayes import plot_coverage

    plot_coverage(
        {m: {"parameters": t["parameters"], "tool points": t["tool_points"]} for m, t in table.items()},
        out / "coverage.png",
    )
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
