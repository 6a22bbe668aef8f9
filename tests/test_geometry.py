import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from bayescal.geometry import (
    left_jacobian_inverse,
    right_jacobian_inverse,
    rotation_from_tilt_torsion,
    so3_exp,
    so3_log,
    tangent_basis,
    tilt_torsion_angles,
    tilted_direction,
)

rotvecs = arrays(np.float64, 3, elements=st.floats(-1.5, 1.5))


@given(rotvecs)
@settings(max_examples=50, deadline=None)
def test_exp_log_round_trip(w):
    R = so3_exp(w)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(so3_log(R), w, atol=1e-9)


def test_exp_matches_closed_form_about_z():
    a = 0.3
    R = so3_exp([0, 0, a])
    assert np.allclose(R, [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


@pytest.mark.parametrize("phi", [[0.0, 0.0, 0.0], [0.3, -0.2, 0.5], [1e-7, 0, 0]])
def test_jacobian_inverses_by_finite_differences(phi):
    phi = np.array(phi)
    h = 1e-6
    Jl = np.empty((3, 3))
    Jr = np.empty((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        Jl[:, k] = (so3_log(so3_exp(d) @ so3_exp(phi)) - so3_log(so3_exp(-d) @ so3_exp(phi))) / (2 * h)
        Jr[:, k] = (so3_log(so3_exp(phi) @ so3_exp(d)) - so3_log(so3_exp(phi) @ so3_exp(-d))) / (2 * h)
    assert np.allclose(left_jacobian_inverse(phi), Jl, atol=1e-7)
    assert np.allclose(right_jacobian_inverse(phi), Jr, atol=1e-7)


def test_tilted_direction_derivative_and_first_order_rotation():
    u0 = np.array([0.0, 0.0, 1.0])
    t = np.array([2e-3, -1e-3])
    u, du = tilted_direction(u0, (0, 1), t)
    assert np.isclose(np.linalg.norm(u), 1.0)
    h = 1e-7
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        fd = (tilted_direction(u0, (0, 1), t + e)[0] - tilted_direction(u0, (0, 1), t - e)[0]) / (2 * h)
        assert np.allclose(du[:, k], fd, atol=1e-8)
    # to first order, tilt about x by a rotates z towards -y
    u_small, _ = tilted_direction(u0, (0, 1), [1e-6, 0])
    assert np.allclose(u_small, so3_exp([1e-6, 0, 0]) @ u0, atol=1e-11)


@given(arrays(np.float64, 3, elements=st.floats(-1, 1)).filter(lambda v: np.linalg.norm(v) > 0.1))
@settings(max_examples=30, deadline=None)
def test_tangent_basis_is_orthonormal(v):
    n = v / np.linalg.norm(v)
    t = tangent_basis(n)
    M = np.vstack([t, n])
    assert np.allclose(M @ M.T, np.eye(3), atol=1e-12)


@given(st.floats(-3, 3), st.floats(0.01, 1.4), st.floats(-3, 3))
@settings(max_examples=50, deadline=None)
def test_tilt_torsion_round_trip(phi, theta, psi):
    R = rotation_from_tilt_torsion(phi, theta, psi)
    a = tilt_torsion_angles(R)
    assert np.allclose(rotation_from_tilt_torsion(*a), R, atol=1e-10)
    assert np.isclose(a[1], theta)
    # the tilt is the angle of the platform normal from base z
    assert np.isclose(np.arccos(R[2, 2]), theta)


def test_log_accurate_near_a_half_turn():
    """Rotary tables reach half a turn: the log must stay exact there (arccos and the
    antisymmetric part alone lose every digit at pi)."""
    a = np.array([0.6, 0.0, -0.8])
    th = np.array([2.9, 3.05, np.pi - 1e-4, np.pi - 1e-7, np.pi - 1e-10, np.pi])
    R = so3_exp(th[:, None] * a)
    w = so3_log(R)
    assert np.allclose(so3_exp(w), R, atol=1e-14)
    assert np.allclose(w[:-1], th[:-1, None] * a, atol=1e-12)
    assert np.allclose(np.abs(w[-1]), np.pi * np.abs(a), atol=1e-12)  # at pi either sign is the same rotation


@pytest.mark.parametrize("scale", [0.0, 1e-7, 1e-3, 0.5, 2.5])
def test_left_jacobian_against_finite_differences_and_its_inverse(scale):
    from bayescal.geometry import left_jacobian, left_jacobian_inverse, so3_exp, so3_log

    phi = np.array([0.3, -0.7, 0.5]) * scale
    J = left_jacobian(phi)
    np.testing.assert_allclose(J @ left_jacobian_inverse(phi), np.eye(3), atol=1e-12)
    h = 1e-6
    for k in range(3):
        d = np.eye(3)[k] * h
        # exp(phi + d) exp(phi)^T = exp([J d]x): its rotation vector over h is J's column k
        col = so3_log(so3_exp(phi + d) @ so3_exp(phi).T) / h
        np.testing.assert_allclose(col, J[:, k], atol=1e-6)


def test_a_stack_of_small_and_large_angles_gives_each_row_what_it_gives_alone():
    """The Rodrigues-type formulas evaluate only the branches (Taylor series near zero, closed form elsewhere)
    some row takes (issue 32): a stack mixing both, all small, all large, gives row by row, bit for bit, what
    each vector gives alone; at zero the identity, and so3_log of one matrix a vector."""
    from bayescal.geometry import left_jacobian, left_jacobian_inverse, so3_exp, so3_log

    rng = np.random.default_rng(4)
    scales = np.array([1.0, 1e-9, 2.0, 0.0, 1e-6, 3e-5, 3.1])[:, None]
    stacks = [rng.normal(size=(7, 3)) * scales, rng.normal(size=(4, 3)) * 1e-10, rng.normal(size=(4, 3))]
    for w in stacks:
        for f in (so3_exp, left_jacobian, left_jacobian_inverse):
            whole = f(w)
            for i in range(len(w)):
                assert np.array_equal(whole[i], f(w[i])), (f.__name__, i)
        R = so3_exp(w)
        logs = so3_log(R)
        for i in range(len(w)):
            assert np.array_equal(logs[i], so3_log(R[i]))
    for f in (so3_exp, left_jacobian, left_jacobian_inverse):
        assert np.array_equal(f(np.zeros(3)), np.eye(3))
    assert so3_log(np.eye(3)).shape == (3,) and not so3_log(np.eye(3)).any()
