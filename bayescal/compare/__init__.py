"""Statistical comparison of identification methods, in-process or distributed (docs/compare.md).

Called, ``bayescal.compare(machine, methods="ls,ridge,tsvd", trials=500, recording=None, dof=None, poses=None,
alpha=0.05, out=None, seed=0, workers=...)`` is the front door's verb :func:`bayescal.api.compare`
(:func:`~bayescal.compare.verb.compare_files`; its docstring documents the options, and an unknown one is refused
by name).
"""

from .methods import METHODS, Method, MethodSpec, parse_methods, register_method, tsvd_snr_rank
from .result import Comparison, compare_methods, comparison_from_records
from .runner import load_trials, run_trials
from .trial import METRICS, CompareConfig, run_trial, trial_rng
from .verb import compare_files, write_comparison_folder

__all__ = [
    "METHODS",
    "METRICS",
    "Method",
    "MethodSpec",
    "CompareConfig",
    "Comparison",
    "compare_methods",
    "compare_files",
    "write_comparison_folder",
    "comparison_from_records",
    "load_trials",
    "parse_methods",
    "register_method",
    "run_trial",
    "run_trials",
    "trial_rng",
    "tsvd_snr_rank",
]


class _CallablePackage(type(__import__("sys"))):
    """``bayescal.compare`` is this package and, called, the front door's verb (:func:`bayescal.api.compare`).

    Importing a submodule sets the package as the parent's attribute, so a
    function ``bayescal.compare`` could not live beside the package; calling
    the package instead does what the verb does (a path or a machine in).
    """

    def __call__(self, machine, **options):
        return compare_files(machine, **options)


__import__("sys").modules[__name__].__class__ = _CallablePackage
