"""Simulated recordings with concealed physical effects and auxiliary channels."""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..machines.base import Machine
from ..simulate import SimulatedRecording, draw_errors, draw_poses, measure
from .registry import get_effect
from .thermal_expansion import warmup_temperature

__all__ = ["AUX_CHANNELS", "simulate_aux", "parse_effect_spec", "simulate_with_effects"]

#: Channels ``bayescal simulate --aux`` can record.
AUX_CHANNELS = ("time_s", "temp_C", "payload_kg")


def simulate_aux(n_poses: int, rng: np.random.Generator) -> dict[str, NDArray]:
    """Every auxiliary channel of a simulated session.

    ``time_s``: 20-40 s per pose; ``temp_C``: a warm-up from 20 degC by
    5 K with a 25-minute time constant plus 0.02 K sensor noise;
    ``payload_kg``: a tool/workpiece mass of 0-25 kg, changed between poses.
    """
    t = np.cumsum(rng.uniform(20.0, 40.0, n_poses)) - 30.0
    t -= t[0]
    temp = warmup_temperature(t) + rng.normal(0.0, 0.02, n_poses)
    payload = rng.choice(np.arange(0.0, 26.0, 5.0), n_poses)
    return {"time_s": t, "temp_C": temp, "payload_kg": payload}


def parse_effect_spec(spec: str) -> tuple[str, float]:
    """``NAME[:magnitude]`` -> (name, magnitude); the effect's default magnitude if omitted."""
    from ..limits import MAX_FILE_NUMBER

    name, colon, mag = spec.partition(":")
    eff = get_effect(name.strip())
    if not colon:
        return eff.name, eff.default_magnitude
    try:
        value = float(mag)
    except ValueError:
        # 'backlash:' (nothing after the colon) took the default silently
        raise InputError(f"--effect {spec}: expected NAME[:magnitude] with a number in {eff.magnitude_unit}") from None
    if not np.isfinite(value) or not 0 <= value <= MAX_FILE_NUMBER:
        # 1e300 um of backlash was simulated and written into the truth
        raise InputError(f"--effect {spec}: expected a magnitude from 0 to {MAX_FILE_NUMBER:g} ({eff.magnitude_unit})")
    return eff.name, value


def simulate_with_effects(
    machine: Machine,
    n_poses: int,
    *,
    seed: int,
    dof: int = 6,
    effects: Sequence[tuple[str, float]] = (),
    record: Sequence[str] = (),
    tolerance: NDArray | None = None,
    extra: Sequence = (),
) -> SimulatedRecording:
    """A recording of a machine with drawn errors and concealed effects.

    Parameters
    ----------
    machine : Machine
    n_poses : int
    seed : int
    dof : {6, 5, 3}
    effects : sequence of (name, magnitude)
        Library effects at a magnitude in their ``magnitude_unit``.
    record : sequence of str
        Auxiliary channels to write into the recording (subset of
        :data:`AUX_CHANNELS`); the physics is driven by all of them
        (temperature still rises when it is not recorded), except
        ``payload_kg``, which is zero when not recorded.
    tolerance : ndarray, optional
        One-sigma geometric errors (the machine's by default).
    extra : sequence of PoseTransform
        Further transforms (physics outside the library).

    Returns
    -------
    SimulatedRecording
        ``info["effects"]`` holds the true parameter values by name.
    """
    bad = [c for c in record if c not in AUX_CHANNELS]
    if bad:
        raise InputError(f"--aux: unknown channel(s) {', '.join(bad)}; expected some of {', '.join(AUX_CHANNELS)}")
    if len(set(record)) != len(record):
        raise InputError(f"--aux: a channel given more than once ({','.join(record)}); expected each channel once")
    if n_poses < 2:
        raise InputError(f"n_poses: expected at least 2, got {n_poses}")
    names = [name for name, _ in effects]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        # 'backlash --effect backlash:2' simulated one of them, silently
        raise InputError(f"--effect {twice[0]}: given more than once; expected each effect once, with one magnitude")
    rng = np.random.default_rng(seed)
    theta = draw_errors(machine, rng, tolerance=tolerance)
    q = draw_poses(machine, n_poses, rng, theta)
    full = simulate_aux(n_poses, rng)
    recorded = {c: full[c] for c in AUX_CHANNELS if c in record}
    hidden = {k: v for k, v in full.items() if k != "payload_kg" and k not in recorded}
    th_rows = np.broadcast_to(theta, (n_poses, machine.n_params))
    bound, info = [], {}
    for name, mag in effects:
        eff = get_effect(name)
        why = eff.not_applicable(machine, {**hidden, **recorded})
        if why:
            raise InputError(f"--effect {name}: {why}")
        aux_f = {**hidden, **recorded}
        if name == "thermal_expansion":
            aux_f = {"temp_C": full["temp_C"]}  # the physics follows the true temperature
        poses = machine.forward(q, th_rows) if eff.needs_poses else None
        feats = eff.features(machine, q, th_rows, aux_f, np.arange(n_poses), poses)
        values = eff.simulated_values(machine, feats, mag, rng)
        # a compliance on drives that carry no load would silently simulate nothing; other effects'
        # admissibility (the screw pitch against the stroke) is about diagnosing, not simulating
        why = eff.inadmissible(feats) if name == "joint_compliance" else None
        if mag > 0 and why is not None:
            raise InputError(f"--effect {name}:{mag:g}: has no effect on the {machine.kind} {machine.name!r}: {why}")
        bound.append(eff.bind(machine, values, hidden_aux={"temp_C": full["temp_C"]} if name == "thermal_expansion" else hidden))
        info[name] = {
            "magnitude": mag,
            "parameters": [{"name": p.name, "value": float(v), "unit": p.unit} for p, v in zip(eff.params(machine, feats), values)],
        }
    rec = measure(machine, q, theta, dof, rng, aux=recorded, effects=[*bound, *extra])
    return SimulatedRecording(recording=rec, theta_true=theta, seed=seed, names=machine.layout.names,
                              info={"effects": info, "aux_recorded": list(recorded)})
