"""The seed's LS-vs-RE-vs-TSVD study, reproduced, with automatic lambda and k.

    python studies/seed2_ls_re_tsvd.py [--quick] [--out DIR] [--reps N]

For every manipulator (the 3-PRS of ``examples/prs3/machine.toml``; the
RU-PUS-PRS of ``examples/rupus_prs/machine.toml`` when that kind is in
``bayescal.machines.KINDS``) and both measurement types (6-DOF, 5-DOF):

* output error against lambda and against k (the seed's Figures 6, 8, 10, 11),
  every point a full Gauss-Newton identification, with the value every
  automatic rule picks;
* iteration histories of LS, RE and TSVD (Figures 7, 9), bayescal's
  total-deviation iteration and the seed's increment-filtered iteration;
* identified errors of one chain against the truth (Tables 5, 6) and output
  errors before and after calibration (Tables 7, 8);
* checked findings (a)-(d), written to ``findings.md`` and ``summary.json``.

Set-up (docs/regularisation.md explains the choices):

* 36 measurement poses drawn once (seeded) uniformly within ``q_limits``;
  the measurement noise of the main run is the seed's Appendix 1 table
  (``studies/data/seed2_appendix1_measurement_errors.csv``): X, Y, Z added
  to the tool point, (phi, theta, psi) applied as a small rotation vector in
  the base frame before the true orientation; 5-DOF drops psi.  The table
  looks uniform on +-0.01 mm and +-1.75e-4 rad, so the instrument sigma is
  ``half-width / sqrt(3)`` and repetitions draw fresh uniform noise.
* The true machine: errors ``N(0, tolerance^2)`` (machine file tolerances).
* The 3-PRS keeps the example file's geometry but uses a 200 mm actuator
  stroke (400-600 mm, ``STUDY_Q_LIMITS``) for measurement and evaluation:
  with the file's 100 mm stroke, link length and actuator offset are nearly
  confounded and even 6-DOF LS diverges.
* Evaluation range: a full factorial grid over ``q_limits`` (5 levels per
  actuator for three actuators, 11 for two); output error = RMS distance of
  the calibrated model's tool point from the true machine's (mm), with the
  RMS tool-axis angle error (rad) beside it.
* The seed's parameter set: the set identifiable with 6-DOF measurement at
  the measurement poses (33 for the 3-PRS: 11 per chain, the tool point
  fixed), used by LS, RE and TSVD in every situation; under 5-DOF it is rank
  deficient.  LS also runs on bayescal's automatically reduced 5-DOF set.

Exit code 0 when findings (a) and (b) hold, 1 otherwise; (c) and (d) are
reported, and the (d) target is stated as met or not, with reasons.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
import warnings
from pathlib import Path

# many small SVDs: BLAS threads only contend (25x slower on a loaded 2-core machine); set before numpy loads
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))  # run from a checkout without installing

from bayescal.errors import ConvergenceWarning  # noqa: E402
from bayescal.geometry import so3_exp, so3_log  # noqa: E402
from bayescal.identifiability import analyse_identifiability  # noqa: E402
from bayescal.identify import filtered_solve, identify, whitened_system  # noqa: E402
from bayescal.identify.ceiling import choice_ceiling  # noqa: E402
from bayescal.identify.choose import (  # noqa: E402
    DEFAULT_RULE,
    RULE_NAMES,
    RULES,
    choose_linear,
    choose_regularisation,
    lambda_grid,
    linearised_problem,
)
from bayescal.io import Recording, write_json_atomic, write_text_atomic  # noqa: E402
from bayescal.machines import KINDS, MeasurementNoise  # noqa: E402
from bayescal.machines.files import load_machine  # noqa: E402
from bayescal.measurement import MeasurementModel  # noqa: E402
from bayescal.plots import regularisation as plots  # noqa: E402
from bayescal.simulate import draw_errors, draw_poses  # noqa: E402

MACHINES = (
    ("3-PRS", ROOT / "examples" / "prs3" / "machine.toml"),
    ("RU-PUS-PRS", ROOT / "examples" / "rupus_prs" / "machine.toml"),
)
APPENDIX = ROOT / "studies" / "data" / "seed2_appendix1_measurement_errors.csv"
HALF_WIDTH_POSITION = 0.01  # mm: Appendix 1's X, Y, Z lie within +-0.00999
HALF_WIDTH_ANGLE = 1.75e-4  # rad: Appendix 1's angles lie within +-1.74e-4
N_POSES = 36
POSE_SEED, TRUTH_SEED, REP_SEED, CEILING_SEED = 2026, 7, 1000, 3000
TARGET_RATIO, TARGET_FRACTION = 1.10, 0.90
#: Actuator range (measurement and evaluation) per kind, where the study departs from the example file:
#: the 3-PRS example's 100 mm stroke leaves link length and actuator offset nearly confounded
#: (smallest singular value 1e-5 of the largest) and 6-DOF LS diverges; a 200 mm stroke is the study's choice.
STUDY_Q_LIMITS = {"3-PRS": [[400.0, 600.0]] * 3}


# ----------------------------------------------------------------- set-up
#: Options of the ``targets`` rule's calibration (k); ``--quick`` makes it coarse (the tests' mode).
TARGET_CALIBRATION: dict = {}


def appendix_noise() -> np.ndarray:
    """The seed's Appendix 1 measurement errors, shape (36, 6): mm, mm, mm, rad, rad, rad."""
    rows = [ln for ln in APPENDIX.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    table = np.array([[float(v) for v in ln.split(",")] for ln in rows[1:]])  # rows[0]: the header
    if table.shape != (36, 7):
        raise RuntimeError(f"{APPENDIX}: expected 36 rows of 7 columns, got {table.shape}")
    return table[:, 1:]


def study_machine(kind: str, path: Path):
    """The machine file with the instrument sigma of the seed's noise and the study's actuator range."""
    m = load_machine(path)
    noise = MeasurementNoise(HALF_WIDTH_POSITION / np.sqrt(3), HALF_WIDTH_ANGLE / np.sqrt(3), given=True)
    changes = {"noise": noise}
    if kind in STUDY_Q_LIMITS:
        changes["q_limits"] = np.array(STUDY_Q_LIMITS[kind], dtype=float)
    return dataclasses.replace(m, **changes)


def robust_poses(machine, q: np.ndarray, n_machines: int = 5) -> np.ndarray:
    """The rows of ``q`` that the nominal machine and ``n_machines`` machines with 3-tolerance errors all solve.

    Keeps poses away from the edge of the reachable workspace, so that every
    true machine a repetition draws can be measured there.
    """
    rng = np.random.default_rng(12345)
    ok = machine.forward(q).success
    for _ in range(n_machines):
        ok &= machine.forward(q, 3.0 * draw_errors(machine, rng)).success
    return q[ok]


def measurement_poses(machine, n: int = N_POSES) -> np.ndarray:
    """``n`` seeded poses drawn uniformly within ``q_limits`` (fixed over repetitions, as in the seed)."""
    q = robust_poses(machine, draw_poses(machine, 4 * n, np.random.default_rng(POSE_SEED)))
    if q.shape[0] < n:
        raise RuntimeError(f"only {q.shape[0]} robustly solvable poses in q_limits")
    return q[:n]


def eval_grid(machine) -> np.ndarray:
    """Full factorial grid over ``q_limits`` (5 levels for 3 actuators, 11 for 2), robustly solvable points."""
    m = machine.n_actuators
    levels = max(3, int(round(125 ** (1.0 / m))))
    axes = [np.linspace(lo, hi, levels) for lo, hi in machine.q_limits]
    return robust_poses(machine, np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1))


def noisy_recording(machine, q, theta, dof, noise) -> Recording:
    """Measure the true machine with the given noise rows (n, 6)."""
    poses = machine.forward(q, theta)
    if not poses.success.all():
        raise RuntimeError("a measurement pose of the true machine cannot be solved")
    rot = noise[:, 3:].copy()
    if dof == 5:
        rot[:, 2] = 0.0  # 5-DOF: the torsion about the tool axis is not measured
    R = so3_exp(rot) @ poses.rotation
    pos = poses.position + noise[:, :3]
    if dof == 6:
        return Recording(q=q.copy(), position=pos, rotvec=so3_log(R))
    return Recording(q=q.copy(), position=pos, axis=R[:, :, 2].copy())


class Evaluator:
    """Output error of calibrated models against the true machine over the evaluation grid."""

    def __init__(self, machine, q_eval, theta_true):
        self.machine, self.q = machine, q_eval
        true = machine.forward(q_eval, theta_true)
        self.pos, self.axis = true.position, true.rotation[:, :, 2]

    def __call__(self, thetas) -> tuple[np.ndarray, np.ndarray]:
        """RMS tool-point error (mm) and RMS tool-axis error (rad), one per row of ``thetas``."""
        th = np.atleast_2d(thetas)
        n, m = self.q.shape[0], th.shape[0]
        p = self.machine.forward(np.tile(self.q, (m, 1)), np.repeat(th, n, axis=0))
        dp = np.linalg.norm(p.position - np.tile(self.pos, (m, 1)), axis=1)
        cosang = np.clip(np.sum(p.rotation[:, :, 2] * np.tile(self.axis, (m, 1)), axis=1), -1, 1)
        da = np.arccos(cosang)
        dp[~p.success], da[~p.success] = np.inf, np.inf
        return np.sqrt(np.mean(dp.reshape(m, n) ** 2, axis=1)), np.sqrt(np.mean(da.reshape(m, n) ** 2, axis=1))


def seed_parameter_set(machine, q) -> np.ndarray:
    """The set identifiable with 6-DOF measurement at these poses (the seed's parameter set)."""
    model = MeasurementModel(machine, q, dof=6)
    pred = model.predict(None)
    J = (model.jacobian(None, pred) / model.sigma[None, :, None]).reshape(-1, machine.n_params)
    return analyse_identifiability(J, machine.layout).kept_index


def _quiet_identify(model, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return identify(model, **kw)


def increment_identify(model, method, *, lam=None, k=None, free, max_iter=50, xtol=1e-8):
    """The seed's iteration (study only): the filter acts on the Gauss-Newton *increment*.

    ``delta = sum f_i (u_i . r) / s_i v_i`` at every iteration; with ridge this
    is Levenberg-Marquardt with a fixed damping (it converges towards the LS
    solution), with TSVD the subspace is recomputed each iteration.
    Returns (history of theta, success).
    """
    machine = model.machine
    S = machine.tolerance[free]
    theta = np.zeros(machine.n_params)
    pred = model.predict(theta)
    hist = [theta.copy()]
    for _ in range(max_iter):
        r, J = whitened_system(model, theta, pred)
        sol = filtered_solve(J[:, free] * S, r, method, lam=lam, k=k)
        theta = theta.copy()
        theta[free] += S * sol.x
        pred = model.predict(theta, guess=pred.poses)
        hist.append(theta.copy())
        if not pred.success.all():
            return np.array(hist), False
        if np.max(np.abs(sol.x)) < xtol:
            return np.array(hist), True
    return np.array(hist), False


# ----------------------------------------------------------- one situation
def run_situation(machine, dof, q, q_eval, theta_true, noise, seed_set, *, n_lam, k_stride=1, inc_iter=40):
    """Everything the figures and tables of one (machine, dof) need, by full Gauss-Newton."""
    rec = noisy_recording(machine, q, theta_true, dof, noise)
    model = MeasurementModel.from_recording(machine, rec)
    ev = Evaluator(machine, q_eval, theta_true)
    P = machine.n_params
    before = ev(np.zeros(P))
    out = {"dof": dof, "before": (float(before[0][0]), float(before[1][0])), "n_free": int(seed_set.size)}
    ls_seed = _quiet_identify(model, method="ls", free=seed_set)
    ls_auto = _quiet_identify(model, method="ls")
    out["ls_seed"], out["ls_auto"] = ls_seed, ls_auto
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        ch_r, re_auto = choose_regularisation(model, "ridge", free=seed_set)
        ch_k, ts_auto = choose_regularisation(model, "tsvd", free=seed_set, target_calibration=TARGET_CALIBRATION)
    out["choice_ridge"], out["choice_tsvd"], out["re_auto"], out["ts_auto"] = ch_r, ch_k, re_auto, ts_auto

    # output error against lambda: warm-started from large lambda (near nominal) down
    A0, z0, _ = linearised_problem(model, np.zeros(P), seed_set, machine.tolerance)
    lams = np.sort(np.unique(np.concatenate([lambda_grid(np.linalg.svd(A0, compute_uv=False), n_lam),
                                             list(ch_r.choices.values())])))
    th_lam, it_lam, ok_lam = {}, {}, {}
    start = np.zeros(P)
    for lam in lams[::-1]:
        res = _quiet_identify(model, method="ridge", lam=float(lam), free=seed_set, theta0=start)
        th_lam[lam], it_lam[lam], ok_lam[lam] = res.theta, res.iterations, res.success
        start = res.theta if res.success else start
    err_lam = ev(np.array([th_lam[v] for v in lams]))
    ks = np.unique(np.concatenate([np.arange(1, seed_set.size + 1, k_stride), [seed_set.size],
                                   list(ch_k.choices.values())])).astype(int)
    th_k, ok_k = [], []
    for k in ks:
        res = _quiet_identify(model, method="tsvd", k=int(k), free=seed_set)
        th_k.append(res.theta)
        ok_k.append(res.success)
    err_k = ev(np.array(th_k))
    out.update(lams=lams, err_lam=err_lam, ok_lam=np.array([ok_lam[v] for v in lams]), ks=ks, err_k=err_k, ok_k=np.array(ok_k))
    out["ls_err"] = ev(ls_seed.theta) if ls_seed.success else (np.array([np.inf]), np.array([np.inf]))
    out["ls_auto_err"] = ev(ls_auto.theta) if ls_auto.success else (np.array([np.inf]), np.array([np.inf]))
    out["re_auto_err"], out["ts_auto_err"] = ev(re_auto.theta), ev(ts_auto.theta)
    i_best_lam, i_best_k = int(np.argmin(err_lam[0])), int(np.argmin(err_k[0]))
    out["re_best"] = _quiet_identify(model, method="ridge", lam=float(lams[i_best_lam]), free=seed_set)
    out["ts_best"] = _quiet_identify(model, method="tsvd", k=int(ks[i_best_k]), free=seed_set)
    out["re_best_err"], out["ts_best_err"] = ev(out["re_best"].theta), ev(out["ts_best"].theta)

    # the linearised curves the repetitions use, against these Gauss-Newton curves
    lin = linear_curves(model, machine, seed_set, lams, ks)
    gap_lam = np.abs(ev(lin[0])[0] / err_lam[0] - 1)
    gap_k = np.abs(ev(lin[1])[0] / err_k[0] - 1)
    ok_l, ok_kk = out["ok_lam"], out["ok_k"]
    near = [gap_lam[int(np.argmin(err_lam[0]))], gap_k[int(np.argmin(err_k[0]))],
            gap_lam[int(np.argmin(np.abs(lams - ch_r.choices[DEFAULT_RULE["ridge"]])))],
            gap_k[int(np.flatnonzero(ks == ch_k.choices[DEFAULT_RULE["tsvd"]])[0])]]
    out["linearisation_gap"] = {
        "best_and_default": float(np.max(near)),
        "all_converged": float(max(np.max(gap_lam[ok_l]), np.max(gap_k[ok_kk]))),
    }

    # iteration histories, from nominal (Figures 7, 9); the seed's increment variant beside them
    lam_d, k_d = float(ch_r.choices[DEFAULT_RULE["ridge"]]), int(ch_k.choices[DEFAULT_RULE["tsvd"]])
    re_d = _quiet_identify(model, method="ridge", lam=lam_d, free=seed_set)
    ts_d = _quiet_identify(model, method="tsvd", k=k_d, free=seed_set)
    inc_re, inc_re_ok = increment_identify(model, "ridge", lam=lam_d, free=seed_set, max_iter=inc_iter)
    inc_ts, inc_ts_ok = increment_identify(model, "tsvd", k=k_d, free=seed_set, max_iter=inc_iter)
    ls_hist = ls_seed if ls_seed.success else ls_auto
    tol = machine.tolerance
    out["histories"] = {
        f"LS{'' if ls_seed.success else ' (reduced set)'}": ls_hist.history / tol,
        f"RE lambda={lam_d:.3g}": re_d.history / tol,
        f"TSVD k={k_d}": ts_d.history / tol,
        "seed RE-increment": inc_re / tol,
        "seed TSVD-increment": inc_ts / tol,
    }
    out["iterations"] = {
        "LS": ls_hist.iterations, "RE": re_d.iterations, "TSVD": ts_d.iterations,
        "seed RE-increment": inc_re.shape[0] - 1 if inc_re_ok else None,
        "seed TSVD-increment": inc_ts.shape[0] - 1 if inc_ts_ok else None,
    }
    out["lam_default"], out["k_default"] = lam_d, k_d
    return out


def linear_curves(model, machine, free, lams, ks):
    """Identified thetas from one linearisation at the lambda = 1 ridge solution (TSVD: subspace from nominal).

    This is what the repetitions use instead of a Gauss-Newton run per grid
    value; the main run reports how far it is from the Gauss-Newton curves.
    """
    P, tol = machine.n_params, machine.tolerance
    pilot = _quiet_identify(model, method="ridge", lam=1.0, free=free)
    A, z, _ = linearised_problem(model, pilot.theta, free, tol)
    A0, _, _ = linearised_problem(model, np.zeros(P), free, tol)
    return linear_curves_at(A, z, pilot.theta, free, tol, "ridge", lams), linear_tsvd_at(A0, A, z, P, free, tol, ks)


def linear_tsvd_at(A0, A, z, P, free, tol, ks):
    """TSVD thetas ``phi = V_k c``: subspace ``V_k`` of ``A0`` (start geometry, as bayescal's TSVD),
    coordinates ``c`` by least squares on the problem ``A phi ~ z`` linearised near the solution."""
    V = np.linalg.svd(A0, full_matrices=False)[2].T
    B = A @ V
    th = np.zeros((len(ks), P))
    for j, k in enumerate(ks):
        c = np.linalg.lstsq(B[:, :k], z, rcond=None)[0]
        th[j, free] = (V[:, :k] @ c) * tol[free]
    return th


# ------------------------------------------------------------- repetitions
def run_repetition(machine, dof, q, q_eval, seed_set, seed, lam_grid):
    """One seeded repetition: fresh true machine and noise; rule / best output-error ratios."""
    rng = np.random.default_rng(seed)
    theta_true = draw_errors(machine, rng)
    noise = np.concatenate([rng.uniform(-HALF_WIDTH_POSITION, HALF_WIDTH_POSITION, (q.shape[0], 3)),
                            rng.uniform(-HALF_WIDTH_ANGLE, HALF_WIDTH_ANGLE, (q.shape[0], 3))], axis=1)
    model = MeasurementModel.from_recording(machine, noisy_recording(machine, q, theta_true, dof, noise))
    ev = Evaluator(machine, q_eval, theta_true)
    P, tol = machine.n_params, machine.tolerance
    pilot = _quiet_identify(model, method="ridge", lam=1.0, free=seed_set)
    A, z, groups = linearised_problem(model, pilot.theta, seed_set, tol)
    # the 'success' rule judges candidates by the study's own output error: tool points over the evaluation grid
    G = (machine.tool_jacobian(q_eval, None, machine.forward(q_eval))[:, :3, :][:, :, seed_set]
         * tol[seed_set]).reshape(-1, seed_set.size)
    ch_r = choose_linear(A, z, "ridge", groups=groups, seed=seed, output_map=G)
    A0, z0, groups0 = linearised_problem(model, np.zeros(P), seed_set, tol)
    ch_k = choose_linear(A0, z0, "tsvd", groups=groups0, seed=seed, output_map=G, target_calibration=TARGET_CALIBRATION)
    # the grid, every rule's lambda, and lambda = 1 (MAP under the tolerance prior: the yardstick)
    lams = np.concatenate([lam_grid, [ch_r.choices[r] for r in RULES], [1.0]])
    ks = np.arange(1, seed_set.size + 1)
    th_r = linear_curves_at(A, z, pilot.theta, seed_set, tol, "ridge", lams)
    th_k = linear_tsvd_at(A0, A, z, P, seed_set, tol, ks)
    err = ev(np.vstack([th_r, th_k]))[0]
    e_r, e_k = err[: lams.size], err[lams.size:]
    best_r, best_k = float(np.min(e_r)), float(np.min(e_k))
    ridge = {r: float(e_r[lam_grid.size + i] / best_r) for i, r in enumerate(RULES)}
    ridge["prior (lambda=1)"] = float(e_r[-1] / best_r)
    return {
        "ridge": ridge,
        "tsvd": {**{r: float(e_k[ch_k.choices[r] - 1] / best_k) for r in RULE_NAMES if r in ch_k.choices},
                 # Bayes-optimal k in expectation for machines drawn from the tolerance prior: keep s_i > 1
                 "prior (k = #{s > 1})": float(e_k[max(int(np.sum(ch_k.singular_values > 1.0)), 1) - 1] / best_k)},
        "best_lam": float(lams[np.argmin(e_r)]), "best_k": int(ks[np.argmin(e_k)]),
        "error_mm": {"before": float(ev(np.zeros(P))[0][0]), "RE (best lambda)": best_r, "TSVD (best k)": best_k,
                     "RE (auto)": float(e_r[lam_grid.size + RULES.index(DEFAULT_RULE["ridge"])]),
                     "TSVD (auto)": float(e_k[ch_k.choices[DEFAULT_RULE["tsvd"]] - 1]),
                     "LS (linearised)": float(e_k[-1])},
        "choices_ridge": dict(ch_r.choices), "choices_tsvd": dict(ch_k.choices),
    }


def linear_curves_at(A, z, theta_lin, free, tol, method, values):
    """Thetas of the linear problem ``A x ~ z`` (the total deviation) for each lambda or k."""
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    coef = (U.T @ z) / np.where(s > 0, s, np.inf)
    if method == "ridge":
        F = s[None, :] ** 2 / (s[None, :] ** 2 + np.asarray(values, float)[:, None])
    else:
        F = (np.arange(s.size)[None, :] < np.asarray(values)[:, None]).astype(float)
    th = np.tile(theta_lin, (len(values), 1))
    th[:, free] = (F * coef[None, :]) @ Vt * tol[free]
    return th


# --------------------------------------------------------------- reporting
def _fmt(x, f="{:.4g}"):
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f.format(x)


def chain_table(name, machine, theta_true, sits) -> tuple[str, str]:
    """Identified errors of one chain vs truth (Tables 5, 6), Markdown and CSV."""
    names = machine.layout.names
    prefix = names[0].split(".")[0]
    rows = [i for i, n in enumerate(names) if n.split(".")[0] == prefix]
    cols = []
    for s in sits:
        d = s["dof"]
        cols.append((f"LS {d}-DOF", s["ls_seed"]))
        if not s["ls_seed"].success:
            cols.append((f"LS {d}-DOF reduced set", s["ls_auto"]))
        cols += [(f"RE {d}-DOF (lambda={s['re_auto'].lam:.3g})", s["re_auto"]), (f"TSVD {d}-DOF (k={s['ts_auto'].k})", s["ts_auto"])]
    head = ["parameter", "unit", "true"] + [c for c, _ in cols]
    md = [f"Identified errors of {prefix} of the {name} against the truth (lambda, k: default rules)", "",
          "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    csv = [",".join(h.replace(",", ";") for h in head)]
    for i in rows:
        vals = [_fmt(float(r.theta[i])) if r.success and r.free[i] else ("failed" if not r.success else "fixed") for _, r in cols]
        cells = [names[i], machine.layout.units[i], _fmt(float(theta_true[i]))] + vals
        md.append("| " + " | ".join(cells) + " |")
        csv.append(",".join(cells))
    return "\n".join(md) + "\n", "\n".join(csv) + "\n"


def output_table(name, sits) -> tuple[str, str]:
    """Output errors before and after calibration (Tables 7, 8), Markdown and CSV."""
    head = ["method"] + [f"{s['dof']}-DOF {q}" for s in sits for q in ("RMS position (mm)", "RMS axis (rad)", "iterations", "success")]
    def cells(get):
        out = []
        for s in sits:
            res, err = get(s)
            ok = res is None or res.success
            out += [_fmt(float(err[0][0])) if ok else "failed", _fmt(float(err[1][0]), "{:.3e}") if ok else "failed",
                    "-" if res is None else str(res.iterations), "-" if res is None else str(res.success)]
        return out
    lines = [
        ("before calibration", lambda s: (None, (np.array([s["before"][0]]), np.array([s["before"][1]])))),
        ("LS, seed's parameter set", lambda s: (s["ls_seed"], s["ls_err"])),
        ("LS, bayescal's reduced set", lambda s: (s["ls_auto"], s["ls_auto_err"])),
        ("RE, best lambda on the curve", lambda s: (s["re_best"], s["re_best_err"])),
        (f"RE, lambda by '{DEFAULT_RULE['ridge']}'", lambda s: (s["re_auto"], s["re_auto_err"])),
        ("TSVD, best k on the curve", lambda s: (s["ts_best"], s["ts_best_err"])),
        (f"TSVD, k by '{DEFAULT_RULE['tsvd']}'", lambda s: (s["ts_auto"], s["ts_auto_err"])),
    ]
    md = [f"Output errors of the {name} over the evaluation grid, true machine vs calibrated model", "",
          "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    csv = [",".join(head)]
    for label, get in lines:
        c = [label] + cells(get)
        md.append("| " + " | ".join(c) + " |")
        csv.append(",".join(x.replace(",", ";") for x in c))
    return "\n".join(md) + "\n", "\n".join(csv) + "\n"


def attainable(machine, dof, q, q_eval, free, lam_grid, *, n_data, n_posterior, seed):
    """The most any rule can achieve on the (d) target, in the linear-Gaussian idealisation of this situation.

    ``A``: the whitened, tolerance-scaled identification matrix at nominal
    for the measurement poses; ``G``: tool-point Jacobians over the
    evaluation grid (the output error is their RMS).  See
    :mod:`bayescal.identify.ceiling`.
    """
    tol = machine.tolerance
    model = MeasurementModel(machine, q, dof=dof)
    J = (model.jacobian(None, model.predict(None)) / model.sigma[None, :, None]).reshape(-1, machine.n_params)
    A = J[:, free] * tol[free]
    G = (machine.tool_jacobian(q_eval, None, machine.forward(q_eval))[:, :3, :][:, :, free] * tol[free]).reshape(-1, free.size)
    lams = np.concatenate([lam_grid, [1.0]])
    ks = np.arange(1, int(np.linalg.matrix_rank(A)) + 1)
    kw = dict(n_data=n_data, n_posterior=n_posterior, seed=seed)
    s = np.linalg.svd(A, compute_uv=False)
    return {
        "ridge": choice_ceiling(A, G, "ridge", lams, fixed={"prior (lambda=1)": 1.0}, **kw).to_dict(),
        "tsvd": choice_ceiling(A, G, "tsvd", ks, fixed={"prior (k = #{s > 1})": max(int(np.sum(s > 1.0)), 1)}, **kw).to_dict(),
    }


def ratio_stats(values) -> dict:
    v = np.asarray(values, dtype=float)
    return {"median": float(np.median(v)), "p10": float(np.percentile(v, 10)), "p90": float(np.percentile(v, 90)),
            "max": float(np.max(v)), "within_10pct": float(np.mean(v <= TARGET_RATIO))}


# -------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="reduced run (coarse lambda grid, few repetitions)")
    ap.add_argument("--out", default=str(ROOT / "studies" / "out" / "seed2"), help="output directory")
    ap.add_argument("--reps", type=int, help="repetitions for finding (d) (default 50, quick 2)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    reps = args.reps if args.reps is not None else (2 if args.quick else 50)
    if args.quick:  # the targets rule's calibration, coarse: 30 data sets per scale, 200 draws
        TARGET_CALIBRATION.update(n_data=30, n_draws=200)
    n_lam = 7 if args.quick else 29
    t_start = time.perf_counter()
    notes, summary, md = [], {"quick": args.quick, "reps": reps, "situations": {}}, []
    machines = []
    for kind, path in MACHINES:
        if kind not in KINDS or not path.exists():
            notes.append(f"{kind}: machine kind not available in this bayescal (not in bayescal.machines.KINDS "
                         f"or {path.relative_to(ROOT)} missing); only the other manipulators are run")
            continue
        machines.append((kind, study_machine(kind, path)))
    checks = []
    ratios_fig = {}
    noise_table = appendix_noise()
    for kind, machine in machines:
        tag = kind.lower().replace("-", "")
        q = measurement_poses(machine)
        q_eval = eval_grid(machine)
        seed_set = seed_parameter_set(machine, q)
        theta_true = draw_errors(machine, np.random.default_rng(TRUTH_SEED))
        sits = []
        for dof in (6, 5):
            s = run_situation(machine, dof, q, q_eval, theta_true, noise_table[:N_POSES], seed_set, n_lam=n_lam,
                              k_stride=6 if args.quick else 1, inc_iter=8 if args.quick else 40)
            sits.append(s)
            key = f"{kind} {dof}-DOF"
            plots.plot_output_error(
                s["lams"], s["err_lam"][0], s["ks"], s["err_k"][0], out / f"{tag}_{dof}dof_output_error.png",
                lam_choices={r: (v, float(s["err_lam"][0][np.argmin(np.abs(s["lams"] - v))])) for r, v in s["choice_ridge"].choices.items()},
                k_choices={r: (v, float(s["err_k"][0][np.flatnonzero(s["ks"] == v)[0]])) for r, v in s["choice_tsvd"].choices.items()},
                ls_error=float(s["ls_err"][0][0]), before=s["before"][0],
                title=f"{key}: output error against lambda and k (every point a full Gauss-Newton fit)",
            )
            plots.plot_histories(s["histories"], out / f"{tag}_{dof}dof_history.png", title=f"{key}: iteration histories")
            plots.plot_choice(s["choice_ridge"], out / f"{tag}_{dof}dof_rules_ridge.png", title=f"{key}: rules for lambda")
            plots.plot_choice(s["choice_tsvd"], out / f"{tag}_{dof}dof_rules_tsvd.png", title=f"{key}: rules for k")
            # (a) LS works with 6-DOF, is refused as ill-posed with 5-DOF on the seed's set
            ls = s["ls_seed"]
            if dof == 6:
                checks.append((f"(a) {key}: LS on the seed's set converges and reduces the output error at least 5x",
                               bool(ls.success and s["ls_err"][0][0] < 0.2 * s["before"][0])))
            else:
                checks.append((f"(a) {key}: LS on the seed's set is refused as ill-posed (success=False, clear message)",
                               bool((not ls.success) and "ill-posed" in ls.message)))
                checks.append((f"(a) {key}: LS on bayescal's reduced set converges and reduces the output error at least 5x",
                               bool(s["ls_auto"].success and s["ls_auto_err"][0][0] < 0.2 * s["before"][0])))
            # (b) RE and TSVD succeed
            for lab, res, err in (("RE", s["re_auto"], s["re_auto_err"]), ("TSVD", s["ts_auto"], s["ts_auto_err"])):
                checks.append((f"(b) {key}: {lab} with the automatic choice converges and reduces the output error at least 5x",
                               bool(res.success and err[0][0] < 0.2 * s["before"][0])))
            errs = {"LS": float(s["ls_err"][0][0]) if ls.success else float(s["ls_auto_err"][0][0]),
                    "RE (best lambda)": float(s["re_best_err"][0][0]), "TSVD (best k)": float(s["ts_best_err"][0][0]),
                    "RE (auto)": float(s["re_auto_err"][0][0]), "TSVD (auto)": float(s["ts_auto_err"][0][0])}
            summary["situations"][key] = {
                "before_rms_position_mm": s["before"][0], "output_error_mm": errs,
                "smallest": min(errs, key=errs.get), "iterations": s["iterations"],
                "lambda_choices": s["choice_ridge"].choices, "k_choices": s["choice_tsvd"].choices,
                "best_lambda_on_curve": float(s["lams"][np.argmin(s["err_lam"][0])]),
                "best_k_on_curve": int(s["ks"][np.argmin(s["err_k"][0])]),
                "ls_seed_set_message": ls.message, "n_seed_set": int(seed_set.size),
                "n_reduced_set": int(s["ls_auto"].free.sum()),
                "linearised_vs_gauss_newton_rel_gap": s["linearisation_gap"],
            }
            # (d) repetitions
            lam_grid = np.logspace(np.log10(s["lams"][0]), np.log10(s["lams"][-1]), 2 * n_lam + 1)
            reps_out = [run_repetition(machine, dof, q, q_eval, seed_set, REP_SEED + 97 * i + dof, lam_grid) for i in range(reps)]
            for method in ("ridge", "tsvd"):
                rr = {r: [x[method][r] for x in reps_out] for r in reps_out[0][method]}
                summary["situations"][key][f"ratios_{method}"] = {r: ratio_stats(v) for r, v in rr.items()}
                ratios_fig[(key, method)] = rr
            summary["situations"][key]["rep_best_lambda_range"] = [min(x["best_lam"] for x in reps_out), max(x["best_lam"] for x in reps_out)]
            summary["situations"][key]["rep_best_k_range"] = [min(x["best_k"] for x in reps_out), max(x["best_k"] for x in reps_out)]
            em = {m_: np.array([x["error_mm"][m_] for x in reps_out]) for m_ in reps_out[0]["error_mm"]}
            summary["situations"][key]["rep_output_error_median_mm"] = {m_: float(np.median(v)) for m_, v in em.items()}
            summary["situations"][key]["rep_fraction_tsvd_best_below_re_best"] = float(np.mean(em["TSVD (best k)"] < em["RE (best lambda)"]))
            summary["situations"][key]["rep_fraction_tsvd_auto_below_re_auto"] = float(np.mean(em["TSVD (auto)"] < em["RE (auto)"]))
            summary["situations"][key]["attainable"] = attainable(
                machine, dof, q, q_eval, seed_set, lam_grid, n_data=20 if args.quick else 400,
                n_posterior=100 if args.quick else 400, seed=CEILING_SEED + dof)
        t5, c5 = chain_table(kind, machine, theta_true, sits)
        t7, c7 = output_table(kind, sits)
        write_text_atomic(out / f"{tag}_table_chain.md", t5)
        write_text_atomic(out / f"{tag}_table_chain.csv", c5)
        write_text_atomic(out / f"{tag}_table_output.md", t7)
        write_text_atomic(out / f"{tag}_table_output.csv", c7)
        md += [f"## {kind}", "", t5, t7]
    if ratios_fig:
        plots.plot_ratio_spread(ratios_fig, out / "repetitions_ratio.png",
                                title=f"{reps} repetitions: output error of each rule's choice / best on the curve")
    # (c) and (d) reported
    sec_c, sec_c2, sec_d, sec_ceil, target_ok, attainable_ok = [], [], [], [], True, True
    for key, v in summary["situations"].items():
        med = v["rep_output_error_median_mm"]
        sec_c2.append(f"| {key} | " + " | ".join(f"{med[m]:.5f}" for m in med)
                      + f" | {100 * v['rep_fraction_tsvd_best_below_re_best']:.0f}% | {100 * v['rep_fraction_tsvd_auto_below_re_auto']:.0f}% |")
        e = v["output_error_mm"]
        sec_c.append(f"| {key} | {v['before_rms_position_mm']:.4f} | " + " | ".join(f"{e[m]:.5f}" for m in e)
                     + f" | {v['smallest']} | " + ", ".join(f"{m} {n if n is not None else 'n/c'}" for m, n in v["iterations"].items()) + " |")
        for method in ("ridge", "tsvd"):
            a = v["attainable"][method]
            attainable_ok &= a["ceiling"] >= TARGET_FRACTION
            (fixed_label, fixed_rate), = a["fixed_rates"].items()
            default_rate = v[f"ratios_{method}"][DEFAULT_RULE[method]]["within_10pct"]
            sec_ceil.append(f"| {key} | {method} | {100 * a['ceiling']:.0f}% (+- {100 * a['ceiling_se']:.1f}) | "
                            f"{100 * a['bayes_rule_rate']:.0f}% | {100 * fixed_rate:.0f}% | "
                            f"{100 * default_rate:.0f}% |")
            st = v[f"ratios_{method}"]
            for r in st:
                x = st[r]
                default = r == DEFAULT_RULE[method]
                met = x["within_10pct"] >= TARGET_FRACTION
                if default:
                    target_ok &= met
                sec_d.append(f"| {key} | {method} | {r}{' (default)' if default else ''} | {x['median']:.3f} | "
                             f"{x['p10']:.3f} - {x['p90']:.3f} | {x['max']:.3f} | {100 * x['within_10pct']:.0f}% |")
    elapsed = time.perf_counter() - t_start
    summary.update(checks=[{"finding": c, "holds": ok} for c, ok in checks], target_met=bool(target_ok),
                   target_attainable_by_any_rule=bool(attainable_ok),
                   notes=notes, elapsed_seconds=elapsed, default_rule=DEFAULT_RULE)
    first = next(iter(summary["situations"].values())) if summary["situations"] else {}
    keys_e = list(first.get("output_error_mm", {}))
    keys_m = list(first.get("rep_output_error_median_mm", {}))
    text = [
        "# Seed 2 (LS vs RE vs TSVD): findings", "",
        f"Run: {'quick' if args.quick else 'full'}, {reps} repetitions, {elapsed:.0f} s.", "",
        *[f"- note: {n}" for n in notes], "",
        "## (a), (b): checked", "",
        *[f"- [{'x' if ok else ' '}] {c}" for c, ok in checks], "",
        "## (c) output error (RMS tool point, mm) and iterations", "",
        "| situation | before | " + " | ".join(keys_e) + " | smallest | iterations |",
        "|" + "---|" * (len(keys_e) + 4), *sec_c, "",
        "Iterations: bayescal's total-deviation Gauss-Newton (LS, RE, TSVD) and the seed's increment-filtered "
        "iteration (n/c: not converged within the iteration cap).", "",
        f"Over the {reps} repetitions (linearised curves; median output error in mm, and how often TSVD beats RE):", "",
        "| situation | " + " | ".join(keys_m) + " | TSVD best < RE best | TSVD auto < RE auto |",
        "|" + "---|" * (len(keys_m) + 3), *sec_c2, "",
        f"## (d) rule / best-on-curve output-error ratio over {reps} repetitions", "",
        "Each repetition draws a fresh true machine and fresh uniform noise (the Appendix 1 distribution) at the same "
        "36 poses. Curves are computed from one linearisation at the lambda = 1 ridge solution (TSVD subspace from "
        "nominal); against full Gauss-Newton on the main run the relative gap is "
        + ", ".join(f"{k}: {100 * v['linearised_vs_gauss_newton_rel_gap']['best_and_default']:.2f}% at the best value "
                    f"and the default picks, {100 * v['linearised_vs_gauss_newton_rel_gap']['all_converged']:.0f}% "
                    f"over all grid points" for k, v in summary["situations"].items())
        + " (the large gaps lie in the weakly regularised region, where estimates reach tens of tolerances). "
        "'prior (lambda=1)' is not a rule but the yardstick: the MAP estimate under the tolerance prior the true "
        "machines are drawn from, Bayes-optimal in expectation; 'prior (k = #{s > 1})' is its TSVD counterpart "
        "(keeping direction i lowers the expected error iff s_i > 1 when the truth is drawn from the prior).", "",
        f"Target: the default rule within {100 * (TARGET_RATIO - 1):.0f}% of the best in at least "
        f"{100 * TARGET_FRACTION:.0f}% of repetitions in every situation: **{'met' if target_ok else 'NOT met'}**.", "",
        "| situation | method | rule | median | p10 - p90 | max | within 10% |", "|---|---|---|---|---|---|---|", *sec_d, "",
        "### What any rule can attain", "",
        "The linear-Gaussian idealisation of each situation (the study's identification matrix at nominal, the "
        "evaluation grid's tool-point Jacobians, truths from the tolerance prior, Gaussian whitened noise): the "
        "largest expected share of data sets on which ANY rule is within 10% of the curve's best "
        "(bayescal.identify.ceiling: the Bayes decision for that event, knowing the prior exactly), the share that "
        "rule realised on the simulated truths, the yardstick's realised share there, and the default rule's share "
        "in the repetitions above. Target attainable by any rule in every situation: "
        f"**{'yes' if attainable_ok else 'no'}**.", "",
        "| situation | method | ceiling (any rule) | Bayes rule realised | yardstick realised | default rule (repetitions) |",
        "|---|---|---|---|---|---|", *sec_ceil, "",
        *md,
    ]
    write_text_atomic(out / "findings.md", "\n".join(text) + "\n")
    write_json_atomic(out / "summary.json", summary)
    print("\n".join(text[: text.index("", text.index(sec_d[-1])) if sec_d else len(text)]))
    print(f"\nwrote {out} in {elapsed:.1f} s")
    return 0 if all(ok for _, ok in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
