"""The two-axis positioner's source model, re-implemented from its description, and a scipy baseline.

This is the *baseline* of ``studies/real_recordings.py``: it does not use
bayescal's kinematics, so it is an independent check of bayescal's serial
machine, instrument frame and tool parameters on the same real data.

Model (``../shared/data/real/positioner/nominal.md``, ros-industrial
industrial_calibration, ``createTwoAxisPositioner()``): classical DH rows
``[d, theta, r, alpha]``, ``T_i = Tz(d) Rz(theta) Tx(r) Rx(alpha)`` with the
joint value added to ``theta``; ``FK(q) = base_offset T_1(q1) T_2(q2)`` with
``base_offset = Trans(2.2, 0, 1.6) Rot_x(pi/2)`` (m); the measurement is the
target pose in the sensor frame,
``inv(camera_mount_to_camera) FK(q) target_mount_to_target``.

Two fits:

* :func:`fit_source` -- the source's own cost: translation residuals of
  ``measured pred^-1`` in metres, ``100 x`` the angular distance, priors
  ``offset / 0.005`` on j1's four DH offsets (j2's masked), both transforms
  free; solved to tight tolerances (the source's published optimum,
  1.74 mm mean position error, was not converged; see nominal.md).
* :func:`fit_full` -- the full-parameter baseline: every DH offset of both
  joints and both transforms, residuals whitened by the noise (position in
  mm over ``sigma_position``, rotation vector of ``R_meas R_pred^T`` over
  ``sigma_angle``), no prior, ``scipy.optimize.least_squares`` with a
  finite-difference Jacobian.  Parameters that the data cannot determine
  make the problem rank-deficient; least_squares' trust region still
  returns a minimiser (the residual, which is what is compared, is unique).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

DH_NOMINAL = np.array([[0.0, 0.0, 0.0, -np.pi / 2], [-0.475, -np.pi / 2, 0.0, 0.0]])  # [d, theta, r, alpha], m, rad
BASE_OFFSET_T = np.array([2.2, 0.0, 1.6])  # m
BASE_OFFSET_R = Rotation.from_rotvec([np.pi / 2, 0.0, 0.0]).as_matrix()


@dataclass(frozen=True)
class PositionerData:
    """The 205 observations: joints (rad), target position (m) and rotation in the sensor frame."""

    q: np.ndarray
    position_m: np.ndarray
    rotation: np.ndarray
    keys: tuple[str, ...]


def load_positioner(folder: Path) -> PositionerData:
    """Read ``measurements.yaml`` (mapping key -> camera_joints, pose{x,y,z,qw,qx,qy,qz}, target_joints)."""
    import yaml

    raw = yaml.safe_load((Path(folder) / "measurements.yaml").read_text())
    keys = tuple(raw)
    q = np.array([raw[k]["target_joints"] for k in keys], dtype=float)
    p = np.array([[raw[k]["pose"][c] for c in "xyz"] for k in keys], dtype=float)
    quat = np.array([[raw[k]["pose"][c] for c in ("qx", "qy", "qz", "qw")] for k in keys], dtype=float)  # scipy: scalar last
    return PositionerData(q=q, position_m=p, rotation=Rotation.from_quat(quat).as_matrix(), keys=keys)


def load_guesses(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """``camera_mount_to_camera`` and ``target_mount_to_target`` guesses as 4x4 (m)."""
    import yaml

    raw = yaml.safe_load((Path(folder) / "pose_initial_guesses.yaml").read_text())

    def tf(d):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([d["qx"], d["qy"], d["qz"], d["qw"]]).as_matrix()
        T[:3, 3] = [d["x"], d["y"], d["z"]]
        return T

    return tf(raw["camera_mount_to_camera_guess"]), tf(raw["target_mount_to_target_guess"])


def _dh(d, theta, r, alpha) -> np.ndarray:
    """Classical DH transforms, vectorised: Tz(d) Rz(theta) Tx(r) Rx(alpha), shape (n, 4, 4)."""
    n = np.broadcast(d, theta).shape[0]
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    T = np.zeros((n, 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2], T[:, 0, 3] = ct, -st * ca, st * sa, r * ct
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2], T[:, 1, 3] = st, ct * ca, -ct * sa, r * st
    T[:, 2, 1], T[:, 2, 2], T[:, 2, 3] = sa, ca, d
    T[:, 3, 3] = 1.0
    return T


def _pose(x6: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(x6[3:]).as_matrix()
    T[:3, 3] = x6[:3]
    return T


def predict(q: np.ndarray, dh_offsets: np.ndarray, camera: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Predicted sensor-to-target transforms (n, 4, 4), m.

    ``dh_offsets`` (2, 4) added to :data:`DH_NOMINAL`; ``camera`` and
    ``target`` are (6,) translation (m) + rotation vector (rad) of
    camera_mount_to_camera and target_mount_to_target.
    """
    dh = DH_NOMINAL + dh_offsets
    n = q.shape[0]
    base = np.eye(4)
    base[:3, :3], base[:3, 3] = BASE_OFFSET_R, BASE_OFFSET_T
    T = np.broadcast_to(base, (n, 4, 4))
    for j in range(2):
        T = T @ _dh(np.full(n, dh[j, 0]), dh[j, 1] + q[:, j], np.full(n, dh[j, 2]), np.full(n, dh[j, 3]))
    return np.linalg.inv(_pose(camera)) @ T @ _pose(target)


def errors(data: PositionerData, pred: np.ndarray, idx=None) -> tuple[np.ndarray, np.ndarray]:
    """Per observation position error (mm) and angular distance (rad) of ``pred^-1 measured``."""
    idx = np.arange(data.q.shape[0]) if idx is None else np.asarray(idx)
    Tm = np.zeros((idx.size, 4, 4))
    Tm[:, :3, :3], Tm[:, :3, 3], Tm[:, 3, 3] = data.rotation[idx], data.position_m[idx], 1.0
    D = np.linalg.inv(pred) @ Tm
    pos = 1e3 * np.linalg.norm(D[:, :3, 3], axis=1)
    ang = Rotation.from_matrix(D[:, :3, :3]).magnitude()
    return pos, ang


@dataclass(frozen=True)
class SourceFit:
    dh_offsets: np.ndarray
    camera: np.ndarray
    target: np.ndarray
    cost_per_obs: float
    nfev: int

    def predict(self, q: np.ndarray) -> np.ndarray:
        return predict(q, self.dh_offsets, self.camera, self.target)


def _x6(T: np.ndarray) -> np.ndarray:
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


def fit_source(data: PositionerData, guesses, idx=None, *, static_dh: bool = False) -> SourceFit:
    """The source's cost (metres, 100 x angle, j1 DH offset priors of 0.005), tightly converged."""
    idx = np.arange(data.q.shape[0]) if idx is None else np.asarray(idx)
    cam0, tgt0 = (_x6(T) for T in guesses)
    n_dh = 0 if static_dh else 4

    def unpack(x):
        off = np.zeros((2, 4))
        off[0] = x[12:12 + n_dh] if n_dh else 0.0
        return off, x[:6], x[6:12]

    Tm = np.zeros((idx.size, 4, 4))
    Tm[:, :3, :3], Tm[:, :3, 3], Tm[:, 3, 3] = data.rotation[idx], data.position_m[idx], 1.0

    def resid(x):
        off, cam, tgt = unpack(x)
        P = predict(data.q[idx], off, cam, tgt)
        D = Tm @ np.linalg.inv(P)  # measured * pred^-1
        ang = Rotation.from_matrix(D[:, :3, :3]).magnitude()
        r = np.concatenate([D[:, :3, 3], 100.0 * ang[:, None]], axis=1).ravel()
        return np.concatenate([r, x[12:12 + n_dh] / 0.005])

    x0 = np.concatenate([cam0, tgt0, np.zeros(n_dh)])
    sol = least_squares(resid, x0, method="trf", x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=5000)
    off, cam, tgt = unpack(sol.x)
    return SourceFit(off, cam, tgt, float(np.sqrt(2 * sol.cost / (4 * idx.size + 8))), int(sol.nfev))


def fit_full(data: PositionerData, start: SourceFit, idx=None, *, sigma_position_mm: float, sigma_angle: float) -> SourceFit:
    """All 8 DH offsets and both transforms, noise-whitened, no prior (the full-parameter LS baseline)."""
    idx = np.arange(data.q.shape[0]) if idx is None else np.asarray(idx)
    Tm = np.zeros((idx.size, 4, 4))
    Tm[:, :3, :3], Tm[:, :3, 3], Tm[:, 3, 3] = data.rotation[idx], data.position_m[idx], 1.0

    def resid(x):
        off = x[12:].reshape(2, 4)
        P = predict(data.q[idx], off, x[:6], x[6:12])
        pos = 1e3 * (Tm[:, :3, 3] - P[:, :3, 3]) / sigma_position_mm
        rot = Rotation.from_matrix(Tm[:, :3, :3] @ np.swapaxes(P[:, :3, :3], 1, 2)).as_rotvec() / sigma_angle
        return np.concatenate([pos, rot], axis=1).ravel()

    x0 = np.concatenate([start.camera, start.target, start.dh_offsets.ravel()])
    sol = least_squares(resid, x0, method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
    return SourceFit(sol.x[12:].reshape(2, 4), sol.x[:6], sol.x[6:12], float(np.sqrt(2 * sol.cost / sol.fun.size)),
                     int(sol.nfev))
