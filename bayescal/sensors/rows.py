"""Body tilt sensors as measurement rows: two tilt angles per sensor and pose (docs/formats.md section 8).

Model, per pose ``i`` and sensor ``s`` on body ``b`` (every direction a unit vector):

* the up direction in the machine's base frame, ``g_i = exp([E_g d_g]x) g0_i``
  with ``g0_i = R0_base u_base,i`` (a base sensor's reading ``u_base,i`` turned
  by its nominal mounting ``R0_base``, the smallest rotation taking the mean
  reading to the machine's up ``+z``) or, without a base sensor, ``g0_i = +z``.
  ``d_g`` (2 angles, rad, about the base axes most perpendicular to up) is the
  base sensor's mounting tilt (``sensor.base.mount.r<a>``) or, without one,
  the level of the machine's base (``gravity.tilt.r<a>``);
* the predicted reading ``u_i = exp(-[E_s d_s]x) R0_s^T R_b(q_i, theta)^T g_i``,
  with ``R_b`` the body's orientation in the base frame from the geometry
  being fitted, ``R0_s`` the sensor's nominal mounting (sensor to body frame)
  and ``d_s`` its mounting angles (``sensor.<body>.mount.r<a>``, rad): two
  tilts about the sensor axes most perpendicular to its mean reading and,
  on a body that tilts against gravity from pose to pose at the nominal
  geometry (by :data:`WAHBA_SPREAD` or more), the turn about that reading
  (named after the sensor axis the reading is mostly along).  On a body
  that does not (a column turning about a vertical axis) the turn is not
  seen to first order and is not fitted: the sensor's horizontal axes are
  taken along the body's (an error of ``e`` rad turns the pattern of tilts
  the sensor sees by ``e``);
* the rows ``y_k = t_k . u_i``, ``k = 1, 2``, with ``t_1, t_2`` a tangent basis of
  the *measured* reading (fixed by the data, so the rows are smooth in
  theta); the measured rows are zero, so ``y_meas - y = -t_k . u_i`` is the
  tilt error in rad to first order, weighted by ``[measurement] sigma_tilt``.

``R0_s`` is computed once from the data at the nominal geometry: the
rotation that best maps the readings onto the body-frame up directions
(Wahba's problem, scipy's ``align_vectors``) when the body turns far enough
against gravity (:data:`WAHBA_SPREAD`) to fix the sensor's rotation about
up, else the smallest rotation between the mean directions (the sensor's
horizontal axes are then taken along the body's).  A sensor mounted at any
orientation therefore works; what is fitted is what remains.

Readings are the specific force (an accelerometer at rest reads *up*).  A
base sensor whose readings point down on most poses (the other convention)
has every sensor's readings read with the opposite sign, as the gravity-
driven effects read it (:mod:`bayescal.effects.gravity_field`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ..geometry import left_jacobian, skew, so3_exp, tangent_basis, tilt_axes

__all__ = ["SensorSet", "WAHBA_SPREAD", "UP", "smallest_rotation"]

#: rad: body-frame up directions spread at least this far from their mean fix a sensor's rotation about up
WAHBA_SPREAD = 0.05
#: The machine's nominal up in its base frame (gravity along -z, as the gravity-driven effects assume).
UP = np.array([0.0, 0.0, 1.0])
_XYZ = "xyz"


def smallest_rotation(a: NDArray, b: NDArray) -> NDArray:
    """The rotation of least angle taking unit vector ``a`` (3,) to unit vector ``b`` (3,), (3, 3)."""
    c = np.cross(a, b)
    s, d = np.linalg.norm(c), float(a @ b)
    if s < 1e-12:
        if d > 0:
            return np.eye(3)
        k = np.eye(3)[int(np.argmin(np.abs(a)))]  # opposite: half a turn about any axis normal to a
        axis = np.cross(a, k) / np.linalg.norm(np.cross(a, k))
        return so3_exp(np.pi * axis)
    return so3_exp(c / s * np.arctan2(s, d))


def tilt_pair(v: NDArray) -> tuple[NDArray, tuple[str, str]]:
    """Two orthonormal axes normal to unit ``v`` (columns of a (3, 2) array), from the axes ``v`` is most perpendicular to, and their names."""
    ax = tilt_axes(v)
    out = []
    for k in ax:
        e = np.eye(3)[k] - v * v[k]
        for o in out:
            e = e - o * (o @ e)
        out.append(e / np.linalg.norm(e))
    return np.stack(out, axis=1), (f"r{_XYZ[ax[0]]}", f"r{_XYZ[ax[1]]}")


@dataclass(frozen=True, eq=False)
class SensorSet:
    """The body sensors of a recording, with their nominal mountings fixed from the data.

    Attributes
    ----------
    bodies : tuple of str
        The bodies carrying a sensor (not the base), recording order; ``S`` of them.
    frames : tuple of (int, ndarray (3, 3))
        Per body, the joint whose frame it is fixed to and its orientation there (``Serial.body_frame``).
    u : ndarray, shape (n, S, 3)
        The measured unit readings (sign convention applied).
    tangent : ndarray, shape (n, S, 2, 3)
        Tangent basis of each measured reading (the rows' directions).
    R0 : ndarray, shape (S, 3, 3)
        Nominal mountings, sensor frame to body frame.
    E : ndarray, shape (S, 3, 3)
        Each sensor's mounting axes, sensor frame: two tilts, then the mean reading (the turn).
    turn : tuple of bool
        Per sensor, whether its turn is fitted (three mounting angles, else two).
    g0 : ndarray, shape (n, 3)
        Up per pose before the fitted tilt, base frame.
    E_g : ndarray, shape (3, 2)
        The tilt axes of up, base frame.
    names : tuple of str
        The parameter names: each sensor's mounting (two tilts, the turn where fitted), then up's two tilts.
    base_sensor : bool
        Whether ``g0`` comes from a base sensor.
    flipped : bool
        Whether the readings were taken with the opposite sign (a base sensor reading down).
    """

    bodies: tuple
    frames: tuple
    u: NDArray
    tangent: NDArray
    R0: NDArray
    E: NDArray
    g0: NDArray
    E_g: NDArray
    names: tuple
    turn: tuple = ()
    base_sensor: bool = False
    flipped: bool = False
    bend: NDArray | None = None

    def with_bend(self, bend: NDArray | None) -> "SensorSet":
        """The same sensors with their bodies turned further by ``bend`` (n, S, 3), a small base-frame rotation
        per pose and sensor (what an effect that bends the structure adds; None: none)."""
        if bend is not None:
            bend = np.asarray(bend, dtype=float)
            if bend.shape != (self.u.shape[0], self.n_sensors, 3) or not np.all(np.isfinite(bend)):
                raise ValueError(f"bend: expected finite values of shape {(self.u.shape[0], self.n_sensors, 3)}, got {bend.shape}")
        return replace(self, bend=bend)

    def per_sensor(self, per_body: dict) -> NDArray | None:
        """``{body: (n, ...)}`` (an effect's turn of bodies, or its Jacobian) as (n, S, ...) in sensor order.

        Sensors on bodies ``per_body`` leaves out get zeros, bodies without a sensor are dropped; None when
        ``per_body`` names no sensor's body.
        """
        mine = {b: np.asarray(v, dtype=float) for b, v in per_body.items() if b in self.bodies}
        if not mine:
            return None
        first = next(iter(mine.values()))
        out = np.zeros((first.shape[0], self.n_sensors) + first.shape[1:])
        for body, v in mine.items():
            out[:, self.bodies.index(body)] = v
        return out

    def bent(self, body_R: NDArray, body_J: NDArray) -> tuple[NDArray, NDArray]:
        """Body orientations (N, S, 3, 3) and their Jacobian (N, S, 3, k) with :attr:`bend` applied.

        ``R' = exp([w]x) R``; a small rotation ``J d`` of ``R`` is ``exp([w]x) J d`` of ``R'``.
        """
        if self.bend is None:
            return body_R, body_J
        E = so3_exp(self._tiled(self.bend, body_R.shape[0]).reshape(-1, 3)).reshape(body_R.shape)
        return E @ body_R, E @ body_J

    @property
    def n_sensors(self) -> int:
        return len(self.bodies)

    @property
    def n_rows(self) -> int:
        """Rows per pose: two tilt angles per sensor."""
        return 2 * self.n_sensors

    @property
    def n_params(self) -> int:
        return len(self.names)

    def row_sigma(self, sigma_tilt: float) -> float:
        """One-sigma of a tilt row (rad) for sensors of noise ``sigma_tilt`` (rad per tilt angle).

        With a base sensor, up itself is a reading: its noise enters every
        row, so a row's sigma is ``sqrt(2) sigma_tilt`` (both sensors of the
        stated noise).
        """
        return float(sigma_tilt) * (np.sqrt(2.0) if self.base_sensor else 1.0)

    def tiled(self, reps: int) -> "SensorSet":
        """The readings of ``reps`` stacked copies of the poses (parameter sets evaluated in one call, set-major)."""
        t = lambda a: None if a is None else np.tile(a, (reps,) + (1,) * (a.ndim - 1))  # noqa: E731
        return replace(self, u=t(self.u), tangent=t(self.tangent), g0=t(self.g0), bend=t(self.bend))

    def subset(self, idx) -> "SensorSet":
        """The poses ``idx``, the nominal mountings kept (they are fixed once, from all the rows)."""
        idx = np.asarray(idx)
        return replace(self, u=self.u[idx], tangent=self.tangent[idx], g0=self.g0[idx],
                       bend=None if self.bend is None else self.bend[idx])

    @classmethod
    def start(cls, bodies, frames, readings: NDArray, base_reading: NDArray | None, body_R: NDArray,
              rows=None) -> "SensorSet":
        """The sensors with their nominal mountings fixed from the data at the nominal geometry.

        Parameters
        ----------
        bodies : tuple of str
        frames : tuple of (int, ndarray (3, 3))
        readings : ndarray, shape (n, S, 3)
            Unit readings of the body sensors.
        base_reading : ndarray, shape (n, 3) or None
            Unit readings of a base sensor.
        body_R : ndarray, shape (n, S, 3, 3)
            The bodies' orientations at the nominal geometry.
        rows : array_like of int, optional
            The poses the nominal mountings and the sign convention are fixed
            from (default: all): a recording's ``fit`` rows, so that held-out
            ``check`` readings shape nothing that predicts them.
        """
        u = np.asarray(readings, dtype=float)
        use = np.arange(u.shape[0]) if rows is None or np.size(rows) == 0 else np.asarray(rows)
        flipped = False
        if base_reading is not None:
            b = np.asarray(base_reading, dtype=float)
            if np.median(b[use] @ UP) < 0:  # the other sign convention (reads down): every sensor alike
                b, u, flipped = -b, -u, True
            R0b = smallest_rotation(_mean_dir(b[use]), UP)
            g0 = b @ R0b.T
        else:
            g0 = np.broadcast_to(UP, (u.shape[0], 3)).copy()
        E_g, gnames = tilt_pair(_mean_dir(g0[use]))
        names = []
        R0, E, turns = [], [], []
        for s, body in enumerate(bodies):
            up_body = np.einsum("nji,nj->ni", body_R[use, s], g0[use])  # R_b^T g0
            R, fit_turn = _nominal_mount(u[use, s], up_body)
            R0.append(R)
            turns.append(fit_turn)
            mean = _mean_dir(u[use, s])
            e, mnames = tilt_pair(mean)
            E.append(np.column_stack([e, mean]))
            if fit_turn:
                mnames = mnames + ("r" + _XYZ[({0, 1, 2} - set(tilt_axes(mean))).pop()],)
            names += [f"sensor.{body}.mount.{x}" for x in mnames]
        # up's tilt last: where the data cannot tell it from a sensor's turn, the base is taken as level
        names += [f"{'sensor.base.mount' if base_reading is not None else 'gravity.tilt'}.{x}" for x in gnames]
        tangent = tangent_basis(u.reshape(-1, 3)).reshape(u.shape[0], u.shape[1], 2, 3)
        return cls(tuple(bodies), tuple(frames), u, tangent, np.array(R0), np.array(E), g0, E_g, tuple(names),
                   tuple(turns), base_reading is not None, flipped)

    @property
    def mount_slices(self) -> list[slice]:
        """Each sensor's mounting angles within the sensors' parameters."""
        out, o = [], 0
        for t in self.turn:
            out.append(slice(o, o + 2 + int(t)))
            o += 2 + int(t)
        return out

    def _mount_angles(self, th: NDArray) -> NDArray:
        """(N, S, 3) mounting angles (the turn zero where not fitted) from the parameters (N, k)."""
        d = np.zeros((th.shape[0], self.n_sensors, 3))
        for s, sl in enumerate(self.mount_slices):
            d[:, s, : sl.stop - sl.start] = th[:, sl]
        return d

    # --------------------------------------------------------------- the rows
    def _parts(self, theta_s: NDArray, n_rows: int):
        """Up per row and each sensor's ``exp(-[E d]x) R0^T`` per row, from the sensor parameters (k,) or (n_rows, k)."""
        th = np.broadcast_to(theta_s, (n_rows, self.n_params))
        reps = n_rows // self.g0.shape[0]
        g0 = np.tile(self.g0, (reps, 1)) if reps > 1 else self.g0
        phi_g = th[:, -2:] @ self.E_g.T  # (N, 3)
        g = np.einsum("nij,nj->ni", so3_exp(phi_g), g0)
        psi = -np.einsum("sij,nsj->nsi", self.E, self._mount_angles(th))  # (N, S, 3)
        M = so3_exp(psi) @ np.swapaxes(self.R0, -1, -2)[None]  # (N, S, 3, 3)
        return th, g, phi_g, psi, M

    def _tiled(self, arr: NDArray, n_rows: int) -> NDArray:
        reps = n_rows // arr.shape[0]
        return np.tile(arr, (reps,) + (1,) * (arr.ndim - 1)) if reps > 1 else arr

    def readings(self, body_R: NDArray, theta_s: NDArray) -> NDArray:
        """Predicted unit readings (N, S, 3), in each sensor's frame and the recording's sign, for body
        orientations (N, S, 3, 3) and sensor parameters (k,) or (N, k): what :meth:`rows` projects."""
        n_rows = body_R.shape[0]
        _, g, _, _, M = self._parts(theta_s, n_rows)
        u = np.einsum("nsij,nsj->nsi", M, np.einsum("nsji,nj->nsi", body_R, g))
        return -u if self.flipped else u

    def rows(self, body_R: NDArray, theta_s: NDArray) -> NDArray:
        """Predicted rows, shape (N, 2 S), rad, for body orientations (N, S, 3, 3) and sensor parameters (k,) or (N, k)."""
        n_rows = body_R.shape[0]
        _, g, _, _, M = self._parts(theta_s, n_rows)
        v = np.einsum("nsji,nj->nsi", body_R, g)  # R_b^T g
        u = np.einsum("nsij,nsj->nsi", M, v)
        T = self._tiled(self.tangent, n_rows)
        return np.einsum("nskj,nsj->nsk", T, u).reshape(n_rows, self.n_rows)

    def jacobian(self, body_R: NDArray, body_J: NDArray, theta_s: NDArray) -> tuple[NDArray, NDArray]:
        """Derivatives of :meth:`rows`: by the machine's parameters (N, 2 S, P) and by the sensor parameters (N, 2 S, k).

        ``body_J`` (N, S, 3, P) is the bodies' small-rotation Jacobian
        (``R(theta + d) = exp([J d]x) R(theta)``): ``du = M R_b^T [g]x J d``;
        up's tilt: ``dg = -[g]x J_l(E_g d_g) E_g``; a mounting:
        ``du = [u]x J_l(-E d) E``.
        """
        n_rows, S = body_R.shape[0], self.n_sensors
        th, g, phi_g, psi, M = self._parts(theta_s, n_rows)
        T = self._tiled(self.tangent, n_rows)  # (N, S, 2, 3)
        TMRt = np.einsum("nskj,nsji,nsli->nskl", T, M, body_R)  # t^T M R_b^T, (N, S, 2, 3)
        A = TMRt @ skew(g)[:, None]  # (N, S, 2, 3)
        Jm = np.einsum("nskj,nsjp->nskp", A, body_J).reshape(n_rows, 2 * S, -1)
        Js = np.zeros((n_rows, S, 2, self.n_params))
        dg = -skew(g) @ left_jacobian(phi_g) @ self.E_g  # (N, 3, 2)
        Js[..., -2:] = np.einsum("nskj,njp->nskp", TMRt, dg)
        v = np.einsum("nsji,nj->nsi", body_R, g)
        u = np.einsum("nsij,nsj->nsi", M, v)
        du = skew(u) @ left_jacobian(psi) @ self.E[None]  # (N, S, 3, 3)
        for s, sl in enumerate(self.mount_slices):
            Js[:, s, :, sl] = (T[:, s] @ du[:, s])[:, :, : sl.stop - sl.start]
        return Jm, Js.reshape(n_rows, 2 * S, self.n_params)

    def tilt_errors(self, residual_rows: NDArray) -> NDArray:
        """Per pose and sensor, the tilt error (rad): the norm of its two rows, shape (n, S)."""
        r = np.asarray(residual_rows, dtype=float)
        return np.linalg.norm(r.reshape(r.shape[0], self.n_sensors, 2), axis=2)


def _mean_dir(u: NDArray) -> NDArray:
    m = np.mean(u, axis=0)
    return m / np.linalg.norm(m)


def _nominal_mount(u: NDArray, up_body: NDArray) -> tuple[NDArray, bool]:
    """The rotation R0 (sensor to body frame) with ``R0 u_i ~ up_body_i``, and whether the poses fix its turn.

    Wahba's fit when the body-frame up directions spread by
    :data:`WAHBA_SPREAD` or more, else the smallest rotation between the
    mean directions.
    """
    m = _mean_dir(up_body)
    spread = float(np.max(np.arccos(np.clip(up_body @ m, -1.0, 1.0))))
    if spread >= WAHBA_SPREAD:
        from scipy.spatial.transform import Rotation

        rot, _ = Rotation.align_vectors(up_body, u)
        return rot.as_matrix(), True
    return smallest_rotation(_mean_dir(u), m), False
