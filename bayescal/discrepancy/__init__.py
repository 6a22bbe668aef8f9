"""Model discrepancy: what the kinematic model leaves out, as a smooth function of the inputs (docs/discrepancy.md)."""

from .fit import MIN_EVIDENCE_GAIN, DiscrepancyFit, default_inputs, fit_discrepancy
from .model import OUTPUT_NAMES, Discrepancy, weight_names

__all__ = ["Discrepancy", "DiscrepancyFit", "fit_discrepancy", "default_inputs", "weight_names", "OUTPUT_NAMES",
           "MIN_EVIDENCE_GAIN"]
