"""``identify --fit-effects``: the machine file's effects become unknowns (:mod:`bayescal.effects.joint_model`)."""

from __future__ import annotations

from ..errors import InputError
from ..measurement import MeasurementModel

__all__ = ["joint_effects_model", "with_fitted_effects"]

#: Methods with a prior, which the effects' parameters need (their priors decide what the data do not).
FIT_EFFECTS_METHODS = ("map", "mcmc")


def joint_effects_model(args, machine, rec, model):
    """The joint model of geometry and stored effects for ``--fit-effects``, with the argument errors named."""
    from ..effects.joint_model import effect_model

    if args.method not in FIT_EFFECTS_METHODS:
        raise InputError(f"--fit-effects goes with --method {' or '.join(FIT_EFFECTS_METHODS)} (the effects' parameters "
                         f"are fitted under their priors), got --method {args.method}")
    if not machine.effects:
        raise InputError(f"--fit-effects: {args.machine} has no [effect.*] tables (diagnose --write-machine writes them)")
    if not isinstance(model, MeasurementModel):
        raise InputError(f"--fit-effects: {args.recording} is a constraint recording; fitting effects jointly works on "
                         "pose recordings")
    return effect_model(model.machine, rec, dof=model.tool_dof)


def with_fitted_effects(machine, model, res):
    """``machine`` carrying the effect tables at ``res``'s values when ``model`` fitted them, else as it is."""
    stored = getattr(model, "stored_effects", None)
    if stored is None or res.theta is None:
        return machine
    return machine.with_effects(stored(res.theta))
