"""Figures the HTML reports need beyond each command's own: residuals per pose, correlations, plans, BIC grids."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._backend import pyplot, save

__all__ = ["plot_pose_residuals", "plot_correlation", "plot_plan", "plot_bic_grid"]


def plot_pose_residuals(
    pos_after, path: str | os.PathLike, *, pos_before=None, sigma: float | None = None, outliers=(), n_axes: int = 3,
) -> Path:
    """Position error norm per pose (um) after (and before) calibration; outliers marked in red.

    Parameters
    ----------
    pos_after, pos_before : array_like, shape (n_poses,)
        Per-pose position error norms, mm.
    sigma : float, optional
        Instrument one-sigma per axis, mm: the expected norm ``sigma sqrt(n_axes)`` is drawn.
    n_axes : int
        Position components per row: 3 for a measured point, 1 for a distance or height.
    outliers : iterable of int
        0-based pose indices to mark.
    """
    plt = pyplot()
    after = 1e3 * np.asarray(pos_after, float)
    n = after.size
    x = np.arange(1, n + 1)
    fig, ax = plt.subplots(figsize=(10, 3.6))
    if pos_before is not None:
        ax.bar(x, 1e3 * np.asarray(pos_before, float), color="0.8", label="before calibration (nominal model)")
    ax.bar(x, after, color="C0", label="after calibration")
    out = [i for i in outliers if 0 <= i < n]
    if out:
        ax.bar(np.asarray(out) + 1, after[out], color="C3", label="outlier")
    if sigma:
        ax.axhline(1e3 * sigma * np.sqrt(n_axes), color="k", lw=1, ls="--",
                   label="instrument noise, sigma" + (f" sqrt({n_axes})" if n_axes > 1 else ""))
    ax.set_xlabel("pose (row of the recording)")
    ax.set_ylabel("position error |y - h| (um)")
    if pos_before is not None:
        ax.set_yscale("log")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    return save(fig, path)


def plot_correlation(corr, names, path: str | os.PathLike) -> Path:
    """Heat map of a correlation matrix (dimensionless, -1..1) over the named parameters."""
    plt = pyplot()
    C = np.asarray(corr, float)
    k = C.shape[0]
    size = min(14.0, 3.0 + 0.28 * k)
    fig, ax = plt.subplots(figsize=(size + 1.2, size))
    im = ax.imshow(C, cmap="RdBu_r", vmin=-1, vmax=1)
    fig.colorbar(im, ax=ax, label="correlation (dimensionless)")
    if k <= 40:
        ax.set_xticks(range(k), names, rotation=90, fontsize=7)
        ax.set_yticks(range(k), names, fontsize=7)
    ax.set_title("posterior / estimate correlation of the identified parameters")
    fig.tight_layout()
    return save(fig, path)


def plot_plan(q, path: str | os.PathLike, *, units=(), q_limits=None) -> Path:
    """Planned poses: each actuator against the next, numbered in measurement order."""
    plt = pyplot()
    q = np.asarray(q, float)
    m = q.shape[1]
    pairs = [(i, (i + 1) % m) for i in range(m if m > 2 else 1)]
    fig, axes = plt.subplots(1, len(pairs), figsize=(4.2 * len(pairs), 4), squeeze=False)
    for ax, (i, j) in zip(axes[0], pairs):
        ax.plot(q[:, i], q[:, j], "o", ms=4)
        for k, (a, b) in enumerate(q[:, [i, j]]):
            ax.annotate(str(k + 1), (a, b), fontsize=6, xytext=(2, 2), textcoords="offset points")
        if q_limits is not None:
            ax.set_xlim(*q_limits[i])
            ax.set_ylim(*q_limits[j])
        ui = f" ({units[i]})" if len(units) > i else ""
        uj = f" ({units[j]})" if len(units) > j else ""
        ax.set_xlabel(f"q{i + 1}{ui}")
        ax.set_ylabel(f"q{j + 1}{uj}")
    fig.suptitle("planned poses (numbers: measurement order)")
    fig.tight_layout()
    return save(fig, path)


def plot_bic_grid(grid, path: str | os.PathLike) -> Path:
    """A BIC grid (:class:`bayescal.compensation.CompensationGrid`): ex and ez at the nodes, um."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, k, name in ((axes[0], 0, "ex"), (axes[1], 1, "ez")):
        im = ax.pcolormesh(grid.xs, grid.zs, 1e3 * grid.error[..., k], shading="nearest", cmap="RdBu_r")
        fig.colorbar(im, ax=ax, label=f"{name} (um)")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("z (mm)")
        ax.set_title(f"node error {name} (um)")
    fig.tight_layout()
    return save(fig, path)
