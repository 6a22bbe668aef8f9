"""Closed-form rigid alignment of measured tool poses to a machine's nominal predictions.

The start of an instrument-frame fit (``--frame fit``) and the test that
suggests it: the rotation is found by Kabsch/Horn (weighted, with the
reflection guard) through :meth:`scipy.spatial.transform.Rotation.align_vectors`,
on the centred tool points and, for 6-DOF and 5-DOF recordings, on the
measured orientations (the platform's axes, or the tool axis), each
weighted by the inverse variance of its noise.  Rotations up to 180 degrees
and translations of any size are recovered.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..io.recording import Recording
from ..machines.base import Machine
from ..machines.framed import Frame, base_machine

__all__ = ["align_frame", "frame_start", "FrameCheck", "check_frame"]


def align_frame(
    p_inst: NDArray,
    p_base: NDArray,
    *,
    dirs_inst: NDArray | None = None,
    dirs_base: NDArray | None = None,
    sigma_position: float = 1.0,
    sigma_angle: float = 1.0,
) -> Frame:
    """The rigid frame ``(o, R)`` minimising ``sum |R p_inst + o - p_base|^2 / sp^2 + sum |R d_inst - d_base|^2 / sa^2``.

    Parameters
    ----------
    p_inst, p_base : ndarray, shape (n, 3)
        The same points in the instrument frame and in the base frame, mm.
    dirs_inst, dirs_base : ndarray, shape (m, 3), optional
        The same unit directions in both frames (platform axes, tool axes).
    sigma_position, sigma_angle : float
        Noise of the points (mm) and of the directions (rad): the weights.

    Returns
    -------
    Frame
        Pose of the instrument frame in the base frame.
    """
    p_inst = np.asarray(p_inst, dtype=float)
    p_base = np.asarray(p_base, dtype=float)
    ci, cb = p_inst.mean(axis=0), p_base.mean(axis=0)
    a, b = [p_base - cb], [p_inst - ci]
    w = [np.full(len(p_inst), 1.0 / sigma_position**2)]
    if dirs_inst is not None:
        a.append(np.asarray(dirs_base, dtype=float))
        b.append(np.asarray(dirs_inst, dtype=float))
        w.append(np.full(len(dirs_inst), 1.0 / sigma_angle**2))
    A, B, W = np.concatenate(a), np.concatenate(b), np.concatenate(w)
    if np.linalg.norm(A) == 0 or np.linalg.norm(B) == 0:
        raise InputError("rigid alignment: the poses do not move (all tool points equal); an instrument frame cannot be fitted")
    from scipy.spatial.transform import Rotation  # scipy.spatial: imported where used
    rot, _ = Rotation.align_vectors(A, B, weights=W)
    R = rot.as_matrix()
    return Frame(cb - R @ ci, R)


def _measured(rec: Recording, dof: int):
    """Measured directions per pose in the recording's frame: (n, k, 3) or None."""
    from scipy.spatial.transform import Rotation  # scipy.spatial: imported where used
    if dof == 6 and rec.rotvec is not None:
        return np.swapaxes(Rotation.from_rotvec(rec.rotvec).as_matrix(), 1, 2)  # rows = platform axes
    if dof >= 5:
        ax = rec.axis if rec.axis is not None else Rotation.from_rotvec(rec.rotvec).as_matrix()[:, :, 2]
        return ax[:, None, :]
    return None


def frame_start(machine: Machine, rec: Recording, *, dof: int | None = None) -> Frame:
    """Closed-form start of the instrument frame: the recording aligned to the nominal machine.

    Parameters
    ----------
    machine : Machine
        Its base machine's nominal forward kinematics predicts the tool
        poses at the recording's ``q`` in the base frame.
    rec : Recording
        Measured in the unknown instrument frame.
    dof : int, optional
        How much of the measurement to use (6 uses the platform axes, 5 the
        tool axis, 3 the points only); default: all the recording holds.

    Returns
    -------
    Frame
        Pose of the instrument frame in the base frame.
    """
    base = base_machine(machine)
    dof = rec.dof if dof is None else min(dof, rec.dof)
    nom = base.forward(base.check_q(rec.q))
    ok = nom.success
    if not ok.any():
        raise InputError(f"{rec.path}: the nominal machine {base.source} cannot assemble any pose; cannot align a frame")
    dirs_i = _measured(rec, dof)
    dirs_b = None
    if dirs_i is not None:
        dirs_b = np.swapaxes(nom.rotation, 1, 2) if dof == 6 else nom.rotation[:, None, :, 2]
        dirs_i, dirs_b = dirs_i[ok].reshape(-1, 3), dirs_b[ok].reshape(-1, 3)
    frame = align_frame(
        rec.position[ok], nom.position[ok], dirs_inst=dirs_i, dirs_base=dirs_b,
        sigma_position=base.noise.sigma_position, sigma_angle=base.noise.sigma_angle,
    )
    if dirs_i is None:
        # position only: an unknown tool point (a marker fixed somewhere on the last link) bends the
        # point-to-point alignment, and Gauss-Newton from a frame turned by tens of degrees lands in a
        # local minimum (seen on a real mocap-calibrated arm: marker 95 mm from the nominal tool
        # point, 12.9 mm RMS instead of 2.75 mm). Register the frame and a tool-point offset together.
        frame = register_with_tool_offset(rec.position[ok], nom.position[ok], nom.rotation[ok], frame)
    return frame


def register_with_tool_offset(
    p_inst: NDArray, p_base: NDArray, R_tool: NDArray, frame: Frame, *, iters: int = 500, gain: float = 2.0,
) -> Frame:
    """The frame of a joint rigid registration with an unknown tool-point offset, if it fits far better.

    Minimises ``sum_i |R p_inst_i + o - (p_base_i + R_tool_i dt)|^2`` over the
    frame ``(o, R)`` and an offset ``dt`` of the tool point in the tool frame,
    by alternating the closed-form alignment and the closed-form ``dt``
    (``R_tool`` orthonormal: ``dt = mean_i R_tool_i^T (R p_inst_i + o - p_base_i)``);
    each half-step lowers the sum, so the cost is monotone.  The frame is
    returned only when it fits ``gain`` times better (RMS) than ``frame``:
    a nominal tool point already close to the truth keeps the plain alignment.

    Parameters
    ----------
    p_inst : ndarray, shape (n, 3)
        Measured points, instrument frame, mm.
    p_base : ndarray, shape (n, 3)
        Nominal tool points, base frame, mm.
    R_tool : ndarray, shape (n, 3, 3)
        Nominal orientation of the frame the tool point is fixed in.
    frame : Frame
        The plain alignment (start, and the answer if registration does not help).
    """
    def rms(fr: Frame, dt: NDArray) -> float:
        return float(np.sqrt(np.mean(np.sum((fr.to_base(p_inst) - p_base - R_tool @ dt) ** 2, axis=1))))

    dt = np.zeros(3)
    fr = frame
    start = rms(frame, dt)
    for _ in range(int(iters)):
        dt_new = np.mean(np.einsum("nji,nj->ni", R_tool, fr.to_base(p_inst) - p_base), axis=0)
        fr = align_frame(p_inst, p_base + R_tool @ dt_new)
        if np.max(np.abs(dt_new - dt)) < 1e-9 * max(1.0, float(np.max(np.abs(dt_new)))):
            dt = dt_new
            break
        dt = dt_new
    return fr if rms(fr, dt) * gain < start else frame


@dataclass(frozen=True)
class FrameCheck:
    """Does a rigid transform explain the recording far better than the tolerances?

    Attributes
    ----------
    rms_nominal : float
        Tool-point RMS (mm) of the recording against the nominal machine, as given.
    rms_rigid : float
        The same after the best rigid transform of the measured points.
    rms_tolerance : float
        Tool-point RMS (mm) the tolerances explain: the prior-predictive RMS
        ``sqrt(mean_i trace(J_i S^2 J_i^T))`` of the nominal machine at the poses.
    frame : Frame
        The rigid transform (pose of the instrument frame in the base frame).
    scale : float
        Spread of the nominal points over the spread of the measured ones
        (1 when the units agree).
    """

    rms_nominal: float
    rms_rigid: float
    rms_tolerance: float
    frame: Frame
    scale: float

    #: The nominal RMS must exceed the tolerance RMS by this factor ...
    BEYOND = 5.0
    #: ... and the rigid transform must cut it by this factor, for the check to fire.
    DROP = 5.0
    #: Firing with a nominal RMS above this many times the tolerance RMS: refused, not warned.
    REFUSE = 100.0

    @property
    def fires(self) -> bool:
        """True when a rigid transform, not the tolerances, explains the recording (suggest ``--frame fit``)."""
        return self.rms_nominal > self.BEYOND * self.rms_tolerance and self.rms_rigid * self.DROP < self.rms_nominal

    @property
    def refuses(self) -> bool:
        """True when it fires and the nominal RMS exceeds :attr:`REFUSE` times what the tolerances explain."""
        return self.fires and self.rms_nominal > self.REFUSE * self.rms_tolerance

    @property
    def angle(self) -> float:
        """Rotation angle of the rigid transform, rad."""
        return float(np.linalg.norm(self.frame.rotation_vector))

    def message(self) -> str:
        return (
            f"the recording's tool points are {self.rms_nominal:.4g} mm RMS from the nominal machine, far more than the "
            f"{self.rms_tolerance:.3g} mm its tolerances explain, and a rigid transform (translation "
            f"{np.linalg.norm(self.frame.origin):.4g} mm, rotation {np.degrees(self.angle):.3g} deg) brings them to "
            f"{self.rms_rigid:.3g} mm: the recording looks like it is in an instrument's frame, not the base frame; "
            "try --frame fit"
        )

    def to_dict(self) -> dict:
        return {
            "fires": self.fires, "refuses": self.refuses, "rms_nominal": self.rms_nominal, "rms_rigid": self.rms_rigid,
            "rms_tolerance": self.rms_tolerance, "translation": float(np.linalg.norm(self.frame.origin)),
            "rotation_deg": float(np.degrees(self.angle)), "scale": self.scale,
        }


def check_frame(machine: Machine, rec: Recording) -> FrameCheck | None:
    """Compare the recording (read as base frame) with the nominal machine, as given and rigidly aligned.

    Uses the tool points only (every recording has them).  ``machine`` may
    carry a known instrument frame; the check is then in that frame.
    None when there is nothing to align (fewer than 3 solvable poses, or
    measured points that do not move).
    """
    q = machine.check_q(rec.q)
    nom = machine.forward(q)
    ok = nom.success
    pm, pn = rec.position[ok], nom.position[ok]
    if ok.sum() < 3 or np.ptp(pm, axis=0).max() == 0 or np.ptp(pn, axis=0).max() == 0:
        return None
    rms0 = float(np.sqrt(np.mean(np.sum((pm - pn) ** 2, axis=1))))
    f = align_frame(pm, pn)
    rms1 = float(np.sqrt(np.mean(np.sum((f.to_base(pm) - pn) ** 2, axis=1))))
    J = machine.tool_jacobian(q[ok], None, nom_subset(nom, ok))[:, :3] * machine.tolerance
    rms_tol = float(np.sqrt(np.mean(np.sum(J**2, axis=(1, 2)))))
    s_m = np.sqrt(np.mean(np.sum((pm - pm.mean(0)) ** 2, axis=1)))
    s_n = np.sqrt(np.mean(np.sum((pn - pn.mean(0)) ** 2, axis=1)))
    return FrameCheck(rms0, rms1, rms_tol, f, float(s_n / s_m) if s_m > 0 else float("nan"))


def nom_subset(poses, mask):
    """The solved poses ``mask`` (state fields indexed too)."""
    from ..machines.base import ToolPoses, map_state

    sub = map_state(lambda a: a[mask], poses.state)  # any kind's state, nested ones (hybrid) included
    return ToolPoses(poses.position[mask], poses.rotation[mask], poses.success[mask],
                     tuple(np.asarray(poses.message, dtype=object)[mask]), sub)
