"""Figures of the choice of lambda and k: rule curves, output-error curves, histories, repetition spreads.

matplotlib is imported lazily with the Agg backend, so importing bayescal
never needs a display.  Every function writes one PNG and returns its path.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ._backend import pyplot as _plt
from ._backend import save

__all__ = ["plot_choice", "plot_output_error", "plot_histories", "plot_ratio_spread", "RULE_COLOURS"]

RULE_COLOURS = {"cv": "tab:blue", "lcurve": "tab:orange", "gcv": "tab:green", "discrepancy": "tab:red", "evidence": "tab:purple",
                "risk": "tab:brown", "success": "tab:pink", "targets": "tab:olive"}




def _save(fig, path) -> Path:
    return save(fig, path, dpi=90)


def plot_choice(choice, path, *, title: str = "") -> Path:
    """The rule curves of a :class:`~bayescal.identify.choose.RegularisationChoice`.

    Panels: L-curve (with the corner), GCV, discrepancy, log evidence,
    posterior risk, cross-validation error; each marks the value its rule
    picks and the value used.
    """
    plt = _plt()
    c, g = choice.curves, np.asarray(choice.grid, dtype=float)
    ridge = choice.method == "ridge"
    sym = "lambda" if ridge else "k"
    fig, ax = plt.subplots(2, 3, figsize=(13, 6.5))

    def mark(a, rule, x, y=None):
        v = choice.choices.get(rule)
        if v is None:
            return
        i = int(np.argmin(np.abs(g - v)))
        if y is None:
            a.axvline(v, color=RULE_COLOURS[rule], ls="--", lw=1, label=f"{rule}: {sym}={v:.3g}")
        else:
            a.plot(x[i], y[i], "o", color=RULE_COLOURS[rule], label=f"{rule}: {sym}={v:.3g}")

    a = ax[0, 0]
    a.loglog(c["residual_norm"], c["solution_norm"], ".-", ms=3, color="0.3")
    a.tick_params(axis="x", which="minor", labelbottom=False)  # minor log labels collide on a short decade
    mark(a, "lcurve", c["residual_norm"], c["solution_norm"])
    mark(a, choice.rule, c["residual_norm"], c["solution_norm"])
    a.set(xlabel="residual norm |Ax - z| (whitened)", ylabel="solution norm |x| (tolerances)", title="L-curve")
    a.legend(fontsize=7)
    for a, key, rule, lab in (
        (ax[0, 1], "gcv", "gcv", "GCV |r|^2 / (N - sum f)^2"),
        (ax[0, 2], "discrepancy", "discrepancy", "|r|^2 - (N - sum f)"),
        (ax[1, 0], "log_evidence", "evidence", "log evidence"),
        (ax[1, 1], "posterior_risk", "risk", "posterior expected |x - x_true|^2"),
        (ax[1, 2], "cv", "cv", "held-out mean squared error (whitened)"),
    ):
        if key not in c:  # choices saved before the rule existed
            a.set_axis_off()
            continue
        y = np.asarray(c[key], dtype=float)
        a.plot(g, y, ".-", ms=3, color="0.3")
        if ridge:
            a.set_xscale("log")
        if key in ("gcv", "cv", "posterior_risk"):
            a.set_yscale("log")
        if key == "posterior_risk" and np.isfinite(y).any():
            low = np.nanmin(y)
            a.set_ylim(0.7 * low, min(np.nanmax(y), 1e3 * low) * 1.5)  # a rank-deficient k would swamp the scale
        if key == "discrepancy":
            a.set_yscale("symlog")
            a.axhline(0.0, color="0.6", lw=0.8)
        if key == "log_evidence" and np.isfinite(y).any():
            top = np.nanmax(y)
            a.set_ylim(top - max(50.0, 0.05 * abs(top)), top + 5)
        for r in {rule, choice.rule}:
            mark(a, r, None)
        a.set(xlabel=sym, ylabel=lab)
        a.legend(fontsize=7)
    fig.suptitle(title or f"{choice.method}: rules for {sym} (used: {choice.rule})")
    fig.tight_layout()
    return _save(fig, path)


def plot_output_error(
    lam: NDArray, err_lam: NDArray, k: NDArray, err_k: NDArray, path, *,
    lam_choices: dict | None = None, k_choices: dict | None = None, ls_error: float | None = None,
    before: float | None = None, title: str = "", ylabel: str = "RMS tool-point error (mm)",
) -> Path:
    """Output error against lambda and against k (the seed's Figures 6, 8, 10, 11), with rule picks."""
    plt = _plt()
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for a, x, y, ch, xl in ((ax[0], lam, err_lam, lam_choices, "lambda (ridge)"), (ax[1], k, err_k, k_choices, "k (TSVD)")):
        a.plot(x, y, "o-", ms=3, color="k", label="output error")
        if xl.startswith("lambda"):
            a.set_xscale("log")
        a.set_yscale("log")
        for rule, (v, e) in (ch or {}).items():
            a.plot([v], [e], "s", ms=7, mfc="none", color=RULE_COLOURS.get(rule, "0.5"), label=f"{rule}: {v:.3g}")
        if ls_error is not None and np.isfinite(ls_error):
            a.axhline(ls_error, color="0.5", ls=":", label=f"LS {ls_error:.4f}")
        if before is not None:
            a.axhline(before, color="0.7", ls="--", label=f"before {before:.3f}")
        a.set(xlabel=xl, ylabel=ylabel)
        a.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def plot_histories(histories: dict, path, *, title: str = "") -> Path:
    """Value of every error parameter (in tolerances) per iteration, one panel per method (Figures 7, 9).

    Parameters
    ----------
    histories : dict of str to ndarray, shape (iterations + 1, P)
        Parameter values divided by the tolerances, row 0 the start.
    """
    plt = _plt()
    n = len(histories)
    fig, ax = plt.subplots(1, n, figsize=(3.2 * n, 3.4), squeeze=False)
    for a, (name, h) in zip(ax[0], histories.items()):
        h = np.asarray(h, dtype=float)
        a.plot(np.arange(h.shape[0]), h, lw=0.8)
        a.set(title=f"{name} ({h.shape[0] - 1} it.)", xlabel="iteration", ylabel="error / tolerance")
        lim = np.nanpercentile(np.abs(h), 99) if np.isfinite(h).any() else 1.0
        a.set_ylim(-1.2 * lim - 0.1, 1.2 * lim + 0.1)
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def plot_ratio_spread(ratios: dict, path, *, title: str = "", target: float = 1.10) -> Path:
    """Box plots of output-error ratios (rule / best on the curve) per situation and rule.

    Parameters
    ----------
    ratios : dict of (situation, method) to dict of rule to ndarray
    """
    plt = _plt()
    keys = list(ratios)
    fig, ax = plt.subplots(1, len(keys), figsize=(3.0 * len(keys), 3.6), squeeze=False)
    for a, key in zip(ax[0], keys):
        rules = list(ratios[key])
        data = [np.asarray(ratios[key][r], dtype=float) for r in rules]
        a.boxplot([d[np.isfinite(d)] for d in data], whis=(5, 95), showfliers=True, flierprops={"ms": 2})
        a.set_xticks(range(1, len(rules) + 1), rules, rotation=45, fontsize=7)
        a.axhline(target, color="r", ls=":", lw=1)
        a.set_yscale("log")
        a.set_title(" ".join(key), fontsize=8)
        a.set_ylabel("output error / best on curve")
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)
