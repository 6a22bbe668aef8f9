"""The registry of identification methods a comparison can run.

A method is a named callable ``fn(model, *, free, **options) ->
IdentificationResult``.  Adding a method is one call of
:func:`register_method` (or one entry in :data:`METHODS`); ``--methods``
names them, with options after a colon: ``ridge:lam=0.1``, ``tsvd:k=20``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import InputError
from ..identify import identify, resolve_free, whitened_system
from ..measurement import MeasurementModel

__all__ = ["Method", "METHODS", "MethodSpec", "register_method", "parse_methods", "tsvd_snr_rank"]


@dataclass(frozen=True)
class Method:
    """A registered method: its callable, default options and a one-line description."""

    name: str
    fn: Callable
    defaults: dict = field(default_factory=dict)
    help: str = ""


@dataclass(frozen=True)
class MethodSpec:
    """A method as asked for: ``label`` (as typed), registry ``name``, and options."""

    label: str
    name: str
    options: tuple[tuple[str, object], ...] = ()

    def run(self, model: MeasurementModel, *, free):
        m = METHODS[self.name]
        return m.fn(model, free=free, **{**m.defaults, **dict(self.options)})


#: Registered methods by name.
METHODS: dict[str, Method] = {}


def register_method(name: str, fn: Callable, *, help: str = "", **defaults) -> None:
    """Register ``fn(model, *, free, **options) -> IdentificationResult`` under ``name``."""
    if not name or not name.replace("_", "").isalnum():
        raise InputError(f"method name: expected letters, digits and underscores, got {name!r}")
    METHODS[name] = Method(name, fn, dict(defaults), help)


def tsvd_snr_rank(model: MeasurementModel, free) -> int:
    """TSVD ``k``: singular values of the whitened, tolerance-scaled matrix above 1.

    A direction with ``s_i > 1`` is determined better by the data than by
    the tolerance prior; below 1 the noise dominates what the data say.
    """
    theta = np.zeros(model.n_params)
    free = resolve_free(model, free, theta, prior=True)[0]  # "auto": as identify --method tsvd resolves it
    pred = model.predict(theta)
    _, J = whitened_system(model, theta, pred)
    s = np.linalg.svd(J[:, free] * model.machine.tolerance[free], compute_uv=False)
    return int(max(1, np.sum(s > 1.0)))


def _ls(model, *, free):
    return identify(model, method="ls", free=free)


def _auto(model, method, free, rule):
    from ..identify.choose import choose_regularisation

    return choose_regularisation(model, method, rule=None if rule in (None, "default") else str(rule), free=free)[1]


def _ridge(model, *, free, lam=1.0, rule=None):
    if lam == "auto":
        return _auto(model, "ridge", free, rule)
    if isinstance(lam, str):
        raise InputError(f"--methods: ridge:lam={lam}: expected a number >= 0 or 'auto'")
    return identify(model, method="ridge", lam=float(lam), free=free)


def _tsvd(model, *, free, k="snr", rule=None):
    if k == "auto":
        return _auto(model, "tsvd", free, rule)
    if k == "snr":
        k = tsvd_snr_rank(model, free)
    if isinstance(k, str) or int(k) != k:
        raise InputError(f"--methods: tsvd:k={k}: expected a positive integer, 'snr' or 'auto'")
    return identify(model, method="tsvd", k=int(k), free=free)


def _kalman(model, *, free, variant="ekf"):
    from ..bayes.kalman import kalman_filter

    return kalman_filter(model, variant=str(variant), free=free)


def _mcmc(model, *, free, steps=400, seed=0, surrogate="linear"):
    # the linear surrogate by default: a comparison runs the sampler once per trial, and the
    # full model costs minutes per run; the result still reports (and fails on) a poor linearisation
    from ..bayes.mcmc import sample_posterior

    return sample_posterior(model, free=free, n_steps=int(steps), seed=int(seed), surrogate=str(surrogate))


register_method("ls", _ls, help="Gauss-Newton least squares")
register_method("ridge", _ridge, lam=1.0, help="ridge towards nominal (lam=1: MAP under the tolerance prior; "
                "lam=auto chooses lam by a rule, rule=evidence by default)")
def _map(model, *, free):
    # the identify core scales columns by the tolerances, so ridge with lam = 1 is exactly the MAP
    # estimate under the tolerance prior (bayescal.identify.gauss_newton); point this entry at a
    # dedicated MAP solver when bayescal.identify has one
    return identify(model, method="ridge", lam=1.0, free=free)


register_method("map", _map, help="MAP under the tolerance prior (ridge with lam=1)")
register_method("tsvd", _tsvd, k="snr",
                help="truncated SVD; k=snr keeps singular values > 1 of the tolerance-scaled matrix, k=auto chooses "
                "k by a rule (rule=cv|lcurve|gcv|discrepancy|evidence|risk)")
register_method("kalman", _kalman, variant="ekf", help="recursive Kalman filter, one update per pose (variant=ekf|ukf)")
register_method("mcmc", _mcmc, steps=400, seed=0, surrogate="linear",
                help="posterior mean by emcee (steps=400, surrogate=linear|none); a trial whose chain has not "
                "converged counts as a failure")


def _value(text: str):
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


def parse_methods(text: str) -> tuple[MethodSpec, ...]:
    """``"ls,ridge:lam=0.1,tsvd:k=20"`` -> method specs; unknown names are an InputError listing the known ones."""
    specs = []
    for item in [s.strip() for s in str(text).split(",") if s.strip()]:
        name, _, opts = item.partition(":")
        name = name.strip()
        if name not in METHODS:
            raise InputError(
                f"--methods: unknown method {name!r}; known methods: "
                + "; ".join(f"{m.name} ({m.help})" if m.help else m.name for m in METHODS.values())
            )
        options = []
        for kv in [o for o in opts.split(";") if o.strip()] if opts else []:
            k, eq, v = kv.partition("=")
            if not eq or not k.strip():
                raise InputError(f"--methods: option {kv!r} of {name!r}: expected key=value (e.g. ridge:lam=0.1)")
            options.append((k.strip(), _value(v.strip())))
        specs.append(MethodSpec(label=item, name=name, options=tuple(options)))
    if not specs:
        raise InputError("--methods: expected at least one method, e.g. ls,ridge,tsvd")
    labels = [s.label for s in specs]
    if len(set(labels)) != len(labels):
        raise InputError(f"--methods: a method is listed twice in {text!r}")
    return tuple(specs)
