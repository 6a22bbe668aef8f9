"""The serial chain's all-joints-at-once helpers against the one-joint-at-a-time functions they replace."""

import numpy as np

from bayescal.geometry import _cross_basis, tilt_axes, tilted_direction
from bayescal.machines.serial import _tilted_axes


def test_tilted_axes_equal_tilted_direction_per_axis():
    rng = np.random.default_rng(1)
    u0 = rng.normal(size=(7, 3))
    u0 /= np.linalg.norm(u0, axis=1, keepdims=True)
    axes = [tilt_axes(a) for a in u0]
    G = np.array([[_cross_basis(t[0], a), _cross_basis(t[1], a)] for a, t in zip(u0, axes)]).swapaxes(1, 2)
    for g in (1, 5):  # one geometry for every pose, and one per pose
        tilt = rng.normal(0.0, 1e-3, (g, 7, 2))
        u, du = _tilted_axes(u0, G, tilt)
        for k in range(7):
            a, b = tilted_direction(u0[k], axes[k], tilt[:, k])
            np.testing.assert_array_equal(u[:, k], a)
            np.testing.assert_array_equal(du[:, k], b)
