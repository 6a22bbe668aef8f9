"""A measurement model whose unknowns are the geometry *and* the parameters of the machine file's effects.

Why.  A machine file's ``[effect.*]`` tables (docs/formats.md section 7) hold
values fitted by ``diagnose``; every command applies them as fixed
(:mod:`bayescal.effects.stored`).  A posterior of the geometry alone then
treats a compliance or a thermal coefficient as known exactly, while the
data determine it about as well as a geometric parameter, and often in
trade with one (a joint compliance against a link length under a constant
payload): the intervals of the geometry, and of a compensation grid built
from it, come out too narrow.  :class:`EffectModel` makes the effects'
parameters unknowns like the geometry, with the effects' own priors
(:class:`~bayescal.effects.EffectParam`), so that the MAP, its Laplace
covariance and the MCMC posterior are joint.

How.  The parameter vector is ``(theta, eta)``: the geometric model's
parameters (the machine's, then any nuisance ones it has) followed by every
effect parameter, named ``effect.<effect>.<parameter>`` (the machine file's
key) in the parameter's own unit.  The prediction is
``h(q + sum_e dq_e(features_e, eta_e), theta)``, its tool poses moved by
``sum_e dx_e(features_e, eta_e)`` of the effects that move the tool (a
structure bending under gravity), with the features computed
once from the commanded poses, as the stored effects are applied
(:func:`bayescal.effects.stored.effect_delta_q`), and ``dq`` at ``theta``
for an effect whose ``dq`` depends on the geometry.  The Jacobian's effect
columns are ``(d h / d q) (d dq / d eta)`` plus the rows of ``d dx / d eta``
(:func:`.model.effect_columns`,
the columns of the diagnosis' joint fit).  :class:`EffectAugmented` is the
machine view consumers read the layout, tolerances (the effects' prior
std) and prior means from, so identification, the MAP, Kalman filters and
the MCMC sampler work on it unchanged; ``stored_effects(theta)`` turns a
fitted vector back into ``[effect.*]`` tables.

Scope: pose recordings (:class:`~bayescal.measurement.MeasurementModel`),
and effects whose table alone defines them: not one whose ``dq`` depends on
the geometry (a table is applied at the file's geometry, a joint fit would
evaluate it at the fitted one) nor one whose prior the diagnosis derives
from the residuals (:meth:`Effect.refine`: a screw's pitch).  Those are
refused with the reason.
A stacked prediction (one block per walker) solves every block's own
actuator positions in one kinematics call.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..machines.appended import AppendedParameters
from ..machines.base import Machine, ToolPoses
from ..machines.view import Forwarded
from ..measurement import MeasurementModel, Prediction
from ..params import ParamSpec
from .base import Effect, EffectParam, Features
from .model import _at, _bend, _dq, _dx, _effect_theta, _slices, effect_columns
from .stored import StoredEffect

__all__ = ["EffectAugmented", "EffectModel", "effect_model", "joint_effects_model", "with_fitted_effects",
           "FIT_EFFECTS_METHODS"]

#: Methods with a prior, which the effects' parameters need (their priors decide what the data do not).
FIT_EFFECTS_METHODS = ("map", "mcmc")

#: Tolerance group of the effect parameters in the layout.
EFFECT_GROUP = "effect"


@dataclass(frozen=True, eq=False)
class EffectAugmented(AppendedParameters):
    """A machine's parameter layout extended by effect parameters.

    ``base`` is the geometric model's machine (possibly a view with nuisance
    parameters); ``params`` the effect parameters in layout order and
    ``effect_names`` the effect each belongs to.  As every view of appended
    parameters (:class:`~bayescal.machines.appended.AppendedParameters`), the
    kinematics are the base machine's and the members no view changes its
    machine's (:data:`~bayescal.machines.view.FORWARDED`); the effects'
    priors give the tolerances, prior means and lower bounds.  Unlike
    nuisance parameters, the view is around the geometric model's machine,
    instrument frame included: the frame's layer (``framed``, ``n_frame``,
    ``instrument_frame``, ``inside``, ``base_machine``) is the base machine's.
    """

    base: Machine
    params: tuple[EffectParam, ...]
    effect_names: tuple[str, ...]
    #: The machine file's tables the effects came from (settings, units and source kept in :meth:`tables`).
    stored: tuple[StoredEffect, ...] = ()

    def appended(self):
        specs = tuple(ParamSpec(f"effect.{e}.{p.name}", p.unit, EFFECT_GROUP) for e, p in zip(self.effect_names, self.params))
        return specs, np.array([p.prior_sd for p in self.params], dtype=float)

    def __post_init__(self) -> None:
        super().__post_init__()
        base_mean = self.base.prior_mean
        base_mean = np.zeros(self.base.n_params) if base_mean is None else np.asarray(base_mean, float)
        object.__setattr__(self, "_prior_mean", np.concatenate([base_mean, [p.prior_mean for p in self.params]]))
        # the effects' physical bounds (a compliance, a mass): the sampled prior is truncated there
        low = [-np.inf if p.lower is None else p.lower for p in self.params]
        base_low = self.base.prior_lower  # a view's own bounds (effects fitted under it) kept, as its prior mean is
        base_low = np.full(self.base.n_params, -np.inf) if base_low is None else np.asarray(base_low, float)
        object.__setattr__(self, "_prior_lower", np.concatenate([base_low, low]))

    @property
    def prior_mean(self) -> NDArray:
        """The base machine's prior mean (zero unless it states one), then the effect parameters' prior means."""
        return self._prior_mean

    @property
    def prior_lower(self) -> NDArray:
        """The base machine's lower bounds (none unless a view states them), then the effect parameters' physical ones."""
        return self._prior_lower

    # the frame's layer is the base machine's: the effect parameters follow whatever frame it has
    framed = Forwarded()
    n_frame = Forwarded()
    instrument_frame = Forwarded()
    inside = Forwarded()

    def rewrapped(self, inner: Machine) -> "EffectAugmented":
        """This view over the base machine's frame around ``inner``."""
        return dataclasses.replace(self, base=self.base.rewrapped(inner))

    def base_machine(self) -> Machine:
        """The base machine's machine in its base frame (without the effect parameters and nuisance views)."""
        return self.base.base_machine()

    @property
    def geometry_part(self) -> tuple[Machine, NDArray]:
        """The base machine's geometry part with the effect parameters kept after it.

        A grid or an output error drops nuisance parameters (a fitted frame,
        pivots) but not the effects: they move the drives at every node
        (:meth:`node_actuators`).
        """
        inner, idx = self.base.geometry_part
        view = EffectAugmented(inner, self.params, self.effect_names, self.stored)
        return view, np.concatenate([idx, np.arange(self.n_base, self.n_params)])

    def tables(self, theta: ArrayLike) -> tuple[StoredEffect, ...]:
        """The ``[effect.*]`` tables at the effect parameters of ``theta`` (P + K,), in the order of the effects."""
        eta = self.check_theta(theta)[self.n_base :]
        kept = {s.name: s for s in self.stored}
        out: dict[str, list] = {}
        for name, p, v in zip(self.effect_names, self.params, eta):
            out.setdefault(name, []).append((p, float(v)))
        return tuple(
            StoredEffect(name, tuple((p.name, v) for p, v in pv), tuple(p.unit for p, _ in pv),
                         kept[name].source if name in kept else "<fitted>", kept[name].settings if name in kept else ())
            for name, pv in out.items())

    def node_actuators(self, q: NDArray, theta: NDArray | None = None, aux: dict | None = None) -> tuple[NDArray, NDArray]:
        """Drives at grid nodes under the effects at ``theta``'s values, and ``d q / d (theta, eta)`` (effect columns).

        As :meth:`bayescal.machines.base.Machine.node_actuators` with the
        effects at the parameters' values; the derivative is analytic in the
        effect parameters (:func:`bayescal.effects.stored.static_effect_delta_q_and_jacobian`)
        and zero in the geometry (the loads' dependence on the geometric
        corrections, of their relative size, is neglected as in every stored
        application).
        """
        from .stored import static_effect_delta_q_and_jacobian

        theta = self.check_theta(theta)
        m = self.base.with_effects(self.tables(theta))
        dq, J = static_effect_delta_q_and_jacobian(m, m.effects, q, aux)
        full = np.zeros(J.shape[:2] + (self.n_params,))
        full[:, :, self.n_base :] = J
        return q + dq, full

    def node_tool_offset(self, q: NDArray, theta: NDArray | None = None, aux: dict | None = None) -> NDArray | None:
        """The tool perturbation of the effects at ``theta``'s values at grid nodes (:meth:`Machine.node_tool_offset`)."""
        from .stored import static_effect_delta_x

        m = self.base.with_effects(self.tables(self.check_theta(theta)))
        return static_effect_delta_x(m, m.effects, q, aux)

    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """The geometry's machine file (the effect tables: :meth:`EffectModel.stored_effects`)."""
        return self.base.to_toml(self.machine_theta(self.check_theta(theta)))


def _sub_model(model: MeasurementModel, q: NDArray, guess: ToolPoses | None, bend: NDArray | None = None) -> MeasurementModel:
    """``model`` at the actuator positions ``q`` (a multiple of its poses: stacked blocks), without measured values.

    Its body sensors are stacked alike, their bodies turned by ``bend`` (stacked, or None: as they are).
    """
    own = model.pose_offset
    reps = q.shape[0] // model.q.shape[0]
    sensors = model.sensors
    if sensors is not None:
        sensors = sensors.tiled(reps)
        if bend is not None:
            sensors = sensors.with_bend(bend)
    return dataclasses.replace(model, q=q, y_measured=None, pose_sigma=None, aux=None, guess=guess,
                               pose_offset=None if own is None else np.tile(own, (reps, 1)), sensors=sensors)


def _of_geo(name: str) -> property:
    """The geometric model's member ``name``, read through (the effects do not change it)."""
    return property(lambda self: getattr(self.geo, name), doc=f"The geometric model's ``{name}``.")


@dataclass(frozen=True, eq=False)
class EffectModel:
    """``h(q + dq(eta), theta)`` with ``(theta, eta)`` the unknowns (see the module docstring).

    Attributes
    ----------
    geo : MeasurementModel
        The geometric model at the *commanded* actuator positions (its
        machine carries no stored effects).
    effects : tuple of (Effect, Features)
        The effects and their features for ``geo``'s poses.
    stored : tuple of StoredEffect
        The machine file's tables the effects came from (their settings and
        units are kept when new values are written).
    """

    geo: MeasurementModel
    effects: tuple[tuple[Effect, Features], ...]
    stored: tuple[StoredEffect, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.geo, MeasurementModel):
            raise InputError(f"EffectModel: expected a pose recording's MeasurementModel, got {type(self.geo).__name__}")
        if self.geo.machine.effects:
            raise InputError("EffectModel: the geometric model's machine must not apply stored effects itself")
        params, owners = [], []
        for eff, f in self.effects:
            ps = tuple(eff.params(self.geo.machine, f))
            params += ps
            owners += [eff.name] * len(ps)
        object.__setattr__(self, "machine", EffectAugmented(self.geo.machine, tuple(params), tuple(owners), self.stored))
        object.__setattr__(self, "_slices", _slices(list(self.effects), self.geo))

    # the model contract's members the effects do not change are the geometric model's (bayescal.contract)
    q = _of_geo("q")
    dof = _of_geo("dof")
    tool_dof = _of_geo("tool_dof")
    n_poses = _of_geo("n_poses")
    y_measured = _of_geo("y_measured")
    aux = _of_geo("aux")
    guess = _of_geo("guess")
    sensors = _of_geo("sensors")
    R_ref = _of_geo("R_ref")
    sigma = _of_geo("sigma")
    row_sigma = _of_geo("row_sigma")
    pose_sigma = _of_geo("pose_sigma")
    pose_offset = _of_geo("pose_offset")
    pose_q = _of_geo("pose_q")
    pose_row = _of_geo("pose_row")
    pose_order = _of_geo("pose_order")
    poses_of = _of_geo("poses_of")
    residual = _of_geo("residual")
    errors = _of_geo("errors")
    rms = _of_geo("rms")
    region = _of_geo("region")
    rows_jacobian = _of_geo("rows_jacobian")
    effect_inputs = _of_geo("effect_inputs")
    answer_extras = _of_geo("answer_extras")

    @property
    def calibrated_machine(self) -> EffectAugmented:
        """The machine a calibration reports and writes: :attr:`machine` (the effects' tables filled from theta)."""
        return self.machine

    def with_pose_q(self, pose_q: NDArray, *, keep_guess: bool = True) -> "EffectModel":
        """The same effects on the geometric model at other actuator positions (their features kept)."""
        return dataclasses.replace(self, geo=self.geo.with_pose_q(pose_q, keep_guess=keep_guess))

    def with_pose_offset(self, pose_offset: NDArray | None) -> "EffectModel":
        """The same effects with a tool-pose perturbation of the geometric model's poses (the effects' own added)."""
        return dataclasses.replace(self, geo=self.geo.with_pose_offset(pose_offset))

    @property
    def n_params(self) -> int:
        return self.machine.n_params

    @property
    def effect_params(self) -> tuple[EffectParam, ...]:
        return self.machine.params

    def _split(self, theta: NDArray) -> tuple[NDArray, NDArray]:
        P = self.machine.n_base
        return theta[..., :P], theta[..., P:]

    def delta_q(self, theta: ArrayLike) -> NDArray:
        """``sum_e dq_e`` of every solved pose at the parameters ``theta`` (P + K,), mm (or rad)."""
        th, eta = self._split(self.machine.check_theta(theta))
        return _dq(list(self.effects), self._slices, eta, self.geo.pose_q.shape, _effect_theta(self.geo, th))

    def delta_x(self, theta: ArrayLike) -> NDArray | None:
        """``sum_e dx_e`` of every solved pose at ``theta`` (P + K,), base frame (mm, rad), or None when no effect moves the tool."""
        _, eta = self._split(self.machine.check_theta(theta))
        return _dx(list(self.effects), self._slices, eta, self.geo.pose_q.shape[0])

    def at(self, theta: ArrayLike) -> MeasurementModel:
        """The geometric model at the actuator positions and tool perturbation the effects make at ``theta`` (measured values kept)."""
        eta = self._split(self.machine.check_theta(theta))[1]
        return _at(self.geo, self.geo.pose_q + self.delta_q(theta), self.delta_x(theta),
                   bend=_bend(list(self.effects), self._slices, eta, self.geo))

    def predict(self, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> Prediction:
        """``h`` at ``theta`` of shape (P + K,) or (n_sets * n_poses, P + K) (one block of equal rows per set)."""
        theta = self.machine.check_theta(theta)
        th, _ = self._split(theta)
        if theta.ndim == 1:
            return self.at(theta).predict(th, guess=guess)
        n = self.geo.n_poses
        if theta.shape[0] % n:
            raise InputError(f"theta: {theta.shape[0]} rows is not a multiple of {n} poses")
        blocks = theta.reshape(-1, n, theta.shape[1])
        if not np.all(blocks == blocks[:, :1]):
            raise InputError("theta: the effects take one parameter vector per block of poses, not per pose")
        q = np.concatenate([self.geo.pose_q + self.delta_q(b[0]) for b in blocks])
        g = guess if guess is not None else self.geo.guess
        bends = [_bend(list(self.effects), self._slices, self._split(b[0])[1], self.geo) for b in blocks]
        sub = _sub_model(self.geo, q, g, None if bends[0] is None else np.concatenate(bends))
        dx = [self.delta_x(b[0]) for b in blocks]
        if dx[0] is not None:
            own = self.geo.pose_offset
            sub = sub.with_pose_offset(np.concatenate([d if own is None else own + d for d in dx]))
        return sub.predict(th)

    def jacobian(self, theta: ArrayLike | None, prediction: Prediction) -> NDArray:
        """``d h / d (theta, eta)``, shape (n_poses, dof, P + K): geometric columns at ``q + dq``, then the effects'."""
        theta = self.machine.check_theta(theta)
        th, eta = self._split(theta)
        sub = self.at(theta)
        Jg = sub.jacobian(th, prediction)
        if not self.effects:
            return Jg
        cols, extra = effect_columns(sub, th, prediction, list(self.effects), self._slices, eta)
        if extra is not None:
            Jg = Jg + extra
        return np.concatenate([Jg] + cols, axis=2)

    def subset(self, idx) -> "EffectModel":
        """The model of poses ``idx`` (features subset with them)."""
        return EffectModel(self.geo.subset(idx), tuple((e, f.subset(idx)) for e, f in self.effects), self.stored)

    def with_pose_sigma(self, pose_sigma: NDArray | None) -> "EffectModel":
        return dataclasses.replace(self, geo=self.geo.with_pose_sigma(pose_sigma))

    def without_sensors(self) -> "EffectModel":
        """The same effects on the tool rows alone (a sensor's mounting is no effect's parameter)."""
        if self.geo.sensors is None:
            return self
        return EffectModel(self.geo.without_sensors(), self.effects, self.stored)

    @property
    def theta_start(self) -> NDArray:
        """Where searches start: zero geometry and the stored tables' values (each effect's prior mean where none is stored).

        Not the prior mean: there a product of parameters (a mass times its
        compliances) has no gradient (:attr:`EffectParam.start`).
        """
        kept = {s.name: dict(s.values) for s in self.stored}
        eta = [kept.get(name, {}).get(p.name, p.prior_mean) for name, p in zip(self.machine.effect_names, self.machine.params)]
        return np.concatenate([np.zeros(self.machine.n_base), eta])

    def stored_effects(self, theta: ArrayLike) -> tuple[StoredEffect, ...]:
        """The ``[effect.*]`` tables at the effect parameters of ``theta`` (settings and sources of :attr:`stored`)."""
        return self.machine.tables(theta)


def _not_refittable(eff: Effect) -> str | None:
    """Why a stored table of ``eff`` cannot be refitted from a machine file alone (None: it can)."""
    if eff.geometry_dependent:
        # every command applies a table's dq at the file's geometry (bayescal.effects.stored); a joint fit
        # evaluates it at the fitted geometry, so what it wrote would predict otherwise than what it fitted
        return ("its actuator displacement depends on the geometry, and a machine file's table is applied at the "
                "file's geometry; refit it with bayescal diagnose")
    if type(eff).refine is not Effect.refine:
        # the prior of such an effect (a screw's pitch) comes from the diagnosis' search on the residuals,
        # which the table does not keep
        return "its prior comes from the diagnosis' search of the residuals, which a table does not keep; refit it with bayescal diagnose"
    return None


def effect_model(machine: Machine, rec, *, dof: int | None = None) -> EffectModel:
    """The joint model of a recording on a machine whose file carries ``[effect.*]`` tables.

    Parameters
    ----------
    machine : Machine
        The machine as the recording's model sees it (possibly a fitted
        instrument frame around the file's machine), with the stored effects
        (``machine.effects``); they become unknowns under their library priors.
    rec : Recording
        A pose recording (docs/formats.md section 2).
    dof : int, optional
        As in :meth:`MeasurementModel.from_recording`.

    Returns
    -------
    EffectModel
        Searches start at the stored values (:attr:`EffectModel.theta_start`).
    """

    if not machine.effects:
        raise InputError(f"{machine.source}: the machine file has no [effect.*] tables to fit")
    geo = MeasurementModel.from_recording(machine.with_effects(()), rec, dof=dof)
    aux = dict(rec.aux)
    q = geo.q
    # features where the stored effects are applied (MeasurementModel.from_recording): loads and growth
    # live in the base frame, so a machine seen from an instrument frame is evaluated on its base machine
    if machine.framed:
        fm = machine.base_machine().with_effects(())
        poses = fm.forward(q, None)
    else:
        fm = geo.machine
        poses = fm.forward(q, None, guess=geo.guess)
    poses = poses if poses.success.all() else None
    effects = []
    for st in machine.effects:
        eff = st.effect()
        why = eff.not_applicable(fm, aux) or _not_refittable(eff)
        if why is not None:
            raise InputError(f"{st.source}: [{st.key()}] cannot be fitted to {rec.path}: {why}")
        if eff.needs_poses and poses is None:
            raise InputError(f"{st.source}: [{st.key()}] needs every pose of {rec.path} solved at the nominal geometry")
        f = eff.features(fm, q, np.zeros(fm.n_params), aux, None, poses if eff.needs_poses else None)
        st.vector(tuple(eff.params(fm, f)), f" for {rec.path}")  # the table's parameters are the set this recording calls for
        effects.append((eff, f))
    return EffectModel(geo, tuple(effects), tuple(machine.effects))


def joint_effects_model(model, rec, *, method: str) -> EffectModel:
    """The joint model of geometry and stored effects a fit with ``fit_effects`` (``--fit-effects``) identifies.

    Parameters
    ----------
    model : Model
        The recording's model (its ``fit`` rows), on a machine with ``[effect.*]`` tables.
    rec : Recording or None
        Its recording (``Session.fit_recording``); None for a model given without one.
    method : str
        The identification method: one with a prior (:data:`FIT_EFFECTS_METHODS`).

    Returns
    -------
    EffectModel

    Raises
    ------
    InputError
        Another method, a machine without tables, a constraint recording, no recording.
    """
    if method not in FIT_EFFECTS_METHODS:
        raise InputError(f"fit_effects (--fit-effects) goes with method {' or '.join(FIT_EFFECTS_METHODS)} (the "
                         f"effects' parameters are fitted under their priors), got method {method!r}")
    machine = model.machine
    if not machine.effects:
        raise InputError(f"fit_effects (--fit-effects): {machine.source} has no [effect.*] tables (diagnose "
                         "--write-machine writes them)")
    if not isinstance(model, MeasurementModel):
        where = model.path or "the recording"  # the constraint model's file (grid passes no recording)
        raise InputError(f"fit_effects (--fit-effects): {where} is a constraint recording; fitting effects jointly "
                         "works on pose recordings")
    if rec is None:
        raise InputError("fit_effects: the effects are fitted on a recording: pass what bayescal.load returns")
    return effect_model(machine, rec, dof=model.tool_dof)


def with_fitted_effects(machine: Machine, model, res) -> Machine:
    """``machine`` carrying the effect tables at ``res``'s values when ``model`` fitted them, else as it is."""
    stored = getattr(model, "stored_effects", None)
    if stored is None or res.theta is None:
        return machine
    return machine.with_effects(stored(res.theta))
