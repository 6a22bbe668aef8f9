"""Effects stored in a machine file: ``[effect.<name>]`` tables (docs/formats.md section 7).

A calibrated machine may carry the physical effects found with it, at fixed
values, one table per effect, keyed by the effect's parameter names in the
units of the diagnosis answer::

    [effect.joint_compliance]
    "compliance.q1" = 0.061        # um/N

Everything here goes through the :class:`~bayescal.effects.Effect`
interface (``not_applicable``, ``features``, ``params``, ``delta_q``) and the
registry :data:`bayescal.effects.EFFECTS`: a newly registered effect is read,
written and applied with no code here.

Rules (documented in docs/formats.md section E2):

* an unknown effect name, a parameter the effect does not have, a value
  that is not a finite number, or an effect that cannot act on this machine
  (``redundancy_preload`` on a non-redundant one) is a
  :class:`~bayescal.errors.MachineFileError` naming the file and the key;
* **every parameter of a listed effect must be given** (no default): an
  omitted parameter has no value that means "absent" for every effect (a
  thermal time constant or a screw pitch of 0 is not "no effect"), so a
  partial table is refused with the missing names;
* which parameters an effect has can depend on the recording (thermal
  expansion is parametrised per kelvin with a ``temp_C`` channel, along a
  warm-up curve with ``time_s`` only).  On reading, the keys must form one
  of the parameter sets the effect has for a recording with some of the
  channels :data:`PROBE_CHANNELS`; when applied to a recording they must be
  exactly the set its channels call for.

Application: ``q_actual = q + sum_e delta_q_e(features_e(q, aux, order), eta_e)``
with the features at the machine file's geometry (``theta = 0``), and the
tool poses moved by ``sum_e delta_x_e`` of the effects that move the tool
(:func:`effect_delta_q_and_x`; the measurement models add it after the
kinematics, :func:`bayescal.measurement.offset_poses`).  The
gravity loads of joint compliance change with the identified geometric
corrections by about their relative size (1e-4), which is neglected.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import BayescalError, InputError, MachineFileError
from ..io.machine_file import TomlTable, format_toml_value
from ..limits import AUX_LOWER_BOUNDS
from ..machines.base import Machine, ToolPoses, offset_poses
from .base import Effect, EffectParam
from .registry import EFFECTS, get_effect

__all__ = [
    "StoredEffect", "PROBE_CHANNELS", "read_effect_tables", "effect_tables_toml", "effect_delta_q",
    "static_effect_delta_q", "static_effect_delta_x", "effect_delta_q_jacobian", "effect_delta_q_and_x", "effect_body_rotation", "effect_delta_x_jacobian", "static_effect_delta_q_and_jacobian", "StoredEffectsTransform", "machine_file_text", "parse_aux_values", "predict_poses",
]

#: Auxiliary channels whose presence can change an effect's parameter set (docs/formats.md section 2).
PROBE_CHANNELS = ("time_s", "temp_C", "payload_kg")

#: The machine-file key of the effect tables.
TABLE = "effect"


@dataclass(frozen=True)
class StoredEffect:
    """One ``[effect.<name>]`` table: an effect at fixed parameter values.

    Attributes
    ----------
    name : str
        Registered effect name (:data:`bayescal.effects.EFFECTS`).
    values : tuple of (str, float)
        Parameter name and value, in the parameter's unit, in file order.
    units : tuple of str
        Unit of each value (``""`` when unknown); written as a comment.
    source : str
        The machine file it was read from (named in errors).
    """

    name: str
    values: tuple[tuple[str, float], ...]
    units: tuple[str, ...] = ()
    source: str = "<memory>"
    #: Stated inputs of the effect (``Effect.settings_keys``: e.g. ``gravity`` of joint_compliance), in file order.
    settings: tuple[tuple[str, object], ...] = ()

    def effect(self) -> Effect:
        """The library effect with the table's stated inputs (documented defaults for the others)."""
        return get_effect(self.name, **{k: (np.asarray(v, float) if isinstance(v, (list, tuple)) else v) for k, v in self.settings})

    @staticmethod
    def static_delta_q(machine: Machine, effects: tuple["StoredEffect", ...], q: NDArray, aux: dict | None = None) -> NDArray:
        """:func:`static_effect_delta_q`, reached from a machine's ``effects`` (machines do not import effects)."""
        return static_effect_delta_q(machine, effects, q, aux)

    @staticmethod
    def static_delta_x(machine: Machine, effects: tuple["StoredEffect", ...], q: NDArray, aux: dict | None = None) -> NDArray | None:
        """:func:`static_effect_delta_x`, reached from a machine's ``effects``."""
        return static_effect_delta_x(machine, effects, q, aux)

    def key(self, param: str | None = None) -> str:
        """The dotted machine-file key of the table or of one of its parameters."""
        return f"{TABLE}.{self.name}" + (f'."{param}"' if param is not None else "")

    def vector(self, params: tuple[EffectParam, ...], context: str = "") -> NDArray:
        """The values in the order of ``params``; MachineFileError if the names differ.

        Parameters
        ----------
        params : tuple of EffectParam
            What the effect has for the recording at hand.
        context : str
            Why this parameter set (e.g. which channels the recording has), for the message.
        """
        have = dict(self.values)
        want = [p.name for p in params]
        expected = ", ".join(f"{p.name} ({p.unit})" for p in params)
        extra = [k for k in have if k not in want]
        if extra:
            raise MachineFileError(
                self.source, self.key(extra[0]),
                f"not a parameter of {self.name}{context}; expected exactly: {expected}",
            )
        missing = [k for k in want if k not in have]
        if missing:
            raise MachineFileError(
                self.source, self.key(),
                f"missing parameter(s) {', '.join(missing)} of {self.name}{context}; every parameter must be given: {expected}",
            )
        return np.array([have[k] for k in want], dtype=float)


def _probe_sets(effect: Effect, machine: Machine) -> list[tuple[EffectParam, ...]] | None:
    """The effect's parameter sets over recordings with every subset of :data:`PROBE_CHANNELS`.

    None when they cannot be probed (no ``q_limits`` to place a pose, or the
    home pose does not assemble): names are then checked when applied.
    """
    if machine.q_limits is None:
        return None
    q = np.repeat(machine.home_q()[None, :], 2, axis=0)
    poses = machine.forward(q, None)
    if not poses.success.all():
        return None
    theta = np.zeros(machine.n_params)
    sets: list[tuple[EffectParam, ...]] = []
    errors: list[str] = []
    for k in range(len(PROBE_CHANNELS) + 1):
        for chans in itertools.combinations(PROBE_CHANNELS, k):
            aux = {c: np.array([20.0, 21.0]) for c in chans}
            why = effect.not_applicable(machine, aux)
            if why is not None:
                continue
            try:
                f = effect.features(machine, q, theta, aux, None, poses if effect.needs_poses else None)
                params = tuple(effect.params(machine, f))
            except BayescalError as exc:  # this combination of channels cannot drive it
                errors.append(str(exc))
                continue
            if all(tuple(p.name for p in s) != tuple(p.name for p in params) for s in sets):
                sets.append(params)
    if not sets and errors:
        raise InputError(errors[-1])
    return sets


def _read_one(t: TomlTable, name: str, machine: Machine, path: str) -> StoredEffect:
    key = f"{TABLE}.{name}"
    if name not in EFFECTS:
        raise MachineFileError(path, key, f"unknown effect {name!r}; expected one of: {', '.join(EFFECTS)}")
    raw = t.table(name)
    values: list[tuple[str, float]] = []
    settings: list[tuple[str, object]] = []
    for k in raw.keys():
        v = raw.data[k]
        if k in EFFECTS[name].settings_keys:
            # a stated input (a number, a vector of numbers or a list of vectors), not a fitted parameter
            rows = v if isinstance(v, list) and v and all(isinstance(x, list) for x in v) else [v]
            flat = [x for r in rows for x in (r if isinstance(r, list) else [r])]
            # a link mass may be nan: not known, fitted by the effect
            ok = (lambda x: math.isfinite(x) or math.isnan(x)) if k == "link_mass_kg" else math.isfinite
            if not flat or any(isinstance(x, bool) or not isinstance(x, (int, float)) or not ok(x) for x in flat):
                raise MachineFileError(path, f'{key}."{k}"', f"expected a finite number, a vector of numbers or a list of vectors (an input of {name}), got {v!r}")
            _bounded(path, f'{key}."{k}"', [x for x in flat if not math.isnan(x)])
            settings.append((k, _floats(v)))
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise MachineFileError(path, f'{key}."{k}"', f"expected a finite number (the parameter's value in its unit), got {v!r}")
        _bounded(path, f'{key}."{k}"', [v])
        values.append((k, float(v)))
    try:
        eff = get_effect(name, **{k: (np.asarray(v, float) if isinstance(v, list) else v) for k, v in settings})
    except InputError as exc:
        raise MachineFileError(path, key, str(exc)) from exc
    why = eff.not_applicable(machine, {c: np.zeros(1) for c in PROBE_CHANNELS})
    if why is not None:
        raise MachineFileError(path, key, f"{name} cannot act on this {machine.kind} machine: {why}")
    try:
        sets = _probe_sets(eff, machine)
    except InputError as exc:
        raise MachineFileError(path, key, f"{name} cannot be modelled on this {machine.kind} machine: {exc}") from exc
    units = {}
    if sets is not None:
        if not sets:
            raise MachineFileError(path, key, f"{name} cannot be modelled on this {machine.kind} machine")
        for s in sets:
            units.update({p.name: p.unit for p in s})
        have = [k for k, _ in values]
        for k in have:
            if k not in units:
                raise MachineFileError(
                    path, f'{key}."{k}"',
                    f"not a parameter of {name}; expected " + " or ".join(
                        "{" + ", ".join(f"{p.name} ({p.unit})" for p in s) + "}" for s in sets),
                )
        if not any(set(have) == {p.name for p in s} for s in sets):
            fits = [s for s in sets if set(have) <= {p.name for p in s}]
            if fits:
                missing = [p.name for p in fits[0] if p.name not in have]
                expected = ", ".join(f"{p.name} ({p.unit})" for p in fits[0])
                raise MachineFileError(path, key, f"missing parameter(s) {', '.join(missing)}; every parameter of {name} must be given: {expected}")
            raise MachineFileError(
                path, key, f"parameters of different parametrisations of {name} mixed; expected one of " + " or ".join(
                    "{" + ", ".join(p.name for p in s) + "}" for s in sets),
            )
    return StoredEffect(name, tuple(values), tuple(units.get(k, "") for k, _ in values), path, tuple(settings))


def _bounded(path: str, key: str, values) -> None:
    """Refuse a value beyond :data:`~bayescal.limits.MAX_FILE_NUMBER` in its unit (a typo such as 1e300 um)."""
    from ..limits import file_number_problem

    for x in values:
        if (problem := file_number_problem(float(x))) is not None:
            raise MachineFileError(path, key, problem)


def _floats(v):
    """A number, or (nested) lists of numbers, as floats of the same shape."""
    return [_floats(x) for x in v] if isinstance(v, (list, tuple, np.ndarray)) else float(v)


def _toml_numbers(v) -> str:
    return "[" + ", ".join(_toml_numbers(x) for x in v) + "]" if isinstance(v, (list, tuple, np.ndarray)) else format_toml_value(float(v))


def read_effect_tables(doc: TomlTable, machine: Machine) -> tuple[StoredEffect, ...]:
    """The ``[effect.<name>]`` tables of a machine file (none: an empty tuple).

    Parameters
    ----------
    doc : TomlTable
        The whole machine file.
    machine : Machine
        The machine the file describes (its actuators decide the parameter names).

    Raises
    ------
    MachineFileError
        Naming the file and the key: an unknown effect or parameter, a
        missing parameter, a value that is not a finite number.
    """
    t = doc.table(TABLE, required=False)
    if t is None:
        return ()
    for k in t.keys():
        if not isinstance(t.data[k], dict):
            raise MachineFileError(doc.path, f"{TABLE}.{k}", f"expected a table [{TABLE}.{k}] of parameter values, got {t.data[k]!r}")
    return tuple(_read_one(t, name, machine, doc.path) for name in t.keys())


def effect_tables_toml(effects: tuple[StoredEffect, ...]) -> str:
    """The ``[effect.<name>]`` tables as machine-file text (full float precision, units as comments)."""
    out = []
    for e in effects:
        out.append(f"[{TABLE}.{e.name}]")
        for k, v in e.settings:
            out.append(f"{format_toml_value(k)} = {_toml_numbers(v)}")
        units = e.units or ("",) * len(e.values)
        for (k, v), u in zip(e.values, units):
            line = f"{format_toml_value(k)} = {format_toml_value(float(v))}"
            out.append(f"{line:<40} # {u}" if u else line)
        out.append("")
    return "\n".join(out)


def machine_file_text(machine: Machine, theta=None, effects: tuple[StoredEffect, ...] | None = None) -> str:
    """Machine-file text of ``nominal + theta`` with the effect tables (``machine.effects`` by default).

    What every command that writes a calibrated machine writes, so that a
    machine read with effects is written with them.
    """
    effects = machine.effects if effects is None else effects
    text = machine.to_toml(theta)
    text = text.rstrip("\n") + "\n" + calibration_tables_toml(machine)
    if not effects:
        return text
    # inputs the machine gave implicitly (a URDF's link masses) are written out: the file must stand alone
    effects = tuple(
        dataclasses.replace(e, settings=e.settings + tuple(
            (k, _floats(v)) for k, v in e.effect().implied_settings(machine).items() if k not in dict(e.settings)))
        for e in effects)
    return text.rstrip("\n") + "\n\n" + effect_tables_toml(tuple(effects))


def calibration_tables_toml(machine: Machine) -> str:
    """The ``[discrepancy]`` and ``[calibration]`` tables a calibrated machine carries ("" for none)."""
    parts = []
    if machine.discrepancy is not None:
        from ..discrepancy.table import discrepancy_toml

        parts.append(discrepancy_toml(machine.discrepancy))
    if machine.calibration is not None:
        from ..prediction.record import calibration_toml

        parts.append(calibration_toml(machine.calibration))
    return "".join("\n" + p.rstrip("\n") + "\n" for p in parts)


def _channels(aux: dict) -> str:
    return f" for a recording with channels {', '.join(sorted(aux))}" if aux else " for a recording without auxiliary channels"


def effect_delta_q(
    machine: Machine,
    effects: tuple[StoredEffect, ...],
    q: NDArray,
    aux: dict | None = None,
    *,
    theta: NDArray | None = None,
    order: NDArray | None = None,
    poses: ToolPoses | None = None,
) -> NDArray:
    """Actuator position change of the stored effects, ``sum_e delta_q_e``, shape (n_poses, n_actuators).

    Parameters
    ----------
    machine : Machine
    effects : tuple of StoredEffect
    q : ndarray, shape (n_poses, n_actuators)
        Commanded actuator positions, mm (or rad), in measurement order unless ``order`` is given.
    aux : dict of str to ndarray, optional
        The recording's auxiliary channels.
    theta : ndarray, optional
        Geometry at which the features (loads) are evaluated; the machine file's (zeros) by default.
    order : ndarray of int, optional
        Time rank of each row (rows in measurement order if omitted).
    poses : ToolPoses, optional
        Solved poses at ``q`` and ``theta`` (solved here when an effect needs them and none are given).

    Raises
    ------
    InputError
        The recording lacks a channel an effect needs (naming the machine file's table).
    MachineFileError
        The table's parameters are not the set the recording's channels call for.
    """
    q = machine.check_q(q)
    dq = np.zeros_like(q)
    for _, eff, f, eta in _effect_terms(machine, effects, q, aux, theta, order, poses):
        dq = dq + eff.delta_q(f, eta)
    return dq


def effect_delta_q_and_x(
    machine: Machine,
    effects: tuple[StoredEffect, ...],
    q: NDArray,
    aux: dict | None = None,
    *,
    theta: NDArray | None = None,
    order: NDArray | None = None,
    poses: ToolPoses | None = None,
) -> tuple[NDArray, NDArray | None]:
    """:func:`effect_delta_q` and the stored effects' tool-pose perturbation ``sum_e dx_e``.

    Returns
    -------
    dq : ndarray, shape (n_poses, n_actuators)
    dx : ndarray, shape (n_poses, 6), or None
        Base-frame displacement of the tool point (mm) and small rotation of
        the tool frame (rad) of the effects that move the tool
        (:attr:`Effect.moves_tool`: a structure bending under gravity); None
        when none does.  Arguments and errors as :func:`effect_delta_q`.
    """
    q = machine.check_q(q)
    dq = np.zeros_like(q)
    dx = None
    for _, eff, f, eta in _effect_terms(machine, effects, q, aux, theta, order, poses):
        dq = dq + eff.delta_q(f, eta)
        if eff.moves_tool:
            dx = (0.0 if dx is None else dx) + eff.delta_x(f, eta)
    return dq, dx


def effect_body_rotation(
    machine: Machine,
    effects: tuple[StoredEffect, ...],
    q: NDArray,
    aux: dict | None = None,
    *,
    theta: NDArray | None = None,
    order: NDArray | None = None,
    poses: ToolPoses | None = None,
) -> dict[str, NDArray]:
    """The stored effects' turn of the bodies that carry tilt sensors in ``aux``, ``{body: (n_poses, 3)}`` rad.

    Base-frame small rotations (:meth:`Effect.body_rotation`) of the effects
    that bend the structure (:attr:`Effect.bends_bodies`), summed; empty when
    none does.  Arguments and errors as :func:`effect_delta_q`.
    """
    q = machine.check_q(q)
    out: dict[str, NDArray] = {}
    if not any(st.effect().bends_bodies for st in effects):
        return out
    for _, eff, f, eta in _effect_terms(machine, effects, q, aux, theta, order, poses):
        if eff.bends_bodies:
            for body, w in eff.body_rotation(f, eta).items():
                out[body] = out[body] + w if body in out else w
    return out


def effect_delta_x_jacobian(
    machine: Machine,
    effects: tuple[StoredEffect, ...],
    q: NDArray,
    aux: dict | None = None,
    *,
    theta: NDArray | None = None,
    order: NDArray | None = None,
    poses: ToolPoses | None = None,
) -> NDArray:
    """``d (sum_e dx_e) / d eta`` at the tables' values, shape (n_poses, 6, K), columns as :func:`effect_delta_q_jacobian`."""
    q = machine.check_q(q)
    cols = [eff.delta_x_jacobian(f, eta) if eff.moves_tool else np.zeros((q.shape[0], 6, len(eta)))
            for _, eff, f, eta in _effect_terms(machine, effects, q, aux, theta, order, poses)]
    return np.concatenate(cols, axis=2) if cols else np.zeros((q.shape[0], 6, 0))


def effect_delta_q_jacobian(
    machine: Machine,
    effects: tuple[StoredEffect, ...],
    q: NDArray,
    aux: dict | None = None,
    *,
    theta: NDArray | None = None,
    order: NDArray | None = None,
    poses: ToolPoses | None = None,
) -> NDArray:
    """``d (sum_e delta_q_e) / d eta`` at the tables' values, shape (n_poses, n_actuators, K).

    ``K`` counts every table's parameters, tables in order, each table's
    parameters in the effect's order (:meth:`Effect.params`); analytic
    (:meth:`Effect.delta_q_jacobian`).  Arguments and errors as
    :func:`effect_delta_q`.
    """
    q = machine.check_q(q)
    cols = [eff.delta_q_jacobian(f, eta) for _, eff, f, eta in _effect_terms(machine, effects, q, aux, theta, order, poses)]
    return np.concatenate(cols, axis=2) if cols else np.zeros(q.shape + (0,))


def _effect_terms(machine: Machine, effects, q: NDArray, aux, theta, order, poses):
    """Per stored table: ``(table, effect, features, values)`` for the poses ``q``, every check of :func:`effect_delta_q` made."""
    aux = {} if aux is None else dict(aux)
    theta = np.zeros(machine.n_params) if theta is None else np.asarray(theta, float)
    for st in effects:
        eff = st.effect()
        why = eff.not_applicable(machine, aux)
        if why is not None:
            raise InputError(f"{st.source}: [{st.key()}] cannot be applied{_channels(aux)}: {why}")
        if eff.needs_poses and poses is None:
            poses = machine.forward(q, theta)
        try:
            f = eff.features(machine, q, theta, aux, order, poses if eff.needs_poses else None)
        except InputError as exc:
            raise InputError(f"{st.source}: [{st.key()}] cannot be applied{_channels(aux)}: {exc}") from exc
        try:
            eta = st.vector(tuple(eff.params(machine, f)), _channels(aux))
        except MachineFileError as exc:
            need = _channels_for_table(st, eff, machine, q, theta, aux, order, poses)
            if need is None:
                raise
            # the table's parameter set is that of a recording with other channels: say which to give
            raise MachineFileError(
                st.source, st.key(),
                f"parametrised for a recording with channel(s) {', '.join(need)}; it cannot be applied{_channels(aux)}: "
                f"record {', '.join(need)} (for a compensation grid: " + " ".join(f"--aux {c}=VALUE" for c in need)
                + ("; payload_kg=0 is no payload" if "payload_kg" in need else "") + ")",
            ) from exc
        yield st, eff, f, eta


def _channels_for_table(st: StoredEffect, eff: Effect, machine: Machine, q, theta, aux: dict, order, poses) -> list[str] | None:
    """The fewest :data:`PROBE_CHANNELS` missing from ``aux`` whose presence gives the table's parameter set (None: none do)."""
    have = {k for k, _ in st.values}
    missing = [c for c in PROBE_CHANNELS if c not in aux]
    n = q.shape[0]
    for k in range(1, len(missing) + 1):
        for chans in itertools.combinations(missing, k):
            trial = {**aux, **{c: np.full(n, 20.0) for c in chans}}
            if eff.not_applicable(machine, trial) is not None:
                continue
            try:
                f = eff.features(machine, q, theta, trial, order, poses if eff.needs_poses else None)
                names = {p.name for p in eff.params(machine, f)}
            except BayescalError:
                continue
            if names == have:
                return list(chans)
    return None


def predict_poses(machine: Machine, q: NDArray, aux: dict | None = None, *, theta=None, order: NDArray | None = None) -> ToolPoses:
    """Tool poses the machine reaches at commanded ``q``, with its stored effects applied.

    The library's prediction of a calibrated machine (geometry plus
    ``[effect.*]`` tables) for a recording's poses and channels:
    ``forward(q + sum_e dq_e, theta)``, moved by ``sum_e dx_e`` of the
    effects that move the tool.  Without effects this is
    ``machine.forward(q, theta)``.

    Parameters
    ----------
    machine : Machine
    q : ndarray, shape (n_poses, n_actuators)
        Commanded actuator positions (measurement order unless ``order``).
    aux : dict of str to ndarray, optional
        Auxiliary channels of the poses.
    theta : ndarray, optional
        Geometric errors on top of the machine file's geometry (zeros).
    order : ndarray of int, optional
        Time rank of each row.
    """
    q = machine.check_q(q)
    if not machine.effects:
        return machine.forward(q, theta)
    dq, dx = effect_delta_q_and_x(machine, machine.effects, q, aux, theta=theta, order=order)
    poses = machine.forward(q + dq, theta)
    if dx is None:
        return poses

    return offset_poses(machine, q + dq, theta, poses, dx)


def static_effect_delta_q(machine: Machine, effects: tuple[StoredEffect, ...], q: NDArray, aux: dict | None = None) -> NDArray:
    """:func:`effect_delta_q` for poses reached without a last move (a compensation grid's nodes).

    A grid node has no measurement order, so effects of the approach
    direction (backlash) or of elapsed time must not read one from the
    order of the nodes.  Each node is evaluated as a session of its own
    (the first pose: unknown approach, no elapsed time).  ``aux`` holds
    constants or per-node arrays.
    """
    return static_effect_delta_q_and_jacobian(machine, effects, q, aux)[0]


def static_effect_delta_q_and_jacobian(machine: Machine, effects: tuple[StoredEffect, ...], q: NDArray,
                                       aux: dict | None = None) -> tuple[NDArray, NDArray]:
    """:func:`static_effect_delta_q` and its derivative in the tables' values, shapes (n, N) and (n, N, K).

    Each node's features are computed once for both; the ``K`` columns are
    ordered as in :func:`effect_delta_q_jacobian`.
    """
    q = machine.check_q(q)
    n = q.shape[0]
    aux_n = {k: np.broadcast_to(np.asarray(v, float), (n,)) for k, v in (aux or {}).items()}
    dq, jac = [np.zeros((0, q.shape[1]))], [np.zeros((0, q.shape[1], sum(len(st.values) for st in effects)))]
    # one session per node: the first pose of a session has no known approach (backlash: the centre of
    # the band) and no elapsed time; a node repeated in one session would keep the previous node's lag
    try:
        for j in range(n):
            terms = list(_effect_terms(machine, effects, q[j : j + 1], {k: v[j : j + 1] for k, v in aux_n.items()},
                                       None, None, None))
            dq.append(sum((eff.delta_q(f, eta) for _, eff, f, eta in terms), np.zeros((1, q.shape[1]))))
            jac.append(np.concatenate([eff.delta_q_jacobian(f, eta) for _, eff, f, eta in terms], axis=2) if terms
                       else np.zeros((1, q.shape[1], 0)))
    except MachineFileError:
        raise  # already names the channels to give
    except InputError as exc:  # a channel the effect needs and that has no default (temp_C): say where it goes
        raise InputError(f"{exc}; a compensation grid takes the channels at its nodes as aux (bayescal grid --aux NAME=VALUE, "
                         f"e.g. --aux temp_C=25)") from exc
    return np.concatenate(dq), np.concatenate(jac)


def static_effect_delta_x(machine: Machine, effects: tuple[StoredEffect, ...], q: NDArray, aux: dict | None = None) -> NDArray | None:
    """The stored effects' base-frame tool-pose perturbation at grid nodes, (n, 6), or None when no effect moves the tool.

    The tool-moving effects (:attr:`Effect.moves_tool`: structures bending
    under gravity) read no measurement order, so the nodes are evaluated
    together.  ``aux`` holds constants or per-node arrays, as for
    :func:`static_effect_delta_q`.
    """
    q = machine.check_q(q)
    n = q.shape[0]
    moving = tuple(st for st in effects if st.effect().moves_tool)
    if not moving:
        return None
    aux_n = {k: np.broadcast_to(np.asarray(v, float), (n,)) for k, v in (aux or {}).items()}
    return effect_delta_q_and_x(machine, moving, q, aux_n)[1]


@dataclass(frozen=True, eq=False)
class StoredEffectsTransform:
    """The stored effects as a :class:`bayescal.simulate.PoseTransform` (simulating a machine that carries them)."""

    machine: Machine
    effects: tuple[StoredEffect, ...]

    def transform(self, q: NDArray, theta: NDArray, aux: dict, order: NDArray) -> tuple[NDArray, NDArray]:
        return q + effect_delta_q(self.machine, self.effects, q, aux, theta=theta, order=order), theta

    def pose_offset(self, q: NDArray, theta: NDArray, aux: dict, order: NDArray) -> NDArray | None:
        """The tables' base-frame tool-pose perturbation at commanded ``q`` (None when no effect moves the tool)."""
        return effect_delta_q_and_x(self.machine, self.effects, q, aux, theta=theta, order=order)[1]


def parse_aux_values(items: list[str] | None) -> dict[str, float]:
    """``["payload_kg=5", "temp_C=25"]`` -> ``{"payload_kg": 5.0, "temp_C": 25.0}`` (the ``--aux NAME=VALUE`` options).

    Values are bounded (:data:`AUX_LOWER_BOUNDS` from below, :data:`~bayescal.limits.AUX_UPPER_BOUNDS` from above,
    other channels :data:`~bayescal.limits.MAX_FILE_NUMBER` in magnitude).
    """
    from ..limits import AUX_UPPER_BOUNDS, MAX_FILE_NUMBER

    out: dict[str, float] = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        name = name.strip()
        try:
            v = float(value)
        except ValueError:
            v = math.nan
        if not sep or not name or not math.isfinite(v):
            raise InputError(f"--aux {item}: expected NAME=VALUE with a finite number, e.g. payload_kg=5 or temp_C=25")
        if name in out:
            raise InputError(f"--aux: channel {name} given twice")
        low = AUX_LOWER_BOUNDS.get(name, -MAX_FILE_NUMBER)
        high = AUX_UPPER_BOUNDS.get(name, MAX_FILE_NUMBER)
        if not low <= v <= high:
            # payload_kg=-1e6 or 1e300 moved the drives off the machine, and the error blamed the grid's --range
            raise InputError(f"--aux {item}: expected {name} from {low:g} to {high:g}")
        out[name] = v
    return out

