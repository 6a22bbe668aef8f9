"""Backlash: a lost-motion dead band in each actuator (nut and screw, coupling, gearbox)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..machines.base import Machine, ToolPoses
from .base import Effect, EffectParam, Features, measurement_sequence

__all__ = ["Backlash", "play_operator"]


def play_operator(x: NDArray, half_band: NDArray) -> tuple[NDArray, NDArray]:
    """Positions of a follower dragged through a dead band, and their derivative by the half band.

    The follower (nut, slider) ``y`` only moves when the driver (screw,
    motor) ``x`` pushes it through the play: ``y_t = clip(y_{t-1}, x_t - h,
    x_t + h)`` (the play or backlash operator of hysteresis theory), with
    the first follower position unknown and taken at the centre of the band,
    ``y_0 = x_0``.  Consecutive rows are joined by straight moves, so each
    row is the end of a move in the direction of ``x_t - x_{t-1}``.

    Parameters
    ----------
    x : ndarray, shape (n_poses, n_actuators)
        Driver positions in time order (mm).
    half_band : ndarray, shape (n_actuators,)
        Half the dead band ``h = b / 2`` (mm), ``h >= 0`` physically.  A
        negative ``h`` (a fit's iterate, or a fit that reveals a reversed
        hysteresis, :meth:`Effect.nonphysical`) gives the odd extension
        ``-(y - x)(|h|)``: linear through zero in ``h`` after full moves, so
        that value and derivative agree on both sides (clamped at zero, the
        value stopped moving while the derivative did not, and a fit that
        went below zero could not find its way back).

    Returns
    -------
    y_minus_x : ndarray, shape (n_poses, n_actuators)
        ``y - x`` (mm): ``-h`` after a move up that took up the play, ``+h``
        after a move down, in between after a reversal shorter than ``2 h``.
    d_dh : ndarray, shape (n_poses, n_actuators)
        ``d (y - x) / d h`` (-1, +1 or carried from the last contact; 0 before any).
    """
    # A move of at least the whole band (2 h) ends in flank contact whatever the nut's position before
    # it, so those rows are -h sign(move), vectorised; only rows after shorter moves (and the first) need
    # the recursion, and the Python loop visits just those (rare with poses spread over the workspace).
    signed = np.asarray(half_band, float)
    flip = np.where(signed < 0, -1.0, 1.0)
    h = np.abs(signed)
    n, m = x.shape
    out = np.zeros((n, m))
    der = np.zeros((n, m))
    if n == 0:
        return out, der
    step = np.diff(x, axis=0)
    s = np.sign(step)
    big = np.abs(step) >= 2 * h[None, :]
    out[1:] = np.where(big, -h[None, :] * s, 0.0)
    der[1:] = np.where(big, -s, 0.0)
    small = np.zeros((n, m), dtype=bool)
    small[1:] = ~big
    for t in np.flatnonzero(small.any(axis=1)):
        k = small[t]
        y_prev = x[t - 1, k] + out[t - 1, k]
        lo, hi = x[t, k] - h[k], x[t, k] + h[k]
        below, above = y_prev < lo, y_prev > hi
        out[t, k] = np.where(below, lo, np.where(above, hi, y_prev)) - x[t, k]
        der[t, k] = np.where(below, -1.0, np.where(above, 1.0, der[t - 1, k]))
    # the odd extension: y - x at -h is minus that at h, its derivative by h the same
    return out * flip[None, :], der


class Backlash(Effect):
    """Lost motion between the drive's position sensor and the slider (nut and screw, coupling, gearbox).

    Physics: the commanded position is the screw's (the encoder sits on the
    motor), the slider hangs on the nut, and the nut has a play ``b_i`` (full
    width of the dead band) on the screw thread.  Moving up, the screw flank
    drags the nut from below once the play is taken up, so the nut trails
    the screw by half the band; moving down it trails on the other side:

        dq_i = q_slider - q_commanded = -(b_i / 2) s_i,    s_i = sign of the last move

    (the slider *lags*: it is short of the commanded position in the
    direction it came from).  Exactly, the slider follows the play operator
    of the commanded sequence in measurement order
    (:func:`play_operator`): a reversal shorter than the band leaves the nut
    in the gap; a pose with no move keeps the previous offset.  Assumptions
    the recording cannot tell: consecutive poses are joined by straight
    moves (a machine that approaches every pose from one side, ISO 230-2
    unidirectional, shows a constant offset instead, absorbed by the
    actuator zero); the first pose's history is unknown and taken at the
    centre of the band (``dq = 0``, the mean over an unknown approach); no
    friction or elastic windup inside the band.  With a linear scale on the
    slider (closed loop on the slider position) there is no backlash to see.
    Parameters: ``backlash.q<i>`` in um (full width ``b_i`` of the dead
    band, ``>= 0``; in urad on a revolute drive, the lost motion of its gear
    train, prior 300 urad).  Usual size on machine tools: 1-20 um with preloaded
    ball screws, up to 50-100 um on worn drives or belt/gear axes.
    """

    name = "backlash"
    summary = "a dead band per actuator: the slider lags the commanded position on the side it came from (measurement order)"
    magnitude_unit = "um"
    default_magnitude = 30.0

    def features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order, poses: ToolPoses | None) -> Features:
        n = q.shape[0]
        seq = measurement_sequence(order, n)
        rank = np.empty(n, dtype=int)
        rank[seq] = np.arange(n)
        # the play operator runs over the whole session in time order; a subset of the poses
        # (cross-validation) keeps that history and only picks its rows
        to_q = np.array([u.small_to_q for u in machine.actuator_unit_info])  # um -> mm, urad -> rad
        return Features({"rank": rank}, {"q_seq": np.asarray(q, float)[seq], "m": q.shape[1], "to_q": to_q})

    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        return tuple(EffectParam(f"backlash.q{i + 1}", u.small, 30.0 * u.per_um, lower=0.0)
                     for i, u in enumerate(machine.actuator_unit_info))

    @staticmethod
    def _play(features: Features, eta: NDArray) -> tuple[NDArray, NDArray]:
        y, d = play_operator(features.const["q_seq"], 0.5 * features.const["to_q"] * np.asarray(eta, float))
        rank = features.per_pose["rank"]
        return y[rank], d[rank]

    def delta_q(self, features: Features, eta: NDArray) -> NDArray:
        return self._play(features, eta)[0]

    def delta_q_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        _, d = self._play(features, eta)
        n, m = d.shape
        J = np.zeros((n, m, m))
        J[:, np.arange(m), np.arange(m)] = 0.5 * features.const["to_q"][None, :] * d
        return J

    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng) -> NDArray:
        return magnitude * rng.uniform(0.6, 1.4, machine.n_actuators)
