"""Measurement-pose planning by information (docs/planning.md).

Candidate poses within ``q_limits``, their whitened and column-scaled
identification Jacobian blocks, the criteria D, A, E, O1..O5, the
Bayesian expected information gain and I-optimality (expected tool-point
error), greedy selection with rank-k updates and DETMAX-style exchange, and for I the
Frank-Wolfe relaxation: a certified bound on sqrt(E[MSE]) and a rounded design near it, and a
bound for designs of whole poses by branch and bound on orthant counts, and a yes/no search for a design of
whole poses below a threshold (cells split where the relaxed weight lies).  Works for any machine kind through
:class:`bayescal.measurement.MeasurementModel`.
"""

from .bound import DesignMSEBound, design_mse_bound
from .exact_bound import ExactDesignBound, exact_design_bound, orthant_cells
from .exact_decision import ExactDesignDecision, exact_design_below
from .candidates import SCALINGS, CandidateSet, candidate_set_from_jacobian, column_scale, draw_candidates
from .criteria import CRITERIA, PRIOR_BASED, SPECTRAL, check_criterion, criteria_from_singular_values, criterion_value
from .criteria import i_value, output_weight, utility
from .plan import METHODS, PosePlan, default_method, evaluate_selection, plan_poses, plan_to_csv, relaxed_select
from .plan import root_expected_mse, select_from_candidates, write_plan
from .rounding import design_mse, local_search, round_weights
from .select import Selection, brute_force_greedy, candidate_gains, exchange_refine, greedy_select

__all__ = [
    "CRITERIA",
    "METHODS",
    "PRIOR_BASED",
    "SPECTRAL",
    "SCALINGS",
    "CandidateSet",
    "DesignMSEBound",
    "ExactDesignBound",
    "ExactDesignDecision",
    "PosePlan",
    "Selection",
    "brute_force_greedy",
    "candidate_gains",
    "candidate_set_from_jacobian",
    "check_criterion",
    "column_scale",
    "criteria_from_singular_values",
    "criterion_value",
    "default_method",
    "design_mse",
    "draw_candidates",
    "evaluate_selection",
    "exchange_refine",
    "greedy_select",
    "i_value",
    "local_search",
    "design_mse_bound",
    "exact_design_below",
    "exact_design_bound",
    "orthant_cells",
    "output_weight",
    "plan_poses",
    "plan_to_csv",
    "relaxed_select",
    "root_expected_mse",
    "round_weights",
    "select_from_candidates",
    "utility",
    "write_plan",
]
