"""How well the geometry written by a diagnosis is known, and what it trades off against.

An effect can be partly indistinguishable from the geometry: the constant
part of a gravity sag is exactly an actuator zero offset, a thermal drift at
a constant temperature is one too.  The data then fix the sum (geometry plus
effect), not the split, and the geometry written by ``--write-machine`` (the
machine *without* the effect) is uncertain along the split, however well the
recording is fitted.  This module measures it from the Laplace posterior of
the final joint fit:

* ``tool_std``: the posterior RMS uncertainty of the tool point predicted by
  the written geometry alone (no effect), over the recording's poses,
  ``sqrt(trace(G Sigma_theta G^T) / n)`` with ``G = d x_tool / d theta``;
* ``geometric_tool_std``: the same for the geometry-only calibration (what
  a clean recording would give: the yardstick);
* the *leading trade-off*: the posterior direction that moves the written
  tool point most, ``delta = Sigma^(1/2) u`` with ``u`` the top eigenvector
  of ``Sigma^(1/2) H Sigma^(1/2)``, ``H = G^T G / n`` on the geometric block
  (zero on the effect block).  Along it the geometric and effect parameters
  move together by one posterior sigma; its largest components (in prior
  sigmas) name what trades off, and ``sqrt(eigenvalue)`` is how far the tool
  moves (RMS over the poses).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..effects.base import Effect
from ..effects.model import EffectFit
from ..errors import KinematicsError
from ..machines.base import Machine

__all__ = ["GeometryConfound", "geometry_confound", "written_tool_jacobian", "CONFOUND_RATIO"]

#: Written-geometry uncertainty above this many times the geometry-only one is reported as a confound.
CONFOUND_RATIO = 2.0
#: Most poses the tool-point RMS is averaged over (evenly spread over the recording beyond that).
MAX_POSES = 2000


@dataclass(frozen=True)
class GeometryConfound:
    """The written geometry's uncertainty at the tool and its leading trade-off.

    Attributes
    ----------
    tool_std_um : float
        Posterior RMS uncertainty of the tool point of the written geometry (um).
    geometric_tool_std_um : float
        The same for the geometry-only calibration of this recording (um).
    trade_tool_um : float
        RMS tool motion (um) along the leading trade-off (one posterior sigma).
    geometry : tuple of (str, float, str)
        Largest geometric components of the trade-off: name, shift, unit.
    effect : tuple of (str, float, str)
        Largest effect components of the trade-off: name, shift, unit.
    note : str
        The effects' own explanation of the confound (:meth:`Effect.confound_note`).
    next_sessions : tuple of SeparatingSession
        Where confounded: second sessions under changed conditions that
        would separate the effects from the geometry, best first
        (:mod:`bayescal.diagnose.separate`).
    """

    tool_std_um: float
    geometric_tool_std_um: float
    trade_tool_um: float
    geometry: tuple[tuple[str, float, str], ...]
    effect: tuple[tuple[str, float, str], ...]
    note: str = ""
    next_sessions: tuple = ()

    @property
    def confounded(self) -> bool:
        """Whether the effect makes the written geometry markedly less certain than a geometry-only calibration."""
        return self.tool_std_um > CONFOUND_RATIO * self.geometric_tool_std_um

    def to_dict(self) -> dict:
        return {
            "tool_std_um": self.tool_std_um, "geometric_tool_std_um": self.geometric_tool_std_um,
            "confounded": self.confounded,
            "trade_off": {
                "tool_um": self.trade_tool_um,
                "geometry": [{"name": n, "shift": v, "unit": u} for n, v, u in self.geometry],
                "effect": [{"name": n, "shift": v, "unit": u} for n, v, u in self.effect],
            },
            "note": self.note,
            "next_measurement": [x.to_dict() for x in self.next_sessions],
        }

    def report(self) -> str:
        """Lines for the diagnosis report."""
        head = (f"written geometry (without the effect): uncertain by {self.tool_std_um:.1f} um RMS at the tool "
                f"(geometry-only calibration: {self.geometric_tool_std_um:.1f} um)")
        if not self.confounded:
            return head
        geo = ", ".join(f"{n} {_fmt_geometry(v, u)}" for n, v, u in self.geometry)
        eff = ", ".join(f"{n} {v:+.3g} {u}" for n, v, u in self.effect)
        lines = [head + ": CONFOUNDED",
                 f"  leading trade-off, {self.trade_tool_um:.1f} um at the tool per sigma: {geo} against {eff}"]
        if self.note:
            lines.append(f"  {self.note}")
        lines += [x.report() for x in self.next_sessions[:2]]
        return "\n".join(lines)


def _fmt_geometry(v: float, unit: str) -> str:
    if unit == "mm":  # geometric errors are microns
        return f"{1e3 * v:+.1f} um"
    return f"{v:+.3g} {unit}"


def _tool_rms_um(G: np.ndarray, cov: np.ndarray, n: int, s2: float) -> float:
    return 1e3 * float(np.sqrt(max(np.einsum("ij,jk,ik->", G, cov, G), 0.0) * s2 / n))


def written_tool_jacobian(machine: Machine, q: np.ndarray, theta: np.ndarray, keep: np.ndarray | None = None
                          ) -> tuple[np.ndarray, int]:
    """The written geometry's tool-point Jacobian over the poses its uncertainty is averaged over.

    Parameters
    ----------
    machine : Machine
        The nominal machine (no effects), bound to the recording's poses.
    q : ndarray, shape (n_poses, n_actuators)
        The recording's commanded positions.
    theta : ndarray, shape (P,)
        The written geometry (mm, rad).
    keep : ndarray of int, optional
        Poses to average over (outliers left out); at most :data:`MAX_POSES`, evenly spread.

    Returns
    -------
    G : ndarray, shape (3 n, P)
        mm per parameter unit.
    n : int
        Poses averaged over (those that assemble without the effects).

    Raises
    ------
    KinematicsError
        No pose assembles at the written geometry without the effects.
    """
    P = machine.n_params
    # the machine stays bound to the poses it evaluates (an instrument with several stations: Machine.for_poses)
    q = np.asarray(q, float)
    if keep is not None:
        q, machine = q[keep], machine.for_poses(keep)
    if q.shape[0] > MAX_POSES:
        # an RMS over the workspace: evenly spread poses of a tracker-size recording give it to a percent,
        # without a (n, 6, P) Jacobian of 50,000 poses
        sel = np.linspace(0, q.shape[0] - 1, MAX_POSES).astype(int)
        q, machine = q[sel], machine.for_poses(sel)
    poses = machine.forward(q, theta)
    if not poses.success.all():
        # the fits solved the poses with the effects applied; without them a pose near the workspace's edge may
        # not assemble: average over those that do
        ok = np.flatnonzero(poses.success)
        q, machine = q[ok], machine.for_poses(ok)
        poses = machine.forward(q, theta)
    n = q.shape[0]
    if n == 0:
        raise KinematicsError("no pose of the recording assembles at the written geometry without the effects")
    return machine.tool_jacobian(q, theta, poses)[:, :3, :].reshape(-1, P), n


def geometry_confound(machine: Machine, q: np.ndarray, final: EffectFit, geometric: EffectFit, effects: list[Effect],
                      *, noise_scale2: float = 1.0, keep: np.ndarray | None = None, top: int = 3) -> GeometryConfound:
    """Uncertainty of the written geometry and its leading trade-off (module docstring).

    Parameters
    ----------
    machine : Machine
        The nominal machine (no effects).
    q : ndarray, shape (n_poses, n_actuators)
        The recording's commanded positions.
    final, geometric : EffectFit
        The final joint fit (geometry and the selected effects) and the geometry-only fit.
    effects : list of Effect
        The selected effects, in the order of ``final.effect_slices``.
    noise_scale2 : float
        Factor on the instrument variance (the diagnosis' fitted scale, >= 1).
    keep : ndarray of int, optional
        Poses to average over (outliers left out); at most
        :data:`MAX_POSES` of them, evenly spread, are used.
    top : int
        How many components of each kind to name.

    Returns
    -------
    GeometryConfound

    Raises
    ------
    KinematicsError
        No pose assembles at the written geometry without the effects.
    """
    P = machine.n_params
    # the fits' parameters: the machine's, then a model's own nuisance parameters (ballbar pivots), then the effects'
    Pm = final.theta.size
    G, n = written_tool_jacobian(machine, q, final.theta[:P], keep)
    cov = final.covariance
    std = _tool_rms_um(G, cov[:P, :P], n, noise_scale2)
    std0 = _tool_rms_um(G, geometric.covariance[:P, :P], n, noise_scale2)
    # leading direction: symmetric square root of the joint covariance, tool metric on the geometric block
    w, V = np.linalg.eigh(cov)
    S = (V * np.sqrt(np.clip(w, 0, None))) @ V.T
    H = np.zeros_like(cov)
    H[:P, :P] = G.T @ G / n
    lam, U = np.linalg.eigh(S @ H @ S)
    delta = S @ U[:, -1] * np.sqrt(noise_scale2)
    trade = 1e3 * float(np.sqrt(max(lam[-1], 0.0) * noise_scale2))
    tol = machine.tolerance
    geo_rank = np.argsort(-np.abs(delta[:P]) / tol)[:top]
    sign = np.sign(delta[geo_rank[0]]) or 1.0  # report the direction with its largest geometric component positive
    names, units = machine.layout.names, machine.layout.units
    geo = tuple((names[j], float(sign * delta[j]), units[j]) for j in geo_rank)
    sd = np.array([p.prior_sd for p in final.params])
    eff_rank = np.argsort(-np.abs(delta[Pm:]) / sd)[:top] if sd.size else np.zeros(0, int)
    eff = tuple((final.params[k].name, float(sign * delta[Pm + k]), final.params[k].unit) for k in eff_rank)
    note = " ".join(filter(None, (e.confound_note() for e in effects)))
    return GeometryConfound(std, std0, trade, geo, eff, note)
