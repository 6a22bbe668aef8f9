import numpy as np

from bayescal.identify.solvers import filter_factors, filtered_solve


def test_filter_factors_closed_forms():
    s = np.array([10.0, 1.0, 0.1])
    assert np.allclose(filter_factors(s, "ridge", lam=1.0), [100 / 101, 0.5, 0.01 / 1.01])
    assert np.allclose(filter_factors(s, "tsvd", k=2), [1, 1, 0])
    assert np.allclose(filter_factors(s, "ls"), 1)


def test_ridge_equals_normal_equations_and_ls_equals_lstsq():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(30, 6)) @ np.diag([1, 1, 1, 1e-2, 1e-3, 1e-4])
    z = rng.normal(size=30)
    lam = 0.37
    x = filtered_solve(A, z, "ridge", lam=lam).x
    assert np.allclose(x, np.linalg.solve(A.T @ A + lam * np.eye(6), A.T @ z), rtol=1e-10)
    assert np.allclose(filtered_solve(A, z, "ls").x, np.linalg.lstsq(A, z, rcond=None)[0], rtol=1e-8)
    assert np.allclose(filtered_solve(A, z, "tsvd", k=6).x, filtered_solve(A, z, "ls").x, rtol=1e-12)
