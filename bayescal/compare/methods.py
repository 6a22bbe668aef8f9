"""The registry of identification methods a comparison can run.

A method is a named callable ``fn(model, *, free, **options) ->
IdentificationResult``.  Adding a method is one call of
:func:`register_method` (or one entry in :data:`METHODS`); ``--methods``
names them, with options after a colon: ``ridge:lam=0.1``, ``tsvd:k=20``.
The library's own methods are described in :data:`bayescal.constants.COMPARE_METHODS`,
which ``bayescal compare --help`` lists without importing this module.
"""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..constants import COMPARE_METHODS
from ..errors import InputError
from ..identify import identify, resolve_free, whitened_system
from ..limits import LAM_RANGE, lam_problem
from ..measurement import MeasurementModel

__all__ = ["Method", "METHODS", "MethodSpec", "register_method", "parse_methods", "tsvd_snr_rank"]


@dataclass(frozen=True)
class Method:
    """A registered method: its callable, default options and a one-line description."""

    name: str
    fn: Callable
    defaults: dict = field(default_factory=dict)
    help: str = ""
    check: Callable[[dict, str], None] | None = None


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


def register_method(name: str, fn: Callable, *, help: str = "", check: Callable[[dict, str], None] | None = None,
                    **defaults) -> None:
    """Register ``fn(model, *, free, **options) -> IdentificationResult`` under ``name``.

    ``check(options, label)``, if given, raises InputError for option values
    the method cannot take (options are the defaults updated by the ones
    asked for), so :func:`parse_methods` refuses them before any trial.
    """
    if not name or not name.replace("_", "").isalnum():
        raise InputError(f"method name: expected letters, digits and underscores, got {name!r}")
    METHODS[name] = Method(name, fn, dict(defaults), help, check)


def _option_names(fn: Callable) -> tuple[str, ...]:
    """The options a method's callable takes: its keyword parameters other than ``model`` and ``free``."""
    params = inspect.signature(fn).parameters.values()
    return tuple(p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and p.name not in ("model", "free"))


def _bad(label: str, key: str, value, expected: str) -> InputError:
    return InputError(f"--methods: {label}: {key}={value}: expected {expected}")


def _is_number(v, lo: float = 0.0) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and v >= lo


def _check_rule(o: dict, label: str, auto: bool, what: str) -> None:
    from ..identify.choose import RULE_NAMES

    rule = o.get("rule")
    if rule in (None, "default"):
        return
    if rule not in RULE_NAMES:
        raise _bad(label, "rule", rule, "one of " + ", ".join(RULE_NAMES))
    if not auto:
        raise InputError(f"--methods: {label}: rule={rule} is the rule of {what}=auto; give {what}=auto with it")


def _check_ridge(o: dict, label: str) -> None:
    lam = o.get("lam")
    if lam != "auto" and not (_is_number(lam) and lam_problem(float(lam)) is None):
        raise _bad(label, "lam", lam, f"a number from {LAM_RANGE[0]:g} to {LAM_RANGE[1]:g} or 'auto'")
    _check_rule(o, label, lam == "auto", "lam")


def _check_tsvd(o: dict, label: str) -> None:
    k = o.get("k")
    if k not in ("auto", "snr") and (isinstance(k, bool) or not isinstance(k, int) or k < 1):
        raise _bad(label, "k", k, "a positive integer, 'snr' or 'auto'")
    _check_rule(o, label, k == "auto", "k")


def _check_kalman(o: dict, label: str) -> None:
    if o.get("variant") not in ("ekf", "ukf"):
        raise _bad(label, "variant", o.get("variant"), "ekf or ukf")


def _check_mcmc(o: dict, label: str) -> None:
    from ..limits import SEED_MAX

    steps, seed = o.get("steps"), o.get("seed")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 20:
        raise _bad(label, "steps", steps, "an integer >= 20")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= SEED_MAX:
        raise _bad(label, "seed", seed, f"an integer from 0 to {SEED_MAX}")
    if o.get("surrogate") not in ("none", "linear"):
        raise _bad(label, "surrogate", o.get("surrogate"), "none or linear")
    ess = o.get("ess")
    if ess is not None and not (_is_number(ess) and ess > 0):
        raise _bad(label, "ess", ess, "a positive effective sample size (the chain stops there, steps the most)")


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


def _mcmc(model, *, free, steps=400, seed=0, surrogate="linear", ess=None):
    # the linear surrogate by default: a comparison runs the sampler once per trial, and the
    # full model costs minutes per run; the result still reports (and fails on) a poor linearisation.
    # ess: each trial's chain stops at that effective sample size (steps the most), as identify --ess
    from ..bayes.mcmc import sample_posterior

    return sample_posterior(model, free=free, n_steps=int(steps), seed=int(seed), surrogate=str(surrogate),
                            ess=None if ess is None else float(ess))


# the descriptions are bayescal.constants.COMPARE_METHODS (``bayescal compare --help`` lists them without importing
# this module)
register_method("ls", _ls, help=COMPARE_METHODS["ls"])
register_method("ridge", _ridge, lam=1.0, check=_check_ridge, help=COMPARE_METHODS["ridge"])
def _map(model, *, free):
    # what `bayescal identify --method map` answers (bayescal.identify.calibrate: the prior scale from the data
    # where it can be estimated, the outlier test and robust refit, the noise test): a comparison of "map" must
    # compare what a user gets, not ridge with lam = 1 under the machine file's tolerances
    from ..identify.calibrate import calibrate

    return calibrate(model, method="map", free=free).result


register_method("map", _map, help=COMPARE_METHODS["map"])
register_method("tsvd", _tsvd, k="snr", check=_check_tsvd, help=COMPARE_METHODS["tsvd"])
register_method("kalman", _kalman, variant="ekf", check=_check_kalman, help=COMPARE_METHODS["kalman"])
register_method("mcmc", _mcmc, steps=400, seed=0, surrogate="linear", check=_check_mcmc, help=COMPARE_METHODS["mcmc"])


def _value(text: str):
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


def _check_options(method: Method, label: str, options: dict) -> None:
    """Refuse option names the method does not take and values it cannot use (before any trial)."""
    known = _option_names(method.fn)
    for key in options:
        if key not in known:
            takes = f"its options are {', '.join(known)}" if known else "it takes no options"
            raise InputError(f"--methods: {label}: unknown option {key!r} of {method.name} ({takes})")
    if method.check is not None:
        method.check({**method.defaults, **options}, label)


def parse_methods(text: str) -> tuple[MethodSpec, ...]:
    """``"ls,ridge:lam=0.1,tsvd:k=20"`` -> method specs; unknown names are an InputError listing the known ones."""
    specs = []
    items = [s.strip() for s in str(text).split(",")]
    if any(not s for s in items) and any(items):
        raise InputError(f"--methods {text!r}: an empty method between commas; expected names such as ls,ridge,tsvd")
    for item in [s for s in items if s]:
        name, colon, opts = item.partition(":")
        name = name.strip()
        if colon and not opts.replace(";", "").strip():
            # 'ridge:' ran ridge's defaults, silently
            raise InputError(f"--methods: {item}: nothing after ':'; expected key=value options (e.g. ridge:lam=0.1) "
                             "or the name alone")
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
        _check_options(METHODS[name], item, dict(options))
        specs.append(MethodSpec(label=item, name=name, options=tuple(options)))
    if not specs:
        raise InputError("--methods: expected at least one method, e.g. ls,ridge,tsvd")
    labels = [s.label for s in specs]
    if len(set(labels)) != len(labels):
        raise InputError(f"--methods: a method is listed twice in {text!r}")
    return tuple(specs)
