"""The session's refit terms of the predictive covariance, where the session has a nearly unidentifiable direction.

``predict --frame fit`` with a body sensor fits, on the fit rows, the stations' frames (mm and rad) and the
sensors' mountings with the level of up, which a sensor on a column sees as nearly one direction: on the
telescope's session b the whitened fit rows' Jacobian has singular values down to 1e-7 of the largest with its
columns at unit norm (1.7e-7 without). Built from the normal matrix, that direction sat at its round-off: the
session's noise term came out indefinite (eigenvalues of -4e-10 rad^2 against a noise of 2e-10) and the tip
sensor's fit-row chi-square took 423, 450, 483, 581 or 669 on 176 degrees of freedom with the numpy, scipy and
the last digits of the calibrated file (40-digit arithmetic on the same rows: 424.6).

The reference here needs neither the small singular values nor the units: the session's Jacobian is built as
``Z R^-1 diag(s) W^T D`` with ``Z``'s fit rows ``= Q R`` (QR), so that the fit rows' pseudo-inverse maps every
row through ``Z R^-1 Q^T``, whatever ``s`` (singular values) and ``D`` (units).

These are the least-squares terms (no prior), those of a frame; the mountings' MAP prior, which now decides that
weak direction in ``predict``, and the fit rows' residual covariance against Monte Carlo are in
tests/prediction/test_fit_rows.py (the chi-square above is the old test's: docs/real-setup.md shows today's).
"""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.prediction.engine import _session_terms


def _session(s, units, seed=3):
    rng = np.random.default_rng(seed)
    n, dof, p, k = 120, 5, s.size, 20
    fr = np.arange(n) % 4 != 3
    sig = np.tile([5e-3, 5e-3, 5e-3, 1e-5, 1e-5], (n, 1))
    Z = rng.normal(size=(n * dof, p))
    Zf = Z.reshape(n, dof, p)[fr].reshape(-1, p)
    Q, R = np.linalg.qr(Zf)
    W, _ = np.linalg.qr(rng.normal(size=(p, p)))
    T = np.linalg.solve(R, np.eye(p))  # R^-1
    whitened = (Z @ T @ np.diag(s) @ W.T @ np.diag(units)).reshape(n, dof, p)
    Js = whitened * sig[:, :, None]
    Jm = rng.normal(size=(n, dof, k)) * sig[:, :, None] * 30.0
    c = np.array([1.06, 1.06, 1.06, 1.0, 1.0])
    # reference: the map of the fit rows onto every row, Js pinv(A_s) = Z R^-1 Q^T (whitened), without s or units
    H = (Z @ T @ Q.T).reshape(n, dof, -1) * sig[:, :, None]
    Am = (Jm[fr] / sig[fr][:, :, None]).reshape(-1, k)
    G_ref = Jm - H @ Am
    c_rows = np.tile(c, int(fr.sum()))
    extra_ref = (H * c_rows) @ np.swapaxes(H, 1, 2)
    # a fit row's residual: its own noise less the fit's, S c S - h c S - S c h^T + H c H^T with h = H's own block
    own = H[fr].reshape(-1, dof, int(fr.sum()), dof)[np.arange(int(fr.sum())), :, np.arange(int(fr.sum()))]
    S = sig[fr][:, :, None] * np.eye(dof)
    hcS = own * c @ S
    fit_ref = S * c @ S - hcS - np.swapaxes(hcS, 1, 2) + extra_ref[fr]
    return (Js, Jm, sig, c, fr), G_ref, extra_ref, fit_ref


@pytest.mark.parametrize("weak", [1.0, 1e-7])
def test_session_terms_match_the_reference_whatever_the_units_and_a_weak_direction(weak):
    # 16 session parameters (two frames' 12, four mounting and level angles), columns from 1 to 3e6 per unit
    s = np.r_[np.linspace(1.0, 0.03, 14), 8.3 * weak, 5.0 * weak]
    units = np.r_[[1.0] * 3, [2e3] * 3, [1.3] * 3, [3e3] * 3, [6e2] * 4]
    args, G_ref, extra_ref, fit_ref = _session(s, units)
    t = _session_terms(*args)
    G, extra = t.G, t.extra
    assert np.max(np.abs(G - G_ref)) < 1e-7 * np.max(np.abs(G_ref))
    assert np.max(np.abs(extra - extra_ref)) < 1e-7 * np.max(np.abs(extra_ref))
    # the session estimate's noise, seen by every row, is a covariance: never below zero in any direction
    assert np.linalg.eigvalsh(extra).min() >= -1e-12 * np.max(np.abs(extra_ref))
    # so is a fit row's residual covariance, the estimate's noise taken off its own
    assert np.max(np.abs(t.fit_noise - fit_ref)) < 1e-7 * np.max(np.abs(fit_ref))
    assert np.linalg.eigvalsh(t.fit_noise).min() >= -1e-12 * np.max(np.abs(fit_ref))


def test_session_terms_do_not_depend_on_the_session_parameters_units():
    s = np.r_[np.linspace(1.0, 0.03, 14), 8.3e-7, 5.0e-7]
    a = _session(s, np.ones(16))[0]
    b = _session(s, np.geomspace(1.0, 3e6, 16))[0]
    ta, tb = _session_terms(*a), _session_terms(*b)
    (Ga, ea), (Gb, eb) = (ta.G, ta.extra), (tb.G, tb.extra)
    assert np.max(np.abs(Ga - Gb)) < 1e-7 * np.max(np.abs(Ga))
    assert np.max(np.abs(ea - eb)) < 1e-7 * np.max(np.abs(ea))
