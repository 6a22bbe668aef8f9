"""The linear delta: vertical towers with carriages, parallelogram arms, a translating effector.

Kinematics (docs/delta.md).  Tower ``i`` stands at angle ``a_i`` and radius
``r_i``: its axis crosses the plane ``z = 0`` of the base frame at
``B_i = (r_i cos a_i, r_i sin a_i, 0)`` and runs along the unit direction
``u_i`` (nominally ``e_z``).  The carriage's arm joint is at

    C_i = B_i + (z0_i + q_i) u_i

(``z0_i`` the tower's zero: where the joint is at ``q_i = 0``).  A
parallelogram arm of length ``L_i`` keeps the effector from rotating, so the
effector is a point ``p`` (the centre of its arm-joint pattern, the arms'
horizontal offsets folded into ``r_i`` as Klipper's ``delta_radius`` does)
with

    F_i = (|p - C_i|^2 - L_i^2) / 2 = 0,     i = 1..N.

The effector is below the carriages (``(C_i - p) . u_i > 0``).  The tool
point is ``p + t`` and the rotation is the identity.  With ``N = 3`` the
three equations fix ``p``; with more towers the model takes the least-squares
compromise of the arm equations (a rigid over-constrained machine cannot
assemble otherwise), whose derivative follows from the normal equations.

Error parameters per tower (6): ``tower<i>.angle`` (rad), ``tower<i>.radius``
(mm), ``tower<i>.zero`` (mm, the endstop or zero offset along the tower),
``tower<i>.direction.tilt_{a,b}`` (rad, the tower's tilt about the two base
axes it is most perpendicular to, :func:`bayescal.geometry.tilted_direction`),
``tower<i>.arm_length`` (mm); plus the effector offset of the measured point
``tool.point.{x,y,z}`` (mm).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..geometry import tilt_axes, tilted_direction
from ..io.machine_file import TomlTable, format_toml_value
from ..params import ParamLayout, ParamSpec
from .base import Machine, MeasurementNoise, ToolPoses
from .common import common_toml, read_noise, read_q_limits, read_tolerance
from .tolerance import tolerance_vector
from .prs3 import _condition_numbers

__all__ = ["LinearDelta", "DELTA_TOLERANCE_DEFAULTS"]

#: Documented one-sigma defaults of the ``[tolerance]`` table (mm or rad).
DELTA_TOLERANCE_DEFAULTS: dict[str, float] = {
    "tower_angle": 2.0e-3,
    "tower_radius": 0.2,
    "tower_zero": 0.2,
    "tower_direction": 1.0e-3,
    "arm_length": 0.2,
    "tool_point": 0.2,
}

_XYZ = "xyz"
_PER_TOWER = 6
_NEWTON_TOL = 1e-10  # relative step (of the arm length) below which a pose counts as converged
_NEWTON_MAXIT = 60
_SINGULAR_COND = 1e12  # condition number of d^T d above which a pose counts as singular
_OVERCONSTRAINED_TOL = 1e-2  # relative arm-length mismatch a >3-tower compromise may leave (assembly strain)


@dataclass(frozen=True)
class _Geometry:
    B: NDArray  # (n, N, 3) tower axis at z = 0
    dB_da: NDArray  # (n, N, 3) derivative of B by the tower angle
    dB_dr: NDArray  # (n, N, 3) derivative by the radius
    u: NDArray  # (n, N, 3) tower directions
    du: NDArray  # (n, N, 3, 2) derivative by the two tilts
    z0: NDArray  # (n, N) zeros
    L: NDArray  # (n, N) arm lengths
    t: NDArray  # (n, 3) tool point


@dataclass(frozen=True)
class _EffectorState:
    p: NDArray  # (n, 3) effector reference point, base frame, mm


@dataclass(frozen=True, eq=False)
class LinearDelta(Machine):
    """A linear delta machine (3D printer, delta robot on linear axes).

    Parameters
    ----------
    angle : ndarray, shape (N,)
        Tower angles, rad (machine file ``angle_deg``, degrees).
    radius : ndarray, shape (N,)
        Horizontal distance of each tower axis from the effector's arm-joint
        centre line, mm (Klipper's ``delta_radius``).
    zero : ndarray, shape (N,)
        Position of each carriage's arm joint along its tower at ``q = 0``, mm.
    direction : ndarray, shape (N, 3)
        Unit tower directions (``q`` grows along them).
    arm_length : ndarray, shape (N,)
        mm.
    tool_point : ndarray, shape (3,)
        Measured point relative to the effector's reference point, mm.
    name, noise, q_limits, tolerance_groups, source
        As for every kind.
    """

    kind = "linear-delta"

    angle: NDArray
    radius: NDArray
    zero: NDArray
    direction: NDArray
    arm_length: NDArray
    tool_point: NDArray
    name: str = "linear delta"
    noise: MeasurementNoise = field(default_factory=MeasurementNoise)
    q_limits: NDArray | None = None
    tolerance_groups: dict = field(default_factory=lambda: dict(DELTA_TOLERANCE_DEFAULTS))
    source: str = "<memory>"

    def __post_init__(self) -> None:
        n = len(self.angle)
        if n < 3:
            raise InputError(f"a linear delta needs at least 3 towers, got {n}")
        axes = tuple(tilt_axes(u) for u in self.direction)
        object.__setattr__(self, "_axes", axes)
        specs = []
        for i in range(n):
            c = f"tower{i + 1}"
            specs += [
                ParamSpec(f"{c}.angle", "rad", "tower_angle"),
                ParamSpec(f"{c}.radius", "mm", "tower_radius"),
                ParamSpec(f"{c}.zero", "mm", "tower_zero"),
            ]
            specs += [ParamSpec(f"{c}.direction.tilt_{_XYZ[k]}", "rad", "tower_direction") for k in axes[i]]
            specs += [ParamSpec(f"{c}.arm_length", "mm", "arm_length")]
        specs += [ParamSpec(f"tool.point.{x}", "mm", "tool_point") for x in _XYZ]
        object.__setattr__(self, "layout", ParamLayout(tuple(specs)))
        object.__setattr__(self, "tolerance", tolerance_vector(specs, self.tolerance_groups))

    @property
    def n_actuators(self) -> int:
        return len(self.angle)

    # ----------------------------------------------------------------- set-up
    @classmethod
    def from_toml(cls, doc: TomlTable, path: str) -> "LinearDelta":
        doc.reject_unknown({"kind", "name", "tower", "tool", "measurement", "workspace", "tolerance"})
        towers = doc.array_of_tables("tower")
        if len(towers) < 3:
            raise doc.error("tower", f"expected at least 3 [[tower]] tables, got {len(towers)}")
        ang, rad, zero, dirs, arms = [], [], [], [], []
        for tw in towers:
            tw.reject_unknown({"angle_deg", "radius", "position", "zero", "direction", "arm_length"})
            if tw.has("position"):
                if tw.has("angle_deg") or tw.has("radius"):
                    raise tw.error("position", "give either position = [x, y] or angle_deg and radius, not both")
                xy = tw.vector("position", 2)
                r = float(np.hypot(*xy))
                if r <= 0:
                    raise tw.error("position", f"expected a tower off the centre line, got {xy.tolist()}")
                ang.append(float(np.arctan2(xy[1], xy[0])))
                rad.append(r)
            else:
                ang.append(np.deg2rad(tw.number("angle_deg")))
                rad.append(tw.number("radius", positive=True))
            zero.append(tw.number("zero", 0.0))
            u = tw.vector("direction", unit=True, default=[0.0, 0.0, 1.0])
            if abs(u[2]) < 0.5:
                raise tw.error("direction", f"expected a tower direction within 60 degrees of vertical (+z or -z), got {u.tolist()}")
            dirs.append(u)
            arms.append(tw.number("arm_length", positive=True))
        tool = doc.table("tool", required=False)
        t = np.zeros(3)
        if tool is not None:
            tool.reject_unknown({"point"})
            t = tool.vector("point", default=[0.0, 0.0, 0.0])
        n = len(towers)
        return cls(
            angle=np.array(ang), radius=np.array(rad), zero=np.array(zero), direction=np.array(dirs),
            arm_length=np.array(arms), tool_point=t, name=doc.string("name", "linear delta"),
            noise=read_noise(doc), q_limits=read_q_limits(doc, n),
            tolerance_groups=read_tolerance(doc, DELTA_TOLERANCE_DEFAULTS), source=path,
        )

    def _theta_rows(self, theta: ArrayLike | None, n: int) -> NDArray:
        theta = self.check_theta(theta, n)
        return np.broadcast_to(theta, (n, self.n_params)) if theta.ndim == 1 else theta

    def _geometry(self, theta: NDArray) -> _Geometry:
        """Geometry for theta of shape (n, P)."""
        n, N = theta.shape[0], self.n_actuators
        th = theta[:, : _PER_TOWER * N].reshape(n, N, _PER_TOWER)
        a = self.angle[None] + th[:, :, 0]
        r = self.radius[None] + th[:, :, 1]
        ca, sa = np.cos(a), np.sin(a)
        zeros = np.zeros_like(a)
        B = np.stack([r * ca, r * sa, zeros], axis=-1)
        dB_da = np.stack([-r * sa, r * ca, zeros], axis=-1)
        dB_dr = np.stack([ca, sa, zeros], axis=-1)
        u = np.empty((n, N, 3))
        du = np.empty((n, N, 3, 2))
        for i in range(N):
            u[:, i], du[:, i] = tilted_direction(self.direction[i], self._axes[i], th[:, i, 3:5])
        z0 = self.zero[None] + th[:, :, 2]
        L = self.arm_length[None] + th[:, :, 5]
        t = self.tool_point[None] + theta[:, _PER_TOWER * N:]
        return _Geometry(B=B, dB_da=dB_da, dB_dr=dB_dr, u=u, du=du, z0=z0, L=L, t=t)

    def geometry_arrays(self, theta: ArrayLike | None = None) -> dict[str, NDArray]:
        """Actual geometry ``nominal + theta`` (theta of shape (P,)) as the machine file's arrays (angles in rad)."""
        theta = self.check_theta(theta)
        g = self._geometry(theta[None, :])
        N = self.n_actuators
        th = theta[: _PER_TOWER * N].reshape(N, _PER_TOWER)
        return {
            "angle": self.angle + th[:, 0], "radius": self.radius + th[:, 1], "zero": g.z0[0],
            "direction": g.u[0], "arm_length": g.L[0], "tool_point": g.t[0],
        }

    def carriages(self, q: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """Carriage arm-joint centres ``C_i = B_i + (z0_i + q_i) u_i``, shape (n_poses, N, 3), mm."""
        q = self.check_q(q)
        g = self._geometry(self._theta_rows(theta, q.shape[0]))
        return g.B + (g.z0 + q)[..., None] * g.u

    # ------------------------------------------------------------ kinematics
    def _solve(self, q: NDArray, g: _Geometry, p: NDArray):
        """Gauss-Newton on the arm equations (Newton for three towers), batched over poses."""
        C = g.B + (g.z0 + q)[..., None] * g.u
        scale = g.L.mean(axis=1)
        converged = np.zeros(q.shape[0], dtype=bool)
        below = np.zeros(q.shape[0], dtype=bool)
        p = p.copy()
        for _ in range(_NEWTON_MAXIT):
            d = p[:, None, :] - C
            F = 0.5 * (np.einsum("nki,nki->nk", d, d) - g.L**2)
            H = np.einsum("nki,nkj->nij", d, d)
            gvec = np.einsum("nki,nk->ni", d, F)
            try:
                dp = -np.linalg.solve(H, gvec[..., None])[..., 0]
            except np.linalg.LinAlgError:
                dp = -np.einsum("nij,nj->ni", np.linalg.pinv(H), gvec)
            dp = np.where(np.isfinite(dp), dp, 0.0)
            # cap the step: far from the solution Newton may jump to the upper branch
            size = np.linalg.norm(dp, axis=1) / scale
            dp *= np.minimum(1.0, 0.2 / np.maximum(size, 1e-300))[:, None]
            now = size < _NEWTON_TOL
            # one more step taken below the tolerance polishes the pose to round-off
            converged |= now & below
            below = now
            p = np.where(converged[:, None], p, p + dp)
            if converged.all():
                break
        d = p[:, None, :] - C
        mismatch = np.abs(np.linalg.norm(d, axis=2) - g.L) / g.L
        return p, converged | below, mismatch, d, C

    def _initial_p(self, q: NDArray, g: _Geometry) -> NDArray:
        """A start below the carriages: on the mean tower line, one arm's height below."""
        C = g.B + (g.z0 + q)[..., None] * g.u
        horiz = np.linalg.norm(C[:, :, :2] - C[:, :, :2].mean(axis=1, keepdims=True), axis=2)
        drop = np.sqrt(np.maximum(g.L**2 - horiz**2, 0.01 * g.L**2)).mean(axis=1)
        p = C.mean(axis=1)
        p[:, 2] -= drop
        return p

    def forward(self, q: ArrayLike, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> ToolPoses:
        """Forward kinematics: the effector point where the arms meet, below the carriages.

        Parameters
        ----------
        q : array_like, shape (n_poses, N)
            Carriage positions along the towers, mm.
        theta : array_like, shape (P,) or (n_poses, P), optional
            Geometric errors (actual minus nominal); zeros if omitted.
        guess : ToolPoses, optional
            A nearby solution to start from.

        Returns
        -------
        ToolPoses
            Tool point ``p + t``, identity rotations; ``success`` False with a
            message where the arms cannot reach (no intersection), the
            solution is above a carriage, or the pose is singular.
        """
        q = self.check_q(q)
        n = q.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        warm = guess is not None and isinstance(guess.state, _EffectorState) and guess.state.p.shape == (n, 3)
        p0 = guess.state.p if warm else self._initial_p(q, g)
        p, conv, mismatch, d, _ = self._solve(q, g, p0)
        tol = 1e-9 if self.n_actuators == 3 else _OVERCONSTRAINED_TOL
        msgs = [""] * n
        unreached = ~conv | (mismatch.max(axis=1) > tol)
        below = ~unreached & (np.einsum("nki,nki->nk", d, g.u) >= 0).any(axis=1)  # (C - p) . u <= 0
        # cond(d^T d) = cond(d)^2 for three towers; the cheap 1-norm bound where it is clearly fine
        cond = _condition_numbers(np.einsum("nki,nkj->nij", d, d), _SINGULAR_COND)
        singular = ~unreached & ~below & (~np.isfinite(cond) | (cond > _SINGULAR_COND))
        for i in np.flatnonzero(unreached):
            msgs[i] = f"the arms cannot reach a common point (arm-length mismatch {mismatch[i].max() * g.L[i].mean():.3g} mm)"
        for i in np.flatnonzero(below):
            msgs[i] = "effector not below all carriages (other assembly branch or arm horizontal)"
        for i in np.flatnonzero(singular):
            msgs[i] = f"singular pose (arm-direction matrix condition number {cond[i]:.2e})"
        success = ~(unreached | below | singular)
        R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        return ToolPoses(position=p + g.t, rotation=R, success=success, message=tuple(msgs), state=_EffectorState(p=p))

    def guess_from_measurement(
        self, q: NDArray, position: NDArray, rotation: NDArray | None = None, axis: NDArray | None = None
    ) -> ToolPoses:
        """Effector start ``p = y - t`` from measured tool points (the rotation is the identity)."""
        position = np.asarray(position, dtype=float)
        n = position.shape[0]
        p = position - self.tool_point[None]
        R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        return ToolPoses(position=position, rotation=R, success=np.ones(n, bool), message=("",) * n, state=_EffectorState(p=p))

    def inverse(self, position: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """Closed-form inverse kinematics: carriage positions for tool points.

        Parameters
        ----------
        position : array_like, shape (n_poses, 3)
            Tool points, base frame, mm.
        theta : array_like, optional
            Geometric errors.

        Returns
        -------
        ndarray, shape (n_poses, N)
            ``q`` (mm) with the carriages above the effector; NaN where an arm
            cannot reach.  From ``|w - s u|^2 = L^2`` with ``w = p - B``:
            ``s = w.u + sqrt((w.u)^2 - |w|^2 + L^2)``, ``q = s - z0``.
        """
        pos = np.atleast_2d(np.asarray(position, dtype=float))
        n = pos.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        w = (pos - g.t)[:, None, :] - g.B
        wu = np.einsum("nki,nki->nk", w, g.u)
        disc = wu**2 - np.einsum("nki,nki->nk", w, w) + g.L**2
        with np.errstate(invalid="ignore"):
            return wu + np.sqrt(np.where(disc >= 0, disc, np.nan)) - g.z0

    @property
    def actuator_box_reachable(self) -> bool:
        """False: carriages far apart within ``q_limits`` pull the arms past their length."""
        return False

    def sample_q(self, n: int, rng: np.random.Generator) -> NDArray:
        """``n`` reachable actuator vectors within ``q_limits``.

        Tool points are drawn in a cylinder (half the smallest tower radius,
        heights that ``q_limits`` allow at the centre) and mapped by the
        inverse kinematics; those outside ``q_limits`` are drawn again.  A
        box of ``q`` would hold unreachable poses and, with more than three
        towers, poses the arms cannot assemble at all.
        """
        if self.q_limits is None:
            raise InputError(f"{self.source}: the machine file has no [workspace] q_limits; they are needed to draw poses")
        lo, hi = self.q_limits[:, 0], self.q_limits[:, 1]
        centre = np.zeros((1, 3))
        q_c = self.inverse(centre)[0]  # q at the centre, z = 0
        z_lo, z_hi = float(np.max(lo - q_c)), float(np.min(hi - q_c))  # q grows with z one to one at the centre
        if not z_lo < z_hi:
            raise InputError(f"{self.source}: [workspace] q_limits leave no height at which the effector can be on the centre line")
        rho = 0.5 * float(self.radius.min())
        out = np.empty((0, self.n_actuators))
        for _ in range(200):
            m = 4 * n
            ang = rng.uniform(0, 2 * np.pi, m)
            rad = rho * np.sqrt(rng.random(m))
            pts = np.column_stack([rad * np.cos(ang), rad * np.sin(ang), rng.uniform(z_lo, z_hi, m)]) + self.tool_point
            q = self.inverse(pts)
            ok = np.isfinite(q).all(axis=1) & (q >= lo).all(axis=1) & (q <= hi).all(axis=1)
            out = np.vstack([out, q[ok]])
            if out.shape[0] >= n:
                return out[:n]
        raise InputError(f"{self.source}: could not draw {n} reachable poses within [workspace] q_limits")

    def _jacobian_solve(self, g: _Geometry, d: NDArray, Fv: NDArray, G: NDArray, dC: NDArray) -> NDArray:
        """``dp`` from the normal equations of ``min sum F_k^2``.

        ``d^T F = 0`` differentiated: ``(d^T d + sum F_k I) dp = -(d^T G - sum_k F_k dC_k)``
        where ``G`` (n, N, k) is the derivative of F at fixed ``p`` and ``dC``
        (n, N, 3, k) that of the carriage points; with three towers F = 0 and
        this is ``-d^{-1} G``.
        """
        H = np.einsum("nki,nkj->nij", d, d) + Fv.sum(axis=1)[:, None, None] * np.eye(3)
        rhs = np.einsum("nki,nkp->nip", d, G) - np.einsum("nk,nkip->nip", Fv, dC)
        return -np.linalg.solve(H, rhs)

    def tool_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Identification Jacobian by the implicit function theorem.

        With ``d_i = p - C_i`` and ``F_i = (|d_i|^2 - L_i^2)/2``:
        ``dF_i/dp = d_i``, ``dF_i/d(a_i, r_i) = -d_i . dB_i``,
        ``dF_i/dz0_i = -d_i . u_i``, ``dF_i/dtilt_i = -(z0_i + q_i) d_i . du_i``,
        ``dF_i/dL_i = -L_i``; ``dp = -F_p^{-1} F_theta`` (least-squares form
        for more than three towers); the tool point adds the identity for
        ``tool.point``.  Rotation rows are zero.  Shape (n_poses, 6, P).
        """
        q = self.check_q(q)
        n, N = q.shape
        g = self._geometry(self._theta_rows(theta, n))
        p = poses.state.p
        s = g.z0 + q
        C = g.B + s[..., None] * g.u
        d = p[:, None, :] - C
        Fv = 0.5 * (np.einsum("nki,nki->nk", d, d) - g.L**2)
        P = self.n_params
        G = np.zeros((n, N, P))
        dC = np.zeros((n, N, 3, P))
        for i in range(N):
            o = _PER_TOWER * i
            dC[:, i, :, o] = g.dB_da[:, i]
            dC[:, i, :, o + 1] = g.dB_dr[:, i]
            dC[:, i, :, o + 2] = g.u[:, i]
            dC[:, i, :, o + 3 : o + 5] = s[:, i, None, None] * g.du[:, i]
            G[:, i, o : o + 5] = -np.einsum("nj,njp->np", d[:, i], dC[:, i, :, o : o + 5])
            G[:, i, o + 5] = -g.L[:, i]
        dp = self._jacobian_solve(g, d, Fv, G, dC)
        J = np.zeros((n, 6, P))
        J[:, :3] = dp
        J[:, :3, _PER_TOWER * N:] += np.eye(3)
        return J

    def actuator_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Tool-point derivative by the carriage positions, analytic: ``dC_i/dq_i = u_i``.

        Shape (n_poses, 6, N); rotation rows zero.
        """
        q = self.check_q(q)
        n, N = q.shape
        g = self._geometry(self._theta_rows(theta, n))
        p = poses.state.p
        C = g.B + (g.z0 + q)[..., None] * g.u
        d = p[:, None, :] - C
        Fv = 0.5 * (np.einsum("nki,nki->nk", d, d) - g.L**2)
        dC = np.zeros((n, N, 3, N))
        G = np.zeros((n, N, N))
        for i in range(N):
            dC[:, i, :, i] = g.u[:, i]
            G[:, i, i] = -np.einsum("nj,nj->n", d[:, i], g.u[:, i])
        J = np.zeros((n, 6, N))
        J[:, :3] = self._jacobian_solve(g, d, Fv, G, dC)
        return J

    # ------------------------------------------------------------------ output
    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """Machine file of the geometry ``nominal + theta``, same kind and keys."""
        g = self.geometry_arrays(theta)
        f = format_toml_value
        out = ['kind = "linear-delta"', f"name = {f(self.name)}", ""]
        for i in range(self.n_actuators):
            out += [
                "[[tower]]",
                f"angle_deg = {f(float(np.rad2deg(g['angle'][i])))}",
                f"radius = {f(float(g['radius'][i]))}",
                f"zero = {f(float(g['zero'][i]))}",
                f"direction = {f(g['direction'][i])}",
                f"arm_length = {f(float(g['arm_length'][i]))}",
                "",
            ]
        out += ["[tool]", f"point = {f(g['tool_point'])}", ""]
        return "\n".join(out) + common_toml(self, self.tolerance_groups)
