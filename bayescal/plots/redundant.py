"""Figures of the redundant-module study (the seed's Figures 8 to 12)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._backend import pyplot as _plt
from ._backend import save

__all__ = ["plot_procedure", "plot_comparison", "plot_grid_std"]




def plot_procedure(result, out_dir) -> list[Path]:
    """Position errors before/after RM1-SI1 and after BIC; orientation errors after RM2-SI2 and RM3-SI3."""
    plt = _plt()
    out = Path(out_dir)
    paths = []
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    for ax, k, lab in zip(axes, (0, 1), ("x", "z")):
        for ev, name in ((result.before, "initial"), (result.after_si1, "after RM1/SI1"), (result.after_bic, "after BIC")):
            ax.plot(ev.position[:, k] * 1e3, ".-", lw=0.7, label=name)
        ax.set_xlabel("evaluation pose (translation grid, rotation 0)")
        ax.set_ylabel(f"position error e{lab} (um)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    paths.append(out / "position_errors.png")
    save(fig, paths[-1], dpi=90)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    for ev, name in ((result.before, "initial"), (result.after_si2, "after RM2/SI2")):
        axes[0].plot(np.degrees(ev.orientation_translation), ".-", label=name)
    axes[0].set_xlabel("evaluation pose (translation grid, rotation 0)")
    axes[0].set_ylabel("orientation error (deg)")
    for ev, name in ((result.before, "initial"), (result.after_si3, "after RM3/SI3")):
        axes[1].plot(np.degrees(ev.phi_eval), np.degrees(ev.orientation_rotation), "o-", label=name)
    axes[1].set_xlabel("rotation (deg), translation at zero")
    axes[1].set_ylabel("orientation error (deg)")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out / "orientation_errors.png")
    save(fig, paths[-1], dpi=90)
    return paths


def plot_comparison(comp, out_dir) -> Path:
    """Error peaks per step, previous (non-redundant) method vs proposed."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    for meth, style in (("previous", "s--"), ("proposed", "o-")):
        axes[0].plot(comp.position[meth] * 1e3, style, label=meth)
        axes[1].plot(comp.orientation[meth], style, label=meth)
    axes[0].set_ylabel("max position error (um)")
    axes[1].set_ylabel("max rotation-range error (deg)")
    for ax, what in zip(axes, ("RM1/SI1", "RM3/SI3")):
        ax.set_xlabel(f"{what} steps (0 = before)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(out_dir) / "comparison.png"
    save(fig, path, dpi=90)
    return path


def plot_grid_std(grid, path, *, title: str = "") -> Path:
    """Heat maps of a BIC grid's node std (``std_ex``, ``std_ez``, um) over the translation range.

    Parameters
    ----------
    grid : bayescal.compensation.CompensationGrid
    path : str or Path
        PNG to write.
    """
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    dx = np.diff(grid.xs).mean() / 2
    dz = np.diff(grid.zs).mean() / 2
    ext = (grid.xs[0] - dx, grid.xs[-1] + dx, grid.zs[0] - dz, grid.zs[-1] + dz)
    for ax, k, lab in zip(axes, (0, 1), ("ex", "ez")):
        im = ax.imshow(grid.std[..., k] * 1e3, origin="lower", extent=ext, aspect="auto", cmap="viridis")
        ax.plot(*np.meshgrid(grid.xs, grid.zs), "w.", ms=3)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("z (mm)")
        ax.set_title(f"std of {lab} at the nodes")
        fig.colorbar(im, ax=ax, label="um")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    save(fig, path, dpi=90)
    return path
