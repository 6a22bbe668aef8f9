"""Figures of pose planning: output error against the number of poses, planned and random."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._backend import pyplot, save

__all__ = ["plot_error_vs_poses"]


def plot_error_vs_poses(rows: list[dict], path: str | os.PathLike, *, metric: str = "rms") -> Path:
    """Median (and quartiles) of the post-calibration error against the number of poses.

    Parameters
    ----------
    rows : list of dict
        One per (dof, design, n_poses) with keys ``dof`` (one panel per
        value: a measurement's degrees of freedom, or a setting's name),
        ``design`` (``random``, or ``planned``/``planned-<criterion>``),
        ``n_poses``, ``{metric}_median``, ``{metric}_q25``, ``{metric}_q75``
        (mm), and optionally ``title``, the panel's title (default ``"<dof>-DOF
        measurement"`` for an integer ``dof``, else ``dof`` itself).
    path : path
        PNG to write.
    """
    plt = pyplot()
    dofs = sorted({r["dof"] for r in rows}, reverse=True)
    fig, axes = plt.subplots(1, len(dofs), figsize=(4.2 * len(dofs), 3.6), squeeze=False)
    colors = _design_colors(rows)
    for ax, dof in zip(axes[0], dofs):
        designs = sorted({r["design"] for r in rows if r["dof"] == dof and r["design"] != "random"}) + ["random"]
        for design in designs:
            color = colors[design]
            rr = sorted((r for r in rows if r["dof"] == dof and r["design"] == design
                         and np.isfinite(r[f"{metric}_median"])), key=lambda r: r["n_poses"])
            if not rr:
                continue  # not run (e.g. a study with least squares only): nothing to draw
            n = np.array([r["n_poses"] for r in rr])
            med = 1e3 * np.array([r[f"{metric}_median"] for r in rr])
            lo = 1e3 * np.array([r[f"{metric}_q25"] for r in rr])
            hi = 1e3 * np.array([r[f"{metric}_q75"] for r in rr])
            ax.plot(n, med, "o-", color=color, label=f"{design} (median)")
            ax.fill_between(n, lo, hi, color=color, alpha=0.12, lw=0)
            if design == "random" and 36 in n:
                ax.axhline(med[list(n).index(36)], color=color, ls=":", lw=1, label="random, 36 poses")
        if ax.has_data():
            ax.set_yscale("log")
            # plain numbers in um on the log axis ("3", not "3 x 10^0"), minor ticks labelled too: the
            # range of a panel is often less than a decade
            from matplotlib.ticker import FormatStrFormatter

            ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
            ax.yaxis.set_minor_formatter(FormatStrFormatter("%g"))
            ax.tick_params(axis="y", which="minor", labelsize=7)
        ax.set_xlabel("number of measured poses")
        ax.set_ylabel(f"{metric} position error after calibration [um]")
        ax.set_title(_panel_title(rows, dof), fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save(fig, path, dpi=110)
    return path


def _design_colors(rows: list[dict]) -> dict:
    """One matplotlib colour per design across every panel: a design's colour must not depend on which other
    designs a panel shows (planned-I was red in a panel without planned-D and purple beside it)."""
    planned = sorted({r["design"] for r in rows if r["design"] != "random"})
    return {d: f"C{3 + i}" for i, d in enumerate(planned)} | {"random": "C0"}


def _panel_title(rows: list[dict], dof) -> str:
    """A panel's ``title`` if its rows give one; "<n>-DOF measurement" for an integer ``dof``; else ``dof`` as it is."""
    title = next((r["title"] for r in rows if r["dof"] == dof and r.get("title")), None)
    if title is not None:
        return str(title)
    return f"{dof}-DOF measurement" if isinstance(dof, (int, np.integer)) else str(dof)
