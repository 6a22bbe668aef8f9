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

from ..errors import InputError
from ..identifiability import analyse_identifiability
from ..machines.base import Machine
from ..measurement import MeasurementModel

__all__ = ["CandidateSet", "SCALINGS", "column_scale", "draw_candidates", "candidate_set_from_jacobian"]

SCALINGS = ("tolerance", "candidates")


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

    @property
    def n(self) -> int:
        return self.q.shape[0]


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
    n_drawn: int | None = None,
) -> CandidateSet:
    """Build a :class:`CandidateSet` from whitened per-pose Jacobians (N, dof, P).

    The identifiable set is the one of the whole candidate set
    (:func:`bayescal.identifiability.analyse_identifiability`): no pose
    selection can identify more.
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
    kept = ida.kept_index
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
    )


def draw_candidates(
    machine: Machine, n: int, *, dof: int, rng: np.random.Generator, scaling: str = "tolerance",
    theta: NDArray | None = None,
) -> CandidateSet:
    """Draw ``n`` candidate poses uniformly within ``q_limits`` and linearise there.

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
    """
    if n < 1:
        raise InputError(f"candidates: expected a positive number, got {n}")
    q = machine.sample_q(int(n), rng)
    ok = np.asarray(machine.forward(q, theta).success, dtype=bool)
    if not ok.any():
        raise InputError(f"{machine.source}: none of {n} candidate poses within q_limits can be solved")
    model = MeasurementModel(machine=machine, q=q[ok], dof=dof)
    pred = model.predict(theta)
    good = np.asarray(pred.success, dtype=bool)
    J = model.jacobian(theta, pred) / model.sigma[None, :, None]
    J[~good] = np.nan
    return candidate_set_from_jacobian(q[ok], J, machine.tolerance, machine.layout, scaling=scaling, n_drawn=n)
