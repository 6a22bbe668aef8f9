"""Deterministic identification: Gauss-Newton with LS, ridge (RE) and truncated SVD steps."""

from .gauss_newton import identify, resolve_free, whitened_system
from .result import IdentificationResult, ParameterEstimate
from .solvers import filter_factors, filtered_solve

__all__ = [
    "identify",
    "resolve_free",
    "whitened_system",
    "IdentificationResult",
    "ParameterEstimate",
    "filter_factors",
    "filtered_solve",
]
