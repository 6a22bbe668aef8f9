"""The fit rows' residual covariance, the MAP mountings' prior and the fit rows' test, against Monte Carlo.

A linear session built here, nothing taken from the package but the function under test: 40 poses, the tool's 3
position rows and two tilt sensors' 2 rows each (dof 7). The session's parameters: an instrument frame (6, least
squares), one more tool parameter only fit row 0's x sees (leverage one: no residual there), and the two
sensors' mountings with the shared level of up (6, MAP under a 2 mrad prior). A sensor reads ``m_s + R(phi) l``:
on the fit rows the column barely turns (``phi`` within 2e-7 rad), so each mounting and the level are one
direction to them (the prior decides the split, as on the telescope); the check rows turn it by up to 0.5 rad and
see the split. The machine's 8 parameters carry a covariance ``C`` and move every row.

Each simulated session draws the machine's error from ``C``, the true mountings from their prior, the noise with
the per-component factor ``c`` (1.3 on the tool's rows, 1 on the sensors'), and fits the session's parameters by
``np.linalg.lstsq`` of the stacked whitened fit rows and the prior's rows (the MAP estimate the package's
``_fit_mountings`` makes, written apart here). The empirical covariance of every row's error (a fit row's
residual, a check row's prediction error) over the sessions is compared with ``predictive_rows``' ``cov``, and
the fit rows' test statistic's mean and rejection rate with their nominal values.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.stats import chi2

from bayescal.distributions import weighted_chi2_sf
from bayescal.prediction.engine import PredictiveRows, _session_terms, predictive_rows
from bayescal.prediction.row_tests import _null_weights, row_group_tests
from bayescal.prediction.score import pinv_blocks

N_POSES, TD, DOF = 40, 3, 7
CHECK = np.arange(N_POSES) % 4 == 3  # 30 fit rows, 10 check rows
TOL = 2e-3  # rad, the mountings' and the level's prior std
SIG = np.r_[[5e-3] * 3, [1e-5] * 4]  # mm, rad
C_FACTOR = np.r_[[1.3] * 3, [1.0] * 4]
FRAME, LONE, MOUNT = np.arange(6), np.array([6]), np.arange(7, 13)
MACHINE = np.arange(13, 21)


@dataclass
class _Poses:
    success: np.ndarray
    message: tuple


@dataclass
class _Prediction:
    y: np.ndarray
    success: np.ndarray
    poses: _Poses


@dataclass(frozen=True)
class _Sensors:
    bodies: tuple = ("a", "b")


@dataclass
class LinearModel:
    """The duck type predictive_rows and row_group_tests read: rows ``J theta``, their sigma, measured values."""

    J: np.ndarray
    y_measured: np.ndarray | None = None
    tool_dof: int = TD
    sensors: _Sensors = field(default_factory=_Sensors)

    @property
    def n_poses(self):
        return self.J.shape[0]

    @property
    def dof(self):
        return self.J.shape[1]

    @property
    def row_sigma(self):
        return np.tile(SIG, (self.n_poses, 1))

    def predict(self, theta):
        ok = np.ones(self.n_poses, dtype=bool)
        return _Prediction(self.J @ theta, ok, _Poses(ok, ("",) * self.n_poses))

    def jacobian(self, theta, pred=None):
        return self.J

    def subset(self, idx):
        return LinearModel(self.J[idx], None if self.y_measured is None else self.y_measured[idx])


def _jacobian(machine_scale, seed=11):
    rng = np.random.default_rng(seed)
    J = np.zeros((N_POSES, DOF, 21))
    p = rng.uniform(-800.0, 800.0, size=(N_POSES, 3))
    for i in range(N_POSES):  # a small frame error: the point moves by t + w x p
        J[i, :3, :3] = np.eye(3)
        J[i, :3, 3:6] = -np.array([[0, -p[i, 2], p[i, 1]], [p[i, 2], 0, -p[i, 0]], [-p[i, 1], p[i, 0], 0]])
    J[0, 0, 6] = 1.0  # a tool parameter only fit row 0 sees among the fit rows (and check rows 3, 7)
    J[CHECK, 0, 6] = 0.5
    phi = np.where(CHECK, rng.uniform(-0.5, 0.5, N_POSES), rng.uniform(-2e-7, 2e-7, N_POSES))
    for s in range(2):
        rows = slice(TD + 2 * s, TD + 2 * s + 2)
        J[:, rows, 7 + 2 * s: 9 + 2 * s] = np.eye(2)
        ph = phi + 0.3 * s * CHECK  # the second sensor sits on a body turned further on the check poses
        J[:, rows, 11:13] = np.stack([[np.cos(ph), -np.sin(ph)], [np.sin(ph), np.cos(ph)]]).transpose(2, 0, 1)
    J[:, :, MACHINE] = rng.normal(size=(N_POSES, DOF, 8)) * SIG[None, :, None] * machine_scale
    return J


def _sessions(J, C, reps, seed):
    """Simulated sessions: every row's error after the session's fit (reps, n, dof), and the measured rows."""
    rng = np.random.default_rng(seed)
    fit = ~CHECK
    session = np.r_[FRAME, LONE, MOUNT]
    d = rng.multivariate_normal(np.zeros(8), C, size=reps)
    x = np.zeros((reps, 21))
    x[:, MOUNT] = rng.normal(size=(reps, 6)) * TOL
    x[:, MACHINE] = d
    x[:, FRAME] = rng.normal(size=(reps, 6))  # anything: least squares has no prior to pull it
    y = np.einsum("nip,rp->rni", J, x) + rng.normal(size=(reps, N_POSES, DOF)) * SIG * np.sqrt(C_FACTOR)
    # the estimator, written apart: least squares of the whitened fit rows stacked on the prior's rows (mean 0)
    A = (J[fit][:, :, session] / SIG[None, :, None]).reshape(-1, session.size)
    P = np.zeros((6, session.size))
    P[:, 7:] = np.eye(6) / TOL
    rhs = np.concatenate([(y[:, fit] / SIG).reshape(reps, -1).T, np.zeros((6, reps))])
    s_hat = np.linalg.lstsq(np.vstack([A, P]), rhs, rcond=None)[0].T  # (reps, 13)
    return y - np.einsum("nip,rp->rni", J[:, :, session], s_hat), y


def _predicted(J, C, prior=True):
    std = np.r_[np.full(7, np.inf), np.full(6, TOL)] if prior else None
    return predictive_rows(LinearModel(J), np.zeros(21), C, machine_index=MACHINE, noise_factor=C_FACTOR,
                           session_index=np.r_[FRAME, LONE, MOUNT], fit_rows=~CHECK, session_prior_std=std)


def _relative_error(emp, cov):
    """Each entry's difference over ``sqrt(cov_aa cov_bb)`` (a correlation's scale), rows with variance only."""
    sd = np.sqrt(np.clip(np.einsum("nii->ni", cov), 0.0, None))
    scale = sd[:, :, None] * sd[:, None, :]
    live = scale > 1e-12 * np.max(scale)
    return np.where(live, np.abs(emp - cov) / np.where(live, scale, 1.0), 0.0)


def test_fit_and_check_rows_covariance_equals_monte_carlo():
    """20000 sessions: a variance or a covariance to sqrt(2 / 20000) = 1.0 % of sd_a sd_b (1 sd); 5 % allowed over
    the 40 rows' 7 x 7 entries (the largest of ~1100 within 4 sd)."""
    C = np.eye(8) * 0.3
    J = _jacobian(machine_scale=1.0)
    err, _ = _sessions(J, C, 20000, seed=5)
    emp = np.einsum("rni,rnj->nij", err, err) / err.shape[0]
    pr = _predicted(J, C)
    assert np.max(_relative_error(emp, pr.cov)) < 0.05
    # fit row 0 decided its own x: no residual there, and none predicted
    assert emp[0, 0, 0] < 1e-20 and abs(pr.cov[0, 0, 0]) < 1e-12 * pr.cov[0, 1, 1]
    # the fit rows' residual is smaller than the noise (the hat share subtracted); adding the estimate's noise as
    # for a held-out row, as before, puts the tool's fit rows' variance 5 % above Monte Carlo here (2 h, 7
    # parameters over 90 components, diluted by the machine's share), some 50 times the error of the mean ratio
    fit = ~CHECK
    t = _session_terms(J[:, :, np.r_[FRAME, LONE, MOUNT]], J[:, :, MACHINE], np.tile(SIG, (N_POSES, 1)), C_FACTOR,
                       fit, np.r_[np.full(7, np.inf), np.full(6, TOL)])
    noise = np.diag(SIG**2 * C_FACTOR)
    old = pr.cov[fit] - t.fit_noise + t.extra[fit] + noise
    tool = np.s_[1:, :TD]  # fit row 0 has no x variance
    seen, now, before = (np.einsum("nii->ni", m[fit])[tool] if m is emp else np.einsum("nii->ni", m)[tool]
                         for m in (emp, pr.cov[fit], old))
    assert abs(np.mean(seen / now) - 1.0) < 0.005
    assert np.mean(seen / before) < 0.97


def test_the_prior_decides_the_check_rows_variance_where_the_fit_rows_do_not_see():
    """The pseudo-inverse's variance of the level (the fit rows see it at 2e-7 rad of turn) is that of no
    estimator applied: on the check rows, which turn the column, it is orders of magnitude above Monte Carlo."""
    C = np.eye(8) * 0.3
    J = _jacobian(machine_scale=1.0)
    err, _ = _sessions(J, C, 4000, seed=6)
    emp = np.einsum("rni,rnj->nij", err, err) / err.shape[0]
    sensors = slice(TD, DOF)
    chk = np.flatnonzero(CHECK)
    prior = np.einsum("nii->ni", _predicted(J, C).cov[chk][:, sensors, sensors])
    plain = np.einsum("nii->ni", _predicted(J, C, prior=False).cov[chk][:, sensors, sensors])
    seen = np.einsum("nii->ni", emp[chk][:, sensors, sensors])
    np.testing.assert_allclose(prior, seen, rtol=0.12)  # 4000 sessions: 2.2 % (1 sd)
    assert np.median(plain / seen) > 100.0


@pytest.mark.parametrize("machine_scale", [0.3, 3.0])
def test_fit_rows_test_has_its_mean_and_level(machine_scale):
    """Under the model, the fit rows' statistic averages the components with residual variance, and the test
    rejects at its level. 20000 sessions: binomial SE 0.07 % at 1 %, 0.15 % at 5 %; 4 SE allowed.

    The machine's uncertainty moves every row at once (``machine_scale`` 3: its variance 15 times the noise's
    before the refit), so the statistic's largest null eigenvalues reach 13 of 89: chi-square on the components
    rejects 15 to 19 % of true sessions at a nominal 1 % there (2 % at scale 0.3), which this test would catch.
    """
    C = np.eye(8) * 0.3
    J = _jacobian(machine_scale)
    reps = 20000
    err, y = _sessions(J, C, reps, seed=7)
    pr = _predicted(J, C)
    fit = ~CHECK
    stats = {}
    for name, sl in (("tool", slice(0, TD)), ("a", slice(TD, TD + 2)), ("b", slice(TD + 2, DOF))):
        S = pr.cov[fit][:, sl, sl]
        r = err[:, fit][:, :, sl]
        T = np.einsum("rni,nij,rnj->r", r, np.linalg.pinv(S, rcond=1e-9, hermitian=True), r)
        expected = int(np.sum(np.linalg.matrix_rank(S, rtol=1e-9, hermitian=True)))
        assert expected == (fit.sum() * 3 - 1 if name == "tool" else fit.sum() * 2)  # fit row 0's x: none
        assert abs(T.mean() - expected) < 4 * T.std() / np.sqrt(reps)
        # the package's critical values: where its null distribution's tail is alpha
        Eh, _ = pinv_blocks(S, power=0.5)
        w, h = _null_weights(Eh, pr.joint.base[fit][:, sl, sl], pr.joint.U[fit][:, sl], pr.joint.W)
        for alpha in (0.05, 0.01):
            tail = lambda x, a=alpha, w=w, h=h: weighted_chi2_sf(x, w, h) - a
            crit = brentq(tail, 0.5 * expected, 30.0 * expected)
            assert abs(np.mean(T > crit) - alpha) < 4 * np.sqrt(alpha * (1 - alpha) / reps)
        assert np.mean(T > chi2.isf(0.01, expected)) > 0.015
        stats[name] = (T, crit)
    # row_group_tests itself on some of the sessions (the tool's six largest statistics, rejected or near, and six
    # more): the same statistic, rejecting where it exceeds the critical value at its level (1 %)
    order = np.argsort(stats["tool"][0])
    for k in np.r_[order[-6:], order[np.arange(6) * (reps // 6)]]:
        got = row_group_tests(LinearModel(J, y[k]), PredictiveRows(y[k] - err[k], pr.cov, pr.success, pr.message,
                                                                    pr.joint), fit)
        for t in got:
            T, crit = stats[t.group]
            assert t.chi2 == pytest.approx(T[k], rel=1e-9) and (t.p_value < 0.01) == (T[k] > crit)


def test_large_groups_take_their_largest_eigenvalues_by_lanczos(monkeypatch):
    """Above DENSE_MAX components the null's largest eigenvalues come from products with the whitened covariance
    (eigsh): the same p-values as all the eigenvalues of the formed matrix."""
    import bayescal.prediction.row_tests as row_tests

    C = np.eye(8) * 0.3
    J = _jacobian(machine_scale=3.0)
    err, y = _sessions(J, C, 2, seed=1)
    pr = _predicted(J, C)
    pr = PredictiveRows(y[0] - err[0], pr.cov, pr.success, pr.message, pr.joint)
    dense = row_group_tests(LinearModel(J, y[0]), pr, ~CHECK)
    monkeypatch.setattr(row_tests, "DENSE_MAX", 0)
    lanczos = row_group_tests(LinearModel(J, y[0]), pr, ~CHECK)
    for a, b in zip(dense, lanczos):
        assert b.p_value == pytest.approx(a.p_value, rel=1e-8) and b.chi2 == a.chi2


@dataclass
class _Leftover:
    """A discrepancy without weights whose leftover variance ``D`` (n, dof, dof) is given: what the engine reads."""

    D: np.ndarray

    def rows(self, sub, theta, pred, J=None):
        n, dof = self.D.shape[:2]
        return np.zeros((n, dof)), np.zeros((n, dof, 0)), self.D


def _leftover(seed=12):
    """Each row's leftover variance: a random full 7 x 7 block, 3 times the tool's noise sd, 1.5 the sensors'
    (a discrepancy that carries most of a fit row's error, as where a model leaves much out)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(N_POSES, DOF, DOF)) * np.r_[[1.5e-2] * 3, [1.5e-5] * 4][None, :, None] / np.sqrt(DOF)
    return A @ np.swapaxes(A, 1, 2)


def test_the_discrepancys_leftover_on_fit_rows_goes_through_the_refit():
    """A discrepancy's leftover variance ``D`` is part of a fit row's error as the noise is: the refit absorbs its
    share there and the estimate's error carries it to the check rows.  20000 sessions: every entry within 5 % of
    sd_a sd_b (1 % is 1 sd); the tool's fit rows' variances on average within 0.5 % (0.06 % here; SE about
    0.2 %), where ``D`` added unchanged to a fit row (the engine before) is 4 % above Monte Carlo."""
    C = np.eye(8) * 0.3
    J = _jacobian(machine_scale=1.0)
    D = _leftover()
    reps = 20000
    rng = np.random.default_rng(13)
    chol = np.linalg.cholesky(D)
    err, _ = _sessions(J, C, reps, seed=14)
    # the leftover drawn apart, per row, and put through the same estimator as the noise (linear: added after)
    d = np.einsum("nij,rnj->rni", chol, rng.normal(size=(reps, N_POSES, DOF)))
    fit, session = ~CHECK, np.r_[FRAME, LONE, MOUNT]
    A = (J[fit][:, :, session] / SIG[None, :, None]).reshape(-1, session.size)
    P = np.zeros((6, session.size))
    P[:, 7:] = np.eye(6) / TOL
    rhs = np.concatenate([(d[:, fit] / SIG).reshape(reps, -1).T, np.zeros((6, reps))])
    s_d = np.linalg.lstsq(np.vstack([A, P]), rhs, rcond=None)[0].T
    err = err + d - np.einsum("nip,rp->rni", J[:, :, session], s_d)
    emp = np.einsum("rni,rnj->nij", err, err) / reps
    std = np.r_[np.full(7, np.inf), np.full(6, TOL)]
    kw = dict(machine_index=MACHINE, noise_factor=C_FACTOR, session_index=session, fit_rows=fit, session_prior_std=std)
    pr = predictive_rows(LinearModel(J), np.zeros(21), C, discrepancy=_Leftover(D), **kw)
    assert np.max(_relative_error(emp, pr.cov)) < 0.05
    before = predictive_rows(LinearModel(J), np.zeros(21), C, **kw).cov + np.where(fit[:, None, None], D, 0.0)
    tool = np.s_[1:, :TD]  # fit row 0 has no x variance
    seen = np.einsum("nii->ni", emp[fit])[tool]
    assert abs(np.mean(seen / np.einsum("nii->ni", pr.cov[fit])[tool]) - 1.0) < 0.005
    assert np.mean(seen / np.einsum("nii->ni", before[fit])[tool]) < 0.97  # 0.959 here
    # and the joint covariance the fit rows' test reads is the same model: its diagonal blocks are the rows' cov
    blocks = pr.joint.base[fit] + np.einsum("nik,kl,njl->nij", pr.joint.U[fit], pr.joint.W, pr.joint.U[fit])
    np.testing.assert_allclose(blocks, pr.cov[fit], rtol=1e-9, atol=1e-12 * np.abs(pr.cov[fit]).max())
    # the fit rows' test with it: the tool's statistic rejects true sessions at its levels (4 binomial SE)
    S = pr.cov[fit][:, :TD, :TD]
    T = np.einsum("rni,nij,rnj->r", err[:, fit, :TD], np.linalg.pinv(S, rcond=1e-9, hermitian=True), err[:, fit, :TD])
    Eh, _ = pinv_blocks(S, power=0.5)
    w, h = _null_weights(Eh, pr.joint.base[fit][:, :TD, :TD], pr.joint.U[fit][:, :TD], pr.joint.W)
    for alpha in (0.05, 0.01):
        crit = brentq(lambda x, a=alpha: weighted_chi2_sf(x, w, h) - a, 10.0, 3000.0)
        assert abs(np.mean(T > crit) - alpha) < 4 * np.sqrt(alpha * (1 - alpha) / reps)
