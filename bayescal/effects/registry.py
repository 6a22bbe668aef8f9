"""The library of effects by stable name (docs/formats.md section 3): what a machine file's ``[effect.<name>]`` names."""

from __future__ import annotations

from ..constants import EFFECT_NAMES
from ..errors import InputError
from .backlash import Backlash
from .base import Effect
from .gravity_backlash import GravityBacklash
from .gravity_deflection import GravityDeflection
from .joint_compliance import JointCompliance
from .redundancy_preload import RedundancyPreload
from .screw_periodic_error import ScrewPeriodicError
from .thermal_expansion import ThermalExpansion

__all__ = ["EFFECTS", "get_effect"]

_CLASSES: dict[str, type[Effect]] = {
    cls.name: cls for cls in (JointCompliance, ThermalExpansion, Backlash, ScrewPeriodicError, RedundancyPreload,
                              GravityDeflection, GravityBacklash)
}
if set(_CLASSES) != set(EFFECT_NAMES):  # a new effect is also named in bayescal.constants (the command line's help)
    raise ImportError(f"bayescal.constants.EFFECT_NAMES {EFFECT_NAMES} does not name the effect classes {tuple(_CLASSES)}")

#: The library, by stable name (docs/formats.md section 3), in the order they are tried
#: (:data:`bayescal.constants.EFFECT_NAMES`, which the command line lists without importing the effects).
EFFECTS: dict[str, type[Effect]] = {name: _CLASSES[name] for name in EFFECT_NAMES}


def get_effect(name: str, **settings) -> Effect:
    """An effect of the library by its name, with default settings unless given.

    Parameters
    ----------
    name : str
    **settings
        The effect's inputs (its constructor's keyword arguments, e.g.
        ``gravity=[0, 0, -1]`` for ``joint_compliance``); unknown keys are an
        :class:`~bayescal.errors.InputError`.
    """
    if name not in EFFECTS:
        raise InputError(f"unknown effect {name!r}; expected one of: {', '.join(EFFECTS)}")
    cls = EFFECTS[name]
    bad = sorted(set(settings) - set(cls.settings_keys))
    if bad:
        allowed = ", ".join(cls.settings_keys) or "none"
        raise InputError(f"effect {name}: unknown setting(s) {', '.join(bad)}; expected some of: {allowed}")
    return cls(**settings)
