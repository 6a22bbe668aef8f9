"""Figures of a :class:`bayescal.compare.Comparison`."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._backend import pyplot as _plt
from ._backend import save

__all__ = ["plot_comparison", "plot_error_distributions", "plot_paired_differences", "plot_win_rates"]

_SCALE = {"rms_position": ("um", 1e3), "max_position": ("um", 1e3), "rms_angle": ("urad", 1e6)}




def plot_error_distributions(cmp, ax=None):
    """Box plots with the individual trials of the output error per method (log scale), nominal for scale."""
    plt = _plt()
    unit, f = _SCALE.get(cmp.metric, ("", 1.0))
    if ax is None:
        _, ax = plt.subplots(figsize=(1.6 + 1.1 * len(cmp.labels), 4.0))
    data = [f * cmp.errors[k][np.isfinite(cmp.errors[k])] for k in cmp.labels]
    pos = np.arange(1, len(data) + 1)
    keep = [i for i, d in enumerate(data) if d.size]
    ax.boxplot([data[i] for i in keep], positions=pos[keep], widths=0.5, showfliers=False)
    rng = np.random.default_rng(0)  # jitter only
    for i in keep:
        ax.plot(pos[i] + rng.uniform(-0.15, 0.15, data[i].size), data[i], ".", ms=2, alpha=0.4, color="C0")
    ax.axhline(f * np.nanmedian(cmp.nominal), color="0.5", ls="--", lw=0.8, label="nominal (median)")
    ax.set_xticks(pos, [f"{k}\n({cmp.summary[k]['failures']} failed)" for k in cmp.labels], fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel(f"{cmp.metric} [{unit}]")
    ax.set_title(f"output error over {cmp.n_trials} trials", fontsize=9)
    ax.legend(fontsize=7)
    return ax


def plot_paired_differences(cmp, ax=None):
    """Mean paired difference a - b with its bootstrap CI per pair (significant pairs filled)."""
    plt = _plt()
    unit, f = _SCALE.get(cmp.metric, ("", 1.0))
    pairs = cmp.pairs
    if ax is None:
        _, ax = plt.subplots(figsize=(6.0, 0.9 + 0.35 * max(len(pairs), 1)))
    for i, p in enumerate(pairs):
        ax.errorbar(f * p.mean_diff, i, xerr=[[f * (p.mean_diff - p.ci_low)], [f * (p.ci_high - p.mean_diff)]],
                    fmt="o", color="C3" if p.significant else "C0", mfc="C3" if p.significant else "white")
    ax.axvline(0.0, color="0.4", lw=0.8)
    ax.set_yticks(range(len(pairs)), [f"{p.a} - {p.b}" for p in pairs], fontsize=8)
    ax.set_xlabel(f"mean paired difference [{unit}] (negative: first method better)")
    ax.set_title("paired differences, bootstrap CI; filled red: significant (Wilcoxon, Holm)", fontsize=8)
    return ax


def plot_win_rates(cmp, ax=None):
    """Matrix of win rates: row method beats column method in this fraction of trials."""
    plt = _plt()
    labels = list(cmp.labels)
    n = len(labels)
    W = np.full((n, n), np.nan)
    for p in cmp.pairs:
        i, j = labels.index(p.a), labels.index(p.b)
        W[i, j], W[j, i] = p.win_rate, 1.0 - p.win_rate
    if ax is None:
        _, ax = plt.subplots(figsize=(1.5 + 0.8 * n, 1.2 + 0.7 * n))
    im = ax.imshow(W, vmin=0, vmax=1, cmap="RdBu")
    for i in range(n):
        for j in range(n):
            if np.isfinite(W[i, j]):
                ax.text(j, i, f"{100 * W[i, j]:.0f}%", ha="center", va="center", fontsize=8)
    ax.set_xticks(range(n), labels, fontsize=8, rotation=30)
    ax.set_yticks(range(n), labels, fontsize=8)
    ax.set_title("row beats column (trials where both succeeded)", fontsize=8)
    ax.figure.colorbar(im, ax=ax, fraction=0.046)
    return ax


def plot_comparison(cmp, out_dir: str | os.PathLike) -> list[Path]:
    """Write the three figures as PNG into ``out_dir``; returns their paths."""
    from ..io.safe_paths import output_folder

    out = output_folder(out_dir)  # not through a link (bayescal.io.safe_paths)
    paths = []
    for name, fn in (("errors", plot_error_distributions), ("differences", plot_paired_differences),
                     ("win_rates", plot_win_rates)):
        ax = fn(cmp)
        fig = ax.figure
        fig.tight_layout()
        path = out / f"compare_{name}.png"
        save(fig, path, dpi=110)
        paths.append(path)
    return paths
