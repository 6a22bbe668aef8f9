import numpy as np

from bayescal.geometry import so3_exp
from bayescal.machines.construct import circle_intersections, kabsch, rotate_vectors, trilaterate


def test_trilaterate_and_circles_recover_points():
    rng = np.random.default_rng(0)
    p1, p2, p3, x = (rng.normal(size=(30, 3)) * 100 for _ in range(4))
    d = [np.linalg.norm(x - p, axis=1) for p in (p1, p2, p3)]
    sols = trilaterate(p1, d[0], p2, d[1], p3, d[2])
    err = np.linalg.norm(sols - x[:, None], axis=2).min(axis=1)
    assert err.max() < 1e-8
    for k in range(2):  # both solutions satisfy the three distances
        for p, dd in zip((p1, p2, p3), d):
            assert np.allclose(np.linalg.norm(sols[:, k] - p, axis=1), dd, atol=1e-8)
    n = np.cross(p2 - p1, x - p1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = circle_intersections(p1, d[0], p2, np.linalg.norm(x - p2, axis=1), n)
    assert np.linalg.norm(c - x[:, None], axis=2).min(axis=1).max() < 1e-8


def test_no_solution_is_nan_without_warnings():
    z, e = np.zeros((1, 3)), np.array([[10.0, 0.0, 0.0]])
    assert np.isnan(trilaterate(z, np.ones(1), e, np.ones(1), np.array([[0.0, 10.0, 0.0]]), np.ones(1))).all()
    assert np.isnan(circle_intersections(z, np.ones(1), e, np.ones(1), np.array([[0.0, 0.0, 1.0]]))).all()


def test_kabsch_and_minimal_rotation():
    rng = np.random.default_rng(1)
    R = so3_exp(rng.normal(size=(10, 3)))
    src = rng.normal(size=(10, 4, 3))
    dst = np.einsum("nij,nkj->nki", R, src) + rng.normal(size=(10, 1, 3))
    assert np.allclose(kabsch(src, dst), R, atol=1e-10)
    b = rng.normal(size=(10, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    a = np.array([0.0, 0.0, 1.0])
    M = rotate_vectors(a, b, matrix=True)
    assert np.allclose(M @ a, b, atol=1e-12)
    # smallest: the rotation axis is normal to both vectors
    assert np.allclose(np.arccos(np.clip(b @ a, -1, 1)), np.arccos((np.trace(M, axis1=1, axis2=2) - 1) / 2), atol=1e-10)
