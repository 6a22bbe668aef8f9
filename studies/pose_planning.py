"""Study: do planned poses calibrate better than random ones, and with how many fewer?

For the 3-PRS (or any machine file given), with 6-DOF and 5-DOF measurement:
post-calibration output error (RMS and max of the tool-point error over
fresh workspace poses, on simulated machines drawn from the tolerances)
against the number of measured poses, for D-optimal planned poses
(greedy + exchange from a candidate set) and for random poses from the same
candidates.  Identification: ridge with lam = 1 (the MAP estimate under the
tolerance prior) and least squares on the identifiable set (failures
counted).  Then a units check: the ranking of pose sets by every criterion,
before and after rescaling the parameters (mm -> um, rad -> urad), with
the tolerance and candidate column scalings and without scaling.

    python studies/pose_planning.py [--quick] [--out DIR]

Writes DIR/pose_planning.csv, DIR/units_ranking.csv, DIR/summary.json,
DIR/pose_planning.md and DIR/pose_planning.png (default DIR:
studies/out/pose_planning).
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

from bayescal.design import CRITERIA, candidate_set_from_jacobian, criteria_from_singular_values  # noqa: E402
from bayescal.design import draw_candidates, evaluate_selection, select_from_candidates  # noqa: E402
from bayescal.identify import identify  # noqa: E402
from bayescal.io import write_json_atomic, write_text_atomic  # noqa: E402
from bayescal.machines import load_machine  # noqa: E402
from bayescal.measurement import MeasurementModel  # noqa: E402
from bayescal.plots.design import plot_error_vs_poses  # noqa: E402
from bayescal.simulate import draw_errors, draw_poses, measure  # noqa: E402

FULL = dict(n_list=[8, 10, 12, 14, 18, 24, 36], trials=24, candidates=20000, n_eval=200)
QUICK = dict(n_list=[8, 36], trials=2, candidates=300, n_eval=30)


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


def error_study(machine, dof, cfg, seed, criterion="D"):
    rng = np.random.default_rng([seed, dof])
    cands = draw_candidates(machine, cfg["candidates"], dof=dof, rng=rng)
    planned = {n: select_from_candidates(cands, n, criterion).index for n in cfg["n_list"]}
    rows = []
    for n in cfg["n_list"]:
        for design in ("planned", "random"):
            res = {"ridge": [], "ls": []}
            fails = {"ridge": 0, "ls": 0}
            for t in range(cfg["trials"]):
                trng = np.random.default_rng([seed, dof, n, t])  # same true machine for both designs
                theta = draw_errors(machine, trng)
                q_eval = draw_poses(machine, cfg["n_eval"], trng, theta)
                true_poses = machine.forward(q_eval, theta)
                idx = planned[n] if design == "planned" else trng.choice(cands.n, n, replace=False)
                for method in ("ridge", "ls"):
                    th = calibrate(machine, cands.q[idx], theta, dof, np.random.default_rng([seed, dof, n, t, 1]),
                                   list(cands.kept), method)
                    if th is None:
                        fails[method] += 1
                    else:
                        res[method].append(output_error(machine, q_eval, true_poses, th))
            row = {"dof": dof, "design": design, "n_poses": n, "trials": cfg["trials"]}
            for method in ("ridge", "ls"):
                e = np.array(res[method]).reshape(-1, 2)
                pre = "" if method == "ridge" else "ls_"
                for j, name in enumerate(("rms", "max")):
                    v = e[:, j] if e.size else np.array([np.nan])
                    row[f"{pre}{name}_median"] = float(np.median(v))
                    row[f"{pre}{name}_q25"] = float(np.quantile(v, 0.25))
                    row[f"{pre}{name}_q75"] = float(np.quantile(v, 0.75))
                row[f"{pre}failures"] = fails[method]
            rows.append(row)
            print(f"  {dof}-DOF {design:8s} n={n:3d}: median RMS {1e3 * row['rms_median']:.2f} um "
                  f"(ls {1e3 * row['ls_rms_median']:.2f} um, {row['ls_failures']} failed)", flush=True)
    return rows, cands


def units_check(machine, cands, n, n_sets, seed):
    """Kendall tau between the rankings of pose sets before and after rescaling the parameters."""
    rng = np.random.default_rng(seed)
    J = cands.blocks_prior / machine.tolerance  # whitened, unscaled
    c = np.array([1e3 if u == "mm" else 1e6 for u in machine.layout.units])  # mm -> um, rad -> urad
    sets = [select_from_candidates(cands, n, "D").index] + [rng.choice(cands.n, n, replace=False) for _ in range(n_sets)]
    out = []
    for scaling in ("tolerance", "candidates", "none"):
        if scaling == "none":
            kept = [machine.layout.index(k) for k in cands.kept]

            def vals(Jx, s):
                A = Jx[s][:, :, kept].reshape(-1, len(kept))
                v = criteria_from_singular_values(np.linalg.svd(A, compute_uv=False), A.shape[0])
                return [v[k] for k in CRITERIA if k != "EIG"]

            a = np.array([vals(J, s) for s in sets])
            b = np.array([vals(J / c, s) for s in sets])
            names = [k for k in CRITERIA if k != "EIG"]
        else:
            ca = candidate_set_from_jacobian(cands.q, J, machine.tolerance, machine.layout, scaling=scaling)
            cb = candidate_set_from_jacobian(cands.q, J / c, machine.tolerance * c, machine.layout, scaling=scaling)
            a = np.array([list(evaluate_selection(ca, s).values()) for s in sets])
            b = np.array([list(evaluate_selection(cb, s).values()) for s in sets])
            names = list(CRITERIA)
        for j, k in enumerate(names):
            tau = scipy.stats.kendalltau(a[:, j], b[:, j]).statistic
            out.append({"scaling": scaling, "criterion": k, "kendall_tau": float(tau),
                        "max_rel_change": float(np.max(np.abs(b[:, j] - a[:, j]) / np.abs(a[:, j])))})
    return out


def findings_from_rows(rows: list[dict], dof: int) -> dict:
    """Fewest planned poses whose median error reaches that of 36 random poses, per identification method."""
    out = {}
    for method, pre in (("ridge", ""), ("ls", "ls_")):
        f = {}
        for metric in ("rms", "max"):
            key = f"{pre}{metric}_median"
            ref = next(x[key] for x in rows if x["dof"] == dof and x["design"] == "random" and x["n_poses"] == 36)
            reach = [x["n_poses"] for x in rows
                     if x["dof"] == dof and x["design"] == "planned" and x[key] <= ref]
            f[f"random36_{metric}_median_mm"] = ref
            f[f"planned_poses_to_reach_random36_{metric}"] = min(reach) if reach else None
        f["target_met"] = bool(f["planned_poses_to_reach_random36_rms"] is not None
                               and f["planned_poses_to_reach_random36_rms"] <= 18)
        out[f"{dof}dof_{method}"] = f
    return out


def findings_markdown(findings: dict) -> list[str]:
    return [
        f"- {k.replace('_', ', ')}: 36 random poses give a median RMS error of "
        f"{1e3 * f['random36_rms_median_mm']:.2f} um; planned poses reach it with "
        f"{f['planned_poses_to_reach_random36_rms']} poses (median max error: with "
        f"{f['planned_poses_to_reach_random36_max']}); target (<= 18 poses) met: {f['target_met']}"
        for k, f in findings.items()
    ]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small run (a few trials, few candidates)")
    ap.add_argument("--out", default=str(ROOT / "studies" / "out" / "pose_planning"))
    ap.add_argument("--machine", default=str(ROOT / "examples" / "prs3" / "machine.toml"))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--criterion", default="D", help="planning criterion (default D; e.g. EIG)")
    args = ap.parse_args(argv)
    cfg = QUICK if args.quick else FULL
    out = Path(args.out)
    machine = load_machine(args.machine)
    t0 = time.perf_counter()
    rows, units, findings = [], [], {}
    for dof in (6, 5):
        r, cands = error_study(machine, dof, cfg, args.seed, args.criterion)
        rows += r
        findings.update(findings_from_rows(r, dof))
        units += [{"dof": dof, **u} for u in units_check(machine, cands, 18, 5 if args.quick else 20, args.seed)]
    keys = list(rows[0])
    write_text_atomic(out / "pose_planning.csv",
                      ",".join(keys) + "\n" + "\n".join(",".join(repr(r[k]) if isinstance(r[k], float) else str(r[k]) for k in keys) for r in rows) + "\n")
    ukeys = list(units[0])
    write_text_atomic(out / "units_ranking.csv",
                      ",".join(ukeys) + "\n" + "\n".join(",".join(str(u[k]) for k in ukeys) for u in units) + "\n")
    plot_error_vs_poses(rows, out / "pose_planning.png")
    summary = {"config": {**cfg, "seed": args.seed, "criterion": args.criterion, "quick": args.quick,
                          "machine": machine.name,
                          "identification": "ridge lam=1 (MAP) on the identifiable set; ls alongside"},
               "findings": findings, "seconds": time.perf_counter() - t0}
    write_json_atomic(out / "summary.json", summary)
    md = ["# Pose planning study", "", f"machine '{machine.name}', {cfg['trials']} trials per point, "
          f"{cfg['candidates']} candidates, error on {cfg['n_eval']} fresh poses, seed {args.seed}, "
          f"{args.criterion}-optimal plans", "",
          "| DOF | design | poses | RMS median (um) | RMS IQR (um) | max median (um) | LS RMS median (um) | LS failed |",
          "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['dof']} | {r['design']} | {r['n_poses']} | {1e3 * r['rms_median']:.2f} | "
                  f"{1e3 * r['rms_q25']:.2f}-{1e3 * r['rms_q75']:.2f} | {1e3 * r['max_median']:.2f} | "
                  f"{1e3 * r['ls_rms_median']:.2f} | {r['ls_failures']}/{r['trials']} |")
    md += ["", "## Target: planned poses reach the accuracy of 36 random poses with at most 18", ""]
    md += findings_markdown(findings)
    md += ["", "## Units: Kendall tau of pose-set rankings before/after mm->um, rad->urad", "",
           "| DOF | scaling | criterion | tau | max relative change |", "|---|---|---|---|---|"]
    for u in units:
        md.append(f"| {u['dof']} | {u['scaling']} | {u['criterion']} | {u['kendall_tau']:.3f} | {u['max_rel_change']:.2e} |")
    write_text_atomic(out / "pose_planning.md", "\n".join(md) + "\n")
    print("\n".join(md[-(len(units) + 8 + len(findings)):]) if args.quick else "\n".join(md))
    print(f"\nwrote {out} in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
