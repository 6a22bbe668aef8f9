"""What every physical effect provides, and the pieces effects share.

An effect is physics the geometric model leaves out.  It acts on the
actuator positions before the forward kinematics, on the tool pose after
it, or on both:

    q_actual = q_commanded + dq(features, eta)
    tool     = forward(q_actual, theta) moved by dx(features, eta)

``dx`` (shape (n_poses, 6): a base-frame displacement of the tool point in
mm, then a small base-frame rotation of the tool frame in rad) is what a
structure does that no joint coordinate describes: a link or a telescopic
column bending under the weight it carries (:attr:`Effect.moves_tool`).
Consumers apply it in one place, the measurement models' per-pose tool
offset (:meth:`bayescal.measurement.MeasurementModel.with_pose_offset`),
rotated into each pose's measurement frame
(:meth:`bayescal.machines.Machine.measurement_rotation`); its Jacobian
``d dx / d eta`` enters the rows through the same map the geometric
parameters go through (``rows_jacobian``).

where ``features`` are per-pose quantities computed once from the recording
(approach direction, temperature, gravity load on each actuator, ...) and
``eta`` are the effect's named parameters.  ``dq`` is linear in ``eta`` for
most effects; its Jacobian ``d dq / d eta`` is analytic and checked against
finite differences by :func:`bayescal.effects.check_effect`.  The measurement
model then sees ``h(q + dq, theta)``, so ``d h / d eta =
(d h / d q) (d dq / d eta)`` with ``d h / d q`` from
:meth:`bayescal.machines.Machine.actuator_jacobian`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from ..machines.base import Machine, ToolPoses

__all__ = ["Effect", "EffectParam", "Features", "BoundEffect", "approach_direction", "measurement_sequence", "NONPHYSICAL_Z"]

#: How many standard deviations beyond its physical bound a fitted parameter may lie before the
#: fit is rejected as non-physical (noise alone crosses 3 sigma in 0.1 % of the parameters).
NONPHYSICAL_Z = 3.0


@dataclass(frozen=True)
class EffectParam:
    """One named effect parameter with its Gaussian prior.

    Attributes
    ----------
    name : str
        Stable name, e.g. ``compliance.q1``.
    unit : str
        Unit of ``value`` (``um/N``, ``um``, ``mm``, ...).
    prior_sd : float
        One-sigma width of the prior, in ``unit``; also the column scale of the fit.
    prior_mean : float
        Centre of the prior, in ``unit`` (zero: no effect).
    lower : float or None
        Physical lower bound, in ``unit`` (a compliance, a dead band, the
        expansion of a screw cannot be negative); None when either sign is
        physical.  A fit that puts the parameter significantly below it is
        not reported as a detection (:meth:`Effect.nonphysical`).
    start : float or None
        Where the fit starts, in ``unit``; None: at ``prior_mean``.  A
        parameter that enters as a product with others (a platform mass
        times compliances) starts off zero, where the product's gradient
        vanishes and Gauss-Newton would crawl out of the saddle or stop in
        it; the start changes no prior, only where the search begins.
    """

    name: str
    unit: str
    prior_sd: float
    prior_mean: float = 0.0
    lower: float | None = None
    start: float | None = None

    @property
    def start_value(self) -> float:
        """The fit's start, in ``unit`` (``start``, else ``prior_mean``)."""
        return self.prior_mean if self.start is None else self.start


@dataclass(frozen=True)
class Features:
    """What an effect needs from the recording, computed once.

    Attributes
    ----------
    per_pose : dict of str to ndarray
        Arrays with the poses on the leading axis (subset with the poses).
    const : dict
        Settings and recording-wide values (the mode, a reference, ...).
    """

    per_pose: dict = field(default_factory=dict)
    const: dict = field(default_factory=dict)

    def subset(self, idx) -> "Features":
        """The features of poses ``idx`` only (cross-validation)."""
        return Features({k: v[idx] for k, v in self.per_pose.items()}, dict(self.const))


def measurement_sequence(order: NDArray | None, n: int) -> NDArray:
    """Row indices in measurement order (``order[i]`` is the time rank of row ``i``)."""
    if order is None:
        return np.arange(n)
    return np.argsort(np.asarray(order), kind="stable")


def approach_direction(q: NDArray, order: NDArray | None = None) -> NDArray:
    """Sign of each actuator's last move, ``sign(q_i[t] - q_i[t-1])`` in measurement order.

    Parameters
    ----------
    q : ndarray, shape (n_poses, n_actuators)
    order : ndarray of int, shape (n_poses,), optional
        Time rank of each row; rows are in measurement order if omitted.

    Returns
    -------
    ndarray, shape (n_poses, n_actuators)
        +1, -1, or 0 for the first pose (the approach is unknown) and for no move.
    """
    seq = measurement_sequence(order, q.shape[0])
    qs = q[seq]
    s = np.zeros_like(qs)
    s[1:] = np.sign(np.diff(qs, axis=0))
    out = np.empty_like(s)
    out[seq] = s
    return out


class Effect(ABC):
    """A physical effect: a named, parametrised change of the actuator positions (and of the tool pose).

    Subclasses set :attr:`name`, :attr:`summary`, :attr:`magnitude_unit` and
    :attr:`default_magnitude`, and implement :meth:`features`,
    :meth:`params`, :meth:`delta_q`, :meth:`delta_q_jacobian` and
    :meth:`simulated_values`; an effect that moves the tool sets
    :attr:`moves_tool` and implements :meth:`delta_x` and
    :meth:`delta_x_jacobian`.  The class docstring states the physics and
    its usual size on machine tools.
    """

    name: ClassVar[str] = ""
    summary: ClassVar[str] = ""
    #: Unit of the ``NAME:magnitude`` given to ``bayescal simulate --effect``.
    magnitude_unit: ClassVar[str] = ""
    default_magnitude: ClassVar[float] = 0.0
    #: Whether :meth:`features` needs the solved poses (then :class:`BoundEffect` solves them).
    needs_poses: ClassVar[bool] = False
    #: Whether the diagnosis computes the features at the nominal geometry rather than at its geometry-only
    #: fit.  That fit absorbs what it can of a missing effect; an effect whose features are sensitive to
    #: exactly that part of the geometry (a column's bending is driven by the angle between gravity and the
    #: column, which a geometry-only fit tilts to mimic the bending) would be biased by it.
    features_at_nominal: ClassVar[bool] = False
    #: Inputs a user may state (constructor keywords, documented defaults in the class docstring); in a
    #: machine file they sit beside the fitted parameters in the effect's ``[effect.<name>]`` table.
    settings_keys: ClassVar[tuple[str, ...]] = ()

    def confound_note(self) -> str:
        """What part of the effect the geometry cannot be told from, and how a user pins it, or ``""``.

        Reported with the diagnosis when the written geometry is confounded
        with the effect (:mod:`bayescal.diagnose.confound`).
        """
        return ""

    def separating_conditions(self, aux: dict) -> tuple:
        """Second sessions under changed conditions that drive the effect, or ``()``.

        Each is a :class:`bayescal.effects.conditions.Condition`; the
        diagnosis weighs them by how much they would shrink the written
        geometry's uncertainty (:mod:`bayescal.diagnose.separate`).

        Parameters
        ----------
        aux : dict of str to ndarray
            The recording's channels.
        """
        return ()

    def model_note(self, features: Features) -> str:
        """What the model took as known or left out for these features, for the diagnosis' trial note, or ``""``."""
        return ""

    def implied_settings(self, machine: Machine) -> dict:
        """Inputs the machine file gives implicitly (a URDF's link masses), to be written out with the effect, or ``{}``.

        A calibrated machine file must predict alone: what the effect read
        from elsewhere (a URDF the written file no longer names) is written
        into its ``[effect.<name>]`` table as stated inputs.
        """
        return {}

    def not_applicable(self, machine: Machine, aux: dict) -> str | None:
        """Why the effect cannot be modelled for this machine and recording, or None."""
        return None

    def min_poses(self, n_params: int) -> int:
        """Fewest poses with which the effect's ``n_params`` parameters are worth fitting."""
        return max(12, 4 * n_params)

    @abstractmethod
    def features(
        self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order: NDArray | None, poses: ToolPoses | None
    ) -> Features:
        """Per-pose quantities the effect depends on (see :class:`Features`)."""

    @abstractmethod
    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        """The named parameters (their number may depend on the features' mode)."""

    @abstractmethod
    def delta_q(self, features: Features, eta: NDArray) -> NDArray:
        """Actuator position change ``dq``, shape (n_poses, n_actuators), mm (or rad)."""

    @abstractmethod
    def delta_q_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        """``d dq / d eta``, shape (n_poses, n_actuators, n_params)."""

    #: Whether the effect also moves the tool pose after the kinematics (:meth:`delta_x`); consumers
    #: skip the tool offset of effects that do not.
    moves_tool: ClassVar[bool] = False

    def delta_x(self, features: Features, eta: NDArray) -> NDArray:
        """Tool-pose perturbation ``dx``, shape (n_poses, 6): base-frame displacement of the tool point (mm), then a small base-frame rotation of the tool frame (rad).

        Zero unless :attr:`moves_tool`.  First order: the measured tool
        point is ``p + dx[:3]`` and the measured orientation
        ``exp([dx[3:]]x) R``.
        """
        n = next(iter(features.per_pose.values())).shape[0] if features.per_pose else 0
        return np.zeros((n, 6))

    def delta_x_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        """``d dx / d eta``, shape (n_poses, 6, n_params)."""
        dx = self.delta_x(features, eta)
        return np.zeros(dx.shape + (len(np.asarray(eta)),))

    #: Whether the effect also turns bodies that carry tilt sensors (:meth:`body_rotation`): a member that
    #: bends turns every body beyond it, and a sensor on one of them reads that turn.
    bends_bodies: ClassVar[bool] = False

    def body_rotation(self, features: Features, eta: NDArray) -> dict[str, NDArray]:
        """Small base-frame rotation of every sensor-carrying body the effect turns, ``{body: (n_poses, 3)}`` rad.

        First order, like :meth:`delta_x`: the body's orientation is
        ``exp([w]x) R``.  Bodies the effect does not turn are left out
        (empty unless :attr:`bends_bodies`).
        """
        return {}

    def body_rotation_jacobian(self, features: Features, eta: NDArray) -> dict[str, NDArray]:
        """``d w / d eta`` per body of :meth:`body_rotation`, ``{body: (n_poses, 3, n_params)}``."""
        return {}

    #: Whether ``dq`` also depends on the geometric errors ``theta`` being fitted (then the effect overrides
    #: :meth:`delta_q_at`, :meth:`delta_q_jacobian_at` and :meth:`delta_q_theta_jacobian`, and
    #: :meth:`delta_q` is ``dq`` at the geometry its features were computed at).
    geometry_dependent: ClassVar[bool] = False

    def delta_q_at(self, features: Features, eta: NDArray, theta: NDArray) -> NDArray:
        """``dq`` at geometric errors ``theta`` ((P,) or (n_poses, P)); :meth:`delta_q` unless :attr:`geometry_dependent`.

        A geometry-dependent effect (the restrained preload of a redundant
        module, driven by the incompatibility the geometry leaves) changes
        with the geometry a fit is moving; consumers that fit the geometry
        (:func:`bayescal.effects.fit_map`) call this form.
        """
        return self.delta_q(features, eta)

    def delta_q_jacobian_at(self, features: Features, eta: NDArray, theta: NDArray) -> NDArray:
        """``d dq / d eta`` at geometric errors ``theta``, shape (n_poses, n_actuators, n_params)."""
        return self.delta_q_jacobian(features, eta)

    def delta_q_theta_jacobian(self, features: Features, eta: NDArray, theta: NDArray) -> NDArray | None:
        """``d dq / d theta``, shape (n_poses, n_actuators, P), or None when ``dq`` does not depend on ``theta``."""
        return None

    @abstractmethod
    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng: np.random.Generator) -> NDArray:
        """Parameter values of a simulated machine whose effect has size ``magnitude``."""

    def refine(self, features: Features, q: NDArray, dq_residual: NDArray) -> Features:
        """Features with data-driven settings (e.g. a start pitch from a periodogram); unchanged by default.

        Parameters
        ----------
        q : ndarray, shape (n_poses, n_actuators)
        dq_residual : ndarray, shape (n_poses, n_actuators)
            The geometric fit's residual mapped to actuator space (mm).
        """
        return features

    def inadmissible(self, features: Features, eta: NDArray | None = None) -> str | None:
        """Why the effect (with fitted parameters ``eta``, if given) cannot be the explanation, or None.

        Checked by the diagnosis after :meth:`refine` (``eta`` None) and after
        each fit; e.g. a periodic error whose pitch does not fit twice in the
        recorded stroke.
        """
        return None

    def nonphysical(self, params: tuple[EffectParam, ...], eta: NDArray, std: NDArray) -> str | None:
        """Why the fitted parameters ``eta`` (one-sigma ``std``, as named by ``params``) are physically impossible, or None.

        Default: a parameter with a :attr:`EffectParam.lower` bound lies more
        than :data:`NONPHYSICAL_Z` sigma below it (a negative compliance, a
        negative dead band).  Such a fit explains the residuals with physics
        that cannot exist, so it is not a detection (the diagnosis skips it
        with this reason).  Checked on every single and combined fit.
        """
        eta, std = np.asarray(eta, float), np.asarray(std, float)
        bad = []
        for p, v, s in zip(params, eta, std):
            if p.lower is not None and v < p.lower - NONPHYSICAL_Z * s:
                bad.append(f"{p.name} = {v:.3g} +- {s:.2g} {p.unit} < {p.lower:g}")
        if bad:
            return "non-physical fit: " + "; ".join(bad)
        return None

    def occam_penalty(self, features: Features, q: NDArray) -> float:
        """Extra log-evidence penalty (nats) for parameters chosen by a search (look-elsewhere)."""
        return 0.0

    def bind(self, machine: Machine, values, *, hidden_aux: dict | None = None) -> "BoundEffect":
        """This effect with parameter values: a :class:`bayescal.simulate.PoseTransform`."""
        return BoundEffect(self, machine, np.asarray(values, dtype=float), dict(hidden_aux or {}))


@dataclass(frozen=True, eq=False)
class BoundEffect:
    """An effect with fixed parameter values, usable by :func:`bayescal.simulate.simulate_recording`.

    ``hidden_aux`` holds channels that drive the physics but are not
    recorded (the true temperature of a recording that only logs time).
    """

    effect: Effect
    machine: Machine
    values: NDArray
    hidden_aux: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.effect.name

    def features(self, q: NDArray, theta: NDArray, aux: dict, order: NDArray | None) -> Features:
        aux_all = {**self.hidden_aux, **(aux or {})}
        poses = self.machine.forward(q, theta) if self.effect.needs_poses else None
        return self.effect.features(self.machine, q, theta, aux_all, order, poses)

    def transform(self, q: NDArray, theta: NDArray, aux: dict, order: NDArray) -> tuple[NDArray, NDArray]:
        """``(q + dq, theta)``: the :class:`bayescal.simulate.PoseTransform` protocol."""
        f = self.features(q, theta, aux, order)
        return q + self.effect.delta_q(f, self.values), theta

    def pose_offset(self, q: NDArray, theta: NDArray, aux: dict, order: NDArray) -> NDArray | None:
        """The effect's base-frame tool-pose perturbation ``dx`` at commanded ``q`` (n, 6), or None when it moves no tool.

        The optional part of :class:`bayescal.simulate.PoseTransform`: the
        simulator adds it to the solved poses.
        """
        if not self.effect.moves_tool:
            return None
        return self.effect.delta_x(self.features(q, theta, aux, order), self.values)
