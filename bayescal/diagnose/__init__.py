"""Model-mismatch diagnosis: locate the mismatch, name the missing physics, model it, verify it out of sample."""

from .core import DECISIVE, EXPLAINED_FRACTION, P_MISMATCH, diagnose
from .locate import ChannelDependence, Location, distance_correlation, holm, locate
from .result import Diagnosis, EffectTrial, ParameterValue

__all__ = [
    "diagnose", "Diagnosis", "EffectTrial", "ParameterValue", "locate", "Location", "ChannelDependence",
    "distance_correlation", "holm", "DECISIVE", "P_MISMATCH", "EXPLAINED_FRACTION",
]
