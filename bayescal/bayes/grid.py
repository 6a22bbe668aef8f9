"""Compensation grids with uncertainty: the predicted tool-point correction and its std at every node.

Nodes span the actuator range (``q_limits``), ``n`` values per actuator, so
the grid works for any machine kind.  At node ``q`` the predicted error
of the tool point is

    e(q) = p(q, theta_hat) - p(q, 0)        (mm, base frame),

the correction is ``-e(q)`` (what a controller adds to the nominal tool
point), and its std comes from

* a covariance ``C`` of the identified parameters ``theta[idx]``: the
  linearised ``diag(G C G^T)`` with ``G = dp/dtheta[idx]`` at ``theta_hat``;
* or posterior draws: the sample std of ``p(q, theta_s)`` over draws,
  all draws and nodes in one vectorised forward-kinematics call.

Checked on simulation (tests/bayes/test_grid.py): the standardised node
errors ``(e_true - e_hat) / std`` have mean about 0 and spread about 1.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..io import write_text_atomic
from ..machines.base import Machine
from .accuracy import tool_point_std_at

__all__ = ["CompensationGrid", "compensation_grid", "actuator_nodes", "grid_node_count", "check_grid_size"]


@dataclass(frozen=True)
class CompensationGrid:
    """Correction and its std at the nodes of a regular actuator grid.

    Attributes
    ----------
    machine_name : str
    axis_names : tuple of str
        ``q1 .. qm``.
    axis_unit : str
    axes : tuple of ndarray
        Node values per actuator.
    correction : ndarray, shape (*shape, 3)
        ``-(p(q, theta_hat) - p(q, 0))``, mm.
    std : ndarray, shape (*shape, 3)
        Its one-sigma uncertainty per axis, mm.
    source : str
        How the std was obtained.
    """

    machine_name: str
    axis_names: tuple[str, ...]
    axis_unit: str
    axes: tuple[NDArray, ...]
    correction: NDArray
    std: NDArray
    source: str

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(a.size for a in self.axes)

    @property
    def q(self) -> NDArray:
        """Node actuator vectors in C order, shape (n_nodes, m)."""
        return actuator_nodes(self.axes)

    def to_csv(self) -> str:
        """One row per node: q1..qm, dx, dy, dz (correction, mm), sx, sy, sz (std, mm)."""
        head = ",".join(self.axis_names + ("dx", "dy", "dz", "sx", "sy", "sz"))
        vals = np.column_stack([self.q, self.correction.reshape(-1, 3), self.std.reshape(-1, 3)])
        return head + "\n" + "\n".join(",".join(f"{v:.9g}" for v in row) for row in vals) + "\n"

    def write_csv(self, path: str | os.PathLike) -> Path:
        return write_text_atomic(path, self.to_csv())

    def to_dict(self) -> dict:
        return {
            "machine": self.machine_name,
            "axes": {n: a for n, a in zip(self.axis_names, self.axes)},
            "n_nodes": int(np.prod(self.shape)),
            "std_source": self.source,
            **grid_summary(self.correction, self.std),
        }

    def report(self) -> str:
        d = self.to_dict()
        return "\n".join([
            f"bayescal compensation grid of '{self.machine_name}'",
            f"  nodes           {' x '.join(str(s) for s in self.shape)} over {', '.join(self.axis_names)} ({self.axis_unit})",
            f"  correction      max {d['max_correction_mm']:.5f} mm, RMS {d['rms_correction_mm']:.5f} mm",
            f"  its std (3-D)   max {d['max_std_mm']:.5f} mm, RMS {d['rms_std_mm']:.5f} mm ({self.source})",
        ])


def grid_summary(correction: NDArray, std: NDArray) -> dict[str, float]:
    """Largest and RMS 3-D correction and 3-D std over the nodes (mm), the figures every grid reports.

    Parameters
    ----------
    correction, std : ndarray, shape (..., 3)
        Per node: the tool-point correction (or error) and its one-sigma std per axis, mm.
    """
    mag = np.linalg.norm(correction, axis=-1)
    s3 = np.sqrt(np.sum(np.asarray(std) ** 2, axis=-1))
    return {
        "max_correction_mm": float(mag.max()),
        "rms_correction_mm": float(np.sqrt(np.mean(mag**2))),
        "max_std_mm": float(s3.max()),
        "rms_std_mm": float(np.sqrt(np.mean(s3**2))),
    }


def actuator_nodes(axes) -> NDArray:
    """All combinations of the axis values, C order, shape (n_nodes, m)."""
    return np.array(list(itertools.product(*axes)), dtype=float)


def grid_node_count(machine: Machine, n: int, space: str = "actuator") -> int:
    """Nodes of a grid of ``n`` per axis: ``n ** n_actuators`` in actuator space, at most ``n ** 3`` in tool space."""
    return int(n) ** (machine.n_actuators if space == "actuator" else 3)


def check_grid_size(machine: Machine, n: int, space: str = "actuator", *, n_samples: int = 0) -> None:
    """Refuse, before any work, a grid whose arrays would not fit in memory (:func:`bayescal.limits.check_memory`).

    Parameters
    ----------
    machine : Machine
        The machine (its parameters and actuators size the per-node arrays).
    n : int
        Nodes per axis (``--nodes``); at least 2.
    space : {"actuator", "tool", "auto"}
        ``auto``: actuator space when the whole ``q_limits`` box is reachable, else tool space.
    n_samples : int
        Posterior draws evaluated at every node (0: a covariance).
    """
    from ..limits import check_memory

    if isinstance(n, bool) or int(n) != n or n < 2:
        raise InputError(f"n (--nodes): expected at least 2 nodes per axis, got {n!r}")
    if space == "auto":
        space = "actuator" if machine.actuator_box_reachable else "tool"
    nodes = grid_node_count(machine, n, space)
    # per node: the poses and the tool-point Jacobian (3 x P) a few times over, and each draw's forward kinematics
    per_node = 8.0 * (12 * machine.n_params + 64 * machine.n_actuators + 256) + 8.0 * 64 * n_samples
    axes = machine.n_actuators if space == "actuator" else 3
    check_memory(nodes * per_node, f"a grid of {int(n)}^{axes} = {nodes:,} nodes", "lower --nodes (nodes per axis)")


def compensation_grid(
    machine: Machine,
    theta: ArrayLike,
    *,
    covariance: ArrayLike | None = None,
    free: ArrayLike | None = None,
    samples: ArrayLike | None = None,
    n: int = 9,
    axes: tuple[ArrayLike, ...] | None = None,
    aux: dict | None = None,
) -> CompensationGrid:
    """The grid of corrections and their std for identified errors ``theta``.

    Parameters
    ----------
    machine : Machine
    theta : array_like, shape (P,)
        Identified errors.
    covariance : array_like, shape (k, k), optional
        Covariance of ``theta[free]`` (linearised std).
    free : array_like of bool, shape (P,), optional
        Which parameters ``covariance``/``samples`` refer to (default all).
    samples : array_like, shape (S, k), optional
        Posterior draws of ``theta[free]`` (sample std instead of linearised).
    n : int
        Nodes per actuator within ``q_limits``.
    axes : tuple of array_like, optional
        Node values per actuator instead.
    aux : dict of str to float, optional
        Auxiliary channels at which the machine's stored effects
        (``machine.effects``, ``[effect.*]`` tables) act at every node, e.g.
        ``{"payload_kg": 5.0, "temp_C": 25.0}``: the correction is then the
        one under that payload or temperature.  A channel not given is
        absent, as in a recording without it (no payload; thermal expansion
        needs ``temp_C``).  Nodes have no approach direction: backlash and
        elapsed-time effects read none
        (:func:`bayescal.effects.stored.static_effect_delta_q`).

    Returns
    -------
    CompensationGrid
    """
    theta = machine.check_theta(theta)
    axes = _grid_axes(machine, axes, n, samples)
    q_cmd = actuator_nodes(axes)
    shape = tuple(a.size for a in axes) + (3,)
    nominal = machine.forward(q_cmd, None)
    # where the drives really are at each node under the stated aux (the correction includes the effects,
    # and, where the parameters hold effect parameters, how they move the drives)
    q, dq_dtheta = machine.node_actuators(q_cmd, theta, aux)
    est = machine.forward(q, theta, guess=nominal)
    bad = ~(nominal.success & est.success)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"grid node {i + 1} (q = {q_cmd[i].tolist()}) cannot be solved; narrow the grid with --range q1=LO:HI "
            f"(one per actuator, q1..q{machine.n_actuators}), or span the tool point with --space tool"
        )
    reached = est.position
    dx = machine.node_tool_offset(q_cmd, theta, aux)
    if dx is not None:  # effects that move the tool, not the drives (a column bending under its load)
        reached = reached + dx[:, :3]
    correction = -(reached - nominal.position)
    std, source = tool_point_std_at(machine, q, theta, free, covariance=covariance, samples=samples, caller="compensation_grid",
                                    dq_dtheta=dq_dtheta)
    unit = "mm or rad per actuator"  # docs/formats.md section 2: mm for prismatic, rad for revolute actuators
    return CompensationGrid(
        machine_name=machine.name,
        axis_names=tuple(f"q{i + 1}" for i in range(machine.n_actuators)),
        axis_unit=unit,
        axes=axes,
        correction=correction.reshape(shape),
        std=std.reshape(shape),
        source=source,
    )


def _grid_axes(machine, axes, n: int, samples) -> tuple[NDArray, ...]:
    """One node axis per actuator: ``axes`` as given, or ``n`` nodes spanning each ``q_limits`` (checked)."""
    if axes is None:
        if machine.q_limits is None:
            raise InputError(f"{machine.source}: no [workspace] q_limits to span a grid; add them to the machine file "
                             "(or, in the library, pass axes)")
        check_grid_size(machine, n, "actuator", n_samples=0 if samples is None else len(samples))
        axes = tuple(np.linspace(lo, hi, n) for lo, hi in machine.q_limits)
    axes = tuple(np.asarray(a, dtype=float) for a in axes)
    if len(axes) != machine.n_actuators:
        raise InputError(f"axes: expected {machine.n_actuators} (one per actuator), got {len(axes)}")
    return axes
