"""What to measure next: the second session that would separate the selected effects from the geometry.

When the written geometry is confounded with an effect
(:mod:`bayescal.diagnose.confound`), more poses under the same conditions
help little: they fix the same sum again.  A session under changed
conditions (the effects' :meth:`~bayescal.effects.Effect.separating_conditions`:
a heavier payload, a tilted mounting, a temperature step) adds information
along the trade-off.  For each, at the joint fit ``(theta, eta)``, with
``A_0`` the whitened, prior-scaled Jacobian of the recorded session (its
channels as the effects read them) and ``A_1`` that of the same poses under
the new conditions (same instrument noise, same outlier weights), the
Laplace posterior of the two sessions together is

    Sigma_1 = S (A_0^T A_0 + A_1^T A_1 + I)^-1 S,      S = diag(prior sd)

and the written geometry's tool-point uncertainty after the second session is
``sqrt(trace(G Sigma_1 G^T) / n)`` as in the confound (``G`` the written
geometry's tool Jacobian over the recording's poses).  ``Sigma_0`` (without
``A_1``) gives the figure before, computed the same way, so the two are
comparable even where the condition reads a channel the recording lacks
(an absent payload channel is no payload: the effect then gains its payload
parameters, prior-only before).  Linearised at the fit: a forecast to be
checked by the second session's own diagnosis.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from ..effects.base import Effect, Features
from ..effects.conditions import Condition
from ..effects.model import EffectFit, joint_information
from ..errors import InputError, KinematicsError
from ..measurement import MeasurementModel
from ..notebook import ShowsReport

__all__ = ["SeparatingSession", "SessionDesign", "SessionPlan", "separating_sessions", "MAX_POSES", "WORTH"]

#: Most poses the information is computed on (evenly spread beyond that, scaled to the recording's count).
MAX_POSES = 2000
#: A session is proposed only if it cuts the written geometry's uncertainty to below this share.
WORTH = 0.8


@dataclass(frozen=True)
class SessionDesign:
    """What planning a second session needs, in the prior-scaled coordinates of the joint fit.

    Attributes
    ----------
    H0 : ndarray, shape (N, N)
        Posterior precision after the recorded session (``A_0^T A_0 + I``).
    blocks : ndarray, shape (m, d, N)
        Each candidate row's whitened Jacobian under the new conditions (the recording's rows, ``d`` values each).
    M : ndarray, shape (N, N)
        The written geometry's tool metric: ``sum`` over the averaged poses of ``(G S)^T (G S)``, zero on the effects.
    n_tool : int
        Poses the tool metric averages over.
    noise_scale2 : float
    rows : ndarray of int, shape (m,)
        The candidates' rows in the diagnosed model.
    q : ndarray, shape (m, n_actuators)
        Their commanded positions (machine units).
    channels : dict of str to ndarray
        The second session's channels the condition sets, per candidate (recording units).
    """

    H0: NDArray
    blocks: NDArray
    M: NDArray
    n_tool: int
    noise_scale2: float
    rows: NDArray
    q: NDArray
    channels: dict

    def std_um(self, C: NDArray) -> float:
        """RMS tool-point std (um) of the written geometry under the posterior covariance ``C`` (scaled coordinates)."""
        return 1e3 * float(np.sqrt(max(np.sum(self.M * C), 0.0) * self.noise_scale2 / self.n_tool))

    def greedy(self, n: int) -> tuple[NDArray, NDArray]:
        """The ``n`` candidates that shrink the tool std most, chosen one at a time (each at most once).

        Rank-``d`` updates of the covariance ``C = H^-1`` (Woodbury):
        adding block ``B`` lowers ``trace(M C)`` by ``trace((I + B C B^T)^-1 B C M C B^T)``.

        Returns
        -------
        order : ndarray of int, shape (n,)
            Candidate indices in the order chosen.
        std_um : ndarray, shape (n,)
            The tool std after each.
        """
        C = np.linalg.inv(self.H0)
        B = self.blocks
        d = B.shape[1]
        free = np.ones(B.shape[0], dtype=bool)
        order, std = [], []
        for _ in range(min(n, B.shape[0])):
            BC = B @ C  # (m, d, N)
            S = np.eye(d) + BC @ B.transpose(0, 2, 1)  # (m, d, d)
            T = BC @ self.M @ BC.transpose(0, 2, 1)  # (m, d, d): B C M C B^T
            gain = np.einsum("mii->m", np.linalg.solve(S, T))
            gain[~free] = -np.inf
            k = int(np.argmax(gain))
            free[k] = False
            C = C - BC[k].T @ np.linalg.solve(S[k], BC[k])
            order.append(k)
            std.append(self.std_um(C))
        return np.asarray(order, int), np.asarray(std)


@dataclass(frozen=True)
class SeparatingSession:
    """A proposed second session and what it would do to the written geometry.

    Attributes
    ----------
    key : str
        What changes (``payload``, ``temperature``, ``tilt_1``, ``tilt_2``).
    advice : str
        What to record.
    n_poses : int
        Poses of the second session (the recording's, again).
    tool_std_before_um, tool_std_after_um : float
        The written geometry's posterior RMS tool-point uncertainty (um) from
        the recording alone and with the second session (linearised).
    design : SessionDesign
        For :meth:`plan` (not part of the answer).
    """

    key: str
    advice: str
    n_poses: int
    tool_std_before_um: float
    tool_std_after_um: float
    design: SessionDesign | None = field(default=None, repr=False, compare=False)

    @property
    def ratio(self) -> float:
        """After over before."""
        return self.tool_std_after_um / self.tool_std_before_um if self.tool_std_before_um > 0 else 1.0

    def plan(self, n: int) -> "SessionPlan":
        """The ``n`` poses of the recording worth measuring again under this session's conditions.

        Parameters
        ----------
        n : int
            Poses to plan (at most the candidates: the recording's rows, or
            :data:`MAX_POSES` of them spread evenly).

        Raises
        ------
        InputError
            ``n`` below 1 or above the candidates.
        """
        if self.design is None:
            raise InputError("a second session of whole poses cannot be planned for a recording of distances or heights")
        m = self.design.rows.size
        if not 1 <= n <= m:
            raise InputError(f"--n: expected 1 to {m} poses (the recording's poses are the candidates), got {n}")
        order, std = self.design.greedy(n)
        return SessionPlan(self, order, std)

    def to_dict(self) -> dict:
        return {"condition": self.key, "advice": self.advice, "n_poses": self.n_poses,
                "tool_std_before_um": self.tool_std_before_um, "tool_std_after_um": self.tool_std_after_um}

    def report(self) -> str:
        return (f"  next: {self.advice}: the written geometry's uncertainty {self.tool_std_before_um:.1f} -> "
                f"{self.tool_std_after_um:.1f} um RMS at the tool (forecast)")


@dataclass(frozen=True)
class SessionPlan(ShowsReport):
    """Poses of a second session, in the order to measure them, with the channels to set and record.

    Attributes
    ----------
    session : SeparatingSession
    order : ndarray of int
        Candidates chosen, most informative first.
    std_um : ndarray
        The written geometry's forecast RMS tool std (um) after each.
    """

    session: SeparatingSession
    order: NDArray
    std_um: NDArray

    @property
    def q(self) -> NDArray:
        """Commanded positions, shape (n, n_actuators), machine units."""
        return self.session.design.q[self.order]

    @property
    def channels(self) -> dict:
        """The condition's channels per planned pose."""
        return {k: v[self.order] for k, v in self.session.design.channels.items()}

    def to_csv(self) -> str:
        """A pose file (docs/formats.md E7): ``q1..qN``, ``pose_id`` and the condition's channels."""
        q, ch = self.q, self.channels
        head = [f"q{j + 1}" for j in range(q.shape[1])] + ["pose_id"] + list(ch)
        lines = [",".join(head)]
        for i in range(q.shape[0]):
            lines.append(",".join([repr(float(v)) for v in q[i]] + [str(i + 1)] + [repr(float(ch[k][i])) for k in ch]))
        return "\n".join(lines) + "\n"

    def to_dict(self) -> dict:
        return {**self.session.to_dict(), "planned_poses": int(self.order.size),
                "recording_rows": [int(r) + 1 for r in self.session.design.rows[self.order]],
                "tool_std_planned_um": float(self.std_um[-1])}

    def report(self) -> str:
        s = self.session
        return "\n".join([
            f"second session to separate the effects from the geometry ({s.key}): {s.advice}",
            f"  {self.order.size} of the recording's poses, most informative first: the written geometry's uncertainty "
            f"{s.tool_std_before_um:.1f} -> {self.std_um[-1]:.1f} um RMS at the tool (forecast; all "
            f"{s.n_poses} poses again: {s.tool_std_after_um:.1f} um)"])


def _conditions(effects: Sequence[Effect], aux: dict) -> list[Condition]:
    """The selected effects' conditions, one per key (the first effect's wording)."""
    out: dict[str, Condition] = {}
    for eff in effects:
        for c in eff.separating_conditions(aux):
            out.setdefault(c.key, c)
    return list(out.values())


#: Channels a user sets for a session (a load to mount, not a reading): the plan names them at every pose.
SET_CHANNELS = ("payload_kg",)


def _set_channels(aux: dict, session: dict) -> dict:
    """The channels of the second session its pose file names: what the condition changes, and the loads to mount."""
    return {k: v for k, v in session.items()
            if k in SET_CHANNELS or k not in aux or not np.array_equal(np.asarray(v), np.asarray(aux[k]))}


def _same(a: dict, b: dict) -> bool:
    """Whether two sets of channels are equal."""
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def _eta_for(pairs, fit: EffectFit, machine) -> NDArray:
    """The fit's effect parameters by effect and name; a parameter the fit lacks at its start value."""
    fitted = {name: sl for name, sl in fit.effect_slices}
    out = []
    for eff, f in pairs:
        sl = fitted[eff.name]
        have = dict(zip((p.name for p in fit.params[sl]), fit.eta[sl]))
        out += [have.get(p.name, p.start_value) for p in eff.params(machine, f)]
    return np.asarray(out, float)


def separating_sessions(model: MeasurementModel, effects: Sequence[Effect], fit: EffectFit,
                        features_for: Callable[[Effect, dict], Features], aux: dict, G: NDArray, n_tool: int,
                        *, noise_scale2: float = 1.0) -> tuple[SeparatingSession, ...]:
    """The second sessions worth recording, best first (module docstring).

    Parameters
    ----------
    model : MeasurementModel
        The diagnosis' model (outliers down-weighted).
    effects : sequence of Effect
        The selected effects, in the order of ``fit.effect_slices``.
    fit : EffectFit
        The joint fit of the geometry and ``effects``.
    features_for : callable
        ``(effect, pose_aux) -> Features`` as the diagnosis computes them
        (``pose_aux``: channels per solved pose of ``model``).
    aux : dict of str to ndarray
        The recording's channels per solved pose of ``model``.
    G : ndarray, shape (3 * n_tool, P)
        The written geometry's tool-point Jacobian (mm per parameter unit)
        over the poses the uncertainty is averaged over.
    n_tool : int
        Those poses' count.
    noise_scale2 : float
        Factor on the instrument variance (the diagnosis' fitted scale).

    Returns
    -------
    tuple of SeparatingSession
        Those that cut the uncertainty below :data:`WORTH` of itself, best
        first; ``()`` if none does or a session's poses do not assemble.
    """
    machine, P = model.machine, G.shape[1]
    rows = np.arange(model.n_poses)  # rows of the model (a distance row has two solved poses)
    weight = 1.0
    if model.n_poses > MAX_POSES:
        rows = np.linspace(0, model.n_poses - 1, MAX_POSES).astype(int)
        weight = model.n_poses / rows.size  # the information of the whole recording, from a spread subset
    sub = model.subset(rows)
    on = model.poses_of(rows)
    # a second session of whole poses can be planned where each row is one pose (not distances between two)
    plannable = model.pose_q.shape[0] == model.n_poses
    out = []
    known: list[tuple[dict, tuple]] = []  # the recorded session's information per baseline (two tilts share one)
    for cond in _conditions(effects, aux):
        n = model.pose_q.shape[0]
        base = cond.baseline(aux, n)
        before = [(e, features_for(e, base).subset(on)) for e in effects]
        after = [(e, features_for(e, cond.session(aux, n)).subset(on)) for e in effects]
        names = [p.name for e, f in before for p in e.params(machine, f)]
        if names != [p.name for e, f in after for p in e.params(machine, f)]:
            continue  # the new session would need another parameter set: not comparable here
        eta = _eta_for(before, fit, machine)
        try:
            got = next((info for b, info in known if _same(b, base)), None)
            if got is None:
                got = joint_information(sub, before, fit.theta, eta)
                known.append((base, got))
            A0, scale = got
            A1, _ = joint_information(sub, after, fit.theta, eta)
        except KinematicsError:
            continue
        H0 = weight * (A0.T @ A0) + np.eye(scale.size)
        GS = np.zeros((G.shape[0], scale.size))
        GS[:, :P] = G * scale[:P]
        session = cond.session(aux, n)
        design = SessionDesign(H0, A1.reshape(rows.size, -1, scale.size), GS.T @ GS, n_tool, noise_scale2, rows,
                               model.q[rows], {k: np.asarray(v, float)[on] for k, v in _set_channels(aux, session).items()})
        before_um = design.std_um(np.linalg.inv(H0))
        after_um = design.std_um(np.linalg.inv(H0 + weight * (A1.T @ A1)))
        s = SeparatingSession(cond.key, cond.advice, model.n_poses, before_um, after_um,
                              design if plannable else None)
        if s.ratio < WORTH:
            out.append(s)
    return tuple(sorted(out, key=lambda s: s.tool_std_after_um))
