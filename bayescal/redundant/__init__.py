"""Redundantly actuated modules: restrained-deformation physics, error models, relative measurement, step identification.

See docs/redundant.md.
"""

from .models import (
    PoseModel,
    ZeroPosition,
    applicable_error_model,
    geometric_error_model,
    practical_error_model,
    projector_complement,
)
from .physics import PitchCompensation, RestrainedState, TrueModule, internal_force_basis, solve_restrained
from .procedure import Comparison, Evaluation, ProcedureResult, compare_methods, run_procedure
from .relative_io import RelativeRecording, read_relative_recording, write_relative_recording
from .steps import INSTRUMENTS, Instrument, StepResult, anti_disturbance, identify_step, measure_relative

__all__ = [
    "PoseModel",
    "ZeroPosition",
    "applicable_error_model",
    "geometric_error_model",
    "practical_error_model",
    "projector_complement",
    "PitchCompensation",
    "RestrainedState",
    "TrueModule",
    "internal_force_basis",
    "solve_restrained",
    "Comparison",
    "Evaluation",
    "ProcedureResult",
    "compare_methods",
    "run_procedure",
    "RelativeRecording",
    "read_relative_recording",
    "write_relative_recording",
    "INSTRUMENTS",
    "Instrument",
    "StepResult",
    "anti_disturbance",
    "identify_step",
    "measure_relative",
]
