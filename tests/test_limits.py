"""Stated limits (bayescal.limits): seeds, noise sigmas, and the memory budget."""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.errors import InputError
from bayescal.limits import SEED_MAX, check_memory, check_seed, memory_budget, sigma_problem


@pytest.mark.parametrize("seed", [0, 1, SEED_MAX, np.int64(7)])
def test_seeds_numpy_and_emcee_take_are_accepted(seed):
    assert check_seed(seed) == int(seed)
    np.random.RandomState(check_seed(seed))  # the legacy generator emcee seeds from takes every accepted seed


@pytest.mark.parametrize("seed", [-1, SEED_MAX + 1, 2**64, 1.5, True, "3"])
def test_other_seeds_are_refused_naming_the_option(seed):
    with pytest.raises(InputError, match=f"--seed: expected an integer from 0 to {SEED_MAX}"):
        check_seed(seed, "--seed")


def test_the_legacy_generator_refuses_what_check_seed_refuses():
    # the limit is numpy's own: the next integer up is a ValueError there
    with pytest.raises(ValueError):
        np.random.RandomState(SEED_MAX + 1)


@pytest.mark.parametrize("value, kind, ok", [
    (0.005, "position", True), (1e-6, "position", True), (1e3, "position", True), (1e-200, "position", False),
    (2e3, "position", False), (float("nan"), "position", False), (5e-5, "angle", True), (1e-12, "angle", False),
    (3.0, "angle", False),
])
def test_sigma_range(value, kind, ok):
    problem = sigma_problem(value, kind)
    assert (problem is None) == ok
    if not ok:
        assert "expected a one-sigma" in problem and ("mm" if kind == "position" else "rad") in problem


def test_memory_budget_refuses_what_cannot_fit_and_names_the_option():
    budget = memory_budget()
    assert 0 < budget < 2**60
    check_memory(1e6, "a small request", "lower --n")
    with pytest.raises(InputError, match=r"a grid needs about .* TiB of memory, more than the .* available; lower --nodes"):
        check_memory(32 * 2**40 + budget, "a grid", "lower --nodes")


def test_finite_real_takes_numbers_and_numpy_scalars_only():
    import numpy as np

    from bayescal.limits import finite_real

    assert all(finite_real(x) for x in (1, -2.5, np.int64(3), np.float32(0.5)))
    assert not any(finite_real(x) for x in (True, np.bool_(True), "1", None, float("nan"), np.inf, [1.0]))


@pytest.mark.parametrize("lam, ok", [(0, True), (1.0, True), (1e12, True), (1.0000001e12, False), (1e308, False),
                                     (-1e-9, False), (float("nan"), False), (True, False), ("1", False)])
def test_ridge_parameter_range(lam, ok):
    from bayescal.limits import lam_problem

    assert (lam_problem(lam) is None) == ok


@pytest.mark.parametrize("value", ["abc", "-1", "0", "1e400", "inf", "nan", "1e-300", "0.5", "100MB", "0x10"])
def test_a_memory_budget_that_is_no_size_is_refused(monkeypatch, value):
    from bayescal.errors import InputError

    monkeypatch.setenv("BAYESCAL_MEMORY_BUDGET", value)
    with pytest.raises(InputError, match="environment variable BAYESCAL_MEMORY_BUDGET: expected a positive number"):
        memory_budget()


@pytest.mark.parametrize("value,size", [("1", 1.0), (" 2G ", 2.0 * 2**30), ("2g", 2.0 * 2**30), ("1.5K", 1536.0)])
def test_a_memory_budget_that_is_a_size_is_taken(monkeypatch, value, size):
    monkeypatch.setenv("BAYESCAL_MEMORY_BUDGET", value)
    assert memory_budget() == size
