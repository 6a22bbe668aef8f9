"""Model discrepancy: what the kinematic model leaves out, as a smooth function of the inputs (docs/discrepancy.md)."""

from .._lazy import lazy_attributes

__all__ = ["Discrepancy", "DiscrepancyFit", "fit_discrepancy", "default_inputs", "weight_names", "OUTPUT_NAMES",
           "MIN_EVIDENCE_GAIN"]

# imported on first use: the fit pulls in scipy.optimize, which a calibration without a discrepancy never needs
__getattr__, __dir__ = lazy_attributes(__name__, {
    "MIN_EVIDENCE_GAIN": ".fit", "DiscrepancyFit": ".fit", "default_inputs": ".fit", "fit_discrepancy": ".fit",
    "OUTPUT_NAMES": ".model", "Discrepancy": ".model", "weight_names": ".model",
})
