"""Machine-file tables shared by every kind: measurement, workspace, tolerance."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..io.machine_file import TomlTable, format_toml_value, toml_key
from ..limits import sigma_problem
from .base import MeasurementNoise
from .tolerance import is_parameter_key

__all__ = ["read_noise", "read_q_limits", "read_tolerance", "common_toml"]


def read_noise(doc: TomlTable) -> MeasurementNoise:
    """The optional ``[measurement]`` table.

    ``sigma_position`` (mm) and ``sigma_angle`` (rad): the instrument;
    ``sigma_tilt`` (rad, per tilt angle), ``sensor_mount``, ``sensor_turn`` and
    ``base_level`` (rad, one-sigma tolerances of a mounting's tilts and turn
    and of the base's level): body sensors (docs/formats.md section 8).
    """
    t = doc.table("measurement", required=False)
    if t is None:
        return MeasurementNoise()
    t.reject_unknown({"sigma_position", "sigma_angle", "sigma_tilt", "sensor_mount", "sensor_turn", "base_level"})
    d = MeasurementNoise()
    sp = t.number("sigma_position", d.sigma_position, positive=True)
    sa = t.number("sigma_angle", d.sigma_angle, positive=True)
    st = t.number("sigma_tilt", d.sigma_tilt, positive=True)
    sm = t.number("sensor_mount", d.sensor_mount, positive=True)
    sturn = t.number("sensor_turn", d.sensor_turn, positive=True)
    level = t.number("base_level", d.base_level, positive=True)
    # a stated noise outside the plausible range (bayescal.limits) would whiten residuals into overflow
    for key, value, kind in (("sigma_position", sp, "position"), ("sigma_angle", sa, "angle"), ("sigma_tilt", st, "angle")):
        if (problem := sigma_problem(value, kind)) is not None:
            raise t.error(key, problem)
    for key, value in (("sensor_mount", sm), ("sensor_turn", sturn), ("base_level", level)):
        if value > 1.0:
            raise t.error(key, f"expected a one-sigma mounting tolerance of at most 1 rad (the mounting is started "
                          f"from the data; this is what remains), got {value!r}")
    return MeasurementNoise(sigma_position=sp, sigma_angle=sa, given=True, sigma_tilt=st, sensor_mount=sm,
                            sensor_turn=sturn, base_level=level)


def read_q_limits(doc: TomlTable, n_actuators: int) -> NDArray | None:
    """The optional ``[workspace] q_limits``: one ``[min, max]`` per actuator."""
    t = doc.table("workspace", required=False)
    if t is None:
        return None
    t.reject_unknown({"q_limits"})
    lim = t.matrix("q_limits", n_actuators, 2)
    bad = np.flatnonzero(lim[:, 0] >= lim[:, 1])
    if bad.size:
        raise t.error("q_limits", f"actuator q{bad[0] + 1}: expected min < max, got {lim[bad[0]].tolist()}")
    return lim


def read_tolerance(doc: TomlTable, defaults: dict[str, float]) -> dict[str, float]:
    """One-sigma tolerances from the optional ``[tolerance]`` table (mm or rad).

    Keys are the parameter groups (``defaults``' keys; missing ones take the
    documented defaults) and, overriding its group's for one parameter, a
    parameter's name: quoted (``"chain2.link_length" = 0.5``) or not (TOML
    reads ``chain2.link_length = 0.5`` as a nested table, flattened here).
    Whether a parameter key names a parameter of the machine is checked when
    the machine is built (:func:`bayescal.machines.tolerance.tolerance_vector`).
    """
    t = doc.table("tolerance", required=False)
    values = dict(defaults)
    if t is not None:
        for key, table, leaf in _tolerance_entries(t, ""):
            if not is_parameter_key(key) and key not in defaults:
                raise t.error(key, f"unknown key; expected one of: {', '.join(sorted(defaults))}, or a parameter's "
                                   f"name (a key with a dot, e.g. \"tool.point.x\" = 0.1)")
            values[key] = table.number(leaf, positive=True)
    return values


def _tolerance_entries(t: TomlTable, stem: str):
    """``(dotted key, table, leaf key)`` of every number in ``t``, nested tables (unquoted dotted keys) flattened."""
    for key in list(t.keys()):
        name = f"{stem}{key}"
        if isinstance(t.data[key], dict):
            yield from _tolerance_entries(t.table(key), f"{name}.")
        else:
            yield name, t, key


def common_toml(machine, tolerance_groups: dict[str, float]) -> str:
    """The [measurement], [workspace] and [tolerance] tables of a machine file."""
    out = []
    if machine.noise.given:
        out += [
            "[measurement]",
            f"sigma_position = {format_toml_value(machine.noise.sigma_position)}",
            f"sigma_angle = {format_toml_value(machine.noise.sigma_angle)}",
        ]
        d = MeasurementNoise()
        for key in ("sigma_tilt", "sensor_mount", "sensor_turn", "base_level"):
            if getattr(machine.noise, key) != getattr(d, key):
                out.append(f"{key} = {format_toml_value(getattr(machine.noise, key))}")
        out.append("")
    if machine.q_limits is not None:
        out += ["[workspace]", f"q_limits = {format_toml_value(machine.q_limits)}", ""]
    if tolerance_groups:
        # a parameter's own tolerance is written with its name quoted (a bare dotted key would be a nested table)
        out += ["[tolerance]"] + [f"{toml_key(k)} = {format_toml_value(v)}"
                                  for k, v in tolerance_groups.items()] + [""]
    return "\n".join(out)
