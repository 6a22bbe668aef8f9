"""The simulated TRUE redundantly actuated module: restrained deformation at the actuated joints.

With more actuators ``m`` than degrees of freedom ``n``, commanded actuator
positions are compatible only for the exact geometry.  Otherwise the
actuators fight through the closed loops and, the actuated joints (AJs)
being the compliant parts, the structure settles where

* compatibility holds with the deformed joints:   ``q_k + e_k + delta_k = IK_k(x)`` for every k,
* the internal forces are in equilibrium:           ``J_a(x)^T tau = 0``, ``tau = K delta``,

(``e_k`` the following error of AJ k, ``K = diag(k_k)`` the AJ stiffnesses,
N/mm).  Equivalently ``x`` minimises the elastic energy
``sum_k k_k (IK_k(x) - q_k - e_k)^2 / 2``, and ``tau`` lies in the null space
of ``J_a^T`` (dimension ``m - n``).  Without external load only the
stiffness *ratios* matter: scaling every stiffness changes the forces, not
the pose.

Everything here is the simulator's truth.  The identification never sees
:attr:`TrueModule.stiffness`, the straightness errors or the raw following
errors: it sees what the instruments of :mod:`bayescal.redundant.steps` read.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import null_space

from ..errors import InputError
from ..machines.raspm import Raspm

__all__ = ["RestrainedState", "TrueModule", "solve_restrained", "internal_force_basis", "PitchCompensation"]


def internal_force_basis(Ja: NDArray) -> NDArray:
    """Orthonormal basis of ``null(J_a^T)`` per pose: the internal (self-equilibrated) forces.

    Parameters
    ----------
    Ja : ndarray, shape (n_poses, m, n)
        Actuation Jacobian ``dq/dx``.

    Returns
    -------
    ndarray, shape (n_poses, m, m - n)
    """
    Ja = np.asarray(Ja, dtype=float)
    if Ja.ndim != 3 or Ja.shape[1] <= Ja.shape[2]:
        raise InputError(f"Ja: expected shape (n_poses, m, n) with m > n (a redundant module), got {Ja.shape}")
    return np.stack([null_space(J.T) for J in Ja])


@dataclass(frozen=True)
class RestrainedState:
    """The settled module.

    Attributes
    ----------
    x : ndarray, shape (n, 3)
        Planar pose ``(p_x mm, p_z mm, phi rad)``.
    deformation : ndarray, shape (n, m)
        ``delta_k = IK_k(x) - (q_k + e_k)``, mm: how far each AJ is pushed.
    force : ndarray, shape (n, m)
        ``tau_k = k_k delta_k``, N.
    actual_q : ndarray, shape (n, m)
        ``q + e``: the joint positions before deformation, mm.
    success : ndarray of bool, shape (n,)
    """

    x: NDArray
    deformation: NDArray
    force: NDArray
    actual_q: NDArray
    success: NDArray


def solve_restrained(
    machine: Raspm, q: ArrayLike, theta: ArrayLike | None, stiffness: ArrayLike, *, x0: NDArray | None = None
) -> RestrainedState:
    """Static equilibrium of a redundantly actuated module with compliant actuated joints.

    Parameters
    ----------
    machine : Raspm
    q : array_like, shape (n, m)
        Actual (undeformed) actuator positions, mm.
    theta : array_like, shape (P,) or (n, P)
        True geometric errors (per pose for pose-dependent ones).
    stiffness : array_like, shape (m,)
        AJ stiffnesses, N/mm (positive).
    x0 : ndarray, optional
        Start.

    Returns
    -------
    RestrainedState
        Compatibility holds by construction (``delta = IK(x) - q``) and
        ``J_a^T K delta = 0`` to round-off at converged poses.
    """
    k = np.asarray(stiffness, dtype=float)
    if k.shape != (machine.n_actuators,) or np.any(~np.isfinite(k)) or np.any(k <= 0):
        raise InputError(f"stiffness: expected {machine.n_actuators} positive numbers (N/mm), got {stiffness!r}")
    q = machine.check_q(q)
    # the energy minimum: Gauss-Newton on sum_k k_k (IK_k(x) - q_k)^2, whose fixed points are J_a^T K delta = 0
    x, ok = machine.fit_pose(q, theta, k / k.max(), x0=x0)
    delta = machine.inverse_planar(x, theta) - q
    return RestrainedState(x=x, deformation=delta, force=delta * k, actual_q=q, success=ok)


@dataclass(frozen=True)
class PitchCompensation:
    """A measured following-error table per actuator (laser interferometer), applied by linear interpolation.

    Attributes
    ----------
    positions : ndarray, shape (n_points,)
        Actuator positions of the table, mm (common to all actuators is not
        required: one row per actuator in ``errors`` at ``positions[k]``).
    errors : ndarray, shape (m, n_points)
        Measured following error at each position, mm.
    """

    positions: NDArray
    errors: NDArray

    def __call__(self, q: NDArray) -> NDArray:
        """Compensated amount (n, m), mm."""
        return np.column_stack([np.interp(q[:, k], self.positions[k], self.errors[k]) for k in range(q.shape[1])])


@dataclass(frozen=True)
class TrueModule:
    """The simulated true module.

    Parameters
    ----------
    machine : Raspm
        Nominal machine.
    theta : ndarray, shape (P,)
        True geometric errors.
    stiffness : ndarray, shape (m,)
        AJ stiffnesses, N/mm; never given to the identification.
    lead_error : ndarray, shape (m,)
        Cumulative lead error of each screw, mm per mm of travel.
    periodic_error : ndarray, shape (m,)
        Amplitude of a periodic screw error, mm (pitch ``screw_pitch``).
    screw_pitch : float
        mm.
    straightness : ndarray, shape (m,)
        Bow of each rail normal to its direction over its travel (a parabola
        with this amplitude at the ends), mm.  Not in the geometric model.
    pitch_comp : PitchCompensation or None
        The controller's pitch compensation, subtracted from the following error.
    """

    machine: Raspm
    theta: NDArray
    stiffness: NDArray
    lead_error: NDArray = field(default_factory=lambda: np.zeros(0))
    periodic_error: NDArray = field(default_factory=lambda: np.zeros(0))
    screw_pitch: float = 20.0
    straightness: NDArray = field(default_factory=lambda: np.zeros(0))
    pitch_comp: PitchCompensation | None = None

    def __post_init__(self) -> None:
        m = self.machine.n_actuators
        for name in ("lead_error", "periodic_error", "straightness"):
            v = np.asarray(getattr(self, name), dtype=float)
            object.__setattr__(self, name, np.zeros(m) if v.size == 0 else v.reshape(m))
        object.__setattr__(self, "theta", np.asarray(self.theta, dtype=float).reshape(self.machine.n_params))
        object.__setattr__(self, "stiffness", np.asarray(self.stiffness, dtype=float).reshape(m))

    def raw_following_error(self, q: NDArray) -> NDArray:
        """Following error of each AJ before pitch compensation (n, m), mm."""
        mid = self.machine.q_limits.mean(axis=1) if self.machine.q_limits is not None else np.zeros(q.shape[1])
        return self.lead_error * (q - mid) + self.periodic_error * np.sin(2 * np.pi * q / self.screw_pitch)

    def following_error(self, q: NDArray) -> NDArray:
        """Following error left after the pitch compensation (n, m), mm."""
        e = self.raw_following_error(q)
        return e if self.pitch_comp is None else e - self.pitch_comp(q)

    def theta_rows(self, q: NDArray) -> NDArray:
        """Per-pose geometry: true errors plus the rails' straightness at each slider position."""
        m = self.machine
        rows = np.tile(self.theta, (q.shape[0], 1))
        if not np.any(self.straightness):
            return rows
        lo, hi = m.q_limits[:, 0], m.q_limits[:, 1]
        s = ((2 * (q - lo) / (hi - lo) - 1.0) ** 2 - 1.0 / 3.0) * self.straightness  # zero-mean bow
        u = m.rail_direction[:, [0, 2]]
        normal = np.column_stack([-u[:, 1], u[:, 0]])
        names = m.layout.names
        for k in range(m.n_actuators):
            c = m.slider_chain[k]
            j = sum(1 for kk in range(k) if m.slider_chain[kk] == c) + 1
            ix = names.index(f"chain{c + 1}.slider{j}.rail_origin.x")
            rows[:, ix] += s[:, k] * normal[k, 0]
            rows[:, ix + 1] += s[:, k] * normal[k, 1]
        return rows

    def settle(self, q_cmd: ArrayLike) -> RestrainedState:
        """Where the module settles for commanded actuator positions ``q_cmd`` (n, m), mm."""
        q_cmd = self.machine.check_q(q_cmd)
        q_act = q_cmd + self.following_error(q_cmd)
        return solve_restrained(self.machine, q_act, self.theta_rows(q_cmd), self.stiffness)

    def tool(self, q_cmd: ArrayLike) -> tuple[NDArray, NDArray, RestrainedState]:
        """Tool point in the motion plane (n, 2: x, z) mm, rotation phi (n,) rad, and the settled state."""
        st = self.settle(q_cmd)
        if not st.success.all():
            i = int(np.flatnonzero(~st.success)[0])
            raise InputError(f"simulated pose {i + 1} (q = {np.asarray(q_cmd)[i].tolist()}) cannot be settled")
        pos, _ = self.machine.tool_from_planar(st.x, self.theta_rows(self.machine.check_q(q_cmd)))
        return pos[:, [0, 2]], st.x[:, 2], st

    def command_for(self, x: NDArray) -> NDArray:
        """Commanded positions that put the true module at planar poses ``x`` without internal force.

        The calibrating zero position: an operator adjusts each AJ little by
        little until the module sits at ``x`` (the solve below iterates the
        following error, which depends on the commanded position).
        """
        q = self.machine.inverse_planar(x, None)
        for _ in range(5):
            q = self.machine.inverse_planar(x, self.theta_rows(q)) - self.following_error(q)
        return q

    def with_stiffness(self, stiffness: ArrayLike) -> "TrueModule":
        return replace(self, stiffness=np.asarray(stiffness, dtype=float))

    def with_pitch_compensation(self, comp: PitchCompensation | None) -> "TrueModule":
        return replace(self, pitch_comp=comp)
