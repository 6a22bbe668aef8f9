"""Benchmark: bayescal's Gauss-Newton LS against scipy.optimize.least_squares.

One full identification of the bundled 3-PRS (``examples/prs3/machine.toml``):
36 poses, 6-DOF, simulated with a fixed seed, the automatically identified
parameter set (33 parameters), iterated to convergence.

* bayescal: ``identify(model, method="ls")`` (analytic Jacobian by the
  implicit function theorem, warm-started forward kinematics; the timing
  includes the identifiability analysis that picks the free set).
* baselines: ``scipy.optimize.least_squares`` (trust-region reflective)
  with a finite-difference Jacobian, on the same whitened residual
  ``W (y - h(theta))`` (the same ``MeasurementModel.predict``, warm-started
  from the measurement), the same free parameters (scaled by the
  tolerances, as bayescal does) and the same data, in the same run.  Two
  variants: the default two-point differences, and three-point (central)
  differences; a third run gives scipy bayescal's analytic Jacobian, to
  show how much of the gain is the Jacobian and how much the iteration.
  The problem is ill-conditioned (condition number about
  1e5 in scaled coordinates), so the two-point Jacobian's round-off error
  moves the point where the iteration stalls by a few hundredths of a mm;
  only the three-point variant reaches the same answer to 1e-6 mm, so the
  headline ratio is taken against it.

Both are timed as the best of several repeats (``time.perf_counter``); the
answers are compared by the largest difference of predicted tool points on
fresh poses.  Prints a table and writes it as JSON to ``benchmarks/out/``.

Run from the repository root::

    python benchmarks/identify_vs_scipy.py [--repeats 5] [--seed 7] [--out benchmarks/out]
    python benchmarks/identify_vs_scipy.py --machine examples/arm6/machine.toml --poses 1000 --repeats 2 --scipy-repeats 1

Any machine file works (``--machine``); the second line is the serial-arm case: a six-revolute arm, 1,000
poses.  The JSON goes to ``identify_vs_scipy[_<machine folder>].json``.
"""

from __future__ import annotations

import argparse
import os

# Single-threaded BLAS for both contestants, set before numpy loads: the matrices are small
# (216 x 33), where OpenBLAS threads only add overhead, and on a shared machine a threaded
# SVD of that size was measured 10x slower (50 ms instead of 4 ms).  Override from outside.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import platform
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import scipy
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bayescal.identify import identify, resolve_free, whitened_system  # noqa: E402
from bayescal.io import write_json_atomic  # noqa: E402
from bayescal.machines.files import load_machine  # noqa: E402
from bayescal.measurement import MeasurementModel  # noqa: E402
from bayescal.simulate import simulate_recording  # noqa: E402

MACHINE = ROOT / "examples" / "prs3" / "machine.toml"


def best_time(fn, repeats: int):
    """Best wall time (s) over ``repeats`` calls, and the last answer."""
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def make_scipy_fit(model: MeasurementModel, idx: np.ndarray, jac: str):
    """``jac``: "2-point", "3-point", or "analytic" (bayescal's Jacobian, to separate the
    gain of the analytic Jacobian from that of the iteration)."""
    """The baseline: least_squares on the whitened residual over the scaled free parameters."""
    machine = model.machine
    S = machine.tolerance[idx]
    sig = model.sigma
    counter = {"nfev": 0}

    def theta_of(phi):
        theta = np.zeros(machine.n_params)
        theta[idx] = S * phi
        return theta

    def fun(phi):
        counter["nfev"] += 1
        pred = model.predict(theta_of(phi))
        if not pred.success.all():
            # an unsolvable pose: least_squares rejects a step with non-finite residuals
            # and shrinks its trust region (a large finite value would end it by ftol)
            return np.full(model.n_poses * model.dof, np.nan)
        return (model.residual(pred) / sig).reshape(-1)

    def analytic(phi):
        theta = theta_of(phi)
        _, J = whitened_system(model, theta, model.predict(theta))
        return -J[:, idx] * S  # fun is the residual y - h: its derivative is -dh/dtheta

    def fit():
        counter["nfev"] = 0
        jac_arg = analytic if jac == "analytic" else jac
        sol = least_squares(fun, np.zeros(idx.size), jac=jac_arg, method="trf", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        return sol, theta_of(sol.x), counter["nfev"]

    return fit


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="timing repeats of bayescal, best taken (default 5)")
    ap.add_argument("--scipy-repeats", type=int, default=2, help="timing repeats of each scipy run (default 2)")
    ap.add_argument("--seed", type=int, default=7, help="simulation seed (default 7)")
    ap.add_argument("--poses", type=int, default=36)
    ap.add_argument("--machine", default=str(MACHINE), help="machine file (default: the bundled 3-PRS)")
    ap.add_argument(
        "--baselines", default="2-point,3-point,analytic",
        help="comma-separated scipy Jacobians to run: 2-point, 3-point, analytic (default: all)",
    )
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out"), help="folder for the JSON table")
    args = ap.parse_args(argv)

    machine_path = Path(args.machine).resolve()
    machine = load_machine(machine_path)
    sim = simulate_recording(machine, args.poses, seed=args.seed, dof=6)
    model = MeasurementModel.from_recording(machine, sim.recording)
    idx, _ = resolve_free(model, "auto", np.zeros(machine.n_params))
    fresh_q = machine.sample_q(500, np.random.default_rng(args.seed + 1000))

    def chi2(theta):
        return float(np.sum((model.residual(model.predict(theta)) / model.sigma) ** 2))

    t_bc, res = best_time(lambda: identify(model, method="ls"), args.repeats)
    assert res.success, res.message
    assert np.array_equal(np.flatnonzero(res.free), idx)
    p_bc = machine.forward(fresh_q, res.theta).position
    p_true = machine.forward(fresh_q, sim.theta_true).position
    rows = [{
        "solver": "bayescal identify(method='ls'), analytic Jacobian", "label": "bayescal identify(ls)",
        "time_s": t_bc, "iterations": res.iterations, "residual_evaluations": res.iterations + 1,
        "chi2": chi2(res.theta), "max_tool_point_difference_mm": 0.0, "ratio": 1.0,
    }]
    for jac in [b.strip() for b in args.baselines.split(",") if b.strip()]:
        t_sp, (sol, theta_sp, nfev) = best_time(make_scipy_fit(model, idx, jac), args.scipy_repeats)
        diff = float(np.abs(machine.forward(fresh_q, theta_sp).position - p_bc).max())
        rows.append({
            "solver": f"scipy least_squares(method='trf', jac='{jac}', xtol=ftol=gtol=1e-15)",
            "label": f"scipy least_squares ({jac}{' FD' if jac != 'analytic' else ' J'})",
            "time_s": t_sp, "iterations": int(sol.njev or 0), "residual_evaluations": nfev, "chi2": chi2(theta_sp),
            "status": int(sol.status), "max_tool_point_difference_mm": diff, "ratio": t_sp / t_bc,
        })
    # the headline baseline: finite differences only (the analytic-J row is for insight)
    agree = [r for r in rows[1:] if r["max_tool_point_difference_mm"] <= 1e-6 and "analytic" not in r["label"]]
    headline = min(agree, key=lambda r: r["time_s"]) if agree else None
    ratio = headline["ratio"] if headline else None
    table = {
        "benchmark": "identify_vs_scipy",
        "problem": {
            "machine": str(machine_path.relative_to(ROOT)) if machine_path.is_relative_to(ROOT) else str(machine_path),
            "poses": args.poses, "dof": 6, "seed": args.seed,
            "free_parameters": int(idx.size), "fresh_poses": len(fresh_q),
        },
        "rows": rows,
        "speed_ratio": ratio,
        "speed_ratio_baseline": None if headline is None else headline["solver"],
        "rms_against_truth_mm": float(np.sqrt(np.mean(np.sum((p_bc - p_true) ** 2, axis=1)))),
        "target": {"speed_ratio": 20.0, "max_tool_point_difference_mm": 1e-6},
        # the 20x target is the 3-PRS's (issue 2); other machines report their ratio and the agreement only
        "passed": bool(ratio is not None and (ratio >= 20.0 or machine_path != MACHINE.resolve())),
        "repeats": {"bayescal": args.repeats, "scipy": args.scipy_repeats},
        "environment": {
            "python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
            "machine": platform.machine(), "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"), "cpu_count": os.cpu_count(),
        },
    }
    print(f"identification of {args.poses} poses, 6-DOF, {idx.size} free parameters (seed {args.seed}); "
          f"best of {args.repeats} (bayescal) / {args.scipy_repeats} (scipy) runs")
    print(f"  {'solver':<32}{'time [ms]':>11}{'iter':>6}{'h evals':>9}{'chi2':>14}{'max |dp| [mm]':>15}{'ratio':>9}")
    for r in rows:
        print(f"  {r['label']:<32}{1e3 * r['time_s']:11.1f}{r['iterations']:6d}{r['residual_evaluations']:9d}"
              f"{r['chi2']:14.6f}{r['max_tool_point_difference_mm']:15.2e}{r['ratio']:8.1f}x")
    if headline:
        print(f"  speed ratio against the fastest baseline that agrees to 1e-6 mm ({headline['label']}): "
              f"{ratio:.0f}x (target >= 20x)")
    else:
        print("  no baseline reached bayescal's answer to 1e-6 mm")
    print(f"  max |dp|: largest tool-point difference from bayescal's answer on {len(fresh_q)} fresh poses; "
          f"RMS error of bayescal's model against the truth {table['rms_against_truth_mm']:.4f} mm")
    suffix = "" if machine_path == MACHINE.resolve() else f"_{machine_path.parent.name}"
    out = Path(args.out) / f"identify_vs_scipy{suffix}.json"
    write_json_atomic(out, table)
    print(f"  wrote {out}")
    return 0 if table["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
