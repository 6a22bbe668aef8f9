"""Physical effects beyond the geometric model, as plug-ins to the measurement model.

Adding an effect: one module with an :class:`Effect` subclass, one entry in
:data:`EFFECTS` (``registry.py``) and its name in :data:`bayescal.constants.EFFECT_NAMES`
(the command line lists them without importing the effects), and :func:`check_effect`
must pass for it.
"""

from __future__ import annotations

from .backlash import Backlash
from .base import BoundEffect, Effect, EffectParam, Features, approach_direction
from .check import check_effect
from .gravity_backlash import GravityBacklash
from .gravity_deflection import GravityDeflection
from .joint_compliance import JointCompliance, actuator_loads
from .model import EffectFit, fit_map
from .registry import EFFECTS, get_effect
from .redundancy_preload import RedundancyPreload
from .screw_periodic_error import ScrewPeriodicError
from .thermal_expansion import ThermalExpansion

__all__ = [
    "EFFECTS", "get_effect", "Effect", "EffectParam", "Features", "BoundEffect", "approach_direction",
    "check_effect", "actuator_loads", "EffectFit", "fit_map",
    "JointCompliance", "ThermalExpansion", "Backlash", "ScrewPeriodicError", "RedundancyPreload", "GravityDeflection",
    "GravityBacklash",
]
