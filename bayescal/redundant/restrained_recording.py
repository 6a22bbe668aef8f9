"""Recordings of a redundant module simulated with its true restrained physics (for tests and studies).

Independent of the effect models: the platform settles where the elastic
energy of the position-controlled drives is least
(:func:`bayescal.redundant.physics.solve_restrained`), and the instrument
reads the tool point there.  Nothing here calls an effect's ``delta_q``, so
``redundancy_preload`` can be checked against it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..io.recording import Recording
from ..machines.raspm import Raspm
from ..simulate import draw_errors
from .physics import solve_restrained

__all__ = ["RestrainedRecording", "restrained_recording", "true_effect_values"]


@dataclass(frozen=True)
class RestrainedRecording:
    """A simulated recording and its truth.

    Attributes
    ----------
    recording : Recording
        Position-only (3-DOF) unless asked otherwise; ``q`` as commanded (the redundant drive's offset included).
    theta : ndarray, shape (P,)
        True geometric errors (mm, rad).
    stiffness : ndarray, shape (m,)
        Drive stiffnesses, N/mm.
    max_force : float
        Largest internal drive force over the poses, N.
    """

    recording: Recording
    theta: NDArray
    stiffness: NDArray
    max_force: float


def restrained_recording(
    machine: Raspm,
    n_poses: int,
    seed: int,
    *,
    offset_mm: float = 0.0,
    stiffness_n_per_um: tuple[float, float] = (150.0, 500.0),
    alternate_offset: bool = False,
    dof: int = 3,
) -> RestrainedRecording:
    """Poses commanded from the nominal model, the redundant drive ``offset_mm`` beyond, settled by energy minimisation.

    Parameters
    ----------
    machine : Raspm
        Nominal machine (one redundant drive).
    n_poses : int
    seed : int
        Seeds the errors (drawn from the tolerances), the stiffnesses, then the poses and the noise
        (the same seed with more poses is the same module, its first poses the same).
    offset_mm : float
        The redundant drive's commanded offset from the nominal compatible position, mm.
    stiffness_n_per_um : (float, float)
        Range of the uniformly drawn drive stiffnesses, N/um.
    alternate_offset : bool
        Command the offset at every other pose only (a recording designed to show the compliance ratios).
    dof : {3, 6}
        Position only, or position and orientation.
    """
    rng = np.random.default_rng(seed)
    theta = draw_errors(machine, rng)
    # the module first (geometry, stiffnesses), then the poses: one seed is one module whatever n_poses
    k = rng.uniform(*stiffness_n_per_um, machine.n_actuators) * 1e3
    q = machine.inverse_planar(machine.sample_planar(n_poses, rng))
    r = machine.redundant[0]
    q[:, r] += offset_mm * ((np.arange(n_poses) % 2) if alternate_offset else 1.0)
    st = solve_restrained(machine, q, theta, k)
    pos, R = machine.tool_from_planar(st.x, theta)
    pos = pos + rng.normal(0.0, machine.noise.sigma_position, pos.shape)
    rotvec = None
    if dof == 6:
        from ..geometry import so3_exp, so3_log

        rotvec = so3_log(so3_exp(rng.normal(0.0, machine.noise.sigma_angle, (n_poses, 3))) @ R)
    rec = Recording(q=q, position=pos, rotvec=rotvec, path=f"restrained-offset{offset_mm}-seed{seed}")
    return RestrainedRecording(rec, theta, k, float(np.abs(st.force).max()))


def true_effect_values(machine: Raspm, sim: RestrainedRecording, params) -> dict[str, float]:
    """The true values of ``redundancy_preload``'s parameters ``params`` (names as the effect reports them).

    Compliance ratios ``c_s / c_r = k_r / k_s``; the redundant drive's offset
    is its rail's zero error (the commanded offset is in the recorded ``q``);
    the redundant chain's geometric errors are those drawn.
    """
    r = machine.redundant[0]
    names = [n.replace(".", "_") for n in machine.layout.names]
    out = {}
    for p in params:
        head, _, tail = p.name.partition(".")
        if head == "compliance_ratio":
            out[p.name] = float(sim.stiffness[r] / sim.stiffness[int(tail[1:]) - 1])
        elif head == "offset":
            out[p.name] = float(sim.theta[machine.offset_index()[r]])
        else:
            out[p.name] = float(sim.theta[names.index(tail)])
    return out
