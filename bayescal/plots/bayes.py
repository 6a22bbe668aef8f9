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

__all__ = ["plot_filter_history", "plot_trace", "plot_trace_page", "plot_trace_pages", "plot_pair", "plot_coverage", "plot_grid"]




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


#: Display scale of each parameter unit: small errors read better in um and urad.
_DISPLAY = {"mm": (1e3, "um"), "rad": (1e6, "urad"), "m": (1e6, "um")}


def _display(unit: str) -> tuple[float, str]:
    """Factor and unit label a parameter in ``unit`` is drawn in."""
    return _DISPLAY.get(unit, (1.0, unit or "1"))


def _units_of(result, names) -> list[str]:
    unit = dict(zip(result.names, result.units))
    return [unit.get(n, "") for n in names]


def _chain(result) -> np.ndarray:
    """Draws after burn-in, shape (n_walkers, n_kept, n_free)."""
    return np.asarray(result.tree["posterior"]["theta"].values)


def plot_trace_page(result, names, path: str | os.PathLike, *, title: str = "") -> Path:
    """One labelled row per parameter: every walker's trace (thin) and their mean, and the marginal histogram.

    Values are drawn in the parameter's unit scaled for reading (mm as um, rad as urad); the axis
    label names the parameter and the unit.
    """
    plt = _plt()
    chain = _chain(result)
    idx = [result.free_names.index(n) for n in names]
    units = _units_of(result, names)
    k = len(idx)
    fig, axes = plt.subplots(k, 2, figsize=(11, 1.9 * k + 0.6), squeeze=False, gridspec_kw={"width_ratios": [3, 1]})
    steps = result.burn + np.arange(chain.shape[1])
    for row, (j, name, unit) in enumerate(zip(idx, names, units)):
        f, label = _display(unit)
        x = f * chain[:, :, j]
        a, b = axes[row]
        # every walker in one NaN-separated line: one artist instead of one per walker (fast to draw)
        xs = np.tile(np.append(steps, np.nan), x.shape[0])
        ys = np.column_stack([x, np.full(x.shape[0], np.nan)]).ravel()
        a.plot(xs, ys, color="C0", lw=0.3, alpha=0.25)
        a.plot(steps, x.mean(axis=0), color="k", lw=0.9, label="mean over walkers")
        a.set_ylabel(f"{name}\n({label})", fontsize=8)
        a.tick_params(labelsize=7)
        b.hist(x.ravel(), bins=40, orientation="horizontal", color="C0", histtype="stepfilled")
        b.set_ylim(a.get_ylim())
        b.tick_params(labelsize=7, labelleft=False)
        if row == 0:
            a.set_title("trace of every walker (after burn-in)", fontsize=9)
            b.set_title("marginal posterior", fontsize=9)
            a.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("step")
    axes[-1, 1].set_xlabel("draws")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def plot_trace(result, path: str | os.PathLike, *, max_params: int = 6) -> Path:
    """Trace and marginal of the ``max_params`` least-determined parameters, one labelled row each, in their units."""
    names = _top_params(result, max_params)
    return plot_trace_page(result, names, path, title=f"MCMC trace: the {len(names)} least-determined parameters")


def plot_trace_pages(result, out_dir: str | os.PathLike, *, per_page: int = 6, stem: str = "mcmc_trace") -> list[Path]:
    """Traces of every sampled parameter, ``per_page`` labelled rows per figure: ``stem_1.png``, ``stem_2.png``, ..."""
    names = list(result.free_names)
    pages = [names[i:i + per_page] for i in range(0, len(names), per_page)]
    out = Path(out_dir)
    return [
        plot_trace_page(result, page, out / f"{stem}_{p + 1}.png",
                        title=f"MCMC trace, parameters {p * per_page + 1}-{p * per_page + len(page)} of {len(names)}")
        for p, page in enumerate(pages)
    ]


def plot_pair(result, path: str | os.PathLike, *, max_params: int = 5) -> Path:
    """Pair plot of up to ``max_params`` least-determined parameters (thinned draws), axes in their units."""
    plt = _plt()
    names = _top_params(result, max_params)
    idx = [result.free_names.index(n) for n in names]
    scales = [_display(u) for u in _units_of(result, names)]
    x = result.samples[:, idx] * np.array([f for f, _ in scales])
    x = x[:: max(1, x.shape[0] // 2000)]
    k = len(idx)
    fig, axes = plt.subplots(k, k, figsize=(2.4 * k + 0.6, 2.4 * k + 0.6), squeeze=False)
    for i in range(k):
        for j in range(k):
            ax = axes[i, j]
            if j > i:
                ax.axis("off")
            elif i == j:
                ax.hist(x[:, i], bins=40, color="C0", histtype="stepfilled")
            else:
                ax.plot(x[:, j], x[:, i], ",", alpha=0.3, color="C0")
            if i == k - 1:
                ax.set_xlabel(f"{names[j]}\n({scales[j][1]})", fontsize=7)
            if j == 0 and i > 0:
                ax.set_ylabel(f"{names[i]}\n({scales[i][1]})", fontsize=7)
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


def plot_grid(grid, path: str | os.PathLike, *, units=None, max_slices: int = 6) -> Path:
    """Heat maps of a compensation grid: the correction magnitude and its std (um), over two grid axes.

    Axes with one node are dropped.  With more than two axes left, every
    slice through the others gets a row of panels when there are at most
    ``max_slices`` of them; otherwise the rows are the slice with the
    largest std and the slice with the largest correction, named in the
    titles.  ``units`` (one per axis; default ``grid.axis_unit``) label
    the axes.
    """
    plt = _plt()
    mag = np.linalg.norm(grid.correction, axis=-1) * 1000
    std = np.sqrt(np.sum(grid.std**2, axis=-1)) * 1000
    names = list(grid.axis_names)
    units = list(units) if units is not None else [grid.axis_unit] * len(names)
    active = [i for i, a in enumerate(grid.axes) if a.size > 1]
    keep = tuple(slice(None) if i in active else 0 for i in range(len(names)))
    mag, std = mag[keep], std[keep]
    axes_v = [grid.axes[i] for i in active]
    names = [names[i] for i in active]
    units = [units[i] for i in active]
    if len(active) == 1:
        fig, ax = plt.subplots(figsize=(8, 3.8))
        ax.errorbar(axes_v[0], mag, yerr=std, fmt="o-", capsize=3)
        ax.set_xlabel(f"{names[0]} ({units[0]})")
        ax.set_ylabel("correction |dp| +- std (um)")
        fig.tight_layout()
        return _save(fig, path)
    rest = list(range(2, len(active)))
    if rest:
        shape = tuple(axes_v[i].size for i in rest)
        combos = [tuple(c) for c in np.ndindex(*shape)]
        label = lambda c: ", ".join(f"{names[i]} = {axes_v[i][k]:.4g} {units[i]}" for i, k in zip(rest, c))  # noqa: E731
        if len(combos) <= max_slices:
            rows = [(c, f"slice {label(c)}") for c in combos]
        else:
            sl_std = [std[(slice(None), slice(None)) + c].max() for c in combos]
            sl_mag = [mag[(slice(None), slice(None)) + c].max() for c in combos]
            w_std, w_mag = combos[int(np.argmax(sl_std))], combos[int(np.argmax(sl_mag))]
            rows = [(w_std, f"worst slice for the std: {label(w_std)}")]
            if w_mag != w_std:
                rows.append((w_mag, f"worst slice for the correction: {label(w_mag)}"))
    else:
        rows = [((), "")]
    fig, axes = plt.subplots(len(rows), 2, figsize=(10, 3.9 * len(rows) + 0.3), squeeze=False)
    vmax_m, vmax_s = mag.max(), std.max()  # one colour scale for every slice, so slices compare
    for r, (c, title) in enumerate(rows):
        sel = (slice(None), slice(None)) + c
        for ax, val, what, vmax in ((axes[r, 0], mag[sel], "correction |dp| (um)", vmax_m), (axes[r, 1], std[sel], "std of the correction (um)", vmax_s)):
            im = ax.pcolormesh(axes_v[1], axes_v[0], val, shading="nearest", cmap="viridis", vmin=0, vmax=vmax)
            fig.colorbar(im, ax=ax, label=what)
            ax.set_xlabel(f"{names[1]} ({units[1]})")
            ax.set_ylabel(f"{names[0]} ({units[0]})")
            ax.set_title(f"{what.split(' (')[0]}" + (f"\n{title}" if title else ""), fontsize=9)
    fig.tight_layout()
    return _save(fig, path)
