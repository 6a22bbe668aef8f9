"""``identify --fit-effects``: the machine file's effects become unknowns (:mod:`bayescal.effects.joint_model`)."""

from __future__ import annotations

__all__ = ["joint_effects_model"]


def joint_effects_model(args, machine, rec, model):
    """The joint model of geometry and stored effects for ``--fit-effects`` (the library's checks and messages)."""
    from ..effects.joint_model import joint_effects_model as _joint_effects_model

    return _joint_effects_model(model, rec, method=args.method)
