"""The seed's calibration procedure on a simulated module, and the comparison with the previous method.

Procedure: (1) pitch compensation of the AJs from laser-interferometer
tables; (2) the calibrating zero position; (3) RM1/SI1; (4) a BIC grid;
(5) RM2/SI2; (6) RM3/SI3.  Errors are evaluated on fresh poses, relative
to the zero pose (the machine's reference), as actual minus commanded.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..compensation import CompensationGrid, build_grid
from ..machines.raspm import Raspm
from .models import PoseModel, ZeroPosition
from .physics import PitchCompensation, TrueModule
from .steps import INSTRUMENTS, STEP_INSTRUMENT, design_rm1, design_rm2, design_rm3, identify_step, measure_relative

__all__ = [
    "measure_pitch_compensation", "calibrate_zero", "Evaluation", "evaluate", "ProcedureResult", "run_procedure",
    "Comparison", "compare_methods", "previous_subsets",
]

_COMPONENTS = {"RM1": ("dx", "dz"), "RM2": ("dry",), "RM3": ("dry",)}


def measure_pitch_compensation(truth: TrueModule, rng: np.random.Generator | None, *, spacing: float = 5.0) -> PitchCompensation:
    """Laser-interferometer following-error tables of every AJ (one point per ``spacing`` mm)."""
    lim = truth.machine.q_limits
    n = int(np.ceil((lim[:, 1] - lim[:, 0]).max() / spacing)) + 1
    pos = np.linspace(lim[:, 0], lim[:, 1], n).T  # (m, n)
    raw = np.stack([truth.raw_following_error(pos[:, j][None, :])[0] for j in range(n)], axis=1)
    return PitchCompensation(positions=pos, errors=INSTRUMENTS["laser_interferometer"].read(raw, rng))


def calibrate_zero(truth: TrueModule, x0: NDArray, rng: np.random.Generator | None) -> ZeroPosition:
    """Align the true module at ``x0`` (bore dial indicator, dial gauge) and record the commands.

    The alignment is as good as the indicators: the module really sits at
    ``x0`` plus their reading error (position, and rotation over a 200 mm base).
    """
    res = INSTRUMENTS["bore_dial_indicator"]
    err = np.zeros(3) if rng is None else np.array([res.sigma, res.sigma, res.sigma / 200.0]) * rng.normal(size=3)
    q0 = truth.command_for((np.asarray(x0, float) + err)[None])[0]
    return ZeroPosition(x0=np.asarray(x0, float), q0=q0)


@dataclass(frozen=True)
class Evaluation:
    """Errors of the module on fresh poses (actual minus commanded, relative to the zero pose).

    Attributes
    ----------
    position : ndarray, shape (k, 2)
        ``(ex, ez)`` over a translation grid at rotation 0, mm.
    orientation_translation : ndarray, shape (k,)
        Rotation error over the same grid, rad.
    orientation_rotation : ndarray, shape (r,)
        Rotation error over the rotation range at the zero translation, rad.
    x_eval, phi_eval : ndarray
        The evaluation poses.
    """

    position: NDArray
    orientation_translation: NDArray
    orientation_rotation: NDArray
    x_eval: NDArray
    phi_eval: NDArray

    @property
    def peaks(self) -> dict:
        return {
            "position_mm": float(np.abs(self.position).max()),
            "orientation_translation_deg": float(np.degrees(np.abs(self.orientation_translation).max())),
            "orientation_rotation_deg": float(np.degrees(np.abs(self.orientation_rotation).max())),
        }


def _eval_poses(machine: Raspm, zero: NDArray, n: int = 9, n_phi: int = 13, offset: float = 0.37):
    r = machine.pose_range
    # fresh poses: a grid shifted off the measurement lines and BIC nodes
    xs = np.linspace(*r[0], n) + offset * (r[0, 1] - r[0, 0]) / (n - 1) * np.r_[np.ones(n - 1), 0] * 0.5
    zs = np.linspace(*r[1], n) + offset * (r[1, 1] - r[1, 0]) / (n - 1) * np.r_[np.ones(n - 1), 0] * 0.5
    X, Z = np.meshgrid(xs, zs)
    xt = np.column_stack([X.ravel(), Z.ravel(), np.zeros(X.size)])
    xr = np.column_stack([np.full(n_phi, zero[0]), np.full(n_phi, zero[1]), np.linspace(*r[2], n_phi)])
    return xt, xr


def evaluate(
    truth: TrueModule, ctrl: PoseModel, theta: NDArray, *, grid: CompensationGrid | None = None
) -> Evaluation:
    """Position and orientation errors of the true module commanded through ``ctrl`` with ``theta``."""
    m = truth.machine
    th = ctrl.complete(theta)
    zero = ctrl.zero.x0
    xt, xr = _eval_poses(m, zero)
    cmd = xt.copy()
    if grid is not None:
        cmd[:, :2] = grid.compensate(xt[:, 0], xt[:, 1])
    y0, p0, _ = truth.tool(m.inverse_planar(zero[None], th))
    yt, pt, _ = truth.tool(m.inverse_planar(cmd, th))
    yr, pr, _ = truth.tool(m.inverse_planar(xr, th))
    pos_err = (yt - y0) - (xt[:, :2] - zero[:2])
    return Evaluation(
        position=pos_err,
        orientation_translation=(pt - p0) - (xt[:, 2] - zero[2]),
        orientation_rotation=(pr - p0) - (xr[:, 2] - zero[2]),
        x_eval=xt, phi_eval=xr[:, 2],
    )


def _rm(kind: str, truth, ctrl, theta, rng, zero, n_lines=(7, 5)):
    r = truth.machine.pose_range
    if kind == "RM1":
        xf, xt, line = design_rm1(r, *n_lines)
    elif kind == "RM2":
        xf, xt, line = design_rm2(r, zero, *n_lines)
    else:
        xf, xt, line = design_rm3(r, zero)
    inst = INSTRUMENTS[STEP_INSTRUMENT[kind]]
    rec = measure_relative(truth, ctrl, theta, xf, xt, _COMPONENTS[kind], inst, rng, aux={"line": line})
    return rec, np.full(len(_COMPONENTS[kind]), inst.sigma)


@dataclass(frozen=True)
class ProcedureResult:
    """The whole procedure.

    Attributes
    ----------
    before, after_si1, after_bic, after_si2, after_si3 : Evaluation
    steps : tuple of StepResult
    grid : CompensationGrid
    theta_true, theta_final : ndarray
    recordings : dict of str to RelativeRecording
    controller : PoseModel
        The controller's model (with its zero position), e.g. for
        :func:`bayescal.redundant.grid_std.predicted_grid`.
    """

    before: Evaluation
    after_si1: Evaluation
    after_bic: Evaluation
    after_si2: Evaluation
    after_si3: Evaluation
    steps: tuple
    grid: CompensationGrid
    theta_true: NDArray
    theta_final: NDArray
    recordings: dict = field(default_factory=dict)
    controller: PoseModel | None = None

    def report(self) -> str:
        rows = [("initial", self.before), ("after RM1/SI1", self.after_si1), ("after BIC", self.after_bic),
                ("after RM2/SI2", self.after_si2), ("after RM3/SI3", self.after_si3)]
        out = ["stage            max |position| mm   max |orientation| deg (translation / rotation range)"]
        for name, ev in rows:
            p = ev.peaks
            out.append(f"{name:16s} {p['position_mm']:10.4f}          {p['orientation_translation_deg']:.4f} / {p['orientation_rotation_deg']:.4f}")
        return "\n".join(out + [s.report() for s in self.steps])

    def to_dict(self) -> dict:
        return {
            "peaks": {k: getattr(self, k).peaks for k in ("before", "after_si1", "after_bic", "after_si2", "after_si3")},
            "steps": [s.to_dict() for s in self.steps],
            "grid": self.grid.to_dict(),
        }


def run_procedure(
    truth: TrueModule, rng: np.random.Generator | None, *, zero_x: NDArray | None = None, grid_n: int = 5,
    weights: NDArray | None = None,
) -> ProcedureResult:
    """Run the seed's procedure with the proposed (projected, practical) model."""
    m = truth.machine
    zero_x = m._home_x() if zero_x is None else np.asarray(zero_x, float)
    truth = truth.with_pitch_compensation(measure_pitch_compensation(truth, rng))
    zp = calibrate_zero(truth, zero_x, rng)
    ctrl = PoseModel(m, "proposed", weights=weights, zero=zp)
    theta = ctrl.complete(np.zeros(m.n_params))
    before = evaluate(truth, ctrl, theta)
    recs, steps = {}, []
    rm1 = _rm("RM1", truth, ctrl, theta, rng, zero_x)
    s1 = identify_step(ctrl, [rm1], theta, step="SI1")
    theta = s1.theta_after
    after1 = evaluate(truth, ctrl, theta)

    # BIC: measure the residual position error at the grid nodes (dial gauge), relative to the zero pose;
    # a measured node is the true residual error there plus one gauge reading, so its std is the gauge's
    inst = INSTRUMENTS["dial_gauge"]
    th = ctrl.complete(theta)
    state = {"th": th, "y0": truth.tool(m.inverse_planar(zero_x[None], th))[0]}

    def node_error(x, z):
        th, y0 = state["th"], state["y0"]
        xn = np.column_stack([x, z, np.zeros_like(x)])
        y, _, _ = truth.tool(m.inverse_planar(xn, th))
        return inst.read((y - y0) - (xn[:, :2] - zero_x[:2]), rng)

    grid = build_grid(m.pose_range[0], m.pose_range[1], node_error, n=grid_n, std=inst.sigma)
    after_bic = evaluate(truth, ctrl, theta, grid=grid)
    # each later step adds its own measurement to the latest of the earlier ones, so it cannot undo them
    # (their noise inflated by the misfit the earlier step left: unmodelled errors count as noise)
    rm1w = (rm1[0], rm1[1] * max(1.0, s1.rms_after))
    rm2 = _rm("RM2", truth, ctrl, theta, rng, zero_x)
    s2 = identify_step(ctrl, [rm1w, rm2], theta, step="SI2")
    theta = s2.theta_after
    after2 = evaluate(truth, ctrl, theta, grid=grid)
    rm3 = _rm("RM3", truth, ctrl, theta, rng, zero_x)
    rm2w = (rm2[0], rm2[1] * max(1.0, s2.rms_after))
    s3 = identify_step(ctrl, [rm1w, rm2w, rm3], theta, step="SI3")
    theta = s3.theta_after
    # SI2 and SI3 changed the model under the grid of step (4): measure the grid again for the final state
    state["th"] = ctrl.complete(theta)
    state["y0"] = truth.tool(m.inverse_planar(zero_x[None], state["th"]))[0]
    grid = build_grid(m.pose_range[0], m.pose_range[1], node_error, n=grid_n, std=inst.sigma)
    after3 = evaluate(truth, ctrl, theta, grid=grid)
    recs = {"RM1": rm1[0], "RM2": rm2[0], "RM3": rm3[0]}
    steps = (s1, s2, s3)
    return ProcedureResult(before, after1, after_bic, after2, after3, steps, grid, truth.theta, theta, recs, ctrl)


def previous_subsets(machine: Raspm) -> list[tuple[int, ...]]:
    """Non-redundant subsets the previous method alternates between.

    The corresponding non-redundant module leaves a redundant actuator out;
    to calibrate the redundant chain too, the previous method swaps it in
    for the non-redundant actuator it can replace with the best conditioning.
    """
    nr = tuple(machine.nonredundant)
    out = [nr]
    _, Ja = machine.ik_jacobian(machine._home_x()[None])
    for r in machine.redundant:
        best, cond = None, np.inf
        for a in nr:
            sub = tuple(sorted((set(nr) - {a}) | {r}))
            c = np.linalg.cond(Ja[0, list(sub)])
            if c < cond:
                best, cond = sub, c
        out.append(best)
    return out


@dataclass(frozen=True)
class Comparison:
    """Error peaks per repeated step for the proposed and the previous method.

    Attributes
    ----------
    position : dict of str to ndarray, shape (n_steps + 1,)
        Max position error (mm) before and after each RM1/SI1 step.
    orientation : dict of str to ndarray, shape (n_steps + 1,)
        Max rotation-range orientation error (deg) before and after each RM3/SI3 step.
    steps_to_converge : dict of str to dict
        First step after which the peak stays within ``tol`` of its final value.
    """

    position: dict
    orientation: dict
    steps_to_converge: dict
    tol_position: float
    tol_orientation: float

    def report(self) -> str:
        out = []
        for meth in self.position:
            out.append(
                f"{meth:9s} position peaks (mm): " + " ".join(f"{v:.4f}" for v in self.position[meth])
                + " | orientation peaks (deg): " + " ".join(f"{v:.4f}" for v in self.orientation[meth])
                + f" | steps to converge: position {self.steps_to_converge[meth]['position']}, "
                f"orientation {self.steps_to_converge[meth]['orientation']}"
            )
        return "\n".join(out)

    def to_dict(self) -> dict:
        return {
            "position_peaks_mm": {k: v.tolist() for k, v in self.position.items()},
            "orientation_peaks_deg": {k: v.tolist() for k, v in self.orientation.items()},
            "steps_to_converge": self.steps_to_converge,
        }


def _converged_at(peaks: NDArray, tol: float) -> int:
    final = peaks[-1]
    for s in range(1, len(peaks)):
        if np.all(np.abs(peaks[s:] - final) <= tol):
            return s
    return len(peaks) - 1


def compare_methods(
    truth: TrueModule, rng_seed: int, *, n_steps: int = 4, tol_position: float = 0.002, tol_orientation: float = 0.001
) -> Comparison:
    """Repeat RM1/SI1 and then RM3/SI3 ``n_steps`` times with each method, from the same start.

    ``previous``: the corresponding non-redundant module's model (restrained
    deformation ignored), alternating its non-redundant subsets (see
    :func:`previous_subsets`); ``proposed``: the projected, reduced model.
    Commands always go through the current model of the method, so each
    step's measurement is made with the geometry the previous step found.
    """
    m = truth.machine
    zero_x = m._home_x()
    pos, ori, conv = {}, {}, {}
    for meth in ("proposed", "previous"):
        rng = np.random.default_rng(rng_seed)
        tr = truth.with_pitch_compensation(measure_pitch_compensation(truth, rng))
        zp = calibrate_zero(tr, zero_x, rng)
        ctrl = PoseModel(m, "proposed", zero=zp)  # the controller's inverse kinematics is the same for both
        subsets = previous_subsets(m)
        theta = ctrl.complete(np.zeros(m.n_params))
        pk = [evaluate(tr, ctrl, theta).peaks["position_mm"]]
        for s in range(n_steps):
            model = ctrl if meth == "proposed" else PoseModel(m, "previous", zero=zp, subset=subsets[s % len(subsets)])
            rm1 = _rm("RM1", tr, ctrl, theta, rng, zero_x)
            theta = identify_step(model, [rm1], theta, step=f"SI1.{s + 1}").theta_after
            pk.append(evaluate(tr, ctrl, theta).peaks["position_mm"])
        ok = [evaluate(tr, ctrl, theta).peaks["orientation_rotation_deg"]]
        for s in range(n_steps):
            model = ctrl if meth == "proposed" else PoseModel(m, "previous", zero=zp, subset=subsets[s % len(subsets)])
            rm3 = _rm("RM3", tr, ctrl, theta, rng, zero_x)
            theta = identify_step(model, [rm3], theta, step=f"SI3.{s + 1}").theta_after
            ok.append(evaluate(tr, ctrl, theta).peaks["orientation_rotation_deg"])
        pos[meth], ori[meth] = np.array(pk), np.array(ok)
        conv[meth] = {"position": _converged_at(pos[meth], tol_position), "orientation": _converged_at(ori[meth], tol_orientation)}
    return Comparison(pos, ori, conv, tol_position, tol_orientation)
