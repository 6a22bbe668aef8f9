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

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..geometry import so3_exp
from ..io.recording import Recording
from ..machines.base import Machine
from ..machines.framed import Frame

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
    # weighted Kabsch (the rotation minimising sum w |a - R b|^2), as scipy's Rotation.align_vectors
    # computes it; written out because importing scipy.spatial cost every identify 0.36 s
    U, _, Vt = np.linalg.svd((B * W[:, None]).T @ A)
    d = 1.0 if np.linalg.det(Vt.T @ U.T) >= 0 else -1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return Frame(cb - R @ ci, R)


def _measured(rec: Recording, dof: int):
    """Measured directions per pose in the recording's frame: (n, k, 3) or None."""
    if dof == 6 and rec.rotvec is not None:
        return np.swapaxes(so3_exp(rec.rotvec), 1, 2)  # rows = platform axes
    if dof >= 5:
        ax = rec.axis if rec.axis is not None else so3_exp(rec.rotvec)[:, :, 2]
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
    base = machine.base_machine()
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
    """Does a rigid transform explain the recording far better than the tolerances, or does a simpler mistake?

    Three mistakes move a whole recording away from the nominal machine; each is
    fitted to the tool points in closed form and the one that explains them best
    (smallest RMS, at least :attr:`DROP` times below the nominal RMS) is named
    (:attr:`explanation`):

    * ``"frame"``: the recording is in an instrument's frame (a rigid transform);
    * ``"tool"``: the machine file's ``[tool] point`` is wrong (a tool length):
      an offset of the tool point, fixed in the tool's own frame, moves every
      measured point by the pose's rotation of it;
    * ``"swap"``: two position columns are exchanged (a reflection, which no
      rigid transform can undo), possibly in an instrument's frame as well.

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
    rms_tool : float
        Tool-point RMS (mm) after the best offset of the tool point (no frame); NaN when the machine has
        no single ``tool.point`` (a hybrid machine).
    tool_offset : ndarray, shape (3,), or None
        That offset of ``[tool] point``, mm, in the frame the machine file gives the point in.
    tool_sigmas : float
        Its largest component in tolerances of ``tool_point``.
    swapped : str
        The exchanged columns that explain the recording best (``"x, y"``), ``"mirrored"`` when a
        mirror image needs a rigid transform as well (which columns cannot be told then), or ``""``.
    rms_swapped : float
        Tool-point RMS (mm) with those columns exchanged back (after a rigid transform when
        ``swapped_aligned``); NaN when not computed.
    swapped_aligned : bool
        The mirror image needs a rigid transform as well (an instrument frame).
    rms_tolerance_machine : float
        :attr:`rms_tolerance` without the tool's parameters: what the machine's own tolerances
        explain when the file declares the tool point unknown (a tolerance of a metre).
    scale_one_out : float
        :attr:`scale` with the pose farthest from the nominal machine (after the rigid transform) left
        out; NaN when not computed.  Wrong units scale every pose alike; one mistyped cell (163 for
        16.3 mm) moves the spread too, but leaving its pose out brings the scale back to 1.
    odd_line : int
        The CSV line of that pose (0 when not computed).
    odd_column : str
        Its measured column farthest from the nominal machine (``"x"``, ``"y"`` or ``"z"``, in the
        recording's own axes).
    """

    rms_nominal: float
    rms_rigid: float
    rms_tolerance: float
    frame: Frame
    scale: float
    rms_tool: float = float("nan")
    tool_offset: NDArray | None = None
    tool_sigmas: float = float("nan")
    swapped: str = ""
    rms_swapped: float = float("nan")
    swapped_aligned: bool = False
    rms_tolerance_machine: float = float("nan")
    scale_one_out: float = float("nan")
    odd_line: int = 0
    odd_column: str = ""

    #: The nominal RMS must exceed the tolerance RMS by this factor ...
    BEYOND = 5.0
    #: ... and the rigid transform must cut it by this factor, for the check to fire.
    DROP = 5.0
    #: Firing with a nominal RMS above this many times the tolerance RMS: refused, not warned.
    REFUSE = 100.0
    #: A tool-point offset within this many tolerances is the identification's business, not a mistake.
    TOOL_SIGMAS = 10.0

    @property
    def explanation(self) -> str | None:
        """``"frame"``, ``"tool"`` or ``"swap"``: the mistake that explains the recording best, or None.

        A candidate must cut the nominal RMS by :attr:`DROP`; a tool offset must
        also lie beyond :attr:`TOOL_SIGMAS` tolerances, and an exchange of columns
        must beat the best rigid transform by :attr:`DROP` too (for points in a
        plane, a rotation undoes an exchange: that is a frame).  The smallest RMS wins.
        """
        cands = {"frame": self.rms_rigid}
        if math.isfinite(self.rms_swapped) and self.rms_swapped * self.DROP < self.rms_rigid:
            cands["swap"] = self.rms_swapped
        if math.isfinite(self.tool_sigmas) and self.tool_sigmas > self.TOOL_SIGMAS:
            cands["tool"] = self.rms_tool
        ok = {k: v for k, v in cands.items() if math.isfinite(v) and v * self.DROP < self.rms_nominal}
        return min(ok, key=ok.get) if ok else None

    @property
    def fires(self) -> bool:
        """True when a rigid transform, not the tolerances nor a simpler mistake, explains the recording.

        Then suggest ``--frame fit``: the nominal RMS exceeds :attr:`BEYOND` times what
        the tolerances explain, and the rigid transform is the best explanation.
        """
        return self.rms_nominal > self.BEYOND * self.rms_tolerance and self.explanation == "frame"

    @property
    def refuses(self) -> bool:
        """True when it fires and the nominal RMS exceeds :attr:`REFUSE` times what the tolerances explain."""
        return self.fires and self.rms_nominal > self.REFUSE * self.rms_tolerance

    @property
    def angle(self) -> float:
        """Rotation angle of the rigid transform, rad."""
        return float(np.linalg.norm(self.frame.rotation_vector))

    def _rigid_words(self) -> str:
        return (f"a rigid transform (translation {np.linalg.norm(self.frame.origin):.4g} mm, rotation "
                f"{np.degrees(self.angle):.3g} deg)")

    def message(self) -> str:
        return (
            f"the recording's tool points are {self.rms_nominal:.4g} mm RMS from the nominal machine, far more than the "
            f"{self.rms_tolerance:.3g} mm its tolerances explain, and {self._rigid_words()} brings them to "
            f"{self.rms_rigid:.3g} mm: the recording looks like it is in an instrument's frame, not the base frame; "
            "try --frame fit"
        )

    def warning(self) -> str | None:
        """What to tell the user before identifying: the frame message, a wrong tool point or swapped columns."""
        if self.fires:
            return self.message()
        if self.explanation in ("tool", "swap"):
            return self.cause()
        return None

    def cause(self) -> str | None:
        """The likely cause, in words, of a recording this far from the nominal machine (None: no simple mistake)."""
        kind = self.explanation
        if kind == "tool":
            d = self.tool_offset
            return (
                f"wrong tool point: moving [tool] point by ({d[0]:.4g}, {d[1]:.4g}, {d[2]:.4g}) mm "
                f"({np.linalg.norm(d):.4g} mm, {self.tool_sigmas:.0f} tolerances) brings the recording from "
                f"{self.rms_nominal:.4g} mm to {self.rms_tool:.3g} mm RMS of the nominal machine ({self._rigid_words()} "
                f"only to {self.rms_rigid:.3g} mm); check the tool's length and the machine file's [tool] point"
            )
        if kind == "swap" and not self.swapped_aligned:
            a, b = self.swapped.split(", ")
            return (
                f"swapped columns: with columns {a} and {b} exchanged the recording is {self.rms_swapped:.3g} mm "
                f"RMS from the nominal machine, against {self.rms_nominal:.4g} mm as given and {self.rms_rigid:.3g} mm "
                f"after the best rigid transform (which cannot undo an exchange); check the order of the x, y, z columns"
            )
        if kind == "swap":
            return (
                f"swapped columns: the recording is a mirror image of the nominal machine's tool points (two of x, y, z "
                f"exchanged, or one reversed): mirrored and rigidly aligned it is {self.rms_swapped:.3g} mm RMS from "
                f"them, against {self.rms_rigid:.3g} mm after the best rigid transform; check the order and signs of the "
                "x, y, z columns (the instrument's frame may be left-handed), then try --frame fit"
            )
        if kind == "frame" and self.rms_nominal > self.BEYOND * self.rms_tolerance_machine:
            return (
                f"missing --frame fit: {self._rigid_words()} brings the recording's tool points from "
                f"{self.rms_nominal:.4g} mm to {self.rms_rigid:.3g} mm RMS of the nominal machine: the recording looks "
                "like it is in an instrument's frame, not the base frame; identify with --frame fit"
            )
        return None

    def to_dict(self) -> dict:
        return {
            "fires": self.fires, "refuses": self.refuses, "rms_nominal": self.rms_nominal, "rms_rigid": self.rms_rigid,
            "rms_tolerance": self.rms_tolerance, "translation": float(np.linalg.norm(self.frame.origin)),
            "rotation_deg": float(np.degrees(self.angle)), "scale": self.scale, "explanation": self.explanation,
            "rms_tool": self.rms_tool, "tool_offset": None if self.tool_offset is None else self.tool_offset.tolist(),
            "swapped": self.swapped or None, "rms_swapped": self.rms_swapped,
            "rms_tolerance_machine": self.rms_tolerance_machine, "scale_one_out": self.scale_one_out,
            "odd_line": self.odd_line or None, "odd_column": self.odd_column or None,
        }


def check_frame(machine: Machine, rec: Recording) -> FrameCheck | None:
    """Compare the recording (read as base frame) with the nominal machine, as given and rigidly aligned.

    Uses the tool points only (every recording has them).  ``machine`` may
    carry a known instrument frame; the check is then in that frame.  The
    simpler mistakes a rigid transform is weighed against (a tool-point
    offset, exchanged columns) are fitted too (:class:`FrameCheck`).
    None when there is nothing to align (fewer than 3 solvable poses, or
    measured points that do not move).
    """
    q = machine.check_q(rec.q)
    nom = machine.forward(q)
    ok = nom.success
    pm, pn = rec.position[ok], nom.position[ok]
    if ok.sum() < 3 or np.ptp(pm, axis=0).max() == 0 or np.ptp(pn, axis=0).max() == 0:
        return None
    rms0 = _rms(pm - pn)
    f = align_frame(pm, pn)
    rms1 = _rms(f.to_base(pm) - pn)
    J = machine.tool_jacobian(q[ok], None, nom_subset(nom, ok))[:, :3]
    JS = J * machine.tolerance
    rms_tol = float(np.sqrt(np.mean(np.sum(JS**2, axis=(1, 2)))))
    own = np.array([not n.startswith("tool.") for n in machine.layout.names])
    rms_tol_machine = float(np.sqrt(np.mean(np.sum(JS[:, :, own] ** 2, axis=(1, 2)))))
    s_m = np.sqrt(np.mean(np.sum((pm - pm.mean(0)) ** 2, axis=1)))
    s_n = np.sqrt(np.mean(np.sum((pn - pn.mean(0)) ** 2, axis=1)))
    tool = _tool_offset_fit(machine, J, pm - pn)
    swap = _best_swap(pm, pn, rms1)
    return FrameCheck(rms0, rms1, rms_tol, f, float(s_n / s_m) if s_m > 0 else float("nan"), *tool, *swap,
                      rms_tol_machine, *_one_pose_out(pm, pn, f, rec.lines[ok]))


def _spread(p: NDArray) -> float:
    """RMS distance of points from their mean, mm."""
    return float(np.sqrt(np.mean(np.sum((p - p.mean(0)) ** 2, axis=1))))


def _one_pose_out(pm: NDArray, pn: NDArray, f: Frame, lines: NDArray) -> tuple[float, int, str]:
    """The scale without the pose farthest from the nominal machine after ``f``, its line and its worst column."""
    if len(pm) < 4:
        return float("nan"), 0, ""
    d = f.to_base(pm) - pn
    w = int(np.argmax(np.sum(d**2, axis=1)))
    keep = np.arange(len(pm)) != w
    s_m = _spread(pm[keep])
    scale = _spread(pn[keep]) / s_m if s_m > 0 else float("nan")
    # the column in the recording's own axes: the residual turned back into the instrument frame
    column = "xyz"[int(np.argmax(np.abs(f.rotation.T @ d[w])))]
    return float(scale), int(lines[w]), column


def _rms(d: NDArray) -> float:
    """Root-mean-square over points of the 3-D norm, mm."""
    return float(np.sqrt(np.mean(np.sum(np.asarray(d) ** 2, axis=1))))


def _tool_offset_fit(machine: Machine, J: NDArray, diff: NDArray) -> tuple[float, NDArray | None, float]:
    """``(rms, offset, sigmas)`` of the least-squares tool-point offset explaining ``diff`` = measured - nominal.

    The tool point enters every kind's forward kinematics linearly (``p = p_0(q) + R(q) t``),
    so its Jacobian columns ``J[:, :, tool.point.*]`` give the exact fit.
    """
    names = machine.layout.names
    comps = [(c, names.index(f"tool.point.{'xyz'[c]}")) for c in range(3) if f"tool.point.{'xyz'[c]}" in names]
    if not comps:  # a hybrid machine: each module has its own
        return float("nan"), None, float("nan")
    idx = [i for _, i in comps]
    A = J[:, :, idx].reshape(-1, len(idx))
    dt, *_ = np.linalg.lstsq(A, diff.ravel(), rcond=None)
    rms = _rms((diff.ravel() - A @ dt).reshape(-1, 3))
    tol = np.asarray(machine.tolerance, dtype=float)[idx]
    offset = np.zeros(3)  # a planar kind has no parameter for the coordinate it cannot move
    offset[[c for c, _ in comps]] = dt
    return rms, offset, float(np.max(np.abs(dt) / tol))


_PAIRS = ((0, 1, "x, y"), (0, 2, "x, z"), (1, 2, "y, z"))


def _best_swap(pm: NDArray, pn: NDArray, rms_rigid: float) -> tuple[str, float, bool]:
    """``(columns, rms, aligned)``: two exchanged position columns that bring ``pm`` closest to ``pn``.

    An exchange as it is (``"x, y"``, ...) when one beats the best rigid
    transform ``rms_rigid`` by :attr:`FrameCheck.DROP`; else the mirror image
    rigidly aligned (``"mirrored"``, ``aligned`` True): in an instrument's frame
    every exchange (or a reversed axis) composed with a rotation fits the same,
    so which columns cannot be told.
    """
    direct = min((_rms(_exchanged(pm, a, b) - pn), label) for a, b, label in _PAIRS)
    if direct[0] * FrameCheck.DROP < rms_rigid:
        return direct[1], direct[0], False
    mirrored = _exchanged(pm, 0, 1)
    return "mirrored", _rms(align_frame(mirrored, pn).to_base(mirrored) - pn), True


def _exchanged(p: NDArray, a: int, b: int) -> NDArray:
    out = p.copy()
    out[:, [a, b]] = out[:, [b, a]]
    return out


def nom_subset(poses, mask):
    """The solved poses ``mask`` (state fields indexed too)."""
    return poses.take(mask)  # any kind's state, nested ones (hybrid) included
