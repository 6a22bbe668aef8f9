"""One Monte Carlo trial of a comparison: a pure function of the configuration and the trial index.

Trial ``t`` draws everything from ``SeedSequence(seed, spawn_key=(t,))``,
the ``t``-th child of ``SeedSequence(seed).spawn(...)``: the answer does
not depend on which process runs it or in what order.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, replace
from functools import lru_cache

import numpy as np

from ..constants import METRICS
from ..errors import BayescalError
from ..geometry import so3_log
from ..identify import resolve_free
from ..machines.files import machine_from_text
from ..measurement import MeasurementModel
from ..simulate import draw_errors, draw_poses, measure
from .methods import MethodSpec, parse_methods

__all__ = ["CompareConfig", "run_trial", "trial_rng", "METRICS"]

# METRICS, the output-error metrics recorded per method and trial, is defined in bayescal.constants (the command
# line offers them without importing numpy) and exported from here as before.


@dataclass(frozen=True)
class CompareConfig:
    """What a comparison runs (everything a trial needs, picklable and JSON-able).

    Attributes
    ----------
    machine_text : str
        The nominal machine file (rebuilt in each worker).
    methods : str
        Comma-separated method specs (see :func:`bayescal.compare.methods.parse_methods`).
    trials : int
    dof : int
    n_poses : int
        Measured poses per trial (drawn uniformly within ``q_limits``).
    n_eval : int
        Fresh poses per trial on which the output error is evaluated.
    seed : int
    free : str
        ``auto`` (each method resolves it on the trial's poses as
        ``identify`` does: least squares fixes what the data cannot separate,
        methods with a prior let the prior decide it) or ``all``.
    tolerance_scale : float
        True machines drawn from ``N(0, (scale * tol)^2)``.
    recording_text, recording : str
        A recording's CSV text and name (``""``: none).  Given, every trial
        measures what it measured (the same poses, or the same distance
        pairs, heights and ballbar readings of a constraint recording) on
        its true machine instead of ``n_poses`` drawn poses; a ballbar's
        true pivot is drawn about its start estimate with the pivot
        tolerance, and ``n_poses`` and ``dof`` are the recording's.
    """

    machine_text: str
    methods: str
    trials: int
    dof: int = 6
    n_poses: int = 36
    n_eval: int = 100
    seed: int = 0
    free: str = "auto"
    tolerance_scale: float = 1.0
    recording_text: str = ""
    recording: str = ""

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def specs(self) -> tuple[MethodSpec, ...]:
        return parse_methods(self.methods)


def trial_rng(seed: int, t: int) -> np.random.Generator:
    """The generator of trial ``t``: child ``t`` of ``SeedSequence(seed)``."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(t),)))


@lru_cache(maxsize=4)
def _machine(text: str):
    return machine_from_text(text, "<comparison machine>")


@lru_cache(maxsize=4)
def _recording_model(machine_text: str, recording_text: str, name: str, dof: int):
    """The measurement model of the comparison's recording (any kind of recording)."""
    from ..models import model_from_recording, read_any_recording

    return model_from_recording(_machine(machine_text), read_any_recording(name, text=recording_text), dof=dof)


def _trial_model(cfg: "CompareConfig", machine, rng: np.random.Generator):
    """The trial's true parameters and its measurement model with simulated values.

    Returns ``(theta_true, model)``; ``theta_true`` has the model's
    parameters (the machine's, then nuisance ones such as ballbar pivots).
    """
    scale = cfg.tolerance_scale
    if not cfg.recording_text:
        theta = draw_errors(machine, rng, tolerance=machine.tolerance * scale)
        q = draw_poses(machine, cfg.n_poses, rng, theta)
        return theta, MeasurementModel.from_recording(machine, measure(machine, q, theta, cfg.dof, rng), dof=cfg.dof)
    model = _recording_model(cfg.machine_text, cfg.recording_text, cfg.recording, cfg.dof)
    for _ in range(20):  # a true machine that cannot assemble one of the recorded poses is redrawn
        theta = draw_errors(model.machine, rng, tolerance=model.machine.tolerance * scale)
        pred = model.predict(theta)
        if pred.success.all():
            break
    else:
        raise BayescalError(f"{cfg.recording}: 20 true machines drawn from the tolerances could not assemble its poses")
    y = pred.y + model.row_sigma * rng.normal(size=pred.y.shape)
    return theta, replace(model, y_measured=y)


def _output_errors(machine, q_eval, true_poses, theta) -> dict[str, float]:
    pred = machine.forward(q_eval, theta)
    if not pred.success.all():
        return {}
    pos = np.linalg.norm(pred.position - true_poses.position, axis=1)
    ang = np.linalg.norm(so3_log(pred.rotation @ np.swapaxes(true_poses.rotation, -1, -2)), axis=1)
    return {"rms_position": float(np.sqrt(np.mean(pos**2))), "max_position": float(pos.max()),
            "rms_angle": float(np.sqrt(np.mean(ang**2)))}


def run_trial(config: dict, t: int) -> dict:
    """Run trial ``t`` with one BLAS thread (see :func:`_run_trial`).

    Multithreaded BLAS sums in a different order than single-threaded BLAS
    (dask workers run with one thread), which changes the last bits of
    every result; pinning one thread everywhere makes the records identical
    in-process, on local processes and on dask.
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _run_trial(config, t)


def _run_trial(config: dict, t: int) -> dict:
    """Run trial ``t`` of a comparison; returns a JSON-able record.

    Parameters
    ----------
    config : dict
        :meth:`CompareConfig.to_dict`.
    t : int
        Trial index (0-based).

    Returns
    -------
    dict
        ``{"trial": t, "nominal": {metric: value}, "methods": {label: {"success", "message",
        "seconds", metric: value, ...}}}``; errors in mm and rad.
    """
    cfg = CompareConfig(**config)
    machine = _machine(cfg.machine_text)
    rng = trial_rng(cfg.seed, t)
    theta_all, model = _trial_model(cfg, machine, rng)
    # the output error is the geometry's: nuisance parameters (ballbar pivots) are not evaluated
    geo, idx = model.machine.geometry_part
    theta = theta_all[idx]
    q_eval = draw_poses(geo, cfg.n_eval, rng, theta)
    true_poses = geo.forward(q_eval, theta)
    # "auto" is resolved by each method as identify resolves it for a user: least squares needs the
    # parameters the data cannot separate fixed, while a method with a prior (map, ridge, tsvd, kalman)
    # lets the prior decide them (bayescal.identify.resolve_free); one shared set fixed for LS made
    # MAP worse than the nominal geometry on a ballbar recording (docs/delta.md)
    free = cfg.free
    n_free = resolve_free(model, cfg.free, np.zeros(model.n_params))[0].size
    out = {"trial": int(t), "nominal": _output_errors(geo, q_eval, true_poses, np.zeros(geo.n_params)),
           "n_free": int(n_free), "methods": {}}
    for spec in cfg.specs:
        t0 = time.perf_counter()
        entry = {"success": False, "message": ""}
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # a failure is recorded as data, not printed per trial
                res = spec.run(model, free=free)
            entry["success"] = bool(res.success)
            entry["message"] = res.message
            if res.success:
                errs = _output_errors(geo, q_eval, true_poses, np.asarray(res.theta)[idx])
                if errs:
                    entry.update(errs)
                else:
                    entry.update(success=False, message="identified machine cannot reach the evaluation poses")
        except (BayescalError, np.linalg.LinAlgError) as exc:
            entry["message"] = f"{type(exc).__name__}: {exc}"
        entry["seconds"] = time.perf_counter() - t0
        out["methods"][spec.label] = entry
    return out
