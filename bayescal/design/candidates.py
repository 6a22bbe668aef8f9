"""Candidate poses and their whitened, column-scaled Jacobian blocks.

Column scaling (documented in docs/planning.md) makes the criteria
independent of the units of the parameters:

* ``"tolerance"`` (default): column ``j`` multiplied by the tolerance
  ``tol_j`` (one sigma of the prior), the scaling the identification uses;
* ``"candidates"``: column ``j`` divided by its root-mean-square norm per
  pose over the candidate set, ``c_j = sqrt(mean_i |J_i[:, j]|^2)``, so each
  column has unit average information per pose.

Rescaling a parameter (``theta_j' = a_j theta_j``, e.g. mm to um) divides
column ``j`` by ``a_j`` and multiplies its tolerance (and ``c_j``) by the
same factor, so both scalings give the same blocks, criterion values and
selections.  The unscaled Jacobian does not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..constants import SCALINGS
from ..contract import whiten
from ..errors import InputError
from ..identifiability import analyse_identifiability
from ..machines.base import Machine
from ..measurement import MeasurementModel

__all__ = ["CandidateSet", "SCALINGS", "box_points", "column_scale", "draw_candidates", "candidate_set_from_jacobian"]

# SCALINGS is defined in bayescal.constants (the command line offers them without importing numpy).


@dataclass(frozen=True)
class CandidateSet:
    """Usable candidate poses with their Jacobian blocks.

    Attributes
    ----------
    q : ndarray, shape (N, n_actuators)
        Commanded actuator positions of the usable candidates.
    blocks : ndarray, shape (N, dof, L)
        Whitened, column-scaled Jacobian of the identifiable parameters.
    blocks_prior : ndarray, shape (N, dof, P)
        Whitened, tolerance-scaled Jacobian of all parameters (for EIG).
    kept, fixed : tuple of str
        Identifiable parameters (the columns of ``blocks``) and those that
        the whole candidate set cannot identify.
    scale : ndarray, shape (P,)
        Column multipliers used (parameter units).
    scaling : str
    dof : int
    n_drawn, n_rejected : int
        Candidates drawn within ``q_limits`` and rejected (no forward
        solution, or a non-finite Jacobian).
    kept_index : ndarray of int, shape (L,)
        Columns of the parameter vector in ``blocks`` (the ``kept`` names).
    output_jacobian : ndarray, shape (n_e, 3, P), optional
        Tool-point Jacobian (mm per parameter unit, unscaled) at workspace
        poses, for criterion I.
    output_blocks : ndarray, shape (n_e, 3, L), optional
        The same, identifiable columns, tolerance-scaled (mm per tolerance).
    uniform : ndarray of bool, shape (N,), optional
        Which candidates were drawn uniformly within ``q_limits`` (not box
        points): what a random design draws from.
    """

    q: NDArray
    blocks: NDArray
    blocks_prior: NDArray
    kept: tuple[str, ...]
    fixed: tuple[str, ...]
    scale: NDArray
    scaling: str
    dof: int
    n_drawn: int
    n_rejected: int
    kept_index: NDArray | None = None
    output_jacobian: NDArray | None = None
    output_blocks: NDArray | None = None
    uniform: NDArray | None = None

    @property
    def n(self) -> int:
        return self.q.shape[0]

    @property
    def prior_blocks_kept(self) -> NDArray:
        """Whitened, tolerance-scaled Jacobian blocks of the identifiable parameters (N, dof, L)."""
        return self.blocks_prior[:, :, self.kept_index]

    @property
    def output_weight(self) -> NDArray | None:
        """``Q = mean_e G_e^T G_e`` (L, L) of ``output_blocks`` (criterion I), or None."""
        if self.output_blocks is None:
            return None
        from .criteria import output_weight

        return output_weight(self.output_blocks)


def column_scale(J_white: NDArray, tolerance: NDArray, scaling: str) -> NDArray:
    """Column multipliers (P,) for whitened candidate Jacobians ``J_white`` (N, dof, P)."""
    if scaling == "tolerance":
        return np.asarray(tolerance, dtype=float).copy()
    if scaling == "candidates":
        rms = np.sqrt(np.mean(np.sum(J_white**2, axis=1), axis=0))
        # a column no candidate sees stays unscaled; it is dropped as unidentifiable anyway
        return 1.0 / np.where(rms > 0, rms, 1.0)
    raise InputError(f"scaling: expected one of {', '.join(SCALINGS)}, got {scaling!r}")


def candidate_set_from_jacobian(
    q: NDArray, J_white: NDArray, tolerance: NDArray, layout, *, scaling: str = "tolerance",
    n_drawn: int | None = None, output_jacobian: NDArray | None = None, uniform: NDArray | None = None,
) -> CandidateSet:
    """Build a :class:`CandidateSet` from whitened per-pose Jacobians (N, dof, P).

    The identifiable set is the one of the whole candidate set
    (:func:`bayescal.identifiability.analyse_identifiability`): no pose
    selection can identify more.  ``output_jacobian`` (n_e, 3, P): the
    tool-point Jacobian (mm per parameter unit) at workspace poses, which
    criterion I needs.
    """
    J_white = np.asarray(J_white, dtype=float)
    N, dof, P = J_white.shape
    ok = np.all(np.isfinite(J_white), axis=(1, 2))
    q, J_white = np.asarray(q)[ok], J_white[ok]
    if q.shape[0] == 0:
        raise InputError("candidates: no usable candidate pose (all failed or had non-finite Jacobians)")
    scale = column_scale(J_white, tolerance, scaling)
    tol = np.asarray(tolerance, dtype=float)
    # identifiability is a property of the column space; any positive scaling gives the same set
    sub = J_white[: min(J_white.shape[0], 4000)].reshape(-1, P) * tol
    ida = analyse_identifiability(sub, layout)
    kept = np.asarray(ida.kept_index, dtype=int)
    if kept.size == 0:
        # every criterion but EIG works on the identifiable set: an empty one has no information to maximise
        raise InputError(f"candidates: none of the {P} parameters is identifiable from the {q.shape[0]} candidate "
                         "poses (the tolerance-scaled Jacobian has no usable column); expected a machine whose "
                         "[tolerance] values are comparable and whose q_limits move the tool")
    G = None if output_jacobian is None else np.asarray(output_jacobian, dtype=float)
    if G is not None and (G.ndim != 3 or G.shape[1:] != (3, P) or not np.all(np.isfinite(G))):
        raise InputError(f"output_jacobian: expected finite (n_poses, 3, {P}), got shape {G.shape}")
    return CandidateSet(
        q=q,
        blocks=J_white[:, :, kept] * scale[kept],
        blocks_prior=J_white * tol,
        kept=tuple(layout.names[j] for j in kept),
        fixed=tuple(layout.names[j] for j in ida.fixed_index),
        scale=scale,
        scaling=scaling,
        dof=dof,
        n_drawn=N if n_drawn is None else int(n_drawn),
        n_rejected=(N - int(ok.sum())) if n_drawn is None else int(n_drawn) - int(ok.sum()),
        kept_index=kept,
        output_jacobian=G,
        output_blocks=None if G is None else G[:, :, kept] * tol[kept],
        uniform=None if uniform is None else np.asarray(uniform, dtype=bool)[ok],
    )


#: Workspace poses (at most) at which the tool-point Jacobian for criterion I is evaluated.
N_OUTPUT = 2000

#: Up to this many actuators the full 3^m grid of the box is used; beyond, corners and face centres.
_FULL_GRID_MAX = 8


def box_points(q_limits: NDArray, *, inset: float = 0.0) -> NDArray:
    """Corners, edge midpoints, face centres and centre of the actuator box.

    Information-optimal designs put their poses at the extremes of the
    actuator box, where uniformly drawn candidates almost never land (the
    chance that a uniform draw is within 1 % of a given corner in every one
    of m coordinates is 0.01^m).  These points are the grid ``{lo, mid,
    hi}^m`` (3^m points: every corner, edge midpoint and face centre), or,
    for more than 8 actuators, the 2^m corners and the 2m face centres.

    Parameters
    ----------
    q_limits : ndarray, shape (m, 2)
        ``[min, max]`` per actuator (machine units).
    inset : float
        Fraction of each range to move every point towards the centre (a
        corner the machine cannot assemble often has an assemblable point
        just inside it).

    Returns
    -------
    ndarray, shape (n_points, m)
    """
    lim = np.asarray(q_limits, dtype=float)
    lo, hi = lim[:, 0], lim[:, 1]
    m = lim.shape[0]
    if m <= _FULL_GRID_MAX:
        u = np.stack(np.meshgrid(*([np.array([-1.0, 0.0, 1.0])] * m), indexing="ij"), axis=-1).reshape(-1, m)
    else:
        corners = np.stack(np.meshgrid(*([np.array([-1.0, 1.0])] * m), indexing="ij"), axis=-1).reshape(-1, m)
        faces = np.concatenate([np.eye(m), -np.eye(m)])
        u = np.concatenate([corners, faces])
    return 0.5 * (lo + hi) + 0.5 * (hi - lo) * (1.0 - inset) * u


def draw_candidates(
    machine: Machine, n: int, *, dof: int, rng: np.random.Generator, scaling: str = "tolerance",
    theta: NDArray | None = None, n_output: int = N_OUTPUT, box: bool = True,
) -> CandidateSet:
    """Draw ``n`` candidate poses uniformly within ``q_limits``, add the box's extremes, and linearise there.

    Parameters
    ----------
    machine : Machine
        Any kind; needs ``q_limits``.
    n : int
        Candidates drawn (those without a forward solution are rejected and
        counted in ``n_rejected``).
    dof : {6, 5, 3}
    rng : numpy.random.Generator
    scaling : {"tolerance", "candidates"}
    theta : ndarray, shape (P,), optional
        Geometry to linearise at (nominal by default).
    n_output : int
        Workspace poses for criterion I's output weight: the first
        ``n_output`` usable candidates (uniform within ``q_limits`` and
        solvable, the distribution the study's fresh evaluation poses come
        from), so no extra random numbers are drawn.
    box : bool
        Append :func:`box_points` of ``q_limits`` (corners, edges, faces;
        and the same set inset by 1 % and 5 % of each range), after the
        random draws, so that the uniform draws and their random numbers are
        the same with or without them.  Those the machine cannot assemble
        are rejected like any candidate.
    """
    from ..limits import check_memory

    # per candidate: its Jacobian block (dof x P) a few times over, and its forward kinematics
    check_memory(float(n) * 8 * (3 * dof * machine.n_params + 256), f"{int(n):,} candidate poses",
                 "lower --candidates")
    if n < 1:
        raise InputError(f"candidates: expected a positive number, got {n}")
    q = machine.sample_q(int(n), rng)
    n_uniform = q.shape[0]
    if box:
        q = np.concatenate([q] + [box_points(machine.q_limits, inset=f) for f in (0.0, 0.01, 0.05)])
    ok = np.asarray(machine.forward(q, theta).success, dtype=bool)
    if not ok.any():
        raise InputError(f"{machine.source}: none of {n} candidate poses within q_limits can be solved")
    model = MeasurementModel(machine=machine, q=q[ok], dof=dof)
    pred = model.predict(theta)
    good = np.asarray(pred.success, dtype=bool)
    J = whiten(model, model.jacobian(theta, pred))
    J[~good] = np.nan
    uniform = np.flatnonzero(ok) < n_uniform  # criterion I averages over the workspace: uniform draws only
    usable = np.flatnonzero(good & uniform & np.all(np.isfinite(J), axis=(1, 2)))[: max(1, int(n_output))]
    q_out = q[ok][usable]
    G = machine.tool_jacobian(q_out, theta, machine.forward(q_out, theta))[:, :3, :]
    G = G[np.all(np.isfinite(G), axis=(1, 2))]
    return candidate_set_from_jacobian(q[ok], J, machine.tolerance, machine.layout, scaling=scaling, n_drawn=q.shape[0],
                                       output_jacobian=G if G.shape[0] else None, uniform=uniform)
