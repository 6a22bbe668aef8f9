"""What any calibration can reach on Klipper's measurement pattern: leave-one-out floors, exactly and over printers.

Part of ``studies/delta_klipper.py``.  The delta model linearised at the
printer's geometry (``y = J theta + e``; checked against the nonlinear fits
on the same draws by :func:`nonlinear_check`) makes every leave-one-out
error a matrix times the data (:mod:`studies.loo_linear`), so the
calibrations are compared on the same splits, the same printers and the
same noise:

* ``klipper``: ``DELTA_CALIBRATE``'s weighted least squares over its nine
  parameters, its weights recomputed on every split;
* ``tolerance``: MAP under the tolerance prior with the stated sigmas (the
  previous default);
* ``default``: what ``identify --method map --free all`` does on a
  ``bayescal klipper`` recording (no stated noise: the ratio of the
  geometry's spread to the noise from the evidence of the kept rows);
* ``default_auto``: the same with ``--free auto`` (the parameters the data
  cannot determine fixed at nominal);
* ``bayes_optimal``: the posterior mean under the true prior and noise, the
  smallest expected error any calibration has from these rows;
* ``oracle``: the true geometry; its error is the left-out row's noise.

Only the ratio of the geometry's spread to the noise matters for all six
(each is equivariant under scaling both), so the sweep is over that ratio
``r``: the truth is drawn from ``r`` times the tolerances, the noise from the
stated sigmas.  One more scenario takes the scales the real printer's own
data support (evidence, heights' and distances' noise apart).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from bayescal.constraints.model import ConstraintModel
from bayescal.identifiability import analyse_identifiability
from bayescal.klipper.baseline import KLIPPER_PARAMS, MEASURE_WEIGHT
from studies.loo_linear import (
    evidence_map_gain, expected_sq_error, log_evidence, loo_errors, loo_operator, map_gain, wls_gain,
)

LINEAR_METHODS = ("tolerance", "default", "default_auto", "bayes_optimal", "oracle")
RATIOS = (0.25, 0.5, 1.0, 2.0, 5.0)


def klipper_weights(heights: np.ndarray):
    """Klipper's row weights on a split: heights ``n_d / (0.5 n_h)``, distances 1 (klipper_fit)."""
    def w(rows):
        hh = heights[rows]
        nd, nh = int((~hh).sum()), int(hh.sum())
        return np.where(hh, nd / (MEASURE_WEIGHT * nh) if nd and nh else 1.0, 1.0)
    return w


def jacobians(machine, kd, rec, klipper_jacobian, keys):
    """bayescal's Jacobian (n, 21) and Klipper's (n, 9), mm per parameter unit, at the machine's nominal geometry."""
    model = ConstraintModel.from_recording(machine, rec)
    pred = model.predict(None)
    Jb = model.jacobian(None, pred).reshape(rec.n_rows, -1)
    JK, _ = klipper_jacobian(kd, rec)
    JK = (JK * rec.sigma[:, None])[:, [keys.index(n) for n in KLIPPER_PARAMS]]
    return Jb, JK


def real_scales(machine, rec, theta_map, J_at_map):
    """Noise scales (heights, distances) and tolerance scale that maximise the real data's evidence.

    The model is linearised at bayescal's MAP of the real recording
    (``y - f(theta) + J theta ~ J theta + e`` about the nominal), the prior
    centred on the nominal geometry.
    """
    model = ConstraintModel.from_recording(machine, rec)
    y = rec.value - model.predict(theta_map).y[:, 0] + J_at_map @ theta_map
    h = np.array([m == "height" for m in rec.measure])

    def nll(v):
        sh, sd, st = np.exp(v)
        return -log_evidence(J_at_map, y, st * machine.tolerance, rec.sigma * np.where(h, sh, sd))

    best = min((minimize(nll, x0, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-6, "maxiter": 4000})
                for x0 in ([0.0, 0.0, 0.0], [1.5, 1.5, 0.0], [2.0, 1.0, 1.0])), key=lambda r: r.fun)
    sh, sd, st = np.exp(best.x)
    return {"noise_scale_height": float(sh), "noise_scale_distance": float(sd), "tolerance_scale": float(st),
            "log_evidence": float(-best.fun)}


def _fixed_by_auto(Jb, rec, machine):
    ida = analyse_identifiability(Jb / rec.sigma[:, None], machine.layout)
    return np.array([n in ida.fixed for n in machine.layout.names])


def scenario(Jb, JK, rec, machine, truth_tol, noise, n_printers, seed, *, evidence=True):
    """Expected and per-printer leave-one-out errors of every method for one truth/noise scenario.

    Returns a dict: ``expected`` (sqrt of the summed expected squared
    errors over Klipper's, per linear method), ``printers`` (per printer and
    method: the LOO RMS over Klipper's), ``mse`` (per printer and method,
    mm^2, Klipper's included), ``evidence_ratio`` (median prior/noise ratio
    the default chose).
    """
    h = np.array([m == "height" for m in rec.measure])
    tol, sig = machine.tolerance, rec.sigma
    MK = loo_operator(JK, wls_gain(klipper_weights(h)))
    ops = {"tolerance": loo_operator(Jb, map_gain(sig, tol)), "bayes_optimal": loo_operator(Jb, map_gain(noise, truth_tol))}
    ek = expected_sq_error(MK, Jb, truth_tol, noise).sum()
    expected = {k: float(np.sqrt(expected_sq_error(M, Jb, truth_tol, noise).sum() / ek)) for k, M in ops.items()}
    expected["oracle"] = float(np.sqrt(np.sum(noise**2) / ek))
    fixed = _fixed_by_auto(Jb, rec, machine)
    # Klipper's in-sample residual operator (all rows, its weights): for comparing the simulated scale with a real printer's
    wk = np.sqrt(klipper_weights(h)(np.arange(rec.n_rows)))
    RK = np.eye(rec.n_rows) - JK @ np.linalg.pinv(JK * wk[:, None]) * wk[None, :]
    klipper_mm = {"loo_rms": [], "in_sample_rms": []}
    rng = np.random.default_rng(seed)
    mse = {k: [] for k in ("klipper",) + LINEAR_METHODS}
    draws = []
    for _ in range(n_printers):
        theta = truth_tol * rng.normal(size=tol.size)
        e = noise * rng.normal(size=rec.n_rows)
        y = Jb @ theta + e
        draws.append((theta, e))
        err = {"klipper": MK @ y, "oracle": e, **{k: M @ y for k, M in ops.items()}}
        klipper_mm["loo_rms"].append(float(np.sqrt(np.mean(err["klipper"] ** 2))))
        klipper_mm["in_sample_rms"].append(float(np.sqrt(np.mean((RK @ y) ** 2))))
        if evidence:
            err["default"] = loo_errors(Jb, y, evidence_map_gain(y, sig, tol))
            err["default_auto"] = loo_errors(Jb, y, evidence_map_gain(y, sig, np.where(fixed, 0.0, tol)))
        for k, v in err.items():
            mse[k].append(float(np.mean(v**2)))
    mse = {k: np.array(v) for k, v in mse.items() if v}
    printers = {k: np.sqrt(v / mse["klipper"]) for k, v in mse.items() if k != "klipper"}
    return {"expected": expected, "printers": printers, "mse": mse, "draws": draws,
            "klipper_mm": {k: float(np.median(v)) for k, v in klipper_mm.items()}}


def summarise(sc: dict, n_boot: int = 2000, seed: int = 0) -> dict:
    """Per method: median, mean and SE of the per-printer ratio, share at most 0.5, max; the excess-error ratio.

    ``excess``: (mean MSE - oracle's mean MSE) / (Klipper's mean MSE -
    oracle's): the share of Klipper's error above the noise floor a method
    keeps (0: the oracle; 0.5: halved), with a bootstrap SE over printers.
    """
    rng = np.random.default_rng(seed)
    mse = sc["mse"]
    n = mse["klipper"].size
    boot = rng.integers(0, n, size=(n_boot, n))
    out = {}
    for k, r in sc["printers"].items():
        def excess(idx, k=k):
            o, kl = mse["oracle"][idx].mean(axis=-1), mse["klipper"][idx].mean(axis=-1)
            return (mse[k][idx].mean(axis=-1) - o) / (kl - o)
        out[k] = {
            "median": float(np.median(r)), "mean": float(r.mean()), "se": float(r.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan"),
            "share_at_most_half": float(np.mean(r <= 0.5)), "max": float(r.max()),
            "excess": float(excess(np.arange(n))), "excess_se": float(np.std(excess(boot), ddof=1)) if n > 1 else float("nan"),
            "expected": sc["expected"].get(k),
        }
    return out


def nonlinear_check(machine, kd, rec, draws, loo_bayescal, loo_klipper, Jb, JK, rows=None):
    """The same printers (``draws``) through the nonlinear fits: Klipper's and ``identify``'s, against the linear ones.

    Returns per printer the nonlinear and linear LOO RMS of Klipper and of
    the default, and the nonlinear ratio.
    """
    from dataclasses import replace

    h = np.array([m == "height" for m in rec.measure])
    MK = loo_operator(JK, wls_gain(klipper_weights(h)))
    model = ConstraintModel.from_recording(machine, rec)
    y0 = model.predict(None).y[:, 0]
    sel = np.arange(rec.n_rows) if rows is None else np.asarray(rows)
    out = []
    for theta, e in draws:
        pred = model.predict(theta)
        if not pred.success.all():
            continue
        sim = replace(rec, value=pred.y[:, 0] + e)
        y = sim.value - y0
        b, k = loo_bayescal(machine, sim, rows=rows), loo_klipper(kd, sim, rows=rows)
        lin_b = loo_errors(Jb, y, evidence_map_gain(y, rec.sigma, machine.tolerance))[sel]
        lin_k = (MK @ y)[sel]
        rb, rk = np.sqrt(np.nanmean(b.loo_error[sel] ** 2)), np.sqrt(np.nanmean(k.loo_error[sel] ** 2))
        out.append({"bayescal": float(rb), "klipper": float(rk), "ratio": float(rb / rk),
                    "linear_bayescal": float(np.sqrt(np.mean(lin_b**2))), "linear_klipper": float(np.sqrt(np.mean(lin_k**2))),
                    "linear_ratio": float(np.sqrt(np.mean(lin_b**2) / np.mean(lin_k**2))),
                    "oracle_ratio": float(np.sqrt(np.mean(e[sel] ** 2)) / rk)})
    return out
