"""The 3-PRS parallel mechanism (spindle head of a five-axis hybrid machine).

Kinematics (docs/formats.md section 1): slider centre ``C_i = B_i + q_i u_i``;
sphere centre ``A_i = p + R a_i``; each chain imposes

    F1_i = (|A_i - C_i|^2 - l_i^2) / 2 = 0        (link length)
    F2_i = (A_i - C_i) . r_i = 0                   (link turns normal to r_i)

Six equations fix the platform pose ``(p, R)``.  The tool point is
``p + R t`` and the tool axis ``R e_z``.

Error parameters (per chain, 11): ``sphere_center.{x,y,z}`` (platform
frame, mm), ``rail_origin.{x,y,z}`` (base frame, mm; its component along the
rail is the actuator zero offset), ``rail_direction.tilt_{a,b}`` and
``revolute_axis.tilt_{a,b}`` (rad, small rotations of the direction about
the two base axes it is most perpendicular to, see
:func:`bayescal.geometry.tilted_direction`), ``link_length`` (mm); plus
``tool.point.{x,y,z}`` (platform frame, mm).  36 in all.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..geometry import skew, so3_exp, tilt_axes, tilted_direction
from ..io.machine_file import TomlTable, format_toml_value
from ..params import ParamLayout, ParamSpec
from .base import Machine, MeasurementNoise, ToolPoses, geometry_blocks
from .common import common_toml, read_noise, read_q_limits, read_tolerance
from .tolerance import tolerance_vector
from .construct import kabsch

__all__ = ["Prs3", "PRS3_TOLERANCE_DEFAULTS"]

#: Documented one-sigma defaults of the ``[tolerance]`` table (mm or rad).
PRS3_TOLERANCE_DEFAULTS: dict[str, float] = {
    "sphere_center": 0.05,
    "rail_origin": 0.05,
    "rail_direction": 2.0e-4,
    "revolute_axis": 2.0e-4,
    "link_length": 0.05,
    "tool_point": 0.05,
}

_XYZ = "xyz"
_PER_CHAIN = 11
_NEWTON_TOL = 1e-9  # mm; constraint residual at which a pose counts as solved (then polished)
_NEWTON_MAXIT = 60


_SINGULAR_COND = 1e10  # constraint-Jacobian condition number above which a pose counts as singular


def _condition_numbers(M: NDArray, limit: float) -> NDArray:
    """Condition numbers of the square matrices ``M`` (n, k, k), exact (2-norm, SVD) wherever they may exceed ``limit``.

    ``cond_1 = |M|_1 |M^-1|_1`` satisfies ``cond_2 / k <= cond_1 <= k cond_2``,
    so a matrix with ``cond_1 < limit / k`` is below ``limit`` in the 2-norm
    too; for those ``cond_1`` is returned (a batched inverse is several times
    cheaper than a batched SVD, which dominated the forward kinematics of
    samplers), for all others, and for non-finite matrices, ``np.linalg.cond``.
    """
    k = M.shape[-1]
    cond = np.full(M.shape[0], np.nan)
    finite = np.isfinite(M).all(axis=(1, 2))
    sure = np.zeros(M.shape[0], dtype=bool)
    try:
        inv = np.linalg.inv(M[finite])
    except np.linalg.LinAlgError:
        inv = None  # an exactly singular matrix: take the SVD of all
    if inv is not None:
        with np.errstate(invalid="ignore", over="ignore"):
            c1 = np.abs(M[finite]).sum(axis=1).max(axis=1) * np.abs(inv).sum(axis=1).max(axis=1)
        ok = c1 < limit / k
        sure[np.flatnonzero(finite)[ok]] = True
        cond[sure] = c1[ok]
    if not sure.all():
        cond[~sure] = np.linalg.cond(M[~sure])
    return cond


#: Poses per block of :meth:`Prs3.tool_jacobian`: every pose's Jacobian is its own (the same values whatever the
#: blocks), and a block's (block, 6, P) arrays of about 7 MB stay in the cache and are reused by the allocator,
#: while whole arrays of 100,000 poses (170 MB each) cost their page faults again at every call (glibc gives
#: arrays above 32 MB back to the kernel when freed): 0.46 s a call for the batched solve alone, against 25 ms
#: at 10,000 poses.
_BLOCK = 4096


@dataclass(frozen=True)
class _Geometry:
    """Geometry arrays broadcast over poses (leading axis n)."""

    a: NDArray  # (n, 3, 3) sphere centres, platform frame (chain, xyz)
    B: NDArray  # (n, 3, 3) rail origins
    u: NDArray  # (n, 3, 3) rail directions
    du: NDArray  # (n, 3, 3, 2)
    r: NDArray  # (n, 3, 3) revolute axes
    dr: NDArray  # (n, 3, 3, 2)
    l: NDArray  # (n, 3) link lengths
    t: NDArray  # (n, 3) tool point, platform frame


@dataclass(frozen=True)
class _PlatformState:
    p: NDArray  # (n, 3)
    R: NDArray  # (n, 3, 3)


@dataclass(frozen=True, eq=False)
class Prs3(Machine):
    """A 3-PRS machine: nominal geometry, parameter layout, kinematics.

    Parameters
    ----------
    rail_origin, rail_direction, revolute_axis, sphere_center : ndarray, shape (3, 3)
        Per chain (rows), as the machine file's keys; mm or unit vectors.
    link_length : ndarray, shape (3,)
        mm.
    tool_point : ndarray, shape (3,)
        mm, platform frame.
    name : str
    noise : MeasurementNoise
    q_limits : ndarray, shape (3, 2) or None
        mm.
    tolerance_groups : dict
        One-sigma per parameter group (mm or rad).
    links_against_rail : bool
        Assembly mode: True when the links point from the sliders against
        the rail direction (platform on the side of the rail origins), the
        usual spindle-head layout.  Read from the optional top-level key
        ``assembly = "against_rail" | "along_rail"``.
    source : str
        File the machine was read from.
    """

    kind = "3-PRS"

    rail_origin: NDArray
    rail_direction: NDArray
    revolute_axis: NDArray
    sphere_center: NDArray
    link_length: NDArray
    tool_point: NDArray
    name: str = "3-PRS"
    noise: MeasurementNoise = field(default_factory=MeasurementNoise)
    q_limits: NDArray | None = None
    tolerance_groups: dict = field(default_factory=lambda: dict(PRS3_TOLERANCE_DEFAULTS))
    links_against_rail: bool = True
    source: str = "<memory>"

    def __post_init__(self) -> None:
        specs = []
        object.__setattr__(self, "_axes_u", tuple(tilt_axes(u) for u in self.rail_direction))
        object.__setattr__(self, "_axes_r", tuple(tilt_axes(r) for r in self.revolute_axis))
        for i in range(3):
            c = f"chain{i + 1}"
            specs += [ParamSpec(f"{c}.sphere_center.{x}", "mm", "sphere_center") for x in _XYZ]
            specs += [ParamSpec(f"{c}.rail_origin.{x}", "mm", "rail_origin") for x in _XYZ]
            specs += [ParamSpec(f"{c}.rail_direction.tilt_{_XYZ[k]}", "rad", "rail_direction") for k in self._axes_u[i]]
            specs += [ParamSpec(f"{c}.revolute_axis.tilt_{_XYZ[k]}", "rad", "revolute_axis") for k in self._axes_r[i]]
            specs += [ParamSpec(f"{c}.link_length", "mm", "link_length")]
        specs += [ParamSpec(f"tool.point.{x}", "mm", "tool_point") for x in _XYZ]
        object.__setattr__(self, "layout", ParamLayout(tuple(specs)))
        tol = tolerance_vector(specs, self.tolerance_groups)
        object.__setattr__(self, "tolerance", tol)

    # ----------------------------------------------------------------- set-up
    @property
    def n_actuators(self) -> int:
        return 3

    @classmethod
    def from_toml(cls, doc: TomlTable, path: str) -> "Prs3":
        doc.reject_unknown({"kind", "name", "chain", "tool", "measurement", "workspace", "tolerance", "assembly"})
        chains = doc.array_of_tables("chain", 3)
        keys = {"rail_origin", "rail_direction", "revolute_axis", "link_length", "sphere_center"}
        arrs = {k: [] for k in keys}
        for ch in chains:
            ch.reject_unknown(keys)
            arrs["rail_origin"].append(ch.vector("rail_origin"))
            arrs["rail_direction"].append(ch.vector("rail_direction", unit=True))
            arrs["revolute_axis"].append(ch.vector("revolute_axis", unit=True))
            arrs["link_length"].append(ch.number("link_length", positive=True))
            arrs["sphere_center"].append(ch.vector("sphere_center"))
        tool = doc.table("tool")
        tool.reject_unknown({"point"})
        assembly = doc.string("assembly", "against_rail")
        if assembly not in ("against_rail", "along_rail"):
            raise doc.error("assembly", f"expected \"against_rail\" or \"along_rail\", got {assembly!r}")
        return cls(
            rail_origin=np.array(arrs["rail_origin"]),
            rail_direction=np.array(arrs["rail_direction"]),
            revolute_axis=np.array(arrs["revolute_axis"]),
            sphere_center=np.array(arrs["sphere_center"]),
            link_length=np.array(arrs["link_length"]),
            tool_point=tool.vector("point"),
            name=doc.string("name", "3-PRS"),
            noise=read_noise(doc),
            q_limits=read_q_limits(doc, 3),
            tolerance_groups=read_tolerance(doc, PRS3_TOLERANCE_DEFAULTS),
            links_against_rail=assembly == "against_rail",
            source=path,
        )

    def geometry_arrays(self, theta: ArrayLike | None = None) -> dict[str, NDArray]:
        """Actual geometry ``nominal + theta`` as the machine file's arrays (theta of shape (P,))."""
        g = self._geometry(self.check_theta(theta)[None, :])
        return {
            "rail_origin": g.B[0], "rail_direction": g.u[0], "revolute_axis": g.r[0],
            "sphere_center": g.a[0], "link_length": g.l[0], "tool_point": g.t[0],
        }

    def _geometry(self, theta: NDArray) -> _Geometry:
        """Geometry for theta of shape (n, P)."""
        n = theta.shape[0]
        if n > 1 and theta.strides[0] == 0:
            # one geometry for every pose (``_theta_rows`` broadcast it): computed once and broadcast,
            # not once per pose (the tilted directions alone cost more than a Newton step at 10,000 poses)
            one = self._geometry(theta[:1])
            return _Geometry(**{k: np.broadcast_to(v, (n,) + v.shape[1:]) for k, v in vars(one).items()})
        blocks = geometry_blocks(theta)
        if blocks is not None:
            # a sampler's walkers, each repeated over every pose: once per walker (the tilted directions cost
            # as much as a Newton step when computed per row)
            one = self._geometry(theta[blocks[0]])
            return _Geometry(**{k: np.repeat(v, blocks[1], axis=0) for k, v in vars(one).items()})
        th = theta[:, : 3 * _PER_CHAIN].reshape(n, 3, _PER_CHAIN)
        a = self.sphere_center[None] + th[:, :, 0:3]
        B = self.rail_origin[None] + th[:, :, 3:6]
        u = np.empty((n, 3, 3)); du = np.empty((n, 3, 3, 2))
        r = np.empty((n, 3, 3)); dr = np.empty((n, 3, 3, 2))
        for i in range(3):
            u[:, i], du[:, i] = tilted_direction(self.rail_direction[i], self._axes_u[i], th[:, i, 6:8])
            r[:, i], dr[:, i] = tilted_direction(self.revolute_axis[i], self._axes_r[i], th[:, i, 8:10])
        l = self.link_length[None] + th[:, :, 10]
        t = self.tool_point[None] + theta[:, 3 * _PER_CHAIN:]
        return _Geometry(a=a, B=B, u=u, du=du, r=r, dr=dr, l=l, t=t)

    def _theta_rows(self, theta: ArrayLike | None, n: int) -> NDArray:
        theta = self.check_theta(theta, n)
        return np.broadcast_to(theta, (n, self.n_params)) if theta.ndim == 1 else theta

    # ------------------------------------------------------------ kinematics
    def _constraints(self, q: NDArray, g: _Geometry, st: _PlatformState):
        """Residuals F (n, 6) and their derivative F_x (n, 6, 6) w.r.t. (dp, dw)."""
        Ra = np.einsum("nij,nkj->nki", st.R, g.a)  # (n, chain, 3)
        d = st.p[:, None, :] + Ra - g.B - q[:, :, None] * g.u
        n = q.shape[0]
        F = np.empty((n, 6))
        F[:, 0::2] = 0.5 * (np.einsum("nki,nki->nk", d, d) - g.l**2)
        F[:, 1::2] = np.einsum("nki,nki->nk", d, g.r)
        Fx = np.empty((n, 6, 6))
        Fx[:, 0::2, :3] = d
        Fx[:, 0::2, 3:] = np.cross(Ra, d)  # d.(w x Ra) = w.(Ra x d)
        Fx[:, 1::2, :3] = g.r
        Fx[:, 1::2, 3:] = np.cross(Ra, g.r)
        return F, Fx, d, Ra

    def _initial_state(self, q: NDArray, g: _Geometry) -> _PlatformState:
        """A start for Newton on the machine's assembly branch."""
        C = g.B + q[:, :, None] * g.u
        cbar = C.mean(axis=1)
        abar = g.a.mean(axis=1)
        umean = g.u.mean(axis=1)
        umean /= np.linalg.norm(umean, axis=1, keepdims=True)
        # horizontal (normal to the rails) distance between slider and sphere circles
        rel_c = C - cbar[:, None]
        rel_a = g.a - abar[:, None]
        perp = lambda v: v - np.einsum("nki,ni->nk", v, umean)[..., None] * umean[:, None]  # noqa: E731
        rho = np.linalg.norm(perp(rel_c), axis=2).mean(axis=1) - np.linalg.norm(perp(rel_a), axis=2).mean(axis=1)
        h = np.sqrt(np.maximum(g.l.mean(axis=1) ** 2 - rho**2, 1e-6 * g.l.mean(axis=1) ** 2))
        s = -1.0 if self.links_against_rail else 1.0
        # The platform frame need not be aligned with the base frame at home (docs/formats.md section 1 does
        # not ask for it): start from the rotation that lays the sphere-centre pattern onto
        # the slider pattern seen along the rails (Kabsch), so that Newton starts near the
        # machine's own assembly whatever frame the machine file's author chose.
        pa, pc = perp(rel_a), perp(rel_c)
        na, nc = np.linalg.norm(pa, axis=2), np.linalg.norm(pc, axis=2)
        dst = pc * (na.mean(axis=1) / np.maximum(nc.mean(axis=1), 1e-300))[:, None, None]
        R = kabsch(rel_a, dst)
        R = np.where(np.isfinite(R).all(axis=(1, 2))[:, None, None], R, np.eye(3))
        p = cbar - np.einsum("nij,nj->ni", R, abar) + s * h[:, None] * umean
        return _PlatformState(p=p, R=R)

    def _solve(self, q: NDArray, g: _Geometry, st: _PlatformState):
        p, R = st.p.copy(), st.R.copy()
        scale = np.maximum(g.l, 1.0)
        # A pose is finished after one more (quadratically convergent) Newton step taken
        # below the tolerance: that polishes it to round-off, so Jacobians and
        # identification are not limited by the solver's tolerance.
        below = np.zeros(q.shape[0], dtype=bool)
        finished = np.zeros(q.shape[0], dtype=bool)
        for _ in range(_NEWTON_MAXIT):
            F, Fx, d, _ = self._constraints(q, g, _PlatformState(p, R))
            err = np.maximum(np.abs(F[:, 0::2]) / scale, np.abs(F[:, 1::2])).max(axis=1)
            now = err < _NEWTON_TOL
            finished |= now & below
            below = now
            if finished.all():
                # F, Fx, d are those of the final (p, R): no need to evaluate them again
                return _PlatformState(p, R), err < _NEWTON_TOL, Fx, d
            active = ~finished
            try:
                dx = -np.linalg.solve(Fx[active], F[active][..., None])[..., 0]
            except np.linalg.LinAlgError:
                dx = -np.einsum("nij,nj->ni", np.linalg.pinv(Fx[active]), F[active])
            # cap the step: Newton far from the solution may jump branches
            step = np.linalg.norm(dx[:, :3], axis=1) / scale[active].mean(axis=1) + np.linalg.norm(dx[:, 3:], axis=1)
            fac = np.minimum(1.0, 0.2 / np.maximum(step, 1e-300))[:, None]
            dx *= fac
            p[active] += dx[:, :3]
            R[active] = so3_exp(dx[:, 3:]) @ R[active]
        F, Fx, d, _ = self._constraints(q, g, _PlatformState(p, R))
        err = np.maximum(np.abs(F[:, 0::2]) / scale, np.abs(F[:, 1::2])).max(axis=1)
        return _PlatformState(p, R), err < _NEWTON_TOL, Fx, d

    def forward(self, q: ArrayLike, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> ToolPoses:
        """Forward kinematics by batched Newton on the six constraint equations.

        Parameters
        ----------
        q : array_like, shape (n_poses, 3)
            Commanded slider positions, mm.
        theta : array_like, shape (P,) or (n_poses, P), optional
            Geometric errors (actual minus nominal); zeros if omitted.
        guess : ToolPoses, optional
            A nearby solution (its ``state``) to start from; otherwise a start
            on the machine's assembly branch.

        Returns
        -------
        ToolPoses
            With ``success[i]`` False and a message for poses that did not
            converge, are singular, or left the assembly branch.
        """
        q = self.check_q(q)
        n = q.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        warm = guess is not None and isinstance(guess.state, _PlatformState)
        st0 = guess.state if warm else self._initial_state(q, g)
        st, ok, Fx, d = self._solve(q, g, st0)
        msgs = ["" if o else "forward kinematics did not converge (pose unreachable?)" for o in ok]
        cond = _condition_numbers(Fx, _SINGULAR_COND)
        singular = ~np.isfinite(cond) | (cond > _SINGULAR_COND)
        for i in np.flatnonzero(singular & ok):
            msgs[i] = f"singular pose (constraint Jacobian condition number {cond[i]:.2e})"
        along = np.einsum("nki,nki->nk", d, g.u)
        # a warm start (from a measurement or an earlier solution) chooses the branch itself
        wrong = (along > 0).any(axis=1) if self.links_against_rail else (along < 0).any(axis=1)
        wrong &= not warm
        for i in np.flatnonzero(wrong & ok & ~singular):
            msgs[i] = "solution on the other assembly branch"
        success = ok & ~singular & ~wrong
        pos = st.p + np.einsum("nij,nj->ni", st.R, g.t)
        return ToolPoses(position=pos, rotation=st.R, success=success, message=tuple(msgs), state=st)

    def guess_from_measurement(
        self, q: NDArray, position: NDArray, rotation: NDArray | None = None, axis: NDArray | None = None
    ) -> ToolPoses:
        """Platform start ``p = y - R t`` from measured tool points (and orientation if any)."""
        if rotation is not None:
            R = rotation
        else:
            # the nominal machine's start orientation for these q (the platform frame may be
            # turned against the base frame); with a measured axis, the smallest rotation
            # taking its tool axis onto the measured one
            q = self.check_q(q)
            R = self._initial_state(q, self._geometry(np.zeros((q.shape[0], self.n_params)))).R
            if axis is not None:
                ez = R[:, :, 2]
                w = np.cross(ez, axis)
                s = np.linalg.norm(w, axis=1, keepdims=True)
                ang = np.arctan2(s[:, 0], np.einsum("ni,ni->n", ez, axis))
                R = so3_exp(np.where(s > 1e-12, w / np.maximum(s, 1e-300), 0.0) * ang[:, None]) @ R
        n = position.shape[0]
        p = position - np.einsum("nij,j->ni", R, self.tool_point)
        st = _PlatformState(p=p, R=np.array(R, dtype=float))
        return ToolPoses(position=position, rotation=st.R, success=np.ones(n, bool), message=("",) * n, state=st)

    def inverse(self, p: ArrayLike, R: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """Closed-form inverse kinematics from a platform pose.

        Parameters
        ----------
        p : array_like, shape (n_poses, 3)
            Platform origin, base frame, mm.
        R : array_like, shape (n_poses, 3, 3)
            Platform orientation.
        theta : array_like, optional
            Geometric errors.

        Returns
        -------
        ndarray, shape (n_poses, 3)
            Slider positions q (mm) on the machine's assembly branch; NaN where
            the sphere centre is out of reach of the link.  The pose must
            satisfy the revolute constraints (3-PRS poses have 3 DOF).
        """
        p = np.atleast_2d(np.asarray(p, dtype=float))
        R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
        n = p.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        d0 = p[:, None, :] + np.einsum("nij,nkj->nki", R, g.a) - g.B
        du = np.einsum("nki,nki->nk", d0, g.u)
        disc = du**2 - np.einsum("nki,nki->nk", d0, d0) + g.l**2
        s = 1.0 if self.links_against_rail else -1.0
        with np.errstate(invalid="ignore"):
            return du + s * np.sqrt(np.where(disc >= 0, disc, np.nan))

    def tool_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Identification Jacobian of the tool pose by the implicit function theorem.

        ``dx/dtheta = -F_x^{-1} F_theta`` with ``x = (p, w)``; then the tool
        point ``p + R t`` adds ``-[R t]x dw/dtheta`` and ``R`` for the tool
        parameters.  Returns shape (n_poses, 6, P); see
        :meth:`Machine.tool_jacobian`.
        """
        q = self.check_q(q)
        n = q.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        st = poses.state
        if n <= _BLOCK:
            return self._tool_jacobian(q, g, st)
        J = np.empty((n, 6, self.n_params))
        for k in range(0, n, _BLOCK):
            b = slice(k, k + _BLOCK)
            J[b] = self._tool_jacobian(q[b], _Geometry(**{f: v[b] for f, v in vars(g).items()}),
                                       _PlatformState(st.p[b], st.R[b]))
        return J

    def _tool_jacobian(self, q: NDArray, g: _Geometry, st: _PlatformState) -> NDArray:
        """:meth:`tool_jacobian` of one block of poses."""
        # J is dx with its position rows changed in place: the same values as a new array, without paying a
        # (n, 6, P) array's page faults again
        J = self._state_derivative(q, g, st)
        Rt = np.einsum("nij,nj->ni", st.R, g.t)
        J[:, :3] -= skew(Rt) @ J[:, 3:]
        J[:, :3, 3 * _PER_CHAIN :] += st.R
        return J

    def _state_derivative(self, q: NDArray, g: _Geometry, st: _PlatformState) -> NDArray:
        """``d(p, w)/dtheta = -F_x^{-1} F_theta`` of the platform pose, shape (n, 6, P) (the tool point not included)."""
        n = q.shape[0]
        F, Fx, d, Ra = self._constraints(q, g, st)
        P = self.n_params
        Ft = np.zeros((n, 6, P))
        for i in range(3):
            o = _PER_CHAIN * i
            r1, r2 = 2 * i, 2 * i + 1
            Ft[:, r1, o : o + 3] = np.einsum("nj,njk->nk", d[:, i], st.R)
            Ft[:, r2, o : o + 3] = np.einsum("nj,njk->nk", g.r[:, i], st.R)
            Ft[:, r1, o + 3 : o + 6] = -d[:, i]
            Ft[:, r2, o + 3 : o + 6] = -g.r[:, i]
            Ft[:, r1, o + 6 : o + 8] = -q[:, i, None] * np.einsum("nj,njk->nk", d[:, i], g.du[:, i])
            Ft[:, r2, o + 6 : o + 8] = -q[:, i, None] * np.einsum("nj,njk->nk", g.r[:, i], g.du[:, i])
            Ft[:, r2, o + 8 : o + 10] = np.einsum("nj,njk->nk", d[:, i], g.dr[:, i])
            Ft[:, r1, o + 10] = -g.l[:, i]
        dx = np.linalg.solve(Fx, Ft)
        return np.negative(dx, out=dx)  # (n, 6, P): rows dp, dw (negated in place: no second array of that size)

    def tangent_guesses(self, q: ArrayLike, theta: ArrayLike, poses: ToolPoses):
        """Warm starts for the forward kinematics of many geometries near ``theta``, to first order.

        Parameters
        ----------
        q : array_like, shape (n, 3)
            Slider positions, mm.
        theta : array_like, shape (P,)
            The geometry ``poses`` were solved at (a sampler's MAP).
        poses : ToolPoses
            ``forward(q, theta)``.

        Returns
        -------
        callable
            ``thetas (k, P) -> ToolPoses`` of ``k * n`` rows (k stacked blocks
            of n poses, as :meth:`bayescal.measurement.MeasurementModel.predict`
            stacks them): the platform pose ``p + dp`` and ``exp([dw]x) R``
            with ``(dp, dw) = d(p, w)/dtheta (theta_k - theta)`` by the implicit
            function theorem.  That is Newton's first step from ``poses``, done
            once for all geometries: a sampler's solve then starts a step closer
            (3 constraint evaluations instead of 4 on the bundled example).  A
            start only: the solution is Newton's, polished as always.
        """
        q = self.check_q(q)
        theta = self.check_theta(theta)
        n = q.shape[0]
        st = poses.state
        dx = self._state_derivative(q, self._geometry(self._theta_rows(theta, n)), st)

        def guesses(thetas: ArrayLike) -> ToolPoses:
            thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
            k = thetas.shape[0]
            step = np.einsum("nip,kp->kni", dx, thetas - theta).reshape(k * n, 6)
            R = so3_exp(step[:, 3:]) @ np.tile(st.R, (k, 1, 1))
            p = np.tile(st.p, (k, 1)) + step[:, :3]
            tool = p + np.einsum("nij,nj->ni", R, np.repeat(self.tool_point + thetas[:, 3 * _PER_CHAIN :], n, axis=0))
            return ToolPoses(position=tool, rotation=R, success=np.ones(k * n, dtype=bool), message=("",) * (k * n),
                             state=_PlatformState(p=p, R=R))

        return guesses

    def actuator_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Tool-pose derivative with respect to the slider positions, analytic.

        Implicit function theorem on ``F(x, q) = 0``: ``dx/dq = -F_x^{-1} F_q``
        with ``dF1_i/dq_i = -d_i . u_i`` and ``dF2_i/dq_i = -r_i . u_i``
        (``d_i = A_i - C_i``); the tool point adds ``-[R t]x dw/dq``.
        Returns shape (n_poses, 6, 3); see :meth:`Machine.actuator_jacobian`.
        """
        q = self.check_q(q)
        n = q.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        st = poses.state
        _, Fx, d, _ = self._constraints(q, g, st)
        Fq = np.zeros((n, 6, 3))
        for i in range(3):
            Fq[:, 2 * i, i] = -np.einsum("nj,nj->n", d[:, i], g.u[:, i])
            Fq[:, 2 * i + 1, i] = -np.einsum("nj,nj->n", g.r[:, i], g.u[:, i])
        dx = -np.linalg.solve(Fx, Fq)
        Rt = np.einsum("nij,nj->ni", st.R, g.t)
        J = np.empty((n, 6, 3))
        J[:, :3] = dx[:, :3] - skew(Rt) @ dx[:, 3:]
        J[:, 3:] = dx[:, 3:]
        return J

    # ------------------------------------------------------------------ output
    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """Machine file of the geometry ``nominal + theta``, same kind and keys."""
        g = self.geometry_arrays(theta)
        f = format_toml_value
        out = ['kind = "3-PRS"', f"name = {f(self.name)}"]
        if not self.links_against_rail:
            out.append('assembly = "along_rail"')
        out.append("")
        for i in range(3):
            out += [
                "[[chain]]",
                f"rail_origin = {f(g['rail_origin'][i])}",
                f"rail_direction = {f(g['rail_direction'][i])}",
                f"revolute_axis = {f(g['revolute_axis'][i])}",
                f"link_length = {f(g['link_length'][i])}",
                f"sphere_center = {f(g['sphere_center'][i])}",
                "",
            ]
        out += ["[tool]", f"point = {f(g['tool_point'])}", ""]
        return "\n".join(out) + common_toml(self, self.tolerance_groups)
