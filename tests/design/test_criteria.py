"""Criteria on Jacobians with known singular values, and the rank-k gains against direct recomputation."""

import numpy as np
import pytest

from bayescal.design import CRITERIA, candidate_gains, check_criterion, criteria_from_singular_values, criterion_value, utility
from bayescal.design import i_value, output_weight
from bayescal.design.criteria import eig_value
from bayescal.errors import InputError


def diag_jacobian(s, extra_rows=2):
    """A Jacobian with singular values s: diag(s) over zero rows (rows = len(s) + extra_rows)."""
    return np.vstack([np.diag(s), np.zeros((extra_rows, len(s)))])


def test_criteria_of_a_diagonal_jacobian():
    s = np.array([4.0, 2.0, 1.0])
    J = diag_jacobian(s)  # m = 5 rows
    m = 5
    expected = {
        "D": (4 * 2 * 1) ** (2 / 3),  # det(J^T J)^(1/L) = (16*4*1)^(1/3) = 4
        "A": 3 / (1 / 16 + 1 / 4 + 1),
        "E": 1.0,
        "O1": 8 ** (1 / 3) / np.sqrt(m),  # singular values of J, not of J^T J
        "O2": 1 / 4,
        "O3": 1.0,
        "O4": 1 / 4,
        "O5": 1 / (1 / 4 + 1 / 2 + 1),
    }
    vals = criteria_from_singular_values(np.linalg.svd(J, compute_uv=False), m)
    for k, v in expected.items():
        assert vals[k] == pytest.approx(v, rel=1e-12), k
        assert criterion_value(k, J) == pytest.approx(v, rel=1e-12), k
    assert vals["D"] == pytest.approx(4.0)
    assert eig_value(J) == pytest.approx(0.5 * (np.log(17) + np.log(5) + np.log(2)), rel=1e-12)
    assert criterion_value("EIG", J, A_tol=J) == pytest.approx(eig_value(J))


def test_scaling_the_jacobian_scales_the_criteria_as_defined():
    s = np.array([3.0, 1.5, 0.5, 0.2])
    a = criteria_from_singular_values(s, 10)
    b = criteria_from_singular_values(2 * s, 10)
    # homogeneous degrees: D, A, E ~ s^2; O1, O3, O4, O5 ~ s; O2 scale-free
    for k, deg in {"D": 2, "A": 2, "E": 2, "O1": 1, "O2": 0, "O3": 1, "O4": 1, "O5": 1}.items():
        assert b[k] == pytest.approx(a[k] * 2**deg, rel=1e-12), k


def test_rank_deficient_jacobian_scores_zero_and_eig_stays_finite():
    J = diag_jacobian(np.array([2.0, 1.0, 0.0]))
    vals = criteria_from_singular_values(np.linalg.svd(J, compute_uv=False), J.shape[0])
    assert all(v == 0.0 for v in vals.values())
    assert eig_value(J) == pytest.approx(0.5 * (np.log(5) + np.log(2)))


def test_unknown_criterion_is_an_input_error_listing_the_known_ones():
    assert check_criterion("o4") == "O4"
    with pytest.raises(InputError, match="D, A, E"):
        check_criterion("Z")
    with pytest.raises(InputError, match="A_tol"):
        criterion_value("EIG", np.eye(2))


def test_utilities_agree_with_the_reported_criteria():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(12, 4))
    M = A.T @ A
    vals = criteria_from_singular_values(np.linalg.svd(A, compute_uv=False), 12)
    assert utility("D", M) == pytest.approx(4 * np.log(vals["D"]))
    assert utility("A", M) == pytest.approx(-4 / vals["A"])
    for k in ("E", "O2", "O3", "O4", "O5"):
        assert utility(k, M) == pytest.approx(vals[k], rel=1e-9), k


@pytest.mark.parametrize("criterion", ["D", "A", "EIG", "E", "O4", "I"])
def test_rank_k_gains_equal_direct_recomputation(criterion):
    rng = np.random.default_rng(2)
    L, k, N = 5, 3, 40
    blocks = rng.normal(size=(N, k, L))
    A0 = rng.normal(size=(7, L))
    M = A0.T @ A0 + 0.1 * np.eye(L)
    Q = output_weight(rng.normal(size=(30, 3, L))) if criterion == "I" else None
    gains = candidate_gains(blocks, M, criterion, shortlist=N, Q=Q)
    direct = np.array([utility(criterion, M + b.T @ b, Q=Q) - utility(criterion, M, Q=Q) for b in blocks])
    np.testing.assert_allclose(gains, direct, rtol=1e-9, atol=1e-12)
    assert set(CRITERIA) >= {criterion}


def test_i_criterion_of_a_diagonal_problem():
    # A_k = diag(a) (tolerance-scaled), tool-point Jacobians G_e with G^T G averaging to diag(q):
    # Sigma = diag(1 / (1 + a^2)), I = sqrt(sum q / sum q / (1 + a^2))
    a = np.array([3.0, 1.0, 0.0])
    q = np.array([2.0, 8.0, 5.0])
    G = np.zeros((2, 3, 3))
    G[0, 0, 0], G[0, 1, 1], G[1, 2, 2] = np.sqrt(2 * q[0]), np.sqrt(2 * q[1]), np.sqrt(2 * q[2])
    Q = output_weight(G)
    np.testing.assert_allclose(Q, np.diag(q), rtol=1e-14)
    A = diag_jacobian(a)
    expected = np.sqrt(q.sum() / np.sum(q / (1 + a**2)))  # 15 / (0.2 + 4 + 5)
    assert i_value(A, Q) == pytest.approx(expected, rel=1e-12)
    assert criterion_value("I", A, Q=Q) == pytest.approx(expected, rel=1e-12)
    # the selection utility is -trace(Sigma Q) on M = I + A^T A
    assert float(utility("I", np.eye(3) + A.T @ A, Q=Q)) == pytest.approx(-np.sum(q / (1 + a**2)))
    assert i_value(np.zeros((0, 3)), Q) == pytest.approx(1.0)  # no data: the prior, ratio 1
    with pytest.raises(InputError, match="output weight"):
        criterion_value("I", A)
    with pytest.raises(InputError, match="output weight"):
        utility("I", np.eye(3))
