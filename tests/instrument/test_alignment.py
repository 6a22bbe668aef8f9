"""The rigid alignment of an instrument frame against scipy's Rotation.align_vectors (an independent implementation)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bayescal.instrument.alignment import align_frame
from bayescal.machines.framed import Frame


@pytest.mark.parametrize("seed", range(20))
def test_align_frame_matches_scipy(seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    o = rng.normal(size=3) * 1000
    pb = rng.normal(size=(10, 3)) * 300
    pi = (pb - o) @ R + rng.normal(size=(10, 3)) * 0.01  # instrument = R^T (base - o), with noise
    db = rng.normal(size=(10, 3))
    db /= np.linalg.norm(db, axis=1)[:, None]
    di = db @ R + rng.normal(size=(10, 3)) * 1e-4
    f = align_frame(pi, pb, dirs_inst=di, dirs_base=db, sigma_position=0.01, sigma_angle=1e-4)
    A = np.concatenate([pb - pb.mean(0), db])
    B = np.concatenate([pi - pi.mean(0), di])
    ref, _ = Rotation.align_vectors(A, B, weights=np.concatenate([np.full(10, 1e4), np.full(10, 1e8)]))
    np.testing.assert_allclose(f.rotation, ref.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(f.origin, pb.mean(0) - ref.as_matrix() @ pi.mean(0), atol=1e-9)


def test_align_frame_never_reflects():
    # points on a plane: the unconstrained optimum may be a reflection; the answer must stay a rotation
    rng = np.random.default_rng(3)
    pb = np.c_[rng.normal(size=(8, 2)) * 100, np.zeros(8)]
    f = align_frame(pb * [1, 1, 1], pb)
    assert np.linalg.det(f.rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(f.rotation, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 1.0, 3.0, np.pi - 1e-7])
def test_frame_rotation_vector_round_trip(angle):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    rv = axis * angle
    f = Frame.from_rotation_vector([1.0, 2.0, 3.0], rv)
    np.testing.assert_allclose(f.rotation, Rotation.from_rotvec(rv).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(f.rotation_vector, Rotation.from_matrix(f.rotation).as_rotvec(), atol=1e-9)
