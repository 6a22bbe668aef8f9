"""Test helper: a base-frame recording as an instrument in another frame reads it.

Written with scipy's Rotation only (not bayescal's frame code), so the
wrapper is checked against an independent transform.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation


def random_frame(rng, *, max_angle=np.pi, max_offset=3000.0):
    """Origin (mm) and rotation (3, 3) of an instrument frame in the base frame."""
    axis = rng.normal(size=3)
    angle = rng.uniform(0.2, 1.0) * max_angle
    R = Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix()
    return rng.uniform(-1, 1, size=3) * max_offset, R


def to_instrument(rec, origin, R):
    """The recording as read in the frame ``p_base = R p_inst + origin``."""
    p = (rec.position - origin) @ R
    rv = None
    if rec.rotvec is not None:
        rv = (Rotation.from_matrix(R.T) * Rotation.from_rotvec(rec.rotvec)).as_rotvec()
    ax = None if rec.axis is None else rec.axis @ R
    return replace(rec, position=p, rotvec=rv, axis=ax)
