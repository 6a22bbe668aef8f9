"""Locate a model mismatch: which channel the residuals of the best geometric fit depend on.

Channels tried: every auxiliary channel of the recording, each actuator
position, a periodic dependence on each actuator position (Lomb-Scargle
periodogram), each actuator's approach direction, the measurement order,
and the pose region (the measured tool point).  The dependence measure is
the distance correlation (Szekely, Rizzo and Bakirov 2007) between the
channel and the per-pose whitened residual vector: zero only for
independence, so it catches non-monotone relations that a correlation
coefficient misses.  Its p-value is from the exact permutation null
of the distance covariance, summarised by the moment-matched gamma
distribution (the usual approximation of distance-covariance and HSIC
null distributions), so that p-values far below any ``1 / n_perm`` are
resolved and survive the multiple-testing correction; from 1,000 poses on
the test runs on seeded random blocks of 500-999 poses, so that its
cost grows linearly (:mod:`bayescal.diagnose.dependence`, which also says
why not the ``dcor`` package).  The
periodic channels use the Lomb-Scargle false-alarm probability instead
(``M (1 - P)^((N - 3) / 2)`` for ``M`` independent frequencies, Zechmeister
and Kuerster 2009).  All p-values are adjusted together by Holm's step-down
method, which controls the family-wise error for any dependence among the
tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..effects.base import approach_direction
from ..effects.periodogram import PITCH_RANGES, admissible_pitch_range, n_independent_frequencies, periodogram, pitch_grid
from .dependence import BLOCK, ResidualBlocks, distance_correlation

__all__ = ["ChannelDependence", "Location", "locate", "distance_correlation", "holm"]

#: Family-wise significance level of the location tests.
ALPHA = 0.01


@dataclass(frozen=True)
class ChannelDependence:
    """How strongly the residuals depend on one channel.

    Attributes
    ----------
    channel : str
        ``temp_C`` (an auxiliary channel), ``q2``, ``periodic_q2``,
        ``direction_q2``, ``order`` or ``pose_region``.
    kind : str
        ``aux``, ``actuator``, ``periodic``, ``direction``, ``order`` or ``region``.
    strength : float
        Distance correlation (0..1), or the normalised periodogram peak for ``periodic``.
    p_value, p_adjusted : float
        Raw and Holm-adjusted.
    detail : str
        E.g. the pitch of a periodic peak.
    values : ndarray, shape (n_poses,) or (n_poses, k)
        The channel, for figures.
    """

    channel: str
    kind: str
    strength: float
    p_value: float
    p_adjusted: float
    detail: str
    values: NDArray

    @property
    def significant(self) -> bool:
        return self.p_adjusted < ALPHA

    def to_dict(self) -> dict:
        return {"channel": self.channel, "kind": self.kind, "strength": self.strength,
                "p_value": self.p_value, "p_adjusted": self.p_adjusted, "detail": self.detail}


@dataclass(frozen=True)
class Location:
    """All channel dependences, strongest (most significant, then largest) first.

    Attributes
    ----------
    channels : tuple of ChannelDependence
    residual : ndarray, shape (n_poses, dof)
        Whitened residuals of the geometric fit that were tested.
    dq_residual : ndarray, shape (n_poses, n_actuators), optional
        The residuals mapped to actuator space, mm.
    """

    channels: tuple[ChannelDependence, ...]
    residual: NDArray
    dq_residual: NDArray | None = None

    @property
    def strongest(self) -> ChannelDependence | None:
        return self.channels[0] if self.channels else None

    def report(self, top: int = 5) -> str:
        lines = ["channel            strength   p (Holm)   detail"]
        for c in self.channels[:top]:
            mark = "*" if c.significant else " "
            lines.append(f"{c.channel:<18} {c.strength:8.3f}  {c.p_adjusted:9.2g}{mark}  {c.detail}")
        return "\n".join(lines)


def holm(p: NDArray) -> NDArray:
    """Holm step-down adjusted p-values (family-wise error control)."""
    p = np.asarray(p, float)
    m = len(p)
    order = np.argsort(p)
    adj = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, (m - rank) * p[i])
        adj[i] = min(running, 1.0)
    return adj


def locate(
    q: NDArray,
    residual_whitened: NDArray,
    dq_residual: NDArray,
    aux: dict,
    position: NDArray,
    *,
    seed: int = 0,
    block: int = BLOCK,
    direction: NDArray | None = None,
    units: tuple[str, ...] | None = None,
) -> Location:
    """Test every channel for a dependence of the residuals (see the module docstring).

    Parameters
    ----------
    q : ndarray, shape (n_poses, n_actuators)
        Commanded actuator positions, rows in measurement order.
    residual_whitened : ndarray, shape (n_poses, dof)
        Residuals of the geometric fit divided by the instrument sigma.
    dq_residual : ndarray, shape (n_poses, n_actuators)
        The residuals mapped to actuator space (for the periodograms).
    aux : dict of str to ndarray
        Auxiliary channels.
    position : ndarray, shape (n_poses, 3)
        Measured tool points (the pose region), mm.
    seed : int
        Seeds the assignment of poses to the blocks of the dependence tests.
    block : int
        Poses per block of the dependence tests (:data:`bayescal.diagnose.dependence.BLOCK`).
    direction : ndarray, shape (n_poses, n_actuators), optional
        Each row's approach direction (+1, -1, 0); from ``q`` in row order by
        default.  Rows with more than one pose (a distance) approach their
        first pose from the previous row's last, which ``q`` alone does not show.
    units : tuple of str, optional
        Unit of each actuator's ``q`` (``Machine.actuator_units``: ``"mm"`` or
        ``"rad"``); it sets the periods searched by the periodic tests
        (:data:`bayescal.effects.periodogram.PITCH_RANGES`).  All mm if omitted.

    Returns
    -------
    Location
    """
    n, m = q.shape
    blocks = ResidualBlocks(residual_whitened, seed=seed, block=block)
    order = np.arange(n, dtype=float)
    s = approach_direction(q) if direction is None else np.asarray(direction, float)
    tests: list[tuple[str, str, NDArray, str]] = []
    for name, v in aux.items():
        v = np.asarray(v, float)
        if np.ptp(v) > 0:
            tests.append((name, "aux", v, ""))
    for i in range(m):
        tests.append((f"q{i + 1}", "actuator", q[:, i], ""))
    for i in range(m):
        tests.append((f"direction_q{i + 1}", "direction", s[:, i], ""))
    tests.append(("order", "order", order, ""))
    tests.append(("pose_region", "region", position, ""))
    out = []
    for name, kind, v, detail in tests:
        t = blocks.test(v)
        out.append([name, kind, t.strength, t.p_value, detail, v])
    units = ("mm",) * m if units is None else tuple(units)
    bands = _pitch_bands(q, units)
    for i in range(m):
        freqs, M = bands[units[i]]
        power = periodogram(q[:, i], dq_residual[:, i], freqs)
        k = int(np.argmax(power))
        P = float(power[k])
        p = float(min(1.0, M * (1.0 - min(P, 1.0)) ** ((n - 3) / 2)))
        out.append([f"periodic_q{i + 1}", "periodic", P, p, f"pitch {1 / freqs[k]:.3g} {units[i]}", q[:, i]])
    adj = holm(np.array([o[3] for o in out]))
    deps = [ChannelDependence(o[0], o[1], float(o[2]), float(o[3]), float(a), o[4], o[5]) for o, a in zip(out, adj)]
    # significant dependences first, strongest first; then the rest by strength
    deps.sort(key=lambda d: (not d.significant, -d.strength))
    return Location(tuple(deps), residual_whitened, dq_residual)


def _pitch_bands(q: NDArray, units: tuple[str, ...]) -> dict:
    """Per actuator unit, the pitch grid searched and its number of independent frequencies."""
    m = q.shape[1]
    bands = {}
    for u in dict.fromkeys(units):
        # the largest stroke among the actuators of this unit, as for the screw_periodic_error effect
        span = float(max(np.ptp(q[:, j]) for j in range(m) if units[j] == u))
        full = PITCH_RANGES[u]
        # only pitches that repeat at least twice in the stroke
        prange = admissible_pitch_range(span, full) or (full[0], full[0])
        bands[u] = (pitch_grid(span, prange), n_independent_frequencies(span, prange))
    return bands
