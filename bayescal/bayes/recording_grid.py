"""A compensation grid from a recording, as ``bayescal grid`` makes it: identify, keep the geometry, span the nodes.

:func:`recording_grid` is what the command runs, so a notebook gets the
command's grid and JSON:

1. the arguments checked before any work: the auxiliary channels the
   machine file's ``[effect.*]`` tables act at (known channels, and only
   with tables), the grid's size, its space and ranges;
2. the identification: ``map`` (:func:`bayescal.identify.calibrate.calibrate`,
   what ``bayescal identify --method map`` runs: the noise test, outliers and
   prior scale, with the Laplace covariance), ``kalman`` or ``mcmc``
   (:func:`bayescal.identify.probabilistic.calibrate_bayes`, what ``identify``
   runs: the stated noise tested by a MAP, the robust pass's weights, then
   the filter or the sampler; ``mcmc`` with ``free="all"`` taken
   as ``"auto"``: sampling what the measurement does not see only explores
   the prior; the chain thinned to about :data:`GRID_DRAWS` draws); with
   ``fit_effects`` the effect tables' parameters are identified with the
   geometry (:func:`bayescal.effects.joint_model.joint_effects_model`);
   the fit judged by identify's plausibility rule
   (:func:`bayescal.instrument.plausibility.judge_fit`): an implausible
   calibration's grid (one pose, copied rows, errors beyond 10 tolerances)
   is refused by the writers unless ``force=True``, as identify refuses
   its machine file;
3. the nuisance parameters (a fitted instrument frame, ballbar pivots) left
   out: the grid is over the machine in its base frame (:func:`base_frame_parts`);
4. the grid over the actuators (:func:`bayescal.bayes.grid.compensation_grid`)
   or over the tool point (:func:`bayescal.bayes.tool_grid.tool_grid`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..constants import GRID_METHODS
from ..errors import InputError
from ..identify.free import Free, with_fixed
from ..notebook import ShowsReport
from .stopping import checked_ess

__all__ = ["GridAnswer", "recording_grid", "grid_space", "check_grid_ranges", "base_frame_parts", "GRID_METHODS",
           "GRID_DRAWS"]

#: The identification methods a grid is made from.
#: Posterior draws (about) a grid's std is computed over: the chain is thinned to them.
GRID_DRAWS = 400


@dataclass(frozen=True)
class GridAnswer(ShowsReport):
    """The answer of :func:`recording_grid`.

    Attributes
    ----------
    grid : CompensationGrid or ToolGrid or None
        None when the identification did not succeed (no grid is made).
    identification : IdentificationResult, FilterResult or PosteriorResult
        What the grid is computed from (``report()``, ``message``).
    method : str
    space : {"actuator", "tool"}
    machine : Machine
        The machine the grid spans, in its base frame.
    effects : tuple of str
        The machine file's ``[effect.*]`` tables applied at every node (their names).
    aux : dict of str to float
        The auxiliary channels they are applied at.
    effects_fitted : bool
        Their parameters were identified with the geometry.
    plausibility : Plausibility or None
        identify's verdict on the calibration the grid comes from
        (:func:`bayescal.instrument.plausibility.judge_fit`); the writers refuse an implausible one
        unless ``force=True``.
    """

    grid: object | None
    identification: object
    method: str
    space: str
    machine: object
    effects: tuple[str, ...] = ()
    aux: dict = field(default_factory=dict)
    effects_fitted: bool = False
    plausibility: object | None = None

    @property
    def success(self) -> bool:
        return self.grid is not None

    @property
    def plausible(self) -> bool:
        """identify's verdict: False for a calibration the grid's writers refuse (unless ``force``)."""
        return self.plausibility is None or bool(self.plausibility.plausible)

    def to_dict(self) -> dict:
        """The JSON ``bayescal grid --json`` writes, in JSON's own types (``json_text`` of it is that file)."""
        from ..io.answers import to_jsonable

        if self.grid is None:
            raise InputError(f"grid: the identification did not succeed ({self.identification.message}); no grid")
        extra = ({"effects": list(self.effects), "aux": dict(self.aux), "effects_fitted": bool(self.effects_fitted)}
                 if self.effects else {})
        plaus = self.plausibility.to_dict() if self.plausibility is not None else {}
        return to_jsonable({**self.grid.to_dict(), "method": self.method, **extra, **self._bounds(), **plaus})

    def _bounds(self) -> dict:
        """The identification's bounds and the parameters it put on one (their std in the grid: none)."""
        from ..identify.result import bounds_dict

        return bounds_dict(self.identification.bounds, self.identification.at_bound)

    def report(self) -> str:
        """The text ``bayescal grid`` prints."""
        if self.grid is None:
            return (self.identification.report() + f"\nthe identification did not succeed "
                    f"({self.identification.message}); no grid")
        lines = [self.grid.report()]
        if self.effects:
            at = ", ".join(f"{k} = {v:g}" for k, v in self.aux.items()) or "no auxiliary channel"
            how = "fitted with the geometry, " if self.effects_fitted else ""
            lines.append(f"  effects         {', '.join(self.effects)} {how}applied at {at}")
        if self.identification.at_bound:
            lines.append(f"  on a bound      {', '.join(self.identification.at_bound)} (no std: the grid's std is "
                         "conditional on them staying there)")
        if self.plausibility is not None:
            lines.append(self.plausibility.report())
        return "\n".join(lines)

    def write_csv(self, path, *, force: bool = False):
        """The grid as CSV (docs/formats.md): one row per node; an implausible calibration's only with ``force``."""
        return self._grid("write_csv", force).write_csv(path)

    def write_nc_csv(self, path, *, force: bool = False):
        """Tool space only: the NC-loadable grid CSV (docs/formats.md section E8); implausible: only with ``force``."""
        if self.space != "tool":
            raise InputError("nc (--nc): goes with space 'tool' (an NC system compensates tool points)")
        return self._grid("write_nc_csv", force).write_nc_csv(path)

    def _grid(self, what: str, force: bool = False):
        from ..instrument.plausibility import refuse_implausible

        if self.grid is None:
            raise InputError(f"{what}: the identification did not succeed ({self.identification.message}); no grid")
        refuse_implausible(self.plausibility, force, what)
        return self.grid


def grid_space(machine, space: str = "auto") -> str:
    """``"actuator"`` or ``"tool"``: ``auto`` is actuator space where the whole ``q_limits`` box assembles.

    ``machine``: the model's machine (its geometry in the base frame decides,
    :attr:`bayescal.machines.Machine.actuator_box_reachable`).
    """
    if space not in ("auto", "actuator", "tool"):
        raise InputError(f"space (--space): expected 'auto', 'actuator' or 'tool', got {space!r}")
    if space != "auto":
        return space
    return "actuator" if machine.geometry_part[0].actuator_box_reachable else "tool"


def check_grid_ranges(machine, ranges: dict | None, space: str) -> dict:
    """``ranges`` (``{"x": (lo, hi)}``, mm or the actuators' unit) checked against the grid's axes.

    ``space`` is ``"actuator"`` (axes ``q1..qN``) or ``"tool"`` (``x``, ``y``, ``z``).  Returns them as floats.
    """
    base = machine.geometry_part[0]
    names = ("x", "y", "z") if space == "tool" else tuple(f"q{i + 1}" for i in range(base.n_actuators))
    out = {}
    for name, span in (ranges or {}).items():
        try:
            lo, hi = (float(v) for v in span)
        except (TypeError, ValueError):
            raise InputError(f"ranges (--range) {name}: expected (LO, HI), got {span!r}") from None
        if name not in names:
            raise InputError(f"ranges (--range) {name}: {space} space has the axes {', '.join(names)}")
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise InputError(f"ranges (--range) {name}={lo:g}:{hi:g}: expected finite LO < HI")
        out[name] = (lo, hi)
    if out and space == "actuator" and base.q_limits is None:
        raise InputError(f"{base.source}: no [workspace] q_limits to span a grid")
    return out


def _check_aux(machine, aux: dict | None, channels) -> dict:
    """The auxiliary channels the effect tables act at: finite numbers, known channels, and only with tables."""
    from ..effects.stored import PROBE_CHANNELS

    aux = dict(aux or {})
    for name, value in aux.items():
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not math.isfinite(value):
            raise InputError(f"aux (--aux) {name}: expected a finite number, got {value!r}")
    if aux and not machine.effects:
        raise InputError(f"aux (--aux): {machine.source} carries no [effect.*] tables, so the grid depends on no "
                         "channel")
    known = dict.fromkeys([*PROBE_CHANNELS, *channels])
    typo = [k for k in aux if k not in known]
    if typo:  # a misspelt channel would silently leave the effect at its default
        raise InputError(f"aux (--aux) {typo[0]}: unknown channel; expected one of: {', '.join(known)}")
    return {k: float(v) for k, v in aux.items()}


def _parts(data):
    """``(model, recording or None)`` of what :func:`bayescal.load` returns, or of a model."""
    from ..contract import Model
    from ..instrument.prepare import Session

    if isinstance(data, Session):
        return data.fit_model, data.fit_recording
    if isinstance(data, Model):
        return data, None
    raise InputError(f"grid: expected what bayescal.load returns (or a measurement model), got "
                     f"{type(data).__name__} {data!r:.80}; for files: bayescal.grid(bayescal.load(machine, recording))")


def _identify(model, method: str, free, *, steps: int, seed: int, surrogate: str, fit_effects: bool, check=None,
              ess: float | None = None):
    """The fit, the grid's keyword for its std (a covariance or thinned draws) and identify's verdict on the fit."""
    if method == "map":
        # identify --method map's own answer (its noise test, outliers and prior scale), so that the grid's
        # correction and std are those of the calibration a user writes with the same command
        from ..identify.calibrate import calibrate
        from ..instrument.plausibility import judge_fit

        res = calibrate(model, method="map", free=free, fit_effects=fit_effects).result
        return res, {"covariance": res.covariance}, judge_fit(model.machine, model, res, check)[1]
    # kalman, mcmc: identify --method kalman | mcmc's own answer (the noise-testing MAP, the robust pass's
    # weights, then the filter or the sampler)
    from ..identify.probabilistic import calibrate_bayes

    opts = {}
    if method == "mcmc":
        opts = {"steps": steps, "seed": seed, "surrogate": surrogate, "ess": ess}
        if isinstance(free, str) and free == "all":
            free = "auto"  # sampling parameters the measurement does not see only explores the prior
        elif isinstance(free, Free) and free.base == "all":
            free = replace(free, base="auto")
    cal = calibrate_bayes(model, method=method, free=free, fit_effects=fit_effects, check=check, **opts)
    res, plaus = cal.result, cal.plausibility
    if method == "kalman":
        return res, {"covariance": res.covariance}, plaus
    if not res.success:
        return res, {}, plaus
    return res, {"samples": res.samples[:: max(1, res.samples.shape[0] // GRID_DRAWS)]}, plaus


def recording_grid(data, *, method: str = "map", free="all", nodes: int = 9, space: str = "auto",
                   ranges: dict | None = None, aux: dict | None = None, steps: int = 1000, surrogate: str = "none",
                   seed: int = 0, fit_effects: bool = False, fix=None, bounds=None,
                   ess: float | None = None) -> GridAnswer:
    """Identify a recording's errors and span a compensation grid with its std, as ``bayescal grid`` does.

    Parameters
    ----------
    data : Session or Model
        What :func:`bayescal.load` returns (its ``fit`` rows are used), or a measurement or constraint model.
    method : {"map", "kalman", "mcmc"}
    free : "all", "auto" or sequence of str
        Parameters identified (module docstring for mcmc).
    nodes : int
        Nodes per axis, at least 2.
    space : {"auto", "actuator", "tool"}
        See :func:`grid_space`.
    ranges : dict, optional
        ``{"q1": (lo, hi)}`` (actuator unit) or ``{"x": (lo, hi)}`` (mm) narrowing an axis.
    aux : dict of str to float, optional
        Auxiliary channels (``payload_kg``, ``temp_C``, ...) the machine file's effect tables act at; a channel
        not given is absent.
    steps, surrogate, seed
        mcmc: steps per walker, ``"none"`` or ``"linear"`` (sample the linearised model), random seed.
    fit_effects : bool
        map, mcmc: the effect tables' parameters are identified with the geometry (needs a pose recording
        from :func:`bayescal.load`).
    fix : sequence of str, optional
        Parameters held at nominal (:func:`bayescal.identify.calibrate.calibrate`): no std of theirs in the grid.
    bounds : mapping, optional
        ``{name: (lower, upper)}`` (:func:`bayescal.identify.calibrate.calibrate`; map and mcmc).
    ess : float, optional
        mcmc: stop the sampler at this bulk and tail ESS, ``steps`` the most
        (:func:`bayescal.bayes.mcmc.sample_posterior`); default: run ``steps``.

    Returns
    -------
    GridAnswer
        ``grid.correction`` and ``grid.std`` (mm), ``to_dict()`` (the ``--json`` answer), ``report()``,
        ``write_csv(path)``, ``write_nc_csv(path)``; ``plausibility``, identify's verdict: the writers
        refuse an implausible calibration's grid unless ``force=True``.
    """
    model, rec = _parts(data)
    check = getattr(data, "check", None)  # a session's rigid-transform check: the causes of an implausible fit
    if method not in GRID_METHODS:
        raise InputError(f"method (--method): expected one of {', '.join(GRID_METHODS)}, got {method!r}")
    if surrogate not in ("none", "linear"):
        raise InputError(f"surrogate (--surrogate): expected 'none' or 'linear', got {surrogate!r}")
    if ess is not None and method != "mcmc":  # it would be ignored, silently
        raise InputError(f"ess (--ess): goes with method 'mcmc'; it does nothing with method {method!r}")
    checked_ess(ess)  # bad input before the identification runs
    machine = model.machine
    aux = _check_aux(machine, aux, (model.aux or {}).keys())
    from .grid import check_grid_size

    # nodes, space and ranges checked (and arrays that fit in memory) before the identification runs
    check_grid_size(machine.geometry_part[0], nodes, space, n_samples=GRID_DRAWS if method == "mcmc" else 0)
    space = grid_space(machine, space)
    ranges = check_grid_ranges(machine, ranges, space)
    if fit_effects:
        from ..effects.joint_model import joint_effects_model

        model = joint_effects_model(model, rec, method=method)
    res, kw, plaus = _identify(model, method, with_fixed(free, fix, bounds), steps=steps, seed=seed, surrogate=surrogate,
                               fit_effects=fit_effects, check=check, ess=ess)
    effects = {"effects": tuple(e.name for e in machine.effects), "aux": aux, "effects_fitted": bool(fit_effects),
               "plausibility": plaus}
    if not res.success:
        return GridAnswer(None, res, method, space, machine.geometry_part[0], **effects)
    # the grid is over the machine in its base frame: an instrument frame (fitted or known) is left out
    base, theta, free_mask, kw = base_frame_parts(model.machine, res.theta, res.free, kw)
    grid = _span(base, theta, free_mask, kw, space=space, nodes=nodes, ranges=ranges, aux=aux)
    return GridAnswer(grid, res, method, space, base, **effects)


def _span(base, theta, free_mask, kw, *, space, nodes, ranges, aux):
    """The grid's nodes, correction and std over ``base`` (tool space: the tool point's box)."""
    if space == "tool":
        from .tool_grid import tool_grid

        return tool_grid(base, theta, free=free_mask, n=nodes, ranges=ranges, aux=aux, **kw)
    from .grid import compensation_grid

    axes = None
    if ranges:
        lim = {f"q{i + 1}": tuple(b) for i, b in enumerate(base.q_limits)}
        lim.update(ranges)
        axes = tuple(np.linspace(*lim[f"q{i + 1}"], nodes) for i in range(base.n_actuators))
    return compensation_grid(base, theta, free=free_mask, n=nodes, axes=axes, aux=aux, **kw)


def base_frame_parts(machine, theta, free, kw: dict):
    """The geometry's machine, its part of ``theta`` / ``free``, and of the covariance or samples.

    Nuisance parameters of the model's machine (a fitted instrument frame,
    ballbar pivots: :attr:`bayescal.machines.Machine.geometry_part`) are dropped.
    """
    base, idx = machine.geometry_part
    if idx.size == machine.n_params:
        return base, theta, free, kw
    keep = np.zeros(machine.n_params, dtype=bool)
    keep[idx] = True
    inner = keep[np.flatnonzero(free)]  # which columns of the covariance / samples are the geometry's
    out = {}
    if kw.get("covariance") is not None:
        out["covariance"] = kw["covariance"][np.ix_(inner, inner)]
    if kw.get("samples") is not None:
        out["samples"] = kw["samples"][:, inner]
    return base, np.asarray(theta)[idx], np.asarray(free)[idx], out
