"""Locate a model mismatch: which channel the residuals of the best geometric fit depend on.

Channels tried: every auxiliary channel of the recording, each actuator
position, a periodic dependence on each actuator position (Lomb-Scargle
periodogram), each actuator's approach direction, the measurement order,
and the pose region (the measured tool point).  The dependence measure is
the distance correlation (Szekely, Rizzo and Bakirov 2007) between the
channel and the per-pose whitened residual vector: zero only for
independence, so it catches non-monotone relations that a correlation
coefficient misses.  Its p-value is from a seeded permutation test
whose null distribution is summarised by a moment-matched gamma
distribution (the usual approximation of distance-covariance and HSIC
null distributions), so that p-values far below ``1 / n_perm`` are
resolved and survive the multiple-testing correction; the
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
from scipy.stats import gamma as gamma_dist

from ..effects.base import approach_direction
from ..effects.periodogram import PITCH_RANGE_MM, admissible_pitch_range, n_independent_frequencies, periodogram, pitch_grid

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


def _centered(x: NDArray) -> NDArray:
    x = x.reshape(len(x), -1)
    d = np.sqrt(np.sum((x[:, None, :] - x[None, :, :]) ** 2, axis=-1))
    return d - d.mean(axis=0)[None, :] - d.mean(axis=1)[:, None] + d.mean()


def distance_correlation(x: NDArray, y: NDArray) -> float:
    """Sample distance correlation of ``x`` (n,) or (n, k) and ``y`` (n,) or (n, k), in [0, 1].

    (Written here because neither numpy nor scipy has it; the ``dcor``
    package is a new dependency for one function.)
    """
    A, B = _centered(np.asarray(x, float)), _centered(np.asarray(y, float))
    return _dcor(A, B)


def _dcor(A: NDArray, B: NDArray) -> float:
    vxy = np.mean(A * B)
    vxx, vyy = np.mean(A * A), np.mean(B * B)
    if vxx <= 0 or vyy <= 0:
        return 0.0
    return float(np.sqrt(max(vxy, 0.0) / np.sqrt(vxx * vyy)))


def _perm_test(x: NDArray, B: NDArray, rng: np.random.Generator, n_perm: int) -> tuple[float, float]:
    A = _centered(x)
    stat = _dcor(A, B)
    vyy = np.mean(B * B)
    vxx = np.mean(A * A)
    if vxx <= 0 or vyy <= 0:
        return 0.0, 1.0
    obs = np.mean(A * B)
    null = np.empty(n_perm)
    for k in range(n_perm):
        p = rng.permutation(len(x))
        null[k] = np.mean(A[np.ix_(p, p)] * B)
    # shift so the null is positive (the V-statistic is), then match mean and variance of a gamma
    m, v = null.mean(), null.var()
    if v <= 0:
        return stat, 1.0
    shape, scale = m * m / v, v / m
    if m <= 0:
        return stat, float((np.sum(null >= obs) + 1) / (n_perm + 1))
    return stat, float(gamma_dist.sf(obs, shape, scale=scale))


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
    n_perm: int = 199,
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
        Seeds the permutations.
    n_perm : int
        Permutations per test.

    Returns
    -------
    Location
    """
    rng = np.random.default_rng(seed)
    n, m = q.shape
    B = _centered(residual_whitened)
    order = np.arange(n, dtype=float)
    s = approach_direction(q)
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
        stat, p = _perm_test(v, B, rng, n_perm)
        out.append([name, kind, stat, p, detail, v])
    span = float(np.ptp(q, axis=0).max())
    # only pitches that repeat at least twice in the stroke (as for the screw_periodic_error effect)
    prange = admissible_pitch_range(span) or (PITCH_RANGE_MM[0], PITCH_RANGE_MM[0])
    freqs = pitch_grid(span, prange)
    M = n_independent_frequencies(span, prange)
    for i in range(m):
        power = periodogram(q[:, i], dq_residual[:, i], freqs)
        k = int(np.argmax(power))
        P = float(power[k])
        p = float(min(1.0, M * (1.0 - min(P, 1.0)) ** ((n - 3) / 2)))
        out.append([f"periodic_q{i + 1}", "periodic", P, p, f"pitch {1 / freqs[k]:.3g} mm", q[:, i]])
    adj = holm(np.array([o[3] for o in out]))
    deps = [ChannelDependence(o[0], o[1], float(o[2]), float(o[3]), float(a), o[4], o[5]) for o, a in zip(out, adj)]
    # significant dependences first, strongest first; then the rest by strength
    deps.sort(key=lambda d: (not d.significant, -d.strength))
    return Location(tuple(deps), residual_whitened, dq_residual)
