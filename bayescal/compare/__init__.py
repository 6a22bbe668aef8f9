"""Statistical comparison of identification methods, in-process or distributed (docs/compare.md)."""

from .methods import METHODS, Method, MethodSpec, parse_methods, register_method, tsvd_snr_rank
from .result import Comparison, compare_methods, comparison_from_records
from .runner import load_trials, run_trials
from .trial import METRICS, CompareConfig, run_trial, trial_rng

__all__ = [
    "METHODS",
    "METRICS",
    "Method",
    "MethodSpec",
    "CompareConfig",
    "Comparison",
    "compare_methods",
    "comparison_from_records",
    "load_trials",
    "parse_methods",
    "register_method",
    "run_trial",
    "run_trials",
    "trial_rng",
    "tsvd_snr_rank",
]
