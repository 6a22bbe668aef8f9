"""The Frank-Wolfe bound on criterion I: below every plan, tight where the answer is known."""

from itertools import combinations

import numpy as np
import pytest

from bayescal.design import design_mse_bound, output_weight, utility
from bayescal.errors import InputError


def test_bound_is_below_every_plan_and_close_to_the_best():
    rng = np.random.default_rng(3)
    N, k, L, n = 10, 2, 3, 3
    blocks = rng.normal(size=(N, k, L)) * rng.uniform(0.2, 2.0, size=(N, 1, L))
    Q = output_weight(rng.normal(size=(20, 3, L)) * np.array([3.0, 1.0, 0.3]))
    values = [-float(utility("I", np.eye(L) + np.einsum("nki,nkj->ij", blocks[list(s)], blocks[list(s)]), Q=Q))
              for s in combinations(range(N), n)]
    b = design_mse_bound(blocks, Q, n, iters=200, rtol=1e-6)
    assert 0 < b.lower_mse <= b.relaxed_mse <= min(values) + 1e-12
    assert b.relaxed_mse <= b.start_mse
    # the relaxation (fractional repeats allowed) is not far below the best distinct plan here
    assert b.lower_mse > 0.5 * min(values)
    assert "sqrt(E[MSE])" in b.report() and b.to_dict()["lower_root_mse_mm"] == pytest.approx(np.sqrt(b.lower_mse))


def test_one_parameter_bound_equals_the_closed_form():
    # L = 1: f(w) = q / (1 + sum w_i b_i^2), minimised by all n on the largest b: q / (1 + n b_max^2)
    b = np.array([0.5, 2.0, 1.0, 1.5])
    blocks = b[:, None, None]
    Q = np.array([[4.0]])
    res = design_mse_bound(blocks, Q, 3, start=np.array([0, 2, 3]), iters=200, rtol=1e-9)
    exact = 4.0 / (1 + 3 * 4.0)
    assert res.lower_mse <= exact + 1e-12
    assert res.lower_mse == pytest.approx(exact, rel=1e-3)
    assert res.relaxed_mse == pytest.approx(exact, rel=1e-3)
    with pytest.raises(InputError, match="positive number"):
        design_mse_bound(blocks, Q, 0)


def test_bound_is_below_every_exact_design_including_repeats():
    """Exhaustive enumeration with repeated poses: the relaxation allows repeats, so it bounds them too."""
    from itertools import combinations_with_replacement

    rng = np.random.default_rng(11)
    N, k, L, n = 7, 2, 3, 4
    blocks = rng.normal(size=(N, k, L)) * rng.uniform(0.2, 2.0, size=(N, 1, L))
    Q = output_weight(rng.normal(size=(20, 3, L)) * np.array([3.0, 1.0, 0.3]))

    def value(s):
        B = blocks[list(s)]
        return -float(utility("I", np.eye(L) + np.einsum("nki,nkj->ij", B, B), Q=Q))

    with_repeats = [value(s) for s in combinations_with_replacement(range(N), n)]
    distinct = [value(s) for s in combinations(range(N), n)]
    b = design_mse_bound(blocks, Q, n, iters=200, rtol=1e-7)
    assert b.lower_mse <= min(with_repeats) + 1e-12
    assert min(with_repeats) <= min(distinct)
