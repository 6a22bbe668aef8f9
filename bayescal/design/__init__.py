"""Measurement-pose planning by information (docs/planning.md).

Candidate poses within ``q_limits``, their whitened and column-scaled
identification Jacobian blocks, the criteria D, A, E, O1..O5, the
Bayesian expected information gain and I-optimality (expected tool-point
error), greedy selection with rank-k updates and DETMAX-style exchange.  Works for any machine kind through
:class:`bayescal.measurement.MeasurementModel`.
"""

from .bound import OutputErrorBound, output_error_bound
from .candidates import SCALINGS, CandidateSet, candidate_set_from_jacobian, column_scale, draw_candidates
from .criteria import CRITERIA, PRIOR_BASED, SPECTRAL, check_criterion, criteria_from_singular_values, criterion_value
from .criteria import i_value, output_weight, utility
from .plan import PosePlan, evaluate_selection, expected_output_rms, plan_poses, plan_to_csv, select_from_candidates
from .plan import write_plan
from .select import Selection, brute_force_greedy, candidate_gains, exchange_refine, greedy_select

__all__ = [
    "CRITERIA",
    "PRIOR_BASED",
    "SPECTRAL",
    "SCALINGS",
    "CandidateSet",
    "OutputErrorBound",
    "PosePlan",
    "Selection",
    "brute_force_greedy",
    "candidate_gains",
    "candidate_set_from_jacobian",
    "check_criterion",
    "column_scale",
    "criteria_from_singular_values",
    "criterion_value",
    "draw_candidates",
    "evaluate_selection",
    "exchange_refine",
    "expected_output_rms",
    "greedy_select",
    "i_value",
    "output_error_bound",
    "output_weight",
    "plan_poses",
    "plan_to_csv",
    "select_from_candidates",
    "utility",
    "write_plan",
]
