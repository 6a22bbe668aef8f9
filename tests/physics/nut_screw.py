"""An independent physics simulator for tests: nut and screw with play, driven step by step.

Written without bayescal's effect code (no ``delta_q``, no play operator):
the state is the nut's position on the screw; the screw (whose angle the
motor encoder reads, so the commanded position is the screw's) turns in
small steps along the commanded trajectory, including the motion between
measured poses, and pushes the nut only through contact of a thread flank.

Geometry of the contact: the nut's thread sits in the screw's groove with a
total clearance ``b`` (the dead band).  With the gap ``g = x_screw - y_nut``
the upper flank touches at ``g = +b/2`` (the screw ahead, pulling the nut
up) and the lower at ``g = -b/2``.  A screw step that would open the gap
beyond a flank carries the nut along with it; otherwise the nut stays (no
friction drag inside the clearance).  The slider is rigidly fixed to the nut.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class NutScrew:
    """One drive per actuator; ``run`` moves the screws along a trajectory and returns the nut positions.

    Parameters
    ----------
    dead_band_um : ndarray, shape (m,)
        Full clearance ``b`` per drive, um.
    initial_gap_um : ndarray, shape (m,), optional
        Gap ``x - y`` before the first move (the unknown history): anywhere in ``[-b/2, b/2]``.
    step_mm : float
        Largest screw step of the integration, mm (the contact rule is exact
        for any monotone step; small steps only make the integration
        independent of that argument).
    """

    def __init__(self, dead_band_um, initial_gap_um=None, step_mm: float = 0.5):
        self.b = 1e-3 * np.asarray(dead_band_um, float)
        self.gap0 = np.zeros_like(self.b) if initial_gap_um is None else 1e-3 * np.asarray(initial_gap_um, float)
        if np.any(np.abs(self.gap0) > self.b / 2 + 1e-15):
            raise ValueError("the initial gap must lie within the clearance")
        self.step = step_mm

    def run(self, waypoints: NDArray, measured: NDArray) -> NDArray:
        """Nut positions (mm) at the measured waypoints.

        Parameters
        ----------
        waypoints : ndarray, shape (k, m)
            The screws' path in time order (straight segments between
            waypoints), starting where the first gap is given.
        measured : ndarray of bool, shape (k,)
            Which waypoints are measured poses.
        """
        x = waypoints[0].astype(float).copy()
        y = x - self.gap0
        out = []
        if measured[0]:
            out.append(y.copy())
        for k in range(1, len(waypoints)):
            target = waypoints[k]
            n_steps = max(1, int(np.ceil(np.max(np.abs(target - x)) / self.step)))
            start = x.copy()
            for s in range(1, n_steps + 1):
                x = start + (target - start) * (s / n_steps)
                gap = x - y
                # flank contact: the nut is carried by the part of the step beyond the clearance
                over = gap > self.b / 2
                under = gap < -self.b / 2
                y = np.where(over, x - self.b / 2, np.where(under, x + self.b / 2, y))
            if measured[k]:
                out.append(y.copy())
        return np.array(out)


class LostMotion:
    """A :class:`bayescal.simulate.PoseTransform`: commanded poses (measurement order) -> slider positions.

    The screws travel in straight moves from pose to pose, through optional
    intermediate waypoints (``via``: a function of two consecutive poses
    returning extra waypoints), after a pre-history that leaves a random gap.
    """

    def __init__(self, dead_band_um, rng: np.random.Generator, via=None):
        b = np.asarray(dead_band_um, float)
        self.drive = NutScrew(b, initial_gap_um=rng.uniform(-0.5, 0.5, b.shape) * b)
        self.via = via

    def transform(self, q, theta, aux, order):
        seq = np.argsort(np.asarray(order), kind="stable")
        qs = q[seq]
        path, meas = [qs[0]], [True]
        for a, b in zip(qs[:-1], qs[1:]):
            if self.via is not None:
                for w in self.via(a, b):
                    path.append(w)
                    meas.append(False)
            path.append(b)
            meas.append(True)
        y = self.drive.run(np.array(path), np.array(meas))
        out = np.empty_like(q, dtype=float)
        out[seq] = y
        return out, theta
