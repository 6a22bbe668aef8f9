"""The hyperprior on the prior scale, and the posterior of lambda it gives (evidence x hyperprior)."""

import numpy as np
import pytest
from scipy.stats import cauchy, multivariate_normal, norm

from bayescal.errors import InputError
from bayescal.identify.choose import lambda_grid, lambda_posterior
from bayescal.identify.scale_prior import DEFAULT_HYPERPRIOR, FLAT_HYPERPRIOR, ScaleHyperprior


@pytest.mark.parametrize(
    "hp, scipy_log_pdf_of_log_c",
    [
        (ScaleHyperprior("lognormal", centre=1.5, width=0.7), lambda u: norm.logpdf(u, np.log(1.5), 0.7)),
        # half-Cauchy on c (scale 2), density of log c = p(c) c
        (ScaleHyperprior("halfcauchy", centre=2.0), lambda u: cauchy.logpdf(np.exp(u), 0, 2.0) + u),
        (ScaleHyperprior("loguniform", low=0.3, high=6.0),
         lambda u: np.where((u >= np.log(0.3)) & (u <= np.log(6.0)), 0.0, -np.inf)),
    ],
)
def test_densities_against_scipy(hp, scipy_log_pdf_of_log_c):
    """Up to a constant, the log density of log c is scipy's (the half-Cauchy's through the change of variable)."""
    u = np.linspace(-2.0, 2.5, 37)
    ours, ref = hp.log_density(u), scipy_log_pdf_of_log_c(u)
    inside = np.isfinite(ref)
    assert np.array_equal(np.isfinite(ours), inside)
    diff = ours[inside] - ref[inside]
    np.testing.assert_allclose(diff, diff[0], atol=1e-10)


def test_bad_hyperpriors_are_refused():
    with pytest.raises(InputError, match="kind"):
        ScaleHyperprior("gamma")
    with pytest.raises(InputError, match="range"):
        ScaleHyperprior("loguniform", low=2.0, high=1.0)
    with pytest.raises(InputError, match="width"):
        ScaleHyperprior("lognormal", width=0.0)


def test_lambda_posterior_is_evidence_times_hyperprior(rng):
    """The weights against scipy's dense Gaussian density of z times the hyperprior of c = 1/sqrt(lam)."""
    N, p = 14, 4
    A = rng.normal(size=(N, p)) * np.logspace(0.5, -0.5, p)
    z = A @ rng.normal(size=p) + rng.normal(size=N)
    grid, w = lambda_posterior(A, z, hyperprior=DEFAULT_HYPERPRIOR)
    assert np.all(np.diff(grid) > 0) and w.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(grid, lambda_grid(np.linalg.svd(A, compute_uv=False)), rtol=1e-12)
    log_ev = np.array([multivariate_normal(np.zeros(N), np.eye(N) + A @ A.T / lam).logpdf(z) for lam in grid])
    log_c = np.log(1.0 / np.sqrt(grid))
    hp = DEFAULT_HYPERPRIOR
    assert hp.kind == "lognormal"
    inside = (np.exp(log_c) >= hp.low) & (np.exp(log_c) <= hp.high)
    lp = log_ev + np.where(inside, norm.logpdf(log_c, np.log(hp.centre), hp.width), -np.inf)
    ref = np.exp(lp - lp.max())
    np.testing.assert_allclose(w, ref / ref.sum(), atol=1e-9)


def test_unknown_noise_puts_the_hyperprior_on_the_scale_not_on_lambda(rng):
    """Rows whitened by a sigma 3x too small: lam = sigma^2 / c^2, with sigma^2 profiled, and the hyperprior
    judges c = sqrt(sigma^2 / lam); the posterior of lam then sits near 9 / c_true^2, not near 1 / c_true^2."""
    # 30 parameters: the scale c is then known from the data to about 13 % (with 6 it was 30 %, and a draw
    # with c_hat = 0.6 put lam at 25, beyond the tolerance of this check)
    N, p = 400, 30
    A = rng.normal(size=(N, p)) * 0.5
    z = A @ rng.normal(size=p) + 3.0 * rng.normal(size=N)  # c = 1, noise 3 in these units
    grid, w = lambda_posterior(A, z, noise_known=False)
    mean_log_lam = float(np.sum(w * np.log(grid)))
    assert abs(mean_log_lam - np.log(9.0)) < 1.0, np.exp(mean_log_lam)


def _tv(a, b):
    return 0.5 * float(np.abs(a - b).sum())


def test_hyperprior_matters_with_few_rows_and_not_with_many(rng):
    """Truths at twice the tolerances.  With a few weak rows the evidence says little about the scale: the
    hyperprior (median c = 1) moves the posterior mode of lam toward 1 (log lam toward 0) and narrows the
    posterior.  With many rows the evidence dominates: the mode stays, the two posteriors nearly coincide."""
    p = 8
    for N, gain in ((12, 0.15), (3000, 1.0)):
        tvs = []
        for _ in range(5):
            A = rng.normal(size=(N, p)) * gain
            z = A @ (2.0 * rng.normal(size=p)) + rng.normal(size=N)
            grid, w_flat = lambda_posterior(A, z, hyperprior=FLAT_HYPERPRIOR)
            _, w_hp = lambda_posterior(A, z, hyperprior=DEFAULT_HYPERPRIOR)
            u = np.log(grid)
            step = u[1] - u[0]
            mode_flat, mode_hp = u[np.argmax(w_flat)], u[np.argmax(w_hp)]
            sd_flat, sd_hp = (np.sqrt(np.sum(w * u**2) - np.sum(w * u) ** 2) for w in (w_flat, w_hp))
            tvs.append(0.5 * float(np.abs(w_flat - w_hp).sum()))
            if N == 12:
                # between the evidence maximum and the tolerance scale (the hyperprior is log-concave)
                assert min(mode_flat, 0.0) - step <= mode_hp <= max(mode_flat, 0.0) + step, (mode_flat, mode_hp)
                assert abs(mode_hp) <= abs(mode_flat) + step and sd_hp < sd_flat
            else:
                assert abs(mode_hp - mode_flat) <= 2 * step and abs(sd_hp - sd_flat) < 0.1 * sd_flat
        if N == 12:
            assert np.mean(tvs) > 0.2, tvs
        else:
            assert np.mean(tvs) < 0.05, tvs
