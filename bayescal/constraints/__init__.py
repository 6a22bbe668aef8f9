"""Recordings of measured relations (docs/formats.md section 6): heights, distances and ballbar radii.

:mod:`.model` is their measurement model (with the ballbar pivots fitted as
nuisance); :mod:`.simulate` draws such recordings from a machine.  The file
format is read by :mod:`bayescal.io.constraints`.
"""

from .model import PIVOT_TOLERANCE, ConstraintModel, ConstraintPrediction, PivotAugmented, load_constraint_model

__all__ = ["ConstraintModel", "ConstraintPrediction", "PivotAugmented", "PIVOT_TOLERANCE", "load_constraint_model"]
