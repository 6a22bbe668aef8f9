"""bayescal.tallqr against Householder QR (numpy) on systems of known condition."""

import numpy as np
import pytest

from bayescal import tallqr
from bayescal.tallqr import MAX_CONDITION, ridge_factor


def _system(rng, n, p, cond):
    """An (n, p) matrix with singular values spread log-evenly over ``cond``."""
    U, _ = np.linalg.qr(rng.standard_normal((n, p)))
    V, _ = np.linalg.qr(rng.standard_normal((p, p)))
    return (U * np.logspace(0, np.log10(cond), p)[::-1]) @ V.T


def _householder_r(A, lam, sw):
    """The augmented matrix's R from numpy's Householder QR, signs made positive on the diagonal."""
    aug = np.vstack([A * sw[:, None], np.sqrt(lam) * np.eye(A.shape[1])])
    R = np.linalg.qr(aug, mode="r")
    return R * np.sign(np.diag(R))[:, None]


@pytest.mark.parametrize("cond", [1e2, 1e5, 3e6])
@pytest.mark.parametrize("n", [50, 40_000])  # one block and several (BLOCK_ROWS = 16,384)
def test_factor_matches_householder(cond, n):
    rng = np.random.default_rng(int(cond) + n)
    A = _system(rng, n, 12, cond)
    sw = rng.uniform(0.2, 1.5, n)
    lam = 1.0
    R = ridge_factor(A, lam, sw)
    assert R is not None
    assert np.allclose(np.tril(R, -1), 0.0)
    ref = _householder_r(A, lam, sw)
    # both are backward stable: the factors agree to the round-off times the conditioning
    assert np.max(np.abs(R - ref)) <= 1e-11 * np.abs(ref).max() * max(cond / 1e2, 1.0)
    # and the quantity the pose test needs, a_i (A^T W A + lam I)^-1 a_i^T per row, to round-off (the normal
    # equations' own answer is off by cond^2 eps, 1e-6 at cond 1e5: Householder's R is the reference)
    rows = A[:7]
    lev = np.sum((rows @ np.linalg.inv(R)) ** 2, axis=1)
    ref_lev = np.sum((rows @ np.linalg.inv(ref)) ** 2, axis=1)
    assert np.allclose(lev, ref_lev, rtol=1e-10 * max(cond / 1e3, 1.0), atol=0)


def test_first_pass_error_is_removed_by_the_second():
    # cond 3e6: the Gram matrix's condition is 1e13 and its Cholesky factor alone is off by about 1e-4
    rng = np.random.default_rng(3)
    A = _system(rng, 2000, 10, 3e6)
    lam = 1.0
    ref = _householder_r(A, lam, np.ones(2000))
    R1 = np.linalg.cholesky(A.T @ A + lam * np.eye(10)).T
    R = ridge_factor(A, lam)
    one_pass = np.linalg.norm(R1.T @ R1 - ref.T @ ref) / np.linalg.norm(ref.T @ ref)
    two = np.linalg.norm(np.linalg.inv(R) @ ref - np.eye(10))
    one = np.linalg.norm(np.linalg.inv(R1) @ ref - np.eye(10))
    assert two < 1e-8 < one
    assert one_pass < 1e-12  # the Gram matrix itself is fine: it is its factor's directions that are not


def test_declines_beyond_its_accuracy():
    rng = np.random.default_rng(4)
    A = _system(rng, 500, 8, 1e12)
    assert ridge_factor(A, 1.0) is None  # augmented condition number 1e12 > MAX_CONDITION
    assert MAX_CONDITION < 1e8
    assert ridge_factor(A, 1e12) is not None  # a ridge that bounds it to 1e6


def test_rank_deficient_system_with_a_ridge():
    rng = np.random.default_rng(5)
    A = rng.standard_normal((300, 6))
    A[:, 5] = A[:, 4]  # two columns the data cannot tell apart: the ridge decides
    R = ridge_factor(A, 1.0)
    assert np.allclose(R.T @ R, A.T @ A + np.eye(6), rtol=0, atol=1e-10 * np.abs(A.T @ A).max())


def test_refuses_a_ridge_that_is_not_positive():
    with pytest.raises(ValueError, match="lam > 0"):
        ridge_factor(np.eye(3), 0.0)


def test_blocks_do_not_change_the_answer(monkeypatch):
    rng = np.random.default_rng(6)
    A = _system(rng, 3000, 9, 1e4)
    whole = ridge_factor(A, 2.0)
    monkeypatch.setattr(tallqr, "BLOCK_ROWS", 257)
    assert np.allclose(ridge_factor(A, 2.0), whole, rtol=1e-12, atol=1e-12 * np.abs(whole).max())


@pytest.mark.parametrize("cond,small", [(1e3, False), (5e6, True), (5e6, False), (1e12, False)])
def test_ridge_solution_is_the_regularised_least_squares(cond, small):
    """Against Householder least squares of the augmented system: the triangular factor's route (refined: without
    the refinement the semi-normal equations were 3e-4 off at condition 5e6 with a small residual) and the
    least-squares route it declines to (1e12)."""
    from bayescal.tallqr import ridge_solution

    rng = np.random.default_rng(7)
    A = _system(rng, 600, 8, cond)
    # a small residual (the data nearly fitted) is where the semi-normal equations lose most
    b = A @ rng.standard_normal(8) + 1e-6 * rng.standard_normal(600) if small else rng.standard_normal(600)
    sw = rng.uniform(0.3, 1.2, 600)
    x = ridge_solution(A, b, 0.7, sw)
    aug = np.vstack([A * sw[:, None], np.sqrt(0.7) * np.eye(8)])
    ref = np.linalg.lstsq(aug, np.concatenate([sw * b, np.zeros(8)]), rcond=None)[0]
    assert np.allclose(x, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
