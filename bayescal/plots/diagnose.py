"""Figures of a diagnosis: residuals against the channels they depend on most, and the out-of-sample fit."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._backend import pyplot as _pyplot
from ._backend import save

__all__ = ["plot_diagnosis"]




def _save(fig, path: Path) -> Path:
    return save(fig, path, dpi=90)


def plot_diagnosis(diagnosis, out_dir: str | os.PathLike, *, top: int = 6) -> list[Path]:
    """Write ``residuals_vs_channels.png`` and ``cv_rms.png`` for a :class:`~bayescal.diagnose.Diagnosis`.

    Parameters
    ----------
    diagnosis : Diagnosis
    out_dir : path
        Created if missing.
    top : int
        How many channels (strongest first) to draw.

    Returns
    -------
    list of Path
    """
    plt = _pyplot()
    from ..io.safe_paths import output_folder

    out = output_folder(out_dir)  # not through a link (bayescal.io.safe_paths)
    chans = diagnosis.location.channels[:top]
    res = diagnosis.location.residual[:, :3]
    ncol = 3
    nrow = max(1, int(np.ceil(len(chans) / ncol)))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4 * ncol, 3 * nrow), squeeze=False)
    for ax, c in zip(axes.flat, chans):
        x = np.asarray(c.values, float)
        label = c.channel
        if x.ndim == 2:
            # pose region: distance of the tool point from the centre of the measured poses
            x = np.linalg.norm(x - x.mean(axis=0), axis=1)
            label = "distance from pose centre (mm)"
        elif c.kind == "periodic" and c.detail.startswith("pitch"):
            pitch = float(c.detail.split()[1])
            x = np.mod(x, pitch)
            label = f"{c.channel[9:]} modulo {pitch:.3g} mm"
        act = c.channel.rsplit("q", 1)[-1] if c.kind in ("actuator", "direction", "periodic") else ""
        dq = diagnosis.location.dq_residual
        if act.isdigit() and dq is not None:
            # the actuator's own residual (mm -> um): backlash and periodic errors show directly
            if c.kind == "direction":
                x = x + np.random.default_rng(0).uniform(-0.15, 0.15, len(x))  # jitter the three levels apart
            ax.plot(x, 1e3 * dq[:, int(act) - 1], ".", ms=3, color="C3")
            ax.set_ylabel(f"actuator-space residual q{act} (um)")
        else:
            # a pose's x, y, z rows; a constraint recording's one row per measurement
            cols = "xyz"[: res.shape[1]] if res.shape[1] > 1 else ("measured value",)
            for k, col in enumerate(cols):
                ax.plot(x, res[:, k], ".", ms=3, label=col)
            ax.set_ylabel("whitened residual")
            ax.legend(fontsize=7)
        ax.set_xlabel(label)
        ax.set_title(f"{c.channel}: {c.strength:.2f} (p={c.p_adjusted:.1g})", fontsize=9)
    for ax in list(axes.flat)[len(chans):]:
        ax.axis("off")
    fig.suptitle(f"residuals of the geometric fit - verdict: {diagnosis.verdict}", fontsize=10)
    fig.tight_layout()
    paths = [_save(fig, out / "residuals_vs_channels.png")]

    fig, ax = plt.subplots(figsize=(6, 3))
    names = [e.name for e in diagnosis.effects]
    before = [1e3 * e.rms_before for e in diagnosis.effects]
    after = [1e3 * e.rms_after for e in diagnosis.effects]
    y = np.arange(len(names))
    ax.barh(y - 0.2, before, 0.4, label="geometric only")
    ax.barh(y + 0.2, after, 0.4, label="with the effect")
    ax.axvline(1e3 * diagnosis.rms_noise, color="k", ls="--", lw=1, label="noise alone")
    ax.set_yticks(y, names)
    ax.set_xlabel("cross-validated position RMS (um)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(_save(fig, out / "cv_rms.png"))
    d = getattr(diagnosis, "discrepancy", None)
    if d is not None and d.pose_mean is not None:
        paths.append(_plot_discrepancy(plt, d, out / "discrepancy_vs_inputs.png"))
    return paths


def _plot_discrepancy(plt, trial, path: Path) -> Path:
    """The discrepancy's mean against its most relevant inputs, over the residual it was fitted to (mm)."""
    disc = trial.fit.discrepancy
    rel = disc.relevance()
    order = sorted(range(len(disc.inputs)), key=lambda k: -rel[disc.inputs[k]])[:3]
    fig, axes = plt.subplots(1, len(order), figsize=(4.2 * len(order), 3.2), squeeze=False)
    for ax, k in zip(axes[0], order):
        x = np.asarray(trial.input_values, float)[:, k]
        for c, col in enumerate("xyz"):
            ax.plot(x, 1e3 * trial.pose_residual[:, c], ".", ms=2.5, color=f"C{c}", alpha=0.35)
            ax.plot(x, 1e3 * trial.pose_mean[:, c], "o", ms=2.5, color=f"C{c}", mfc="none",
                    label=f"{col}: discrepancy" if k == order[0] else None)
        ax.set_xlabel(f"{disc.inputs[k]} (relevance {rel[disc.inputs[k]]:.2g})")
        ax.set_ylabel("position (um)")
    axes[0][0].legend(fontsize=7, title="dots: residual without it", title_fontsize=7)
    state = "kept" if trial.kept else "not kept"
    fig.suptitle(f"model discrepancy ({state}): carries {100 * disc.explained:.0f} % of the residual; resembles "
                 f"{trial.resembles[:70]}", fontsize=9)
    fig.tight_layout()
    return _save(fig, path)
