"""Study: do planned poses calibrate better than random ones, and with how many fewer?

For the 3-PRS (or any machine file given), with 6-DOF and 5-DOF measurement:
post-calibration output error (RMS and max of the tool-point error over
fresh workspace poses, on simulated machines drawn from the tolerances)
against the number of measured poses, for planned poses (greedy + exchange
from a candidate set, one plan per criterion given, default D and I) and for
random poses from the same candidates.  Identification: ridge with lam = 1
(the MAP estimate under the tolerance prior) and least squares on the
identifiable set (failures counted).

Every design is evaluated identically: trial t draws ONE true machine and
ONE set of fresh evaluation poses, shared by every number of poses and every
design (planned by each criterion, random), and the instrument noise of a
given number of poses is the same stream for every design.  So the target
comparison (planned 18 poses against random 36 poses) is paired per trial:
Wilcoxon signed-rank test and a bootstrap confidence interval of the median
paired difference.

Then a units check: the ranking of pose sets by every criterion, before and
after rescaling the parameters (mm -> um, rad -> urad), with the tolerance
and candidate column scalings and without scaling.

    python studies/pose_planning.py [--quick] [--out DIR] [--criteria D,I] [--trials N]
                                    [--dofs 6,5] [--n-list 8,...,36] [--no-units]

Writes DIR/pose_planning.csv (per design and number of poses),
DIR/trials.csv (every trial), DIR/paired.csv (planned 18 vs random 36),
DIR/units_ranking.csv, DIR/summary.json, DIR/pose_planning.md and
DIR/pose_planning.png (default DIR: studies/out/pose_planning).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import scipy.stats

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bayescal.design import CRITERIA, candidate_set_from_jacobian, check_criterion, criteria_from_singular_values  # noqa: E402
from bayescal.design import draw_candidates, evaluate_selection, expected_output_rms, output_error_bound  # noqa: E402
from bayescal.design import select_from_candidates  # noqa: E402
from bayescal.identify import identify  # noqa: E402
from bayescal.io import write_json_atomic, write_text_atomic  # noqa: E402
from bayescal.machines import load_machine  # noqa: E402
from bayescal.measurement import MeasurementModel  # noqa: E402
from bayescal.plots.design import plot_error_vs_poses  # noqa: E402
from bayescal.simulate import draw_errors, draw_poses, measure  # noqa: E402

# ls_random_n: least squares on random sets only at these numbers of poses.  On smaller random sets LS
# fails in most trials (too ill-conditioned to converge) and each failure costs seconds (50 iterations on
# poses the diverging geometry can hardly solve); the target needs LS on random sets at 36 poses only.
FULL = dict(n_list=[8, 10, 12, 14, 18, 24, 36], trials=100, candidates=20000, n_eval=200, bound_iters=300,
            random_n=None, ls_random_n=[36])
# quick: random sets only at 18 and 36 poses, least squares on them only at 36
QUICK = dict(n_list=[8, 18, 36], trials=3, candidates=300, n_eval=30, bound_iters=10, random_n=[18, 36],
             ls_random_n=[36])
METHODS = (("ridge", ""), ("ls", "ls_"))
#: the target: planned poses reach the median error of N_REF random poses with at most N_TARGET
N_REF, N_TARGET = 36, 18


def output_error(machine, q_eval, true_poses, theta):
    pos = np.linalg.norm(machine.forward(q_eval, theta).position - true_poses.position, axis=1)
    return float(np.sqrt(np.mean(pos**2))), float(pos.max())


def calibrate(machine, q, theta_true, dof, rng, free, method):
    rec = measure(machine, q, theta_true, dof, rng)
    model = MeasurementModel.from_recording(machine, rec, dof=dof)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        kw = {"lam": 1.0} if method == "ridge" else {}
        res = identify(model, method=method, free=free, **kw)
    return res.theta if res.success else None


def _quartiles(v):
    v = v[np.isfinite(v)]
    if not v.size:
        return np.nan, np.nan, np.nan
    return float(np.median(v)), float(np.quantile(v, 0.25)), float(np.quantile(v, 0.75))


def error_study(machine, dof, cfg, seed, criteria=("D", "I"), methods=METHODS, random_n=None):
    """Per-trial errors of every design; returns (rows, trial records, candidates).

    ``methods``: (name, column prefix) pairs of identification methods; ``random_n``: the numbers of
    poses at which random sets are evaluated (default: all of ``cfg["n_list"]``).
    """
    rng = np.random.default_rng([seed, dof])
    cands = draw_candidates(machine, cfg["candidates"], dof=dof, rng=rng)
    planned = {c: {n: select_from_candidates(cands, n, c).index for n in cfg["n_list"]} for c in criteria}
    designs = [f"planned-{c}" for c in criteria] + ["random"]
    free = list(cands.kept)
    trials = []  # one record per (trial, n, design)
    for t in range(cfg["trials"]):
        trng = np.random.default_rng([seed, dof, t])  # the trial's true machine and fresh poses, for every design
        theta = draw_errors(machine, trng)
        q_eval = draw_poses(machine, cfg["n_eval"], trng, theta)
        true_poses = machine.forward(q_eval, theta)
        for n in cfg["n_list"]:
            rand_idx = np.random.default_rng([seed, dof, n, t, 2]).choice(cands.n, n, replace=False)
            for design in designs:
                if design == "random" and random_n is not None and n not in random_n:
                    continue
                idx = rand_idx if design == "random" else planned[design.split("-", 1)[1]][n]
                rec = {"dof": dof, "trial": t, "n_poses": n, "design": design,
                       "predicted_rms": expected_output_rms(cands, idx)}
                for method, pre in methods:
                    if method == "ls" and design == "random" and n not in cfg.get("ls_random_n", [n]):
                        rec[f"{pre}rms"] = rec[f"{pre}max"] = None  # not run (None), unlike a failure (NaN)
                        continue
                    # the same noise stream for every design at this number of poses
                    th = calibrate(machine, cands.q[idx], theta, dof, np.random.default_rng([seed, dof, n, t, 1]),
                                   free, method)
                    e = output_error(machine, q_eval, true_poses, th) if th is not None else (np.nan, np.nan)
                    rec[f"{pre}rms"], rec[f"{pre}max"] = e
                trials.append(rec)
        if (t + 1) % max(1, cfg["trials"] // 10) == 0:
            print(f"  {dof}-DOF: {t + 1}/{cfg['trials']} trials", flush=True)
    rows = []
    for n in cfg["n_list"]:
        for design in designs:
            tr = [r for r in trials if r["n_poses"] == n and r["design"] == design]
            if not tr:
                continue
            row = {"dof": dof, "design": design, "n_poses": n, "trials": len(tr),
                   "predicted_rms": float(np.mean([r["predicted_rms"] for r in tr]))}
            for method, pre in METHODS:
                run = [r for r in tr if r.get(f"{pre}rms") is not None]  # None: method not run on this design
                for name in ("rms", "max"):
                    v = np.array([r[f"{pre}{name}"] for r in run], dtype=float)
                    row[f"{pre}{name}_median"], row[f"{pre}{name}_q25"], row[f"{pre}{name}_q75"] = _quartiles(v)
                # -1 in the tables: not run
                row[f"{pre}failures"] = int(sum(not np.isfinite(r[f"{pre}rms"]) for r in run)) if run else -1
            rows.append(row)
            print(f"  {dof}-DOF {design:10s} n={n:3d}: median RMS {1e3 * row['rms_median']:.2f} um "
                  f"(predicted {1e3 * row['predicted_rms']:.2f}; ls {1e3 * row['ls_rms_median']:.2f} um, "
                  f"{row['ls_failures']} failed of {row['trials']})", flush=True)
    return rows, trials, cands


def linear_bound(cands, trials: list[dict], dof: int, iters: int) -> dict:
    """Linearised check of the target: the best any N_TARGET-pose plan can expect, against N_REF random poses.

    ``output_error_bound`` (Frank-Wolfe on the relaxed I criterion, started from the I plan) gives a
    certified lower bound on the expected RMS error (linear-Gaussian model, MAP under the tolerance prior)
    of every N_TARGET-pose plan from these candidates; the random reference is the median predicted RMS of
    the trials' random N_REF-pose sets.
    """
    start = select_from_candidates(cands, N_TARGET, "I").index
    b = output_error_bound(cands.prior_blocks_kept, cands.output_weight, N_TARGET, start=start, iters=iters)
    rand = [r["predicted_rms"] for r in trials if r["dof"] == dof and r["design"] == "random" and r["n_poses"] == N_REF]
    return {"dof": dof, "n_poses": N_TARGET, "i_plan_predicted_rms": float(np.sqrt(b.start)),
            "any_plan_lower_rms": b.lower_rms, "relaxed_rms": float(np.sqrt(b.relaxed)), "iterations": b.iterations,
            f"random{N_REF}_predicted_rms_median": float(np.median(rand)) if rand else float("nan")}


def paired_target(trials: list[dict], dof: int, seed: int) -> list[dict]:
    """Planned N_TARGET poses against random N_REF poses, paired by trial (same machine, same fresh poses)."""
    out = []
    designs = sorted({r["design"] for r in trials if r["design"].startswith("planned-")})
    ref = {r["trial"]: r for r in trials if r["dof"] == dof and r["design"] == "random" and r["n_poses"] == N_REF}
    for design in designs:
        plan = {r["trial"]: r for r in trials if r["dof"] == dof and r["design"] == design and r["n_poses"] == N_TARGET}
        for method, pre in METHODS:
            if not any(r.get(f"{pre}rms") is not None for r in plan.values()):
                continue
            pairs = np.array([(plan[t][f"{pre}rms"], ref[t][f"{pre}rms"]) for t in sorted(plan) if t in ref
                              and ref[t].get(f"{pre}rms") is not None], dtype=float)
            ok = np.all(np.isfinite(pairs), axis=1)
            a, b = pairs[ok, 0], pairs[ok, 1]
            row = {"dof": dof, "design": design, "method": method, "pairs": int(ok.sum()),
                   "dropped": int((~ok).sum()), f"planned{N_TARGET}_median": np.nan, f"random{N_REF}_median": np.nan,
                   "median_diff": np.nan, "diff_ci_lo": np.nan, "diff_ci_hi": np.nan, "planned_better": np.nan,
                   "wilcoxon_p": np.nan}
            if a.size >= 2:
                d = a - b
                ci = scipy.stats.bootstrap((d,), np.median, n_resamples=2000, confidence_level=0.95,
                                           method="percentile", random_state=np.random.default_rng([seed, dof, 7]))
                row.update({f"planned{N_TARGET}_median": float(np.median(a)), f"random{N_REF}_median": float(np.median(b)),
                            "median_diff": float(np.median(d)), "diff_ci_lo": float(ci.confidence_interval.low),
                            "diff_ci_hi": float(ci.confidence_interval.high), "planned_better": float(np.mean(d < 0)),
                            "wilcoxon_p": float(scipy.stats.wilcoxon(a, b).pvalue) if np.any(d != 0) else 1.0})
            out.append(row)
    return out


def units_check(machine, cands, n, n_sets, seed):
    """Kendall tau between the rankings of pose sets before and after rescaling the parameters."""
    rng = np.random.default_rng(seed)
    J = cands.blocks_prior / machine.tolerance  # whitened, unscaled
    G = cands.output_jacobian  # tool-point Jacobian, mm per parameter unit (criterion I)
    c = np.array([1e3 if u == "mm" else 1e6 for u in machine.layout.units])  # mm -> um, rad -> urad
    sets = [select_from_candidates(cands, n, "D").index] + [rng.choice(cands.n, n, replace=False) for _ in range(n_sets)]
    out = []
    for scaling in ("tolerance", "candidates", "none"):
        if scaling == "none":
            kept = [machine.layout.index(k) for k in cands.kept]
            # EIG and I are defined with the tolerance prior only: nothing to compare unscaled
            names = [k for k in CRITERIA if k not in ("EIG", "I")]

            def vals(Jx, s):
                A = Jx[s][:, :, kept].reshape(-1, len(kept))
                v = criteria_from_singular_values(np.linalg.svd(A, compute_uv=False), A.shape[0])
                return [v[k] for k in names]

            a = np.array([vals(J, s) for s in sets])
            b = np.array([vals(J / c, s) for s in sets])
        else:
            ca = candidate_set_from_jacobian(cands.q, J, machine.tolerance, machine.layout, scaling=scaling,
                                             output_jacobian=G)
            cb = candidate_set_from_jacobian(cands.q, J / c, machine.tolerance * c, machine.layout, scaling=scaling,
                                             output_jacobian=G / c)
            a = np.array([list(evaluate_selection(ca, s).values()) for s in sets])
            b = np.array([list(evaluate_selection(cb, s).values()) for s in sets])
            names = list(CRITERIA)
        for j, k in enumerate(names):
            tau = scipy.stats.kendalltau(a[:, j], b[:, j]).statistic
            out.append({"scaling": scaling, "criterion": k, "kendall_tau": float(tau),
                        "max_rel_change": float(np.max(np.abs(b[:, j] - a[:, j]) / np.abs(a[:, j])))})
    return out


def findings_from_rows(rows: list[dict], dof: int) -> dict:
    """Fewest planned poses whose median error reaches that of N_REF random poses, per design and method."""
    out = {}
    designs = sorted({x["design"] for x in rows if x["dof"] == dof and x["design"] != "random"})
    for design in designs:
        for method, pre in METHODS:
            f = {}
            if not any(x["dof"] == dof and np.isfinite(x[f"{pre}rms_median"]) for x in rows):
                continue  # method not run
            for metric in ("rms", "max"):
                key = f"{pre}{metric}_median"
                ref = next(x[key] for x in rows if x["dof"] == dof and x["design"] == "random" and x["n_poses"] == N_REF)
                reach = [x["n_poses"] for x in rows if x["dof"] == dof and x["design"] == design and x[key] <= ref]
                f[f"random{N_REF}_{metric}_median_mm"] = ref
                f[f"planned_poses_to_reach_random{N_REF}_{metric}"] = min(reach) if reach else None
            n_rms = f[f"planned_poses_to_reach_random{N_REF}_rms"]
            f["target_met"] = bool(n_rms is not None and n_rms <= N_TARGET)
            out[f"{dof}dof_{method}_{design}"] = f
    return out


def findings_markdown(findings: dict) -> list[str]:
    return [
        f"- {k.replace('_', ', ')}: {N_REF} random poses give a median RMS error of "
        f"{1e3 * f[f'random{N_REF}_rms_median_mm']:.2f} um; planned poses reach it with "
        f"{f[f'planned_poses_to_reach_random{N_REF}_rms']} poses (median max error: with "
        f"{f[f'planned_poses_to_reach_random{N_REF}_max']}); target (<= {N_TARGET} poses) met: {f['target_met']}"
        for k, f in findings.items()
    ]


def _csv(rows: list[dict]) -> str:
    keys = list(rows[0])
    return ",".join(keys) + "\n" + "\n".join(
        ",".join(repr(r[k]) if isinstance(r[k], float) else str(r[k]) for k in keys) for r in rows) + "\n"


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small run (a few trials, few candidates)")
    ap.add_argument("--out", default=str(ROOT / "studies" / "out" / "pose_planning"))
    ap.add_argument("--machine", default=str(ROOT / "examples" / "prs3" / "machine.toml"))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--criteria", default="D,I", help="planning criteria, comma-separated (default D,I)")
    ap.add_argument("--trials", type=int, help="trials per point (default 100; quick 3)")
    ap.add_argument("--dofs", default="6,5", help="measurement DOFs, comma-separated (default 6,5)")
    ap.add_argument("--n-list", help=f"numbers of poses, comma-separated (default 8,10,12,14,18,24,36; "
                                     f"must include {N_TARGET} and {N_REF} for the target)")
    ap.add_argument("--no-units", action="store_true", help="skip the units check")
    ap.add_argument("--methods", default="ridge,ls", help="identification methods: ridge (MAP), ls (default both)")
    ap.add_argument("--random-n", help=f"evaluate random sets only at these numbers of poses (e.g. {N_REF})")
    ap.add_argument("--ls-random-n", help=f"least squares on random sets only at these numbers of poses "
                                          f"(default {N_REF}: LS on small random sets fails slowly)")
    ap.add_argument("--bound-iters", type=int, help="Frank-Wolfe steps of the linearised bound (default 300; 0: skip)")
    args = ap.parse_args(argv)
    cfg = dict(QUICK if args.quick else FULL)
    if args.trials:
        cfg["trials"] = args.trials
    if args.n_list:
        cfg["n_list"] = _ints(args.n_list)
    if args.ls_random_n:
        cfg["ls_random_n"] = _ints(args.ls_random_n)
    if args.bound_iters is not None:
        cfg["bound_iters"] = args.bound_iters
    criteria = tuple(check_criterion(c) for c in args.criteria.split(",") if c.strip())
    out = Path(args.out)
    machine = load_machine(args.machine)
    t0 = time.perf_counter()
    rows, trials, paired, units, bounds, findings = [], [], [], [], [], {}
    for dof in _ints(args.dofs):
        methods = tuple(m for m in METHODS if m[0] in args.methods.split(","))
        random_n = _ints(args.random_n) if args.random_n else cfg["random_n"]
        r, tr, cands = error_study(machine, dof, cfg, args.seed, criteria, methods, random_n)
        rows += r
        trials += tr
        if N_REF in cfg["n_list"]:
            findings.update(findings_from_rows(r, dof))
            if N_TARGET in cfg["n_list"]:
                paired += paired_target(tr, dof, args.seed)
                if cfg["bound_iters"] > 0:
                    bounds.append(linear_bound(cands, tr, dof, cfg["bound_iters"]))
        if not args.no_units:
            units += [{"dof": dof, **u} for u in units_check(machine, cands, 18, 5 if args.quick else 20, args.seed)]
    seconds = time.perf_counter() - t0
    write_text_atomic(out / "pose_planning.csv", _csv(rows))
    write_text_atomic(out / "trials.csv", _csv(trials))
    if paired:
        write_text_atomic(out / "paired.csv", _csv(paired))
    if units:
        write_text_atomic(out / "units_ranking.csv", _csv(units))
    plot_error_vs_poses(rows, out / "pose_planning.png")
    summary = {"config": {**cfg, "seed": args.seed, "criteria": list(criteria), "quick": args.quick,
                          "dofs": _ints(args.dofs), "machine": machine.name, "methods": args.methods,
                          "random_n_override": args.random_n,
                          "identification": "ridge lam=1 (MAP) on the identifiable set; ls alongside"},
               "findings": findings, "paired": paired, "linear_bound": bounds, "seconds": seconds}
    write_json_atomic(out / "summary.json", summary)
    md = ["# Pose planning study", "",
          f"machine '{machine.name}', {cfg['trials']} trials (true machine and fresh poses shared by every design "
          f"and number of poses), {cfg['candidates']} candidates, error on {cfg['n_eval']} fresh poses, "
          f"seed {args.seed}, plans by {', '.join(criteria)}, {seconds:.0f} s", "",
          "| DOF | design | poses | RMS median (um) | RMS IQR (um) | predicted RMS (um) | max median (um) | "
          "LS RMS median (um) | LS failed |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['dof']} | {r['design']} | {r['n_poses']} | {1e3 * r['rms_median']:.2f} | "
                  f"{1e3 * r['rms_q25']:.2f}-{1e3 * r['rms_q75']:.2f} | {1e3 * r['predicted_rms']:.2f} | "
                  f"{1e3 * r['max_median']:.2f} | {1e3 * r['ls_rms_median']:.2f} | "
                  f"{r['ls_failures'] if r['ls_failures'] >= 0 else '-'}/{r['trials']} |")
    if findings:
        md += ["", f"## Target: planned poses reach the accuracy of {N_REF} random poses with at most {N_TARGET}", ""]
        md += findings_markdown(findings)
    if paired:
        md += ["", f"## Paired by trial: planned {N_TARGET} against random {N_REF} (RMS, um)", "",
               f"| DOF | design | method | pairs | planned {N_TARGET} median | random {N_REF} median | "
               "median difference [95% CI] | planned better | Wilcoxon p |", "|---|---|---|---|---|---|---|---|---|"]
        for p in paired:
            md.append(f"| {p['dof']} | {p['design']} | {p['method']} | {p['pairs']} | "
                      f"{1e3 * p[f'planned{N_TARGET}_median']:.2f} | {1e3 * p[f'random{N_REF}_median']:.2f} | "
                      f"{1e3 * p['median_diff']:+.2f} [{1e3 * p['diff_ci_lo']:+.2f}, {1e3 * p['diff_ci_hi']:+.2f}] | "
                      f"{100 * p['planned_better']:.0f}% | {p['wilcoxon_p']:.2g} |")
    if bounds:
        md += ["", f"## Linearised: the best any {N_TARGET}-pose plan can expect (MAP, tolerance prior)", "",
               f"| DOF | I plan, predicted RMS (um) | any {N_TARGET}-pose plan >= (um) | "
               f"random {N_REF}, predicted RMS median (um) | Frank-Wolfe steps |", "|---|---|---|---|---|"]
        for b in bounds:
            md.append(f"| {b['dof']} | {1e3 * b['i_plan_predicted_rms']:.3f} | {1e3 * b['any_plan_lower_rms']:.3f} | "
                      f"{1e3 * b[f'random{N_REF}_predicted_rms_median']:.3f} | {b['iterations']} |")
    if units:
        md += ["", "## Units: Kendall tau of pose-set rankings before/after mm->um, rad->urad", "",
               "| DOF | scaling | criterion | tau | max relative change |", "|---|---|---|---|---|"]
        for u in units:
            md.append(f"| {u['dof']} | {u['scaling']} | {u['criterion']} | {u['kendall_tau']:.3f} | "
                      f"{u['max_rel_change']:.2e} |")
    write_text_atomic(out / "pose_planning.md", "\n".join(md) + "\n")
    print("\n".join(md))
    print(f"\nwrote {out} in {seconds:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
