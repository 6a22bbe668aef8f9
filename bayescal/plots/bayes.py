"""Figures of the probabilistic layer: filter histories, MCMC traces and pairs, coverage, grid maps.

Each function takes a result object and a path, imports matplotlib lazily
(Agg backend) and writes one figure file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._backend import pyplot as _plt
from ._backend import save

__all__ = ["plot_filter_history", "plot_trace", "plot_pair", "plot_coverage", "plot_grid"]




def _save(fig, path) -> Path:
    return save(fig, path, dpi=110)


def plot_filter_history(result, path: str | os.PathLike) -> Path:
    """Each state parameter's std relative to its prior std, and the predicted workspace accuracy, pose by pose."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2))
    k = np.arange(result.n_poses + 1)
    rel = result.stds / result.stds[0]
    groups = {}
    for j, name in enumerate(result.free_names):
        groups.setdefault(name.split(".", 1)[-1].rsplit(".", 1)[0], []).append(j)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for c, (g, js) in enumerate(groups.items()):
        for n, j in enumerate(js):
            a1.semilogy(k, rel[:, j], color=colors[c % len(colors)], lw=0.9, label=g if n == 0 else None)
    a1.set_xlabel("poses measured")
    a1.set_ylabel("parameter std / prior std")
    a1.set_title(f"Kalman ({result.variant.upper()}): parameter uncertainty")
    a1.legend(fontsize=7, ncol=2)
    a1.grid(alpha=0.3)
    a2.semilogy(k, result.workspace_accuracy * 1000.0, "k.-", ms=3)
    n_stop = result.poses_needed()
    a2.axvline(n_stop, color="C3", ls="--", lw=1, label=f"within 10% of final after {n_stop} poses")
    a2.set_xlabel("poses measured")
    a2.set_ylabel("predicted tool-point std, RMS over workspace (um)")
    a2.set_title("when can I stop measuring?")
    a2.legend(fontsize=8)
    a2.grid(alpha=0.3, which="both")
    fig.tight_layout()
    return _save(fig, path)


def _top_params(result, max_params: int) -> list[str]:
    """The parameters with the largest posterior std relative to the prior (least determined) first."""
    sd = np.sqrt(np.diag(result.covariance))
    prior_sd = result.tree["constant_data"]["prior_std"].values
    order = np.argsort(-sd / prior_sd)[:max_params]
    return [result.free_names[i] for i in sorted(order)]


def plot_trace(result, path: str | os.PathLike, *, max_params: int = 6) -> Path:
    """Trace and marginal density of up to ``max_params`` parameters (arviz), every walker a chain."""
    import arviz as az

    _plt()
    names = _top_params(result, max_params)
    pc = az.plot_trace_dist(result.tree, var_names=["theta"], coords={"param": names}, backend="matplotlib")
    pc.savefig(path)
    _plt().close("all")
    return Path(path)


def plot_pair(result, path: str | os.PathLike, *, max_params: int = 5) -> Path:
    """Pair plot of up to ``max_params`` parameters (thinned draws)."""
    plt = _plt()
    names = _top_params(result, max_params)
    idx = [result.free_names.index(n) for n in names]
    x = result.samples[:, idx]
    x = x[:: max(1, x.shape[0] // 4000)]
    k = len(idx)
    fig, axes = plt.subplots(k, k, figsize=(2.2 * k, 2.2 * k), squeeze=False)
    for i in range(k):
        for j in range(k):
            ax = axes[i, j]
            if j > i:
                ax.axis("off")
            elif i == j:
                ax.hist(x[:, i], bins=40, color="C0")
            else:
                ax.plot(x[:, j], x[:, i], ",", alpha=0.3, color="C0")
            if i == k - 1:
                ax.set_xlabel(names[j].replace("chain", "c"), fontsize=7)
            if j == 0 and i > 0:
                ax.set_ylabel(names[i].replace("chain", "c"), fontsize=7)
            ax.tick_params(labelsize=6)
    fig.suptitle("posterior pairs (least-determined parameters)")
    fig.tight_layout()
    return _save(fig, path)


def plot_coverage(table: dict, path: str | os.PathLike, *, nominal: float = 0.9, band=(0.85, 0.95)) -> Path:
    """Coverage per method and quantity: ``table[method][quantity] = fraction``."""
    plt = _plt()
    methods = list(table)
    quantities = sorted({q for m in methods for q in table[m]})
    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(methods), 4))
    w = 0.8 / len(quantities)
    for j, q in enumerate(quantities):
        vals = [table[m].get(q, np.nan) for m in methods]
        ax.bar(np.arange(len(methods)) + (j - (len(quantities) - 1) / 2) * w, vals, w, label=q)
    ax.axhspan(*band, color="g", alpha=0.12, label=f"{band[0]:.0%}-{band[1]:.0%}")
    ax.axhline(nominal, color="k", lw=1)
    ax.set_xticks(np.arange(len(methods)), methods)
    ax.set_ylim(0, 1.02)
    ax.set_ylabel(f"fraction inside the nominal {nominal:.0%} interval")
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    return _save(fig, path)


def plot_grid(grid, path: str | os.PathLike) -> Path:
    """Heat maps of a compensation grid: correction magnitude and its std over the first two grid axes."""
    plt = _plt()
    mag = np.linalg.norm(grid.correction, axis=-1)
    std = np.sqrt(np.sum(grid.std**2, axis=-1))
    # the grid may have more axes than two: show the slice through the middle of the others
    sl = tuple(slice(None) if i < 2 else grid.shape[i] // 2 for i in range(len(grid.shape)))
    ax0, ax1 = grid.axes[0], grid.axes[1]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for ax, val, title in ((axes[0], mag[sl] * 1000, "correction |dp| (um)"), (axes[1], std[sl] * 1000, "std of the correction (um)")):
        im = ax.pcolormesh(ax1, ax0, val, shading="nearest", cmap="viridis")
        fig.colorbar(im, ax=ax)
        ax.set_xlabel(f"{grid.axis_names[1]} ({grid.axis_unit})")
        ax.set_ylabel(f"{grid.axis_names[0]} ({grid.axis_unit})")
        ax.set_title(title)
    if len(grid.shape) > 2:
        others = ", ".join(f"{grid.axis_names[i]} = {grid.axes[i][grid.shape[i] // 2]:.4g}" for i in range(2, len(grid.shape)))
        fig.suptitle(f"slice at {others}")
    fig.tight_layout()
    return _save(fig, path)
