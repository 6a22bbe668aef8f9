"""Study: can any rule for k (or lambda) meet the three targets of issue 17 at once?  A duality certificate.

    python studies/choice_frontier.py [--quick] [--n-data N] [--methods tsvd ridge] [--out DIR]

``studies/choice_rules.py`` judges each default rule on three targets per
cell (situation x truth scale): success within 3 points of the ceiling,
regret on the expected ratio at most 0.02 (TSVD; ridge 0.015), and p90 of
the ratio at most 1.40 (ridge 1.25).  Where a rule misses, the question is
whether *any* rule could meet all three, not just each alone (the tail
floor there answers the p90 target alone).

Per data set ``z`` (the linear-Gaussian model of choice_rules.py, truth
``x ~ N(0, c^2 I)``), every candidate ``v`` (``k = 1..rank`` or the 121
lambdas) has, under the true posterior, a success probability ``p_v(z)``,
an expected ratio to the hindsight best ``e_v(z)`` and a tail probability
``t_v(z) = P(ratio_v > T | z)`` (``T`` the p90 target), all from the same
posterior draws.  A rule is any choice ``v(z)`` (randomised or not, knowing
``c`` or not); its success rate, mean ratio and ``P(ratio > T)`` are the
averages over ``z`` of ``p, e, t`` at its choice.  The targets ask

    E[p_v] >= C - 0.03,   E[e_v] <= F + r,   E[t_v] <= 0.10,

with ``C = E[max_v p_v]`` the ceiling and ``F = E[min_v e_v]`` the floor (as
in choice_rules.py; ``p90 <= T`` needs ``P(ratio > T) <= 10 %``).  The
triples a rule can reach form a convex set, so the targets are out of
reach for every rule exactly when some weights ``(a, b, g) >= 0`` separate
them (Lagrangian duality, per data set the best compromise is an argmin):

    D(a, b, g) = E_z[ min_v (-a p_v + b e_v + g t_v) + a max_v p_v - b min_v e_v ] - 0.03 a - r b - 0.10 g > 0.

The study maximises ``D`` over the weights (a grid on the simplex) on half
of the data sets and evaluates it on the other half, with its standard
error: ``D - 2 SE > 0`` certifies (one-sided, about 97.7 %) that no rule
meets the three targets in that cell.  It also reports the best
compromise rule found (the argmin rule of those weights) with its gap,
regret and tail.  Monte Carlo draws bias ``max p`` up and ``min e`` and the
per-data-set minimum down alike, as in choice_rules.py; the targets are
judged on the same draws.

*Rules that do not know the scale.*  A real rule sees only the data, and
must meet the targets at every truth scale of a situation at once (12
constraints).  Data sets are drawn at each scale in equal numbers; each is
valued under the posterior of every scale, and ``w_c(z) = p(z | c) /
p_mix(z)`` reweights the pooled data sets to scale ``c`` (Gaussian
densities of ``U^T z``; the weights are at most the number of scales).
A rule meets constraint ``k = (c, target)`` when the mean over data sets
of ``w_c(z) psi_k(z, v(z))`` is at most 0, so the same duality holds with
12 weights, now chosen by a linear programme (HiGHS;
:func:`bayescal.identify.target_rule.minimax_weights`, the ``targets``
rule's calibration grew out of this study) on the even data
sets and tested on the odd ones.  ``D > 0`` then means no rule that sees
only the data meets every target at every scale; ``D <= 0`` only means
"not excluded".  Whether a rule does meet them is shown by the argmin
rule of the weights found ("compromise"), fitted on the even data sets
and reported per scale on the odd ones (held out).

Writes ``choice_frontier.md`` and ``choice_frontier.json``; exit code 0.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT, ROOT / "studies"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from choice_rules import RATIO, SCALES, SEED, TARGETS, TRUE_POSTERIOR_DRAWS, situation  # noqa: E402
from seed2_ls_re_tsvd import MACHINES, study_machine  # noqa: E402

from bayescal.identify.ceiling import within_best  # noqa: E402
from bayescal.identify.choose import lambda_grid  # noqa: E402
from bayescal.identify.target_rule import RuleTargets, constraint_rows, minimax_weights, scale_log_densities  # noqa: E402
from bayescal.io import write_json_atomic, write_text_atomic  # noqa: E402
from bayescal.machines import KINDS  # noqa: E402

TAIL_SHARE = 0.10  # p90 <= T  <=>  P(ratio > T) <= 10 %


def draw_beta(A_svd, c: float, rng) -> np.ndarray:
    """``U^T z`` of one data set ``z = A x + e``, ``x ~ N(0, c^2 I)`` (all the rules and posteriors use)."""
    U, s, Vt, _ = A_svd
    x = c * rng.normal(size=Vt.shape[1])
    return U.T @ (U @ (s * (Vt @ x)) + rng.normal(size=U.shape[0]))


def posterior_values(A_svd, R, beta: np.ndarray, c: float, method: str, rng, n_draws: int) -> np.ndarray:
    """``(n_candidates, 3)``: success probability, expected ratio and tail probability of each candidate,
    under the posterior of prior scale ``c``, for the data set ``beta``."""
    U, s, Vt, lam = A_svd
    p = Vt.shape[1]
    r = s.size
    inv_s = np.where(s > 1e-12 * s[0], 1.0 / np.where(s > 0, s, 1.0), 0.0)
    F = s[None, :] ** 2 / (s[None, :] ** 2 + lam[:, None]) if method == "ridge" else \
        (np.arange(r)[None, :] < np.arange(1, r + 1)[:, None]).astype(float)
    est = F * (beta[:r] * inv_s)[None, :]
    prec = s**2 + 1.0 / c**2
    mean = np.concatenate([s * beta[:r] / prec, np.zeros(p - r)])
    sd = np.concatenate([1.0 / np.sqrt(prec), np.full(p - r, c)])
    truths = mean + sd * rng.normal(size=(n_draws, p))
    _, rel = within_best(truths, est, R @ Vt.T, RATIO)
    return np.stack([np.mean(rel <= RATIO, axis=0), rel.mean(axis=0), np.mean(rel > TARGETS[method]["p90"], axis=0)],
                    axis=1)


def candidate_values(A_svd, R, c: float, method: str, rng, n_draws: int) -> np.ndarray:
    """:func:`posterior_values` of a data set drawn at scale ``c``, under the true posterior."""
    return posterior_values(A_svd, R, draw_beta(A_svd, c, rng), c, method, rng, n_draws)


def simplex_grid(steps: int) -> np.ndarray:
    """Weights ``(a, b, g) >= 0`` summing to 1 on a grid with ``steps`` intervals per side."""
    return np.array([(i, j, steps - i - j) for i in range(steps + 1) for j in range(steps + 1 - i)], float) / steps


def dual_terms(phi: np.ndarray, weights: np.ndarray, regret: float) -> np.ndarray:
    """Per data set and weight vector, the term whose mean is ``D`` (see the module docstring).

    Parameters
    ----------
    phi : ndarray, shape (n_data, n_candidates, 3)
        ``p_v, e_v, t_v`` per data set and candidate.
    weights : ndarray, shape (n_w, 3)
        ``(a, b, g)``.
    regret : float
        The regret target ``r``.

    Returns
    -------
    ndarray, shape (n_data, n_w)
    """
    signed = phi * np.array([-1.0, 1.0, 1.0])
    out = np.empty((phi.shape[0], weights.shape[0]))
    for i0 in range(0, weights.shape[0], 256):
        w = weights[i0:i0 + 256]
        out[:, i0:i0 + 256] = np.min(np.einsum("dvk,wk->dwv", signed, w), axis=2)
    base = np.stack([phi[:, :, 0].max(axis=1), -phi[:, :, 1].min(axis=1), np.zeros(phi.shape[0])], axis=1)
    return out + base @ weights.T - weights @ np.array([0.03, regret, TAIL_SHARE])


def achieved(phi: np.ndarray, choice: np.ndarray) -> dict:
    """Gap, regret and tail of the rule choosing ``choice[d]`` in data set ``d``, with standard errors."""
    d = np.arange(phi.shape[0])
    gap = phi[:, :, 0].max(axis=1) - phi[d, choice, 0]
    reg = phi[d, choice, 1] - phi[:, :, 1].min(axis=1)
    tail = phi[d, choice, 2]
    n = phi.shape[0]
    return {k: float(v.mean()) for k, v in (("gap", gap), ("regret", reg), ("tail", tail))} | \
        {k + "_se": float(v.std(ddof=1) / np.sqrt(n)) for k, v in (("gap", gap), ("regret", reg), ("tail", tail))}


def certify(phi: np.ndarray, regret: float, steps: int = 60) -> dict:
    """Maximise ``D`` on the first half of the data sets, evaluate it on the second (with its standard error)."""
    W = simplex_grid(steps)
    half = phi.shape[0] // 2
    fit, test = phi[:half], phi[half:]
    D_fit = dual_terms(fit, W, regret).mean(axis=0)
    w = W[int(np.argmax(D_fit))]
    terms = dual_terms(test, w[None, :], regret)[:, 0]
    signed = test * np.array([-1.0, 1.0, 1.0])
    choice = np.argmin(signed @ w, axis=1)
    D, se = float(terms.mean()), float(terms.std(ddof=1) / np.sqrt(terms.size))
    return {"weights": w.tolist(), "D": D, "D_se": se, "certified": bool(D - 2 * se > 0),
            "compromise": achieved(test, choice),
            "tail_floor": float(test[:, :, 2].min(axis=1).mean()),
            "success_rule": achieved(test, np.argmax(test[:, :, 0], axis=1)),
            "tail_rule": achieved(test, np.argmin(test[:, :, 2], axis=1)),
            "n_fit": half, "n_test": int(test.shape[0])}


def agnostic_rows(phi: np.ndarray, w: np.ndarray, regret: float) -> np.ndarray:
    """:func:`bayescal.identify.target_rule.constraint_rows` with this study's targets (gap 0.03, tail 10 %)."""
    return constraint_rows(phi, w, RuleTargets(gap=0.03, regret=regret, tail_share=TAIL_SHARE))


def certify_agnostic(phi: np.ndarray, w: np.ndarray, regret: float, scales) -> dict:
    """Weights by LP on the even data sets, ``D`` and its standard error on the odd ones (module docstring)."""
    a = agnostic_rows(phi, w, regret)
    lam = minimax_weights(a[0::2])[0]
    test = a[1::2] @ lam
    terms = test.min(axis=1)
    D, se = float(terms.mean()), float(terms.std(ddof=1) / np.sqrt(terms.size))
    # the compromise rule: argmin of the weighted constraints, ties (constraints with no weight) broken by all of them
    choice = (a[1::2] @ (lam + 1e-6 / lam.size)).argmin(axis=1)
    pt, wt = phi[1::2], w[1::2]
    d = np.arange(pt.shape[0])
    per_scale = []
    for j, c in enumerate(scales):  # the compromise rule at each scale (self-normalised density weights)
        q = pt[:, j]
        ww = wt[:, j] / wt[:, j].sum()
        row = {"scale": c}
        for key, x in (("gap", q[:, :, 0].max(axis=1) - q[d, choice, 0]),
                       ("regret", q[d, choice, 1] - q[:, :, 1].min(axis=1)), ("tail", q[d, choice, 2])):
            row[key] = float(ww @ x)
            # standard error of a self-normalised weighted mean (delta method)
            row[key + "_se"] = float(np.sqrt(np.sum(ww**2 * (x - row[key]) ** 2)))
        per_scale.append(row)
    K = lam.size
    return {"weights": {f"{scales[k // 3]:g}:{('gap', 'regret', 'tail')[k % 3]}": float(lam[k]) for k in range(K)
                        if lam[k] > 1e-6},
            "D": D, "D_se": se, "certified": bool(D - 2 * se > 0), "compromise": per_scale,
            "n_fit": int(a[0::2].shape[0]), "n_test": int(terms.size)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="3-PRS 6-DOF, scale 0.5, TSVD, 60 data sets (for the tests)")
    ap.add_argument("--n-data", type=int, default=None, help="data sets per cell (default 800: 400 to fit, 400 to test)")
    ap.add_argument("--draws", type=int, default=TRUE_POSTERIOR_DRAWS,
                    help=f"true-posterior draws per data set (default {TRUE_POSTERIOR_DRAWS})")
    ap.add_argument("--methods", nargs="+", choices=("tsvd", "ridge"), default=["tsvd", "ridge"])
    ap.add_argument("--out", default=str(ROOT / "studies" / "out" / "choice_frontier"))
    args = ap.parse_args(argv)
    n_data = args.n_data or (60 if args.quick else 800)
    t0 = time.perf_counter()
    rows, agnostic = [], []
    for kind, path in MACHINES:
        if kind not in KINDS or not path.exists():
            continue
        machine = study_machine(kind, path)
        for dof in (6, 5):
            if args.quick and (kind, dof) != ("3-PRS", 6):
                continue
            A, R, _ = situation(machine, dof)
            U, s, Vt = np.linalg.svd(A, full_matrices=False)
            svd = (U, s, Vt, lambda_grid(s, 121))
            scales = (0.5, 1.0) if args.quick else SCALES
            for method in (("tsvd",) if args.quick else args.methods):
                # every data set (drawn at each scale in turn) valued under the posterior of every scale
                phi_all, logd = [], []
                for j, c in enumerate(scales):
                    rng = np.random.default_rng([SEED, dof, j, len(kind), 17 if method == "tsvd" else 19])
                    for _ in range(n_data):
                        beta = draw_beta(svd, c, rng)
                        phi_all.append([posterior_values(svd, R, beta, cc, method, rng, args.draws) for cc in scales])
                        logd.append(scale_log_densities(svd[1], beta[: svd[1].size], scales))
                phi_all, logd = np.array(phi_all), np.array(logd)
                for j, c in enumerate(scales):  # one cell: its own data sets under the true posterior
                    if args.quick and c != 0.5:
                        continue
                    res = certify(phi_all[j * n_data:(j + 1) * n_data, j], TARGETS[method]["regret"])
                    res.update(situation=f"{kind} {dof}-DOF", scale=c, method=method)
                    rows.append(res)
                    print(f"{kind} {dof}-DOF scale {c:g} {method}: D = {res['D']:.4f} +- {res['D_se']:.4f} "
                          f"({'no rule meets all three' if res['certified'] else 'not excluded'}); "
                          f"{time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
                # rules that do not know the scale: all scales of the situation at once
                w = np.exp(logd - logd.max(axis=1, keepdims=True))
                w = w / w.mean(axis=1, keepdims=True)  # p(z | c) / p_mix(z), the scales in equal shares
                res = certify_agnostic(phi_all, w, TARGETS[method]["regret"], scales)
                res.update(situation=f"{kind} {dof}-DOF", method=method)
                agnostic.append(res)
                print(f"{kind} {dof}-DOF every scale {method}: D = {res['D']:.4f} +- {res['D_se']:.4f} "
                      f"({'no rule meets all targets at every scale' if res['certified'] else 'not excluded'}); "
                      f"{time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    seconds = time.perf_counter() - t0
    md = ["# Can any rule meet the three targets at once? (duality certificate)", "",
          f"{n_data} data sets per cell ({n_data // 2} choose the weights, the rest test them), "
          f"{args.draws} true-posterior draws each; seed {SEED}; {seconds:.0f} s.", "",
          "D > 0: no rule (knowing c or not, randomised or not) meets gap <= 3 points, the regret target and "
          "P(ratio > p90 target) <= 10 % together; certified when D - 2 SE > 0.  Compromise: the rule "
          "argmin_v (-a p_v + b e_v + g t_v) of the weights found, on the test half.", "",
          "| situation | c | method | weights (a, b, g) | D (SE) | no rule meets all three | tail floor | "
          "compromise gap / regret / tail | success rule gap / regret / tail | tail rule gap / regret / tail |",
          "|---|---|---|---|---|---|---|---|---|---|"]

    def trip(a):
        return f"{100 * a['gap']:.1f} / {a['regret']:.4f} / {100 * a['tail']:.1f} %"

    for r in rows:
        md.append(f"| {r['situation']} | {r['scale']:g} | {r['method']} | "
                  f"({', '.join(f'{x:.2f}' for x in r['weights'])}) | {r['D']:.4f} ({r['D_se']:.4f}) | "
                  f"{'yes' if r['certified'] else 'not shown'} | {100 * r['tail_floor']:.1f} % | {trip(r['compromise'])} | "
                  f"{trip(r['success_rule'])} | {trip(r['tail_rule'])} |")
    md += ["", "## Rules that do not know the scale", "",
           f"Per situation, the {len(scales)} scales at once ({n_data} data sets drawn at each; even ones choose the "
           "weights by a linear programme, odd ones test them): D > 0 means no rule that sees only the data meets "
           "every target at every scale.  Weights: the constraints that bind (scale:target).  Compromise: "
           "gap / regret / tail per scale of the rule argmin_v of the weighted constraints.", "",
           "| situation | method | D (SE) | no rule meets every target at every scale | binding weights | compromise per scale |",
           "|---|---|---|---|---|---|"]
    for r in agnostic:
        wts = ", ".join(f"{k} {v:.2f}" for k, v in r["weights"].items())
        comp = "; ".join(f"{c['scale']:g}: {100 * c['gap']:.1f} / {c['regret']:.4f} / {100 * c['tail']:.1f} % "
                         f"(SE {100 * c['gap_se']:.1f} / {c['regret_se']:.4f} / {100 * c['tail_se']:.1f})"
                         for c in r["compromise"])
        md.append(f"| {r['situation']} | {r['method']} | {r['D']:.4f} ({r['D_se']:.4f}) | "
                  f"{'yes' if r['certified'] else 'not shown'} | {wts} | {comp} |")
    out = Path(args.out)
    write_json_atomic(out / "choice_frontier.json", {"n_data": n_data, "draws": args.draws, "seconds": seconds,
                                                     "rows": rows, "agnostic": agnostic})
    write_text_atomic(out / "choice_frontier.md", "\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
