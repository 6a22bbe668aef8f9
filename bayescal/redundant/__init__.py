"""Redundantly actuated modules: restrained-deformation physics, error models, relative measurement, step identification."""

from .models import PoseModel, ZeroPosition, applicable_error_model, geometric_error_model, projector_complement
from .physics import PitchCompensation, RestrainedState, TrueModule, internal_force_basis, solve_restrained

__all__ = [
    "PoseModel",
    "ZeroPosition",
    "applicable_error_model",
    "geometric_error_model",
    "projector_complement",
    "PitchCompensation",
    "RestrainedState",
    "TrueModule",
    "internal_force_basis",
    "solve_restrained",
]
