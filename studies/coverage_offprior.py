"""Coverage of the 90 % intervals when the true machines do NOT come from the prior the methods assume.

    python studies/coverage_offprior.py [--quick] [--n-linear N] [--n-exact N] [--out DIR]

``studies/coverage.py`` draws its true machines from the very tolerance prior
the methods use, so 90 % coverage there is close to a consistency check.
Here the truths are drawn off that prior (tolerance-scaled errors ``x``,
``theta = tolerance * x``):

* ``gauss c``: ``x ~ N(0, c^2)`` for ``c`` = 0.5, 1, 2, 4 (machines better or
  worse than the machine file's tolerances say);
* ``uniform c``: ``x ~ U(-sqrt(3) c, sqrt(3) c)`` (the same variance as
  ``gauss c``, other shape), ``c`` = 0.5, 1, 2, 4;
* ``3sigma``: ``x ~ N(0, 1)`` with 3 randomly chosen parameters set to +-3.

Methods (``_eb``: the prior scale estimated from the data by the evidence,
:func:`bayescal.bayes.priors.empirical_bayes_map`; otherwise the tolerance prior):

* ``ls`` (identifiable set, covariance ``(A^T A)^-1``), ``map`` and ``map_eb``
  on the identifiable set, ``map_all`` and ``map_all_eb`` on all parameters.
  As in ``studies/coverage.py``, the methods on the identifiable set are
  judged against the projected truth, ``map_all*`` against the truth itself.
  (In the linear-Gaussian model the Kalman filter with zero process noise and
  the exact posterior sampled by MCMC coincide with ``map``; they are not
  run separately.)

Two parts, both on the 3-PRS example (36 poses drawn per data set within
``q_limits``, 20 fresh evaluation poses):

1. **linear-Gaussian** (``--n-linear`` data sets per measurement type and
   truth, default 400, cycling through 20 seeded designs of 36 poses): the
   model linearised at nominal, Gaussian whitened noise, every method in closed form (the empirical-Bayes scale by
   :func:`bayescal.identify.choose.evidence_lambda`, like the ridge evidence
   rule); 6-DOF, 5-DOF and position-only (3) measurement;
2. **exact kinematics** (``--n-exact`` machines per measurement type and
   truth, default 30): simulated recordings (``bayescal.simulate``), the
   library's own ``identify`` / ``map_estimate(prior_scale=...)``.

Reported per method, measurement type and truth: coverage of the parameter
intervals and of the tool-point intervals at fresh poses (per axis), with the
standard error over data sets, and the mean and RMS standardised error
``(estimate - truth) / sd``.  Target (issue 17): parameter and tool-point
coverage in 85-95 % for every truth of scale 0.5-2 (gauss and uniform), per
measurement type and part, for ``ls``, ``map_eb`` and ``map_all_eb``; each
check is printed PASS or MISS (``map`` and ``map_all``, which take the
tolerances as given, are printed for reference) and the exit code is 1 if
any is missed, 0 only when all are met.  Writes ``coverage_offprior.md``
and ``.json`` to ``--out``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from studies.targets import verdict  # noqa: E402

from bayescal.identify import resolve_free  # noqa: E402
from bayescal.identify.choose import evidence_lambda  # noqa: E402
from bayescal.io import write_json_atomic, write_text_atomic  # noqa: E402
from bayescal.machines.files import load_machine  # noqa: E402
from bayescal.measurement import MeasurementModel  # noqa: E402
from bayescal.simulate import draw_poses, simulate_recording  # noqa: E402
from coverage_common import Z90, fit_methods, parameter_target, z_scores  # noqa: E402

TRUTHS = ("gauss 1", "gauss 0.5", "gauss 2", "gauss 4", "uniform 0.5", "uniform 1", "uniform 2", "uniform 4", "3sigma")
EXACT_TRUTHS = ("gauss 0.5", "uniform 1", "gauss 2", "3sigma", "gauss 4")
METHODS = ("ls", "map", "map_eb", "map_all", "map_all_eb")
SEED = 1700
#: The target (issue 17): 90 % intervals cover 85-95 % for truths of scale 0.5-2 ...
TARGET_LO, TARGET_HI = 0.85, 0.95
#: ... for the methods bayescal offers as honest off the prior: ``ls`` (no prior) and the
#: empirical-Bayes MAPs (``identify --method map``'s default). ``map`` and ``map_all`` take the
#: tolerances as given and are shown for reference: they cannot hold when the tolerances are wrong.
TARGET_METHODS = ("ls", "map_eb", "map_all_eb")
N_POSES = 36


def draw_truth(kind: str, P: int, rng) -> np.ndarray:
    """Tolerance-scaled errors ``x`` (theta = tolerance * x) of one true machine."""
    if kind == "3sigma":
        x = rng.normal(size=P)
        pick = rng.choice(P, 3, replace=False)
        x[pick] = 3.0 * rng.choice([-1.0, 1.0], 3)
        return x
    shape, c = kind.split()
    c = float(c)
    if shape == "gauss":
        return c * rng.normal(size=P)
    return rng.uniform(-np.sqrt(3) * c, np.sqrt(3) * c, P)


def record(stats: dict, method: str, zp: np.ndarray, zt: np.ndarray) -> None:
    s = stats.setdefault(method, {"p_in": [], "t_in": [], "pz": [], "tz": []})
    s["p_in"].append(np.mean(np.abs(zp) <= Z90))
    s["t_in"].append(np.mean(np.abs(zt) <= Z90))
    s["pz"].append(zp)
    s["tz"].append(zt)


def summarise(stats: dict) -> dict:
    out = {}
    for m, s in stats.items():
        n = len(s["p_in"])
        pz, tz = np.concatenate(s["pz"]), np.concatenate(s["tz"])
        out[m] = {
            "n": n,
            "parameters": float(np.mean(s["p_in"])), "parameters_se": float(np.std(s["p_in"], ddof=1) / np.sqrt(n)),
            "tool_points": float(np.mean(s["t_in"])), "tool_points_se": float(np.std(s["t_in"], ddof=1) / np.sqrt(n)),
            "param_z_mean": float(pz.mean()), "param_z_rms": float(np.sqrt(np.mean(pz**2))),
            "tool_z_mean": float(tz.mean()), "tool_z_rms": float(np.sqrt(np.mean(tz**2))),
        }
    return out


# ------------------------------------------------------------------- linear-Gaussian, closed form
def pose_pool(machine, dof: int, rng, n_sets: int = 20) -> list[tuple]:
    """``n_sets`` designs of 36 poses: (A whitened and scaled, identifiable idx, fixed idx, K projection)."""
    P, tol = machine.n_params, machine.tolerance
    pool = []
    for _ in range(n_sets):
        q = draw_poses(machine, N_POSES, rng)
        model = MeasurementModel(machine, q, dof=dof)
        A = (model.jacobian(None, model.predict(None)) / model.sigma[None, :, None]).reshape(-1, P) * tol
        idx, _ = resolve_free(model, None, np.zeros(P))
        fix = np.setdiff1d(np.arange(P), idx)
        K = np.linalg.lstsq(A[:, idx], A[:, fix], rcond=None)[0] if fix.size else np.zeros((idx.size, 0))
        pool.append((A, idx, fix, K))
    return pool


def linear_case(machine, pool: list, truth: str, n: int, rng, G: np.ndarray) -> dict:
    """Closed-form coverage of every method over ``n`` linear-Gaussian data sets (designs cycled from ``pool``).

    ``G``: tolerance-scaled tool-point Jacobians at the fresh poses (mm per scaled unit), shape (3 n_fresh, P).
    """
    P = machine.n_params
    stats: dict = {}
    for t in range(n):
        A, idx, fix, K = pool[t % len(pool)]
        x = draw_truth(truth, P, rng)
        z = A @ x + rng.normal(size=A.shape[0])
        x_eq = x[idx] + K @ x[fix]  # the reduced-model parameters that reproduce the truth at these poses
        t_true = G @ x
        for m in METHODS:
            cols = np.arange(P) if m.startswith("map_all") else idx
            Ac = A[:, cols]
            lam = 0.0 if m == "ls" else (evidence_lambda(Ac, z) if m.endswith("_eb") else 1.0)
            C = np.linalg.inv(Ac.T @ Ac + lam * np.eye(cols.size))
            est = C @ (Ac.T @ z)
            target = x if m.startswith("map_all") else x_eq
            zp = (est - target) / np.sqrt(np.diag(C))
            Gc = G[:, cols]
            zt = (t_true - Gc @ est) / np.sqrt(np.einsum("ij,jk,ik->i", Gc, C, Gc))
            record(stats, m, zp, zt)
    return summarise(stats)


# ------------------------------------------------------------------------- exact kinematics
def exact_case(machine, dof: int, truth: str, n: int, seed0: int, q_fresh) -> dict:
    """Coverage over ``n`` simulated recordings identified by the library's own functions."""
    P, tol = machine.n_params, machine.tolerance
    stats: dict = {}
    failed = {m: 0 for m in METHODS}
    for i in range(n):
        rng = np.random.default_rng([seed0, i])
        theta = tol * draw_truth(truth, P, rng)
        sim = simulate_recording(machine, N_POSES, seed=seed0 * 1000 + i, dof=dof, theta_true=theta)
        model = MeasurementModel.from_recording(machine, sim.recording)
        p_true = machine.forward(q_fresh, theta).position
        if not machine.forward(q_fresh, theta).success.all():
            continue
        fits = fit_methods(model, METHODS, q_fresh)
        for m, res in fits.items():
            if not res.success:
                failed[m] += 1
                continue
            target = parameter_target(model, theta, res.free, all_params=m.startswith("map_all"))
            zp, zt = z_scores(machine, res, target, q_fresh, p_true)
            record(stats, m, zp, zt.ravel())
    out = summarise(stats)
    for m in out:
        out[m]["failed"] = failed[m]
    return out


def table(results: dict, title: str) -> list[str]:
    lines = [f"### {title}", "",
             "| measurement | truth | method | parameters | tool points | mean z (params) | RMS z (params) | "
             "mean z (tool) | RMS z (tool) |", "|---|---|---|---|---|---|---|---|---|"]
    for dof, by_truth in results.items():
        for truth, by_m in by_truth.items():
            for m, t in by_m.items():
                lines.append(
                    f"| {dof}-DOF | {truth} | {m} | {100 * t['parameters']:.1f} ({100 * t['parameters_se']:.1f}) | "
                    f"{100 * t['tool_points']:.1f} ({100 * t['tool_points_se']:.1f}) | {t['param_z_mean']:+.2f} | "
                    f"{t['param_z_rms']:.2f} | {t['tool_z_mean']:+.2f} | {t['tool_z_rms']:.2f} |")
    return lines + [""]


def _in_scope(truth: str) -> bool:
    """Truths the target covers: gauss and uniform of scale 0.5-2 (not 4, not 3sigma)."""
    return truth != "3sigma" and 0.5 <= float(truth.split()[1]) <= 2


def target_check(results: dict, part: str) -> list[dict]:
    """One check per measurement type and method: parameter and tool-point coverage in 85-95 % for every truth of scale 0.5-2.

    Returns dicts with ``part``, ``dof``, ``method``, ``targeted`` (the
    methods of :data:`TARGET_METHODS`; the tolerance-prior ``map`` and
    ``map_all`` are reported for reference), ``ok``, the truths checked
    and the range of each coverage over them.
    """
    out = []
    for dof, by_truth in results.items():
        for m in METHODS:
            cells = [(t, by_m[m]) for t, by_m in by_truth.items() if _in_scope(t) and m in by_m]
            if not cells:
                continue
            p = [c["parameters"] for _, c in cells]
            tp = [c["tool_points"] for _, c in cells]
            ok = all(TARGET_LO <= v <= TARGET_HI for v in p + tp)
            out.append({"part": part, "dof": dof, "method": m, "targeted": m in TARGET_METHODS, "ok": bool(ok),
                        "truths": [t for t, _ in cells], "parameters": [min(p), max(p)], "tool_points": [min(tp), max(tp)]})
    return out


def check_lines(checks: list[dict]) -> list[str]:
    """PASS / MISS per targeted check; the reference methods marked as such."""
    lines = []
    for c in checks:
        tag = verdict(c["ok"]) if c["targeted"] else ("ref (in range)" if c["ok"] else "ref (out of range)")
        lines.append(
            f"{tag:<18} {c['part']:<7} {c['dof']}-DOF {c['method']:<11} parameters {100 * c['parameters'][0]:.1f}-"
            f"{100 * c['parameters'][1]:.1f} %, tool points {100 * c['tool_points'][0]:.1f}-{100 * c['tool_points'][1]:.1f} % "
            f"over {len(c['truths'])} truths (target {100 * TARGET_LO:.0f}-{100 * TARGET_HI:.0f} %)")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a few data sets, 6-DOF only (for the tests)")
    ap.add_argument("--n-linear", type=int, default=None, help="linear-Gaussian data sets per case (default 400)")
    ap.add_argument("--n-exact", type=int, default=None, help="exact-kinematics machines per case (default 30)")
    ap.add_argument("--machine", default=str(ROOT / "examples" / "prs3" / "machine.toml"))
    ap.add_argument("--out", default=str(ROOT / "studies" / "out" / "coverage_offprior"))
    args = ap.parse_args(argv)
    n_lin = args.n_linear if args.n_linear is not None else (15 if args.quick else 400)
    n_ex = args.n_exact if args.n_exact is not None else (3 if args.quick else 30)
    dofs = (6,) if args.quick else (6, 5, 3)
    truths = ("gauss 2", "uniform 1") if args.quick else TRUTHS
    exact_truths = ("gauss 2",) if args.quick else EXACT_TRUTHS
    machine = load_machine(args.machine)
    q_fresh = draw_poses(machine, 20, np.random.default_rng(SEED - 1))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    lin: dict = {}
    G = machine.tool_jacobian(q_fresh, None, machine.forward(q_fresh))[:, :3, :].reshape(-1, machine.n_params)
    G = G * machine.tolerance
    for dof in dofs:
        lin[dof] = {}
        pool = pose_pool(machine, dof, np.random.default_rng([SEED, dof]), 5 if args.quick else 20)
        for j, truth in enumerate(truths):
            lin[dof][truth] = linear_case(machine, pool, truth, n_lin, np.random.default_rng([SEED, dof, j, 1]), G)
        print(f"linear {dof}-DOF: {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    exact: dict = {}
    for dof in dofs[:2]:
        exact[dof] = {}
        for j, truth in enumerate(exact_truths):
            exact[dof][truth] = exact_case(machine, dof, truth, n_ex, SEED + 100 * dof + j, q_fresh)
        print(f"exact {dof}-DOF: {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    seconds = time.perf_counter() - t0
    checks = target_check(lin, "linear") + target_check(exact, "exact")
    lines = check_lines(checks)
    missed = sum(1 for c in checks if c["targeted"] and not c["ok"])
    verdict = (f"all {sum(c['targeted'] for c in checks)} targeted checks met" if not missed
               else f"{missed} of {sum(c['targeted'] for c in checks)} targeted checks MISSED")
    summary = {"n_linear": n_lin, "n_exact": n_ex, "linear": lin, "exact": exact, "targets": checks,
               "targets_met": not missed, "seconds": seconds}
    md = [f"# Coverage of 90 % intervals with true machines off the prior ({seconds:.0f} s)", "",
          "Coverage in % (standard error over data sets); z = (estimate - truth) / sd. Target: "
          f"{100 * TARGET_LO:.0f}-{100 * TARGET_HI:.0f} % for parameters and tool points, for every truth of scale "
          f"0.5-2 (gauss and uniform), per measurement type, for {', '.join(TARGET_METHODS)} "
          "(map and map_all, the tolerance prior as given, for reference).", "",
          "```text", *lines, verdict, "```", "",
          *table(lin, f"Linear-Gaussian, {n_lin} data sets per row"),
          *table(exact, f"Exact kinematics, {n_ex} machines per row")]
    write_json_atomic(out / "coverage_offprior.json", summary)
    write_text_atomic(out / "coverage_offprior.md", "\n".join(md) + "\n")
    print("\n".join(md))
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
