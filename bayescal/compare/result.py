"""``compare_methods`` and its answer, :class:`Comparison`."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..machines.base import Machine
from ..stats import PairedComparison, compare_pairs, summarise
from .runner import run_trials
from .trial import METRICS, CompareConfig
from ..notebook import ShowsReport

__all__ = ["Comparison", "compare_methods", "comparison_from_records"]

_UNITS = {"rms_position": ("um", 1e3), "max_position": ("um", 1e3), "rms_angle": ("urad", 1e6)}


@dataclass(frozen=True)
class Comparison(ShowsReport):
    """A Monte Carlo comparison of identification methods.

    Attributes
    ----------
    config : dict
        The :class:`~bayescal.compare.trial.CompareConfig` (without the machine text) and the machine name.
    labels : tuple of str
        Methods, in the order asked for.
    metric : str
        The output error the statistics are about (``rms_position`` mm by default).
    errors : dict of str to ndarray, shape (trials,)
        Per method and trial, the metric; NaN where the method failed.
    nominal : ndarray, shape (trials,)
        The metric of the uncalibrated (nominal) model, for scale.
    summary : dict of str to dict
        :func:`bayescal.stats.summarise` per method.
    pairs : tuple of PairedComparison
        Every pair, Holm-corrected.
    failure_messages : dict of str to list of str
        Up to three distinct failure messages per method.
    alpha : float
    info : dict
        Backend, trials resumed and run, wall time (not part of the statistics).
    """

    config: dict
    labels: tuple[str, ...]
    metric: str
    errors: dict
    nominal: NDArray
    summary: dict
    pairs: tuple[PairedComparison, ...]
    failure_messages: dict
    alpha: float = 0.05
    info: dict = field(default_factory=dict)

    @property
    def n_trials(self) -> int:
        return int(self.nominal.size)

    @property
    def failed_everywhere(self) -> tuple[str, ...]:
        """The methods that failed in every trial: the comparison says nothing about them (the command exits 1)."""
        return tuple(k for k in self.labels if np.all(np.isnan(np.asarray(self.errors[k], dtype=float))))

    def table(self) -> dict:
        """The statistics only (what must not depend on backend, workers or resumption)."""
        return {
            "metric": self.metric,
            "summary": self.summary,
            "nominal": summarise(self.nominal),
            "pairs": [p.to_dict() for p in self.pairs],
            "errors": {k: v for k, v in self.errors.items()},
        }

    def to_dict(self) -> dict:
        return {"config": self.config, "labels": list(self.labels), "alpha": self.alpha, "n_trials": self.n_trials,
                "failure_messages": self.failure_messages, "info": self.info, **self.table()}

    def report(self) -> str:
        unit, f = _UNITS.get(self.metric, ("", 1.0))
        c = self.config
        what = (f"the {c['n_poses']} measurements of {c['recording']} re-simulated per trial" if c.get("recording")
                else f"{c['n_poses']} poses per trial")
        lines = [
            f"bayescal comparison on '{c.get('machine', '')}': {self.n_trials} trials, {c['dof']}-DOF, "
            f"{what}, error on {c['n_eval']} fresh poses, seed {c['seed']}",
            f"  metric {self.metric} ({unit}); nominal (uncalibrated) median {f * np.nanmedian(self.nominal):.4g}",
            "",
            f"  {'method':<22}{'ok':>5}{'failed':>8}{'median':>11}{'mean':>11}{'q05':>10}{'q95':>10}",
        ]
        for lab in self.labels:
            s = self.summary[lab]
            lines.append(f"  {lab:<22}{s['n']:>5}{s['failures']:>8}{f * s['median']:>11.4g}{f * s['mean']:>11.4g}"
                         f"{f * s['q05']:>10.4g}{f * s['q95']:>10.4g}")
        if self.pairs:
            lines += [
                "",
                f"  paired differences a - b ({unit}; negative: a better), {100 * self.pairs[0].confidence:.0f}% "
                f"bootstrap CI of the mean, Wilcoxon signed-rank, Holm-corrected over {len(self.pairs)} pairs:",
                f"  {'a':<16}{'b':<16}{'n':>5}{'median d':>11}{'mean d':>11}{'CI':>24}{'a wins':>8}{'p':>10}{'p Holm':>10}",
            ]
            for p in self.pairs:
                if p.n == 0:
                    lines.append(f"  {p.a:<16}{p.b:<16}{0:>5}  no trial where both succeeded")
                    continue
                ci = f"[{f * p.ci_low:.3g}, {f * p.ci_high:.3g}]"
                sig = " *" if p.significant else ""
                lines.append(f"  {p.a:<16}{p.b:<16}{p.n:>5}{f * p.median_diff:>11.3g}{f * p.mean_diff:>11.3g}{ci:>24}"
                             f"{100 * p.win_rate:>7.0f}%{p.p_value:>10.2g}{p.p_holm:>10.2g}{sig}")
            lines.append(f"  * significant at alpha = {self.alpha} after Holm's correction; failures excluded pairwise")
        fails = {k: v for k, v in self.failure_messages.items() if v}
        if fails:
            lines += ["", "  failures (counted separately, not in the error statistics):"]
            for k, msgs in fails.items():
                lines.append(f"    {k}: {self.summary[k]['failures']} trials, e.g. {msgs[0][:160]}")
        if self.info:
            lines += ["", f"  ran {self.info.get('ran', 0)} trials ({self.info.get('resumed', 0)} resumed from saved "
                          f"results), {self.info.get('backend', '?')}, in {self.info.get('seconds', 0):.1f} s"]
        return "\n".join(lines)


def comparison_from_records(
    records: list[dict], config: CompareConfig, *, metric: str = "rms_position", alpha: float = 0.05,
    machine_name: str = "", info: dict | None = None, n_resamples: int = 2000,
) -> Comparison:
    """Statistics of saved trial records (see :func:`bayescal.compare.trial.run_trial`)."""
    if metric not in METRICS:
        raise InputError(f"metric: expected one of {', '.join(METRICS)}, got {metric!r}")
    labels = tuple(s.label for s in config.specs)
    errors, messages = {}, {}
    for lab in labels:
        e = np.array([r["methods"][lab].get(metric, np.nan) if r["methods"][lab]["success"] else np.nan
                      for r in records], dtype=float)
        errors[lab] = e
        msgs = []
        for r in records:
            m = r["methods"][lab]
            if not m["success"] and m["message"] not in msgs:
                msgs.append(m["message"])
        messages[lab] = msgs[:3]
    nominal = np.array([r["nominal"].get(metric, np.nan) for r in records], dtype=float)
    cfg = {k: v for k, v in config.to_dict().items() if k not in ("machine_text", "recording_text")}
    cfg["machine"] = machine_name
    return Comparison(
        config=cfg, labels=labels, metric=metric, errors=errors, nominal=nominal,
        summary={lab: summarise(errors[lab]) for lab in labels},
        pairs=compare_pairs(errors, alpha=alpha, seed=config.seed, n_resamples=n_resamples),
        failure_messages=messages, alpha=alpha, info=dict(info or {}),
    )


def compare_methods(
    machine: Machine,
    *,
    methods: str = "ls,ridge,tsvd",
    trials: int = 500,
    dof: int | None = None,
    n_poses: int = 36,
    n_eval: int = 100,
    seed: int = 0,
    free: str = "auto",
    tolerance_scale: float = 1.0,
    metric: str = "rms_position",
    alpha: float = 0.05,
    out: str | os.PathLike | None = None,
    workers: int = 0,
    dask_workers: int = 0,
    scheduler: str | None = None,
    retries: int = 3,
    progress: bool = True,
    recording: str | os.PathLike | None = None,
) -> Comparison:
    """Compare identification methods by Monte Carlo on simulated machines.

    Per trial: a true machine drawn from the tolerances, ``n_poses`` poses
    within ``q_limits``, instrument noise; every method identifies on the
    same data; the output error is evaluated on ``n_eval`` fresh poses.

    Parameters
    ----------
    machine : Machine
        Nominal machine, any kind (with ``q_limits``).
    methods : str
        Comma-separated registry names with options (``ls,ridge:lam=0.1,tsvd:k=20``).
    trials : int
    dof : {6, 5, 3}, optional
        Default 6, or the recording's.
    n_poses, n_eval : int
    seed : int
        Trial ``t`` uses child ``t`` of ``SeedSequence(seed)``.
    free : {"auto", "all"}
        Identified parameters: the identifiable set of each trial's poses
        (the same for all methods) or all (least squares then fails on a
        rank-deficient set, counted as failures).
    tolerance_scale : float
    metric : {"rms_position", "max_position", "rms_angle"}
    alpha : float
        Family-wise significance level (Holm).
    out : path, optional
        Save and resume trials there (see :mod:`bayescal.compare.runner`).
    workers, dask_workers, scheduler, retries, progress
        Backend (see :func:`bayescal.compare.runner.run_trials`).
    recording : path, optional
        A recording (measured poses, or a constraint recording of
        distances, heights and ballbar readings, docs/formats.md section 6):
        every trial then re-measures what it measured on its true machine,
        with the machine file's noise (or the recording's per-row
        ``sigma_position``), instead of ``n_poses`` drawn poses; ``dof`` as
        for ``identify`` (the recording's by default), ``n_poses`` unused.

    Returns
    -------
    Comparison
    """
    _check_options(machine, methods, trials, seed, tolerance_scale, retries, free, n_poses, n_eval)
    rec_text, rec_name, n_poses, dof = _recording_parts(machine, recording, n_poses, dof)
    config = CompareConfig(machine_text=machine.to_toml(), methods=methods, trials=int(trials), dof=int(dof),
                           n_poses=int(n_poses), n_eval=int(n_eval), seed=int(seed), free=free,
                           tolerance_scale=float(tolerance_scale), recording_text=rec_text, recording=rec_name)
    records, info = run_trials(config, out=out, workers=workers, dask_workers=dask_workers, scheduler=scheduler,
                               retries=retries, progress=progress)
    return comparison_from_records(records, config, metric=metric, alpha=alpha, machine_name=machine.name, info=info)


def _check_options(machine, methods: str, trials, seed, tolerance_scale, retries, free, n_poses, n_eval) -> None:
    """InputError naming the first option of :func:`compare_methods` it cannot take (before any trial runs)."""
    from ..limits import check_seed
    from .methods import parse_methods

    specs = parse_methods(methods)  # unknown methods, options and values refused before anything runs
    for spec in specs:
        k = dict(spec.options).get("k")
        if spec.name == "tsvd" and not isinstance(k, str) and k is not None and k > machine.n_params:
            # every trial failed on it ("k: tsvd needs an integer from 1 to 36") and the command exited 0
            raise InputError(f"--methods: {spec.label}: k={k}: expected at most {machine.n_params}, the machine's "
                             "parameters (or k=snr, k=auto)")
    if isinstance(retries, bool) or int(retries) != retries or retries < 0:
        raise InputError(f"retries (--retries): expected a whole number >= 0, got {retries!r}")
    check_seed(seed, "seed")
    if not (np.isfinite(tolerance_scale) and tolerance_scale > 0):
        raise InputError(f"tolerance_scale (--tolerance-scale): expected a positive number, got {tolerance_scale!r}")
    if isinstance(trials, bool) or not isinstance(trials, (int, np.integer)) or trials < 1:
        raise InputError(f"trials (--trials): expected a positive whole number, got {trials!r}")
    from ..limits import check_memory

    # every trial's record is kept (and saved): about a kilobyte per method
    check_memory(float(trials) * 1024 * (2 + len(parse_methods(methods))), f"{int(trials):,} trials", "lower --trials")
    if free not in ("auto", "all"):
        raise InputError(f"free: expected 'auto' or 'all', got {free!r}")
    for value, name in ((n_poses, "n_poses (--poses)"), (n_eval, "n_eval (--eval-poses)")):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise InputError(f"{name}: expected a positive whole number of poses, got {value!r}")
    if machine.q_limits is None:
        raise InputError(f"{machine.source}: the machine file has no [workspace] q_limits; a comparison draws poses there")


def _recording_parts(machine, recording, n_poses, dof):
    """``(text, name, n_poses, dof)`` of a comparison's recording, read and checked (empty without one; dof 6)."""
    rec_text = rec_name = ""
    if recording is not None:
        from ..models import model_from_recording, read_any_recording

        rec_name = str(recording)
        from ..io.safe_paths import MAX_CSV_BYTES, read_input_text

        rec_text = read_input_text(recording, "a recording (CSV)", limit=MAX_CSV_BYTES)
        # checked here (bad input is an error before any trial), and its size and DOF recorded
        model = model_from_recording(machine, read_any_recording(rec_name, text=rec_text), dof=dof)
        n_poses, dof = model.n_poses, model.tool_dof  # the tool's DOF (body sensors apart)
    elif dof is None:
        dof = 6
    return rec_text, rec_name, n_poses, dof
