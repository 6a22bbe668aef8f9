"""Relative measurement (RM) and step identification (SI) of a redundantly actuated 2T1R module.

Three forms, after the seed (the rotation is decoupled from the planar translation):

* **RM1 / SI1**: rotation held at its nominal zero; tool displacements
  ``(dx, dz)`` along measuring lines across the planar translation range
  (digital dial gauge against a straightedge and gauge blocks);
* **RM2 / SI2**: rotation held at zero; change of orientation ``dry``
  between each pose of a translation grid and the zero pose (digital level);
* **RM3 / SI3**: translation held at the zero position; change of
  orientation ``dry`` over the rotation range (dial gauges on a reference
  bar).

Each step identifies, by Gauss-Newton least squares on the relative
measurements, the directions of parameter space its measurement
determines (truncated SVD of the step's whitened, tolerance-scaled
Jacobian: singular values of at least ``eta_min``), leaves the others at
the current model (minimum-norm update) and updates the model.

**Anti-disturbance index.**  For the whitened (rows divided by the
instrument's sigma), tolerance-scaled identification matrix ``A`` of a
step, parameter ``j``'s index is ``eta_j = tol_j / std_j`` with
``std_j = sqrt((J^T J)^-1_jj)`` the standard deviation the instrument noise
causes: how many times the measurement shrinks the parameter's a-priori
spread (``eta_j < 1``: the step is disturbed more than it learns).  The step's
index is the smallest singular value of ``A``: the worst-determined
direction's gain against noise.  (The seed's references define the index
from the identification matrix's conditioning; this is the form used here.)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import IdentificationError, InputError
from ..iteration import Proposal, StepControl, gauss_newton
from .models import PoseModel
from .physics import TrueModule
from .relative_io import RelativeRecording

__all__ = [
    "Instrument",
    "INSTRUMENTS",
    "STEP_INSTRUMENT",
    "design_rm1",
    "design_rm2",
    "design_rm3",
    "measure_relative",
    "identify_step",
    "StepResult",
    "anti_disturbance",
    "component_columns",
]


@dataclass(frozen=True)
class Instrument:
    """A measuring instrument: reading rounded to its resolution, with repeatability noise.

    Attributes
    ----------
    name : str
    resolution : float
        mm (lengths) or rad (angles).
    unit : str
    repeatability : float
        One-sigma random error before rounding, same unit (half the resolution by default).
    """

    name: str
    resolution: float
    unit: str
    repeatability: float | None = None

    @property
    def sigma(self) -> float:
        """Effective one-sigma error: repeatability and rounding (``res^2 / 12``) combined."""
        rep = self.resolution / 2 if self.repeatability is None else self.repeatability
        return float(np.sqrt(rep**2 + self.resolution**2 / 12.0))

    def read(self, true_value: NDArray, rng: np.random.Generator | None) -> NDArray:
        """What the instrument shows for ``true_value`` (noise-free and unrounded if ``rng`` is None)."""
        if rng is None:
            return np.asarray(true_value, dtype=float).copy()
        rep = self.resolution / 2 if self.repeatability is None else self.repeatability
        v = np.asarray(true_value, dtype=float) + rng.normal(size=np.shape(true_value)) * rep
        return np.round(v / self.resolution) * self.resolution


#: The instruments the seed's procedure implies (its Table 4 is not in the text; resolutions typical).
INSTRUMENTS: dict[str, Instrument] = {
    "laser_interferometer": Instrument("laser interferometer (AJ following errors)", 1.0e-6, "mm", 2.0e-4),
    "dial_gauge": Instrument("digital dial gauge, 0.001 mm (RM1, BIC)", 1.0e-3, "mm"),
    "bore_dial_indicator": Instrument("bore dial indicator, 0.001 mm (zero-position alignment)", 1.0e-3, "mm"),
    "digital_level": Instrument("digital level, 0.001 mm/m (RM2)", 1.0e-6, "rad", 1.0e-6),
    "dial_gauges_on_bar": Instrument("two dial gauges on a 200 mm reference bar (RM3)", 1.0e-3 / 200.0, "rad"),
}

#: Instrument of each relative measurement.
STEP_INSTRUMENT = {"RM1": "dial_gauge", "RM2": "digital_level", "RM3": "dial_gauges_on_bar"}

_COLUMN_OF = {"dx": 0, "dz": 1, "dry": 2}


def component_columns(components: tuple[str, ...]) -> list[int]:
    """Columns of :meth:`PoseModel.tool` (x, z, phi) for measured components; others raise."""
    bad = [c for c in components if c not in _COLUMN_OF]
    if bad:
        raise InputError(f"component {bad[0]!r} is not observable on a 2T1R module; expected dx, dz or dry")
    return [_COLUMN_OF[c] for c in components]


def _grid(lo, hi, n):
    return np.linspace(lo, hi, n)


def design_rm1(pose_range: NDArray, n_x: int = 7, n_z: int = 5) -> tuple[NDArray, NDArray, NDArray]:
    """RM1 pose pairs: lines along x at each z level and along z at each x station, rotation 0.

    Returns ``x_from`` (k, 3), ``x_to`` (k, 3) planar poses and the line number (k,).
    """
    xs, zs = _grid(*pose_range[0], n_x), _grid(*pose_range[1], n_z)
    pf, pt, line = [], [], []
    for j, z in enumerate(zs):
        for x in xs[1:]:
            pf.append([xs[0], z, 0.0]); pt.append([x, z, 0.0]); line.append(j + 1)
    for i, x in enumerate(xs):
        for z in zs[1:]:
            pf.append([x, zs[0], 0.0]); pt.append([x, z, 0.0]); line.append(n_z + i + 1)
    return np.array(pf), np.array(pt), np.array(line, dtype=float)


def design_rm2(pose_range: NDArray, zero: NDArray, n_x: int = 7, n_z: int = 5):
    """RM2 pose pairs: from the zero pose to every node of a translation grid, rotation 0."""
    xs, zs = _grid(*pose_range[0], n_x), _grid(*pose_range[1], n_z)
    pt = np.array([[x, z, 0.0] for z in zs for x in xs])
    return np.tile(zero, (len(pt), 1)), pt, np.ones(len(pt))


def design_rm3(pose_range: NDArray, zero: NDArray, n_phi: int = 11):
    """RM3 pose pairs: from the zero pose to rotations over the range, translation at zero."""
    phis = _grid(*pose_range[2], n_phi)
    pt = np.array([[zero[0], zero[1], p] for p in phis])
    return np.tile(zero, (len(pt), 1)), pt, np.ones(len(pt))


def measure_relative(
    truth: TrueModule,
    controller: PoseModel,
    theta_ctrl: ArrayLike,
    x_from: NDArray,
    x_to: NDArray,
    components: tuple[str, ...],
    instrument: Instrument,
    rng: np.random.Generator | None,
    *,
    aux: dict[str, NDArray] | None = None,
) -> RelativeRecording:
    """Command pose pairs through the controller's model and read the true module's displacements.

    The controller commands every actuator by its inverse kinematics with
    geometry ``theta_ctrl`` (offsets from its zero position), so the
    commands are compatible only if ``theta_ctrl`` is the truth; the true
    module settles with restrained deformation.
    """
    m = truth.machine
    th = controller.complete(np.asarray(theta_ctrl, dtype=float))
    qf, qt = m.inverse_planar(x_from, th), m.inverse_planar(x_to, th)
    yf, pf, _ = truth.tool(qf)
    yt, pt, _ = truth.tool(qt)
    full = np.column_stack([yt - yf, pt - pf])  # dx, dz, dry
    vals = instrument.read(full[:, component_columns(components)], rng)
    extra = {f"{a}d_{t}": v[:, k] for t, v in (("from", x_from), ("to", x_to)) for k, a in enumerate(("x", "z", "phi"))}
    extra.update(aux or {})
    return RelativeRecording(q_from=qf, q_to=qt, components=tuple(components), values=vals, aux=extra)


def anti_disturbance(A: NDArray) -> tuple[NDArray, float]:
    """Per-parameter indices ``eta_j = 1 / sqrt((A^T A)^-1_jj)`` and the step index ``sigma_min(A)``.

    ``A`` is whitened (rows / sigma) and scaled by the tolerances (columns),
    so ``eta_j`` is the tolerance over the noise-induced standard deviation.
    """
    _, s, Vt = np.linalg.svd(A, full_matrices=False)
    # no truncation: a direction the measurement cannot see must give a huge std (small eta)
    var = ((Vt.T / np.maximum(s, 1e-300)) ** 2).sum(axis=1)
    return 1.0 / np.sqrt(var), float(s[-1])


@dataclass(frozen=True)
class StepResult:
    """One step identification.

    Attributes
    ----------
    step : str
        ``"SI1"``, ``"SI2"`` or ``"SI3"``.
    method : str
        ``"proposed"`` or ``"previous"``.
    theta_before, theta_after : ndarray, shape (P,)
    identified : tuple of str
        Parameters this step identified.
    anti_disturbance : ndarray
        ``eta_j`` of the identified parameters.
    step_index : float
        Smallest singular value of the whitened, scaled identification matrix.
    rms_before, rms_after : float
        Whitened residual RMS (1 = at the noise).
    covariance : ndarray, shape (P, P), optional
        Linearised covariance of ``theta_after - theta_true`` (mm, rad) for
        a step started from the nominal model with the truth drawn from the
        tolerance prior ``N(0, diag(tolerance^2))``: in the identified
        directions the instrument noise propagated through the step's
        least squares, in the directions it leaves (unseen, or with no
        leverage) the prior spread; zero rows/columns for the offsets the
        zero position fixes (functions of the others, see ``PoseModel.complete``).
    iterations : int
    success : bool
    message : str
    """

    step: str
    method: str
    theta_before: NDArray
    theta_after: NDArray
    identified: tuple[str, ...]
    anti_disturbance: NDArray
    step_index: float
    rms_before: float
    rms_after: float
    iterations: int
    success: bool
    message: str = ""
    units: tuple[str, ...] = field(default=())
    n_directions: int = 0
    covariance: NDArray | None = None

    def report(self) -> str:
        lines = [
            f"{self.step} ({self.method} model): {self.n_directions} parameter directions identified "
            f"({len(self.identified)} parameters mostly inside them), "
            f"{self.iterations} iterations, whitened residual RMS {self.rms_before:.3g} -> {self.rms_after:.3g}, "
            f"step anti-disturbance index {self.step_index:.3g}" + ("" if self.success else f"  NOT CONVERGED: {self.message}")
        ]
        names = list(self.identified)
        for n, e in zip(names, self.anti_disturbance):
            lines.append(f"  {n:40s} eta = {e:9.3g}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "step": self.step, "method": self.method, "identified": list(self.identified),
            "anti_disturbance": dict(zip(self.identified, self.anti_disturbance.tolist())),
            "step_index": self.step_index, "rms_before": self.rms_before, "rms_after": self.rms_after,
            "n_directions": self.n_directions, "iterations": self.iterations, "success": self.success, "message": self.message,
            "theta_after": self.theta_after.tolist(),
        }


def _relative_prediction(model: PoseModel, rec: RelativeRecording, theta: NDArray, cols: list[int]) -> NDArray:
    n = rec.n_pairs
    y = model.tool(np.vstack([rec.q_from, rec.q_to]), theta)
    return (y[n:] - y[:n])[:, cols]


def _relative_jacobian(model: PoseModel, rec: RelativeRecording, theta: NDArray, cols: list[int]) -> NDArray:
    n = rec.n_pairs
    J = model.tool_jacobian(np.vstack([rec.q_from, rec.q_to]), theta)
    return (J[n:] - J[:n])[:, cols]


def _iterate(model: PoseModel, system, theta: NDArray, r: NDArray, J: NDArray, cand: NDArray, basis: NDArray,
             max_iter: int, xtol: float):
    """Gauss-Newton in the coordinates ``u`` of the kept directions: ``theta[cand] += tol (basis u)``.

    Each step is halved until the cost does not rise (far from the solution a
    full step may overshoot; :func:`bayescal.iteration.gauss_newton`).  The
    state is ``(theta, r, J)``: the completed parameters, whitened residuals
    and Jacobian.
    """
    tol = model.machine.tolerance

    def evaluate(u, state):
        trial = theta.copy()
        trial[cand] += tol[cand] * (basis @ u)
        trial = model.complete(trial)
        r_t, J_t = system(trial)
        return float(r_t @ r_t), (trial, r_t, J_t)

    def propose(u, state):
        A = (state[2][:, cand] * tol[cand]) @ basis
        return Proposal(step=np.linalg.lstsq(A, state[1], rcond=None)[0])

    return gauss_newton(np.zeros(basis.shape[1]), (float(r @ r), (theta, r, J)), evaluate, propose,
                        control=StepControl(descent=True, halvings=7), max_iter=max_iter, xtol=xtol,
                        failures=(InputError,))


def identify_step(
    model: PoseModel,
    recs,
    theta0: ArrayLike,
    *,
    step: str,
    sigma=None,
    free: ArrayLike | None = None,
    max_iter: int = 20,
    xtol: float = 1e-6,
    eta_min: float = 3.0,
) -> StepResult:
    """Identify from relative measurements and return the updated model parameters.

    Parameters
    ----------
    model : PoseModel
        The error model (proposed / previous; practical with a zero position).
    recs : RelativeRecording or sequence of (RelativeRecording, sigma)
        This step's measurement (and, if given, the latest measurements of
        the earlier steps, so that a step does not undo what they fixed).
        ``sigma``: instrument one-sigma per measured component, mm or rad.
    theta0 : array_like, shape (P,)
        The current model (the start and the value of parameters not identified).
    step : str
        Label, e.g. ``"SI1"``.
    sigma : array_like, optional
        With a single recording: its one-sigma per component.
    free : array_like of int, optional
        Candidate parameters; default the model's free set.  Of them, the
        identifiable ones (SVD of the step's Jacobian) are identified.
    eta_min : float
        Directions of parameter space (tolerance-scaled) are identified when
        their singular value is at least this: the step must shrink their
        a-priori spread this many times, or it leaves them to another step.
        Parameters with more than half their weight in those directions are
        reported as identified, with their anti-disturbance index.
    """
    machine = model.machine
    system = _step_system(model, _blocks(machine, recs, sigma))
    theta = model.complete(np.array(theta0, dtype=float))
    cand = model.free_index if free is None else np.intersect1d(np.asarray(free, dtype=int), model.free_index)
    r, J = system(theta)
    cand, basis = _kept_directions(J, cand, machine.tolerance, step, eta_min)
    rms0 = float(np.sqrt(np.mean(r**2)))
    out = _iterate(model, system, theta, r, J, cand, basis, max_iter, xtol)
    return _step_result(model, step, theta0, out, cand, basis, rms0)


def _blocks(machine, recs, sigma) -> list[tuple]:
    """``(recording, component columns, sigma per component)`` of each relative recording, checked against ``machine``."""
    if isinstance(recs, RelativeRecording):
        if sigma is None:
            raise InputError("sigma: required with a single relative recording")
        recs = [(recs, sigma)]
    blocks = []
    for rec, sg in recs:
        rec.check_machine(machine.n_actuators, machine.q_limits)
        cols = component_columns(rec.components)
        blocks.append((rec, cols, np.asarray(sg, dtype=float).reshape(len(cols))))
    return blocks


def _step_system(model: PoseModel, blocks):
    """``system(theta) -> (r, J)``: the whitened residuals and Jacobian of every block, stacked."""
    n_params = model.machine.n_params

    def system(th):
        rs, Js = [], []
        for rec, cols, sg in blocks:
            rs.append(((rec.values - _relative_prediction(model, rec, th, cols)) / sg).ravel())
            Js.append((_relative_jacobian(model, rec, th, cols) / sg[None, :, None]).reshape(-1, n_params))
        return np.concatenate(rs), np.vstack(Js)

    return system


def _kept_directions(J: NDArray, cand: NDArray, tol: NDArray, step: str, eta_min: float) -> tuple[NDArray, NDArray]:
    """The candidate parameters the step's Jacobian reaches, and the directions it keeps (tolerance-scaled basis)."""
    norms = np.linalg.norm(J * tol, axis=0)
    cand = np.array([j for j in cand if norms[j] > 1e-6 * norms.max()], dtype=int)  # columns of round-off only
    if cand.size == 0:
        raise IdentificationError(f"{step}: the measurement identifies no parameter")
    # Truncated SVD in tolerance-scaled coordinates: keep the directions the step determines at
    # least eta_min times better than the a-priori spread.  Directions it cannot see (for a
    # redundant module: geometry that only changes what the actuators fight about) stay at the
    # current model: the minimum-norm update, which splits an unseen combination evenly.
    _, sv, Vt = np.linalg.svd(J[:, cand] * tol[cand], full_matrices=False)
    k = int(np.sum(sv >= eta_min))
    if k == 0:
        raise IdentificationError(
            f"{step}: no direction is determined better than {eta_min} times its tolerance (largest singular value {sv[0]:.3g})"
        )
    return cand, Vt[:k].T


def _step_result(model: PoseModel, step: str, theta0, out, cand: NDArray, basis: NDArray, rms0: float) -> StepResult:
    """The step's answer at the end of the iteration: identified parameters, their indices, the covariance."""
    machine = model.machine
    tol = machine.tolerance
    k = basis.shape[1]
    theta, r, J = out.state
    success, message, it = out.success, out.message, out.iterations
    _, sv, _ = np.linalg.svd(((J[:, cand] * tol[cand]) @ basis), full_matrices=False)
    loading = (basis**2).sum(axis=1)
    sel = loading > 0.5
    idx = cand[sel]
    # std of each parameter (tolerance units) from the kept directions only
    _, s2, Vt2 = np.linalg.svd((J[:, cand] * tol[cand]) @ basis, full_matrices=False)
    W = basis @ Vt2.T / s2
    eta = 1.0 / np.sqrt((W[sel] ** 2).sum(axis=1))
    s_min = float(sv[-1])
    # Linearised covariance (tolerance-scaled): noise in the kept directions (W W^T; no leakage from
    # the others, whose data-space columns are orthogonal to the kept ones at the SVD point), the
    # prior spread (identity) in the directions left unseen and for free parameters with no leverage.
    free = model.free_index
    Cs = np.zeros((machine.n_params, machine.n_params))
    Cs[np.ix_(free, free)] = np.eye(free.size)
    Cs[np.ix_(cand, cand)] = W @ W.T + np.eye(cand.size) - basis @ basis.T
    cov = Cs * tol[:, None] * tol[None, :]
    return StepResult(
        step=step, method=model.method, theta_before=np.asarray(theta0, dtype=float), theta_after=theta,
        identified=tuple(machine.layout.names[j] for j in idx), anti_disturbance=eta, step_index=s_min,
        rms_before=rms0, rms_after=float(np.sqrt(np.mean(r**2))), iterations=it, success=success, message=message,
        units=tuple(machine.layout.units[j] for j in idx), n_directions=k, covariance=cov,
    )
