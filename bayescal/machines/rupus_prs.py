"""The RU-PUS-PRS 2-DOF parallel mechanism (the solar tracker of the LS/RE/TSVD seed).

Topology (seed, section "Construction of the 2-DOF parallel manipulator"):
a base, a moving platform and three chains.

* chain 1, P-U-S: actuated slider ``C_1 = B_1 + q_1 u_1`` on a rail, a
  universal joint at ``C_1``, a link of length ``l_1`` to the sphere centre
  ``A_1`` on the platform;
* chain 2, P-R-S: actuated slider ``C_2 = B_2 + q_2 u_2``, a revolute joint
  at ``C_2`` with axis ``r_2``, a link of length ``l_2`` to ``A_2``;
* chain 3, R-U: a revolute joint at the base point ``O`` with axis ``w``, a
  link of length ``r`` to the centre ``N`` of a universal joint on the
  platform.  The U joint's first axis ``k_1`` is carried by the link, its
  second axis ``k_2`` by the platform.

Modelling decisions (docs/rupus_prs.md explains them):

* The U joint at ``C_1`` and the S joint at ``A_1`` leave the link ``C_1A_1``
  only its length as a constraint on the platform: the U joint's axes fix
  the link's spin about its own axis and nothing else.  Chain 1 therefore
  has no axis keys; their errors could not change any measurement.
* Chain 3: with the R joint at ``beta`` (rad) the link points along
  ``Rot(w, beta) lhat`` and carries the U axis ``Rot(w, beta) k_1``, where
  ``lhat`` (``link_direction``) and ``k_1`` (``universal_axis_link``) are
  given at ``beta = 0``.  In the nominal solar tracker the link stands on the
  R axis (``lhat = w``): R and U together act like a spherical joint at a
  fixed ``N`` and the R joint only frees the over-constraint of the PRS
  chain; an eccentric link (``lhat`` tilted from ``w``) moves ``N`` on a
  small circle.

Unknowns per pose: the platform orientation ``R`` (3, as a small rotation
``dw`` in Newton) and the R-joint angle ``beta`` (1).  The platform origin
follows: ``p = N(beta) - R n`` with ``N(beta) = O + r Rot(w, beta) lhat``
and ``n`` the U centre in the platform frame.  A platform point ``x`` is at
``X = N(beta) + R (x - n)``.  Four equations:

    F0 = (|A_1 - C_1|^2 - l_1^2) / 2 = 0        chain 1, link length
    F1 = (|A_2 - C_2|^2 - l_2^2) / 2 = 0        chain 2, link length
    F2 = (A_2 - C_2) . r_2 = 0                   chain 2, link normal to r_2
    F3 = (Rot(w, beta) k_1) . (R k_2) = 0        chain 3, U joint (cross axes perpendicular)

Counting: 6 platform coordinates + beta = 7 unknowns; chain 3 fixes the
platform point ``n`` at ``N(beta)`` (3 equations, eliminated above) and
``F0..F3`` are the other 4.  With ``q`` free, ``F0`` and ``F1`` drop out and
two degrees of freedom (both rotations about ``N``) remain: a 2-DOF machine
with two actuators.

Error parameters, 38: chain 1 (9): ``sphere_center.{x,y,z}``,
``rail_origin.{x,y,z}``, ``rail_direction.tilt_{a,b}``, ``link_length``;
chain 2 (11): those plus ``revolute_axis.tilt_{a,b}``; chain 3 (15):
``base_point.{x,y,z}``, ``base_axis.tilt_{a,b}``, ``link_direction.tilt_{a,b}``,
``link_length``, ``universal_axis_link.tilt_{a,b}``,
``universal_axis_platform.tilt_{a,b}`` (about platform axes),
``universal_center.{x,y,z}`` (platform frame); ``tool.point.{x,y,z}``.
Directions tilt by :func:`bayescal.geometry.tilted_direction`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..geometry import rotation_from_tilt_torsion, skew, so3_exp, tilt_axes, tilt_torsion_angles, tilted_direction
from ..io.machine_file import TomlTable, format_toml_value
from ..params import ParamLayout, ParamSpec
from .base import Machine, MeasurementNoise, ToolPoses
from .common import common_toml, read_noise, read_q_limits, read_tolerance
from .tolerance import tolerance_vector
from .construct import circle_intersections, kabsch, rotate_vectors, trilaterate

__all__ = ["RupusPrs", "RUPUS_TOLERANCE_DEFAULTS", "rotate_about"]

#: Documented one-sigma defaults of the ``[tolerance]`` table (mm or rad).
RUPUS_TOLERANCE_DEFAULTS: dict[str, float] = {
    "sphere_center": 0.05,
    "rail_origin": 0.05,
    "rail_direction": 2.0e-4,
    "revolute_axis": 2.0e-4,
    "link_length": 0.05,
    "base_point": 0.05,
    "base_axis": 2.0e-4,
    "link_direction": 2.0e-4,
    "universal_axis": 2.0e-4,
    "universal_center": 0.05,
    "tool_point": 0.05,
}

_XYZ = "xyz"
_N1, _N2, _N3 = 9, 11, 15  # parameters of chains 1, 2, 3
_O2, _O3, _OT = _N1, _N1 + _N2, _N1 + _N2 + _N3  # offsets of chain 2, chain 3, tool
_NEWTON_TOL = 1e-9  # mm (lengths) / dimensionless; residual at which a pose counts as solved, then polished
_NEWTON_MAXIT = 60
_CHAIN_KEYS = (
    ("rail_origin", "rail_direction", "link_length", "sphere_center"),
    ("rail_origin", "rail_direction", "revolute_axis", "link_length", "sphere_center"),
    ("base_point", "base_axis", "link_direction", "link_length", "universal_axis_link",
     "universal_axis_platform", "universal_center"),
)
_JOINTS = ("PUS", "PRS", "RU")


def rotate_about(w: NDArray, beta: NDArray, v: NDArray) -> NDArray:
    """``Rot(w, beta) v`` by Rodrigues' formula, batched over the leading axis.

    Parameters
    ----------
    w : ndarray, shape (n, 3)
        Unit axes.
    beta : ndarray, shape (n,)
        Angles, rad.
    v : ndarray, shape (n, 3)
        Vectors to rotate.
    """
    c, s = np.cos(beta)[:, None], np.sin(beta)[:, None]
    wv = np.einsum("ni,ni->n", w, v)[:, None]
    return v * c + np.cross(w, v) * s + w * wv * (1.0 - c)


def _d_rotate_d_axis(w: NDArray, beta: NDArray, v: NDArray) -> NDArray:
    """Derivative of ``Rot(w, beta) v`` with respect to ``w`` (held unnormalised), shape (n, 3, 3)."""
    c, s = np.cos(beta)[:, None, None], np.sin(beta)[:, None, None]
    wv = np.einsum("ni,ni->n", w, v)[:, None, None]
    return -skew(v) * s + (1.0 - c) * (wv * np.eye(3) + w[:, :, None] * v[:, None, :])


@dataclass(frozen=True)
class _Geometry:
    """Geometry arrays broadcast over poses (leading axis n)."""

    a: NDArray  # (n, 2, 3) sphere centres of chains 1, 2, platform frame
    B: NDArray  # (n, 2, 3) rail origins
    u: NDArray  # (n, 2, 3) rail directions
    du: NDArray  # (n, 2, 3, 2)
    r2: NDArray  # (n, 3) revolute axis of chain 2
    dr2: NDArray  # (n, 3, 2)
    l: NDArray  # (n, 2) link lengths of chains 1, 2
    O: NDArray  # (n, 3) base point of chain 3
    w: NDArray  # (n, 3) R-joint axis
    dw: NDArray  # (n, 3, 2)
    lhat: NDArray  # (n, 3) link direction at beta = 0
    dlhat: NDArray  # (n, 3, 2)
    rlen: NDArray  # (n,) link length O-N
    k1: NDArray  # (n, 3) U axis on the link at beta = 0, base frame
    dk1: NDArray  # (n, 3, 2)
    k2: NDArray  # (n, 3) U axis on the platform, platform frame
    dk2: NDArray  # (n, 3, 2)
    n: NDArray  # (n, 3) U centre, platform frame
    t: NDArray  # (n, 3) tool point, platform frame


@dataclass(frozen=True)
class _RupusState:
    p: NDArray  # (n, 3) platform origin, base frame, mm
    R: NDArray  # (n, 3, 3) platform orientation
    beta: NDArray  # (n,) R-joint angle at O, rad


@dataclass(frozen=True)
class _Kin:
    """Quantities at a state that the constraints and the Jacobian share."""

    N: NDArray  # (n, 3) U centre, base frame
    dN: NDArray  # (n, 3) dN/dbeta
    m: NDArray  # (n, 2, 3) R (a_i - n)
    d: NDArray  # (n, 2, 3) A_i - C_i
    k1b: NDArray  # (n, 3) Rot(w, beta) k_1
    v: NDArray  # (n, 3) R k_2


@dataclass(frozen=True, eq=False)
class RupusPrs(Machine):
    """An RU-PUS-PRS machine: nominal geometry, parameter layout, kinematics.

    Parameters
    ----------
    rail_origin, rail_direction : ndarray, shape (2, 3)
        Chains 1 and 2 (rows), base frame; mm and unit vectors.
    revolute_axis : ndarray, shape (3,)
        Chain 2's revolute axis, base frame, unit.
    link_length : ndarray, shape (2,)
        Chains 1 and 2, mm.
    sphere_center : ndarray, shape (2, 3)
        Chains 1 and 2, platform frame, mm.
    base_point, base_axis : ndarray, shape (3,)
        Chain 3's R joint: centre ``O`` (mm) and axis ``w`` (unit), base frame.
    link_direction : ndarray, shape (3,)
        Unit direction of the link ``O -> N`` at R-joint angle 0, base frame.
    center_link_length : float
        ``r = |ON|``, mm.
    universal_axis_link : ndarray, shape (3,)
        U-joint axis carried by the link, at R-joint angle 0, base frame.
    universal_axis_platform : ndarray, shape (3,)
        U-joint axis carried by the platform, platform frame.
    universal_center : ndarray, shape (3,)
        ``N`` in the platform frame, mm.
    tool_point : ndarray, shape (3,)
        mm, platform frame.
    name, noise, q_limits, tolerance_groups, source
        As for every machine.
    links_along_rail : bool
        Assembly mode of chains 1 and 2: True when the links point from the
        sliders along the rail direction (sliders below the platform), the
        solar-tracker layout.  Machine-file key
        ``assembly = "along_rail" | "against_rail"``.
    """

    kind = "RU-PUS-PRS"

    rail_origin: NDArray
    rail_direction: NDArray
    revolute_axis: NDArray
    link_length: NDArray
    sphere_center: NDArray
    base_point: NDArray
    base_axis: NDArray
    link_direction: NDArray
    center_link_length: float
    universal_axis_link: NDArray
    universal_axis_platform: NDArray
    universal_center: NDArray
    tool_point: NDArray
    name: str = "RU-PUS-PRS"
    noise: MeasurementNoise = field(default_factory=MeasurementNoise)
    q_limits: NDArray | None = None
    tolerance_groups: dict = field(default_factory=lambda: dict(RUPUS_TOLERANCE_DEFAULTS))
    links_along_rail: bool = True
    source: str = "<memory>"

    def __post_init__(self) -> None:
        ax = {
            "u1": tilt_axes(self.rail_direction[0]), "u2": tilt_axes(self.rail_direction[1]),
            "r2": tilt_axes(self.revolute_axis), "w": tilt_axes(self.base_axis),
            "lhat": tilt_axes(self.link_direction), "k1": tilt_axes(self.universal_axis_link),
            "k2": tilt_axes(self.universal_axis_platform),
        }
        object.__setattr__(self, "_axes", ax)

        def tilts(prefix, key, group):
            return [ParamSpec(f"{prefix}.tilt_{_XYZ[k]}", "rad", group) for k in ax[key]]

        def xyz(prefix, group):
            return [ParamSpec(f"{prefix}.{x}", "mm", group) for x in _XYZ]

        specs = []
        for i in (1, 2):
            c = f"chain{i}"
            specs += xyz(f"{c}.sphere_center", "sphere_center") + xyz(f"{c}.rail_origin", "rail_origin")
            specs += tilts(f"{c}.rail_direction", f"u{i}", "rail_direction")
            if i == 2:
                specs += tilts(f"{c}.revolute_axis", "r2", "revolute_axis")
            specs += [ParamSpec(f"{c}.link_length", "mm", "link_length")]
        c = "chain3"
        specs += xyz(f"{c}.base_point", "base_point") + tilts(f"{c}.base_axis", "w", "base_axis")
        specs += tilts(f"{c}.link_direction", "lhat", "link_direction")
        specs += [ParamSpec(f"{c}.link_length", "mm", "link_length")]
        specs += tilts(f"{c}.universal_axis_link", "k1", "universal_axis")
        specs += tilts(f"{c}.universal_axis_platform", "k2", "universal_axis")
        specs += xyz(f"{c}.universal_center", "universal_center")
        specs += [ParamSpec(f"tool.point.{x}", "mm", "tool_point") for x in _XYZ]
        object.__setattr__(self, "layout", ParamLayout(tuple(specs)))
        object.__setattr__(self, "tolerance", tolerance_vector(specs, self.tolerance_groups))

    # ----------------------------------------------------------------- set-up
    @property
    def n_actuators(self) -> int:
        return 2

    @classmethod
    def from_toml(cls, doc: TomlTable, path: str) -> "RupusPrs":
        doc.reject_unknown({"kind", "name", "chain", "tool", "measurement", "workspace", "tolerance", "assembly"})
        chains = doc.array_of_tables("chain", 3)
        for ch, keys, joints in zip(chains, _CHAIN_KEYS, _JOINTS):
            ch.reject_unknown(set(keys) | {"joints"})
            if ch.has("joints") and ch.string("joints") != joints:
                raise ch.error("joints", f"expected {joints!r} (chains in the order P-U-S, P-R-S, R-U), got {ch.string('joints')!r}")
        c1, c2, c3 = chains
        w = c3.vector("base_axis", unit=True)
        k1 = c3.vector("universal_axis_link", unit=True)
        if abs(float(k1 @ w)) > 0.99:
            raise c3.error("universal_axis_link", "expected a direction not parallel to base_axis (the R joint would not turn the U joint)")
        tool = doc.table("tool")
        tool.reject_unknown({"point"})
        assembly = doc.string("assembly", "along_rail")
        if assembly not in ("along_rail", "against_rail"):
            raise doc.error("assembly", f"expected \"along_rail\" or \"against_rail\", got {assembly!r}")
        return cls(
            rail_origin=np.array([c1.vector("rail_origin"), c2.vector("rail_origin")]),
            rail_direction=np.array([c1.vector("rail_direction", unit=True), c2.vector("rail_direction", unit=True)]),
            revolute_axis=c2.vector("revolute_axis", unit=True),
            link_length=np.array([c1.number("link_length", positive=True), c2.number("link_length", positive=True)]),
            sphere_center=np.array([c1.vector("sphere_center"), c2.vector("sphere_center")]),
            base_point=c3.vector("base_point"),
            base_axis=w,
            link_direction=c3.vector("link_direction", unit=True),
            center_link_length=c3.number("link_length", positive=True),
            universal_axis_link=k1,
            universal_axis_platform=c3.vector("universal_axis_platform", unit=True),
            universal_center=c3.vector("universal_center"),
            tool_point=tool.vector("point"),
            name=doc.string("name", "RU-PUS-PRS"),
            noise=read_noise(doc),
            q_limits=read_q_limits(doc, 2),
            tolerance_groups=read_tolerance(doc, RUPUS_TOLERANCE_DEFAULTS),
            links_along_rail=assembly == "along_rail",
            source=path,
        )

    def _theta_rows(self, theta: ArrayLike | None, n: int) -> NDArray:
        theta = self.check_theta(theta, n)
        return np.broadcast_to(theta, (n, self.n_params)) if theta.ndim == 1 else theta

    def _geometry(self, theta: NDArray) -> _Geometry:
        """Geometry for theta of shape (n, P)."""
        ax = self._axes
        th1, th2, th3 = theta[:, :_O2], theta[:, _O2:_O3], theta[:, _O3:_OT]
        a = np.stack([self.sphere_center[0] + th1[:, 0:3], self.sphere_center[1] + th2[:, 0:3]], axis=1)
        B = np.stack([self.rail_origin[0] + th1[:, 3:6], self.rail_origin[1] + th2[:, 3:6]], axis=1)
        u1, du1 = tilted_direction(self.rail_direction[0], ax["u1"], th1[:, 6:8])
        u2, du2 = tilted_direction(self.rail_direction[1], ax["u2"], th2[:, 6:8])
        r2, dr2 = tilted_direction(self.revolute_axis, ax["r2"], th2[:, 8:10])
        l = np.stack([self.link_length[0] + th1[:, 8], self.link_length[1] + th2[:, 10]], axis=1)
        w, dw = tilted_direction(self.base_axis, ax["w"], th3[:, 3:5])
        lhat, dlhat = tilted_direction(self.link_direction, ax["lhat"], th3[:, 5:7])
        k1, dk1 = tilted_direction(self.universal_axis_link, ax["k1"], th3[:, 8:10])
        k2, dk2 = tilted_direction(self.universal_axis_platform, ax["k2"], th3[:, 10:12])
        return _Geometry(
            a=a, B=B, u=np.stack([u1, u2], 1), du=np.stack([du1, du2], 1), r2=r2, dr2=dr2, l=l,
            O=self.base_point + th3[:, 0:3], w=w, dw=dw, lhat=lhat, dlhat=dlhat,
            rlen=self.center_link_length + th3[:, 7], k1=k1, dk1=dk1, k2=k2, dk2=dk2,
            n=self.universal_center + th3[:, 12:15], t=self.tool_point + theta[:, _OT:],
        )

    def geometry_arrays(self, theta: ArrayLike | None = None) -> dict[str, NDArray]:
        """Actual geometry ``nominal + theta`` (theta of shape (P,)) under the constructor's names."""
        g = self._geometry(self.check_theta(theta)[None, :])
        return {
            "rail_origin": g.B[0], "rail_direction": g.u[0], "revolute_axis": g.r2[0], "link_length": g.l[0],
            "sphere_center": g.a[0], "base_point": g.O[0], "base_axis": g.w[0], "link_direction": g.lhat[0],
            "center_link_length": float(g.rlen[0]), "universal_axis_link": g.k1[0],
            "universal_axis_platform": g.k2[0], "universal_center": g.n[0], "tool_point": g.t[0],
        }

    # ------------------------------------------------------------ kinematics
    def _kin(self, q: NDArray, g: _Geometry, R: NDArray, beta: NDArray) -> _Kin:
        ell = rotate_about(g.w, beta, g.lhat)
        N = g.O + g.rlen[:, None] * ell
        dN = np.cross(g.w, N - g.O)
        m = np.einsum("nij,nkj->nki", R, g.a - g.n[:, None, :])
        d = N[:, None, :] + m - g.B - q[:, :, None] * g.u
        k1b = rotate_about(g.w, beta, g.k1)
        v = np.einsum("nij,nj->ni", R, g.k2)
        return _Kin(N=N, dN=dN, m=m, d=d, k1b=k1b, v=v)

    def _constraints(self, q: NDArray, g: _Geometry, R: NDArray, beta: NDArray):
        """Residuals F (n, 4), derivative F_x (n, 4, 4) w.r.t. (dw, dbeta), and the shared quantities."""
        k = self._kin(q, g, R, beta)
        n = q.shape[0]
        F = np.empty((n, 4))
        F[:, :2] = 0.5 * (np.einsum("nki,nki->nk", k.d, k.d) - g.l**2)
        F[:, 2] = np.einsum("ni,ni->n", k.d[:, 1], g.r2)
        F[:, 3] = np.einsum("ni,ni->n", k.k1b, k.v)
        Fx = np.empty((n, 4, 4))
        # a platform point moves by dw x m + dN dbeta; d.(dw x m) = dw.(m x d)
        Fx[:, :2, :3] = np.cross(k.m, k.d)
        Fx[:, :2, 3] = np.einsum("nki,ni->nk", k.d, k.dN)
        Fx[:, 2, :3] = np.cross(k.m[:, 1], g.r2)
        Fx[:, 2, 3] = np.einsum("ni,ni->n", g.r2, k.dN)
        Fx[:, 3, :3] = np.cross(k.v, k.k1b)  # k1b.(dw x v) = dw.(v x k1b)
        Fx[:, 3, 3] = np.einsum("ni,ni->n", np.cross(g.w, k.k1b), k.v)
        return F, Fx, k

    def _beta_for(self, g: _Geometry, R: NDArray, beta_ref: NDArray | None = None) -> NDArray:
        """R-joint angle solving the U constraint for a given orientation (root nearest ``beta_ref``).

        ``Rot(w, beta) k_1 . v = A cos(beta) + B sin(beta) + C`` with ``v = R k_2``.
        """
        v = np.einsum("nij,nj->ni", R, g.k2)
        wk = np.einsum("ni,ni->n", g.w, g.k1)
        wv = np.einsum("ni,ni->n", g.w, v)
        A = np.einsum("ni,ni->n", g.k1, v) - wk * wv
        Bc = np.einsum("ni,ni->n", np.cross(g.w, g.k1), v)
        C = wk * wv
        rho = np.hypot(A, Bc)
        phase = np.arctan2(Bc, A)
        # A cos b + B sin b = rho cos(b - phase) = -C
        delta = np.arccos(np.clip(-C / np.maximum(rho, 1e-300), -1.0, 1.0))
        ref = np.zeros(R.shape[0]) if beta_ref is None else beta_ref
        cands = np.stack([phase + delta, phase - delta], axis=1)
        cands = ref[:, None] + (cands - ref[:, None] + np.pi) % (2 * np.pi) - np.pi
        pick = np.argmin(np.abs(cands - ref[:, None]), axis=1)
        return cands[np.arange(R.shape[0]), pick]

    def _initial_state(self, q: NDArray, g: _Geometry) -> tuple[NDArray, NDArray]:
        """A start on the machine's branch, built geometrically.

        With ``N`` at its ``beta = 0`` place: ``A_2`` on the circle of chain 2's
        plane at ``l_2`` from the slider and at ``|a_2 - n|`` from ``N``; then
        ``A_1`` by trilateration from ``N``, ``A_2`` and ``C_1``; the
        orientation by Kabsch's fit.  Exact for an eccentric-free chain 3.
        """
        nq = q.shape[0]
        s = 1.0 if self.links_along_rail else -1.0
        N = g.O + g.rlen[:, None] * g.lhat
        C = g.B + q[:, :, None] * g.u
        rho = np.linalg.norm(g.a - g.n[:, None, :], axis=2)  # (n, 2)
        # --- A2: circle-circle intersection in chain 2's plane
        C2, r2 = C[:, 1], g.r2
        h = np.einsum("ni,ni->n", N - C2, r2)
        Np = N - h[:, None] * r2
        rad = np.sqrt(np.maximum(rho[:, 1] ** 2 - h**2, 0.0))
        A2 = circle_intersections(C2, g.l[:, 1], Np, rad, r2)  # (n, 2, 3)
        along = np.einsum("nci,ni->nc", A2 - C2[:, None], g.u[:, 1])
        A2 = A2[np.arange(nq), np.argmax(s * along, axis=1)]
        # --- A1: three spheres about N, A2 and C1
        c12 = np.linalg.norm(g.a[:, 0] - g.a[:, 1], axis=1)
        A1c = trilaterate(N, rho[:, 0], A2, c12, C[:, 0], g.l[:, 0])  # (n, 2, 3)
        # --- orientation of each candidate; keep the one nearest the home orientation
        src = np.stack([g.n, g.a[:, 0], g.a[:, 1]], axis=1)
        best_R = np.broadcast_to(np.eye(3), (nq, 3, 3)).copy()
        best_tr = np.full(nq, -np.inf)
        for c in range(2):
            dst = np.stack([N, A1c[:, c], A2], axis=1)
            Rc = kabsch(src, dst)
            tr = np.trace(Rc, axis1=1, axis2=2)
            better = np.isfinite(tr) & (tr > best_tr)
            best_R[better], best_tr[better] = Rc[better], tr[better]
        beta = self._beta_for(g, best_R)
        return best_R, beta

    def _solve(self, q: NDArray, g: _Geometry, R: NDArray, beta: NDArray):
        R, beta = R.copy(), beta.copy()
        scale = np.maximum(g.l, 1.0)
        below = np.zeros(q.shape[0], dtype=bool)
        finished = np.zeros(q.shape[0], dtype=bool)

        def error(F):
            lengths = np.maximum(np.abs(F[:, :2]) / scale, np.abs(F[:, 2:3]) / scale[:, 1:2]).max(axis=1)
            return np.maximum(lengths, np.abs(F[:, 3]))

        for _ in range(_NEWTON_MAXIT):
            F, Fx, _ = self._constraints(q, g, R, beta)
            now = error(F) < _NEWTON_TOL
            # one more (quadratically convergent) step below the tolerance polishes to round-off
            finished |= now & below
            below = now
            if finished.all():
                break
            act = ~finished
            try:
                dx = -np.linalg.solve(Fx[act], F[act][..., None])[..., 0]
            except np.linalg.LinAlgError:
                dx = -np.einsum("nij,nj->ni", np.linalg.pinv(Fx[act]), F[act])
            # cap the step: Newton far from the solution may jump branches
            step = np.linalg.norm(dx, axis=1)
            dx *= np.minimum(1.0, 0.2 / np.maximum(step, 1e-300))[:, None]
            R[act] = so3_exp(dx[:, :3]) @ R[act]
            beta[act] += dx[:, 3]
        F, Fx, k = self._constraints(q, g, R, beta)
        return R, beta, error(F) < _NEWTON_TOL, Fx, k

    def forward(self, q: ArrayLike, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> ToolPoses:
        """Forward kinematics by batched Newton on the four constraint equations.

        Parameters
        ----------
        q : array_like, shape (n_poses, 2)
            Commanded slider positions, mm.
        theta : array_like, shape (P,) or (n_poses, P), optional
            Geometric errors (actual minus nominal); zeros if omitted.
        guess : ToolPoses, optional
            A nearby solution (its ``state``) to start from; otherwise a
            geometric start on the machine's assembly branch.

        Returns
        -------
        ToolPoses
            ``state`` holds the platform origin ``p``, orientation ``R`` and the
            R-joint angle ``beta`` (rad).  ``success[i]`` is False, with a
            message, where Newton did not converge, the pose is singular or it
            left the assembly branch.
        """
        q = self.check_q(q)
        n = q.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        warm = guess is not None and isinstance(guess.state, _RupusState)
        if warm:
            R0, b0 = guess.state.R, guess.state.beta
        else:
            with np.errstate(invalid="ignore", divide="ignore"):
                R0, b0 = self._initial_state(q, g)
        R, beta, ok, Fx, k = self._solve(q, g, R0, b0)
        msgs = ["" if o else "forward kinematics did not converge (pose unreachable?)" for o in ok]
        with np.errstate(invalid="ignore", over="ignore"):
            cond = np.linalg.cond(Fx)
        singular = ~np.isfinite(cond) | (cond > 1e10)
        for i in np.flatnonzero(singular & ok):
            msgs[i] = f"singular pose (constraint Jacobian condition number {cond[i]:.2e})"
        along = np.einsum("nki,nki->nk", k.d, g.u)
        wrong = (along < 0).any(axis=1) if self.links_along_rail else (along > 0).any(axis=1)
        wrong &= not warm  # a warm start (measurement or earlier solution) chooses the branch itself
        for i in np.flatnonzero(wrong & ok & ~singular):
            msgs[i] = "solution on the other assembly branch"
        success = ok & ~singular & ~wrong
        p = k.N - np.einsum("nij,nj->ni", R, g.n)
        pos = p + np.einsum("nij,nj->ni", R, g.t)
        return ToolPoses(position=pos, rotation=R, success=success, message=tuple(msgs),
                         state=_RupusState(p=p, R=R, beta=beta))

    def tilt_torsion(self, q: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """Platform orientation as tilt-and-torsion angles, the seed's output convention.

        Returns
        -------
        ndarray, shape (n_poses, 3)
            ``(phi, theta, psi)`` in rad with ``R = Rz(phi) Ry(theta) Rz(psi - phi)``
            (:func:`bayescal.geometry.tilt_torsion_angles`): the platform
            normal is tilted by ``theta`` towards azimuth ``phi``; ``psi`` is the
            torsion about the normal, which the tracker does not need and a
            5-DOF measurement does not see.  NaN rows where the pose failed.
        """
        poses = self.forward(q, theta)
        out = tilt_torsion_angles(poses.rotation)
        out[~poses.success] = np.nan
        return out

    def inverse_tilt(
        self, phi: ArrayLike, tilt: ArrayLike, theta: ArrayLike | None = None
    ) -> tuple[NDArray, NDArray, NDArray]:
        """Slider positions that point the platform normal along T&T angles ``(phi, tilt)``.

        The tracker's output is the normal direction; the torsion ``psi`` and
        the R-joint angle follow from the mechanism.  Newton on
        ``(psi, beta, q1, q2)`` solves the four constraint equations with
        ``R = Rz(phi) Ry(tilt) Rz(psi - phi)``; a change of ``psi`` turns the
        platform about its normal ``R e_z``.

        Parameters
        ----------
        phi, tilt : array_like, shape (n_poses,)
            Azimuth and tilt of the platform normal, rad.
        theta : array_like, optional
            Geometric errors.

        Returns
        -------
        q : ndarray, shape (n_poses, 2)
            mm, on the machine's assembly branch (NaN where not solved).
        psi : ndarray, shape (n_poses,)
            The torsion that goes with it, rad.
        success : ndarray of bool, shape (n_poses,)
        """
        phi, tilt = np.atleast_1d(np.asarray(phi, dtype=float)), np.atleast_1d(np.asarray(tilt, dtype=float))
        n = phi.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        psi, beta = np.zeros(n), np.zeros(n)
        q = self.inverse(rotation_from_tilt_torsion(phi, tilt, psi), theta)
        q = np.where(np.isfinite(q), q, self.home_q() if self.q_limits is not None else 0.0)
        for _ in range(_NEWTON_MAXIT):
            R = rotation_from_tilt_torsion(phi, tilt, psi)
            F, Fx, k = self._constraints(q, g, R, beta)
            A = np.zeros((n, 4, 4))
            A[:, :, 0] = np.einsum("nij,nj->ni", Fx[:, :, :3], R[:, :, 2])
            A[:, :, 1] = Fx[:, :, 3]
            A[:, 0, 2] = -np.einsum("ni,ni->n", k.d[:, 0], g.u[:, 0])
            A[:, 1, 3] = -np.einsum("ni,ni->n", k.d[:, 1], g.u[:, 1])
            A[:, 2, 3] = -np.einsum("ni,ni->n", g.r2, g.u[:, 1])
            try:
                dx = -np.linalg.solve(A, F[..., None])[..., 0]
            except np.linalg.LinAlgError:
                dx = -np.einsum("nij,nj->ni", np.linalg.pinv(A), F)
            # cap angle steps at 0.2 rad and slider steps at 50 mm
            fac = np.minimum(1.0, np.minimum(0.2 / np.maximum(np.abs(dx[:, :2]).max(1), 1e-300),
                                             50.0 / np.maximum(np.abs(dx[:, 2:]).max(1), 1e-300)))
            dx *= fac[:, None]
            psi, beta, q = psi + dx[:, 0], beta + dx[:, 1], q + dx[:, 2:]
            if np.abs(dx).max() < 1e-13 * max(1.0, np.abs(q).max()):
                break
        R = rotation_from_tilt_torsion(phi, tilt, psi)
        F, _, k = self._constraints(q, g, R, beta)
        scale = np.maximum(g.l, 1.0)
        ok = (np.abs(F[:, :3]) / scale[:, [0, 1, 1]]).max(axis=1) < _NEWTON_TOL
        ok &= np.abs(F[:, 3]) < _NEWTON_TOL
        along = np.einsum("nki,nki->nk", k.d, g.u)
        ok &= (along > 0).all(axis=1) if self.links_along_rail else (along < 0).all(axis=1)
        q[~ok] = np.nan
        return q, (psi + np.pi) % (2 * np.pi) - np.pi, ok

    def guess_from_measurement(
        self, q: NDArray, position: NDArray, rotation: NDArray | None = None, axis: NDArray | None = None
    ) -> ToolPoses | None:
        """A Newton start from measured tool poses.

        The orientation is the measured one (6-DOF), else the smallest
        rotation taking ``e_z`` to the measured axis (5-DOF; the torsion the
        PRS chain allows is small), else, for a position-only measurement, the
        axis through the U centre and the tool point when the tool point lies
        off the U centre (the platform turns about ``N``).  None when nothing
        better than the geometric start is available.
        """
        n = position.shape[0]
        g = self._geometry(np.zeros((1, self.n_params)))
        if rotation is None and axis is None:
            arm = self.tool_point - self.universal_center
            L = float(np.linalg.norm(arm))
            if L < 1.0:
                return None
            arm_dir = np.asarray(position, dtype=float) - g.O - g.rlen[:, None] * g.lhat
            arm_dir /= np.maximum(np.linalg.norm(arm_dir, axis=1, keepdims=True), 1e-300)
            axis = rotate_vectors(arm / L, arm_dir)  # where e_z goes if the arm turned minimally
        if rotation is not None:
            R = np.array(rotation, dtype=float)
        else:
            R = rotate_vectors(np.array([0.0, 0.0, 1.0]), np.asarray(axis, dtype=float), matrix=True)
        gg = self._geometry(np.zeros((n, self.n_params)))
        beta = self._beta_for(gg, R)
        N = gg.O + gg.rlen[:, None] * rotate_about(gg.w, beta, gg.lhat)
        p = N - np.einsum("nij,nj->ni", R, gg.n)
        st = _RupusState(p=p, R=R, beta=beta)
        return ToolPoses(position=np.asarray(position, float), rotation=R, success=np.ones(n, bool),
                         message=("",) * n, state=st)

    def inverse(self, R: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """Slider positions for a platform orientation (closed form).

        Parameters
        ----------
        R : array_like, shape (n_poses, 3, 3)
            Platform orientation; it must satisfy chain 2's plane constraint
            (the machine has 2 DOF), which is not checked here.
        theta : array_like, optional
            Geometric errors.

        Returns
        -------
        ndarray, shape (n_poses, 2)
            ``q`` (mm) on the machine's assembly branch; NaN where a sphere
            centre is out of reach of its link.
        """
        R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
        n = R.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        beta = self._beta_for(g, R)
        N = g.O + g.rlen[:, None] * rotate_about(g.w, beta, g.lhat)
        d0 = N[:, None, :] + np.einsum("nij,nkj->nki", R, g.a - g.n[:, None, :]) - g.B
        du = np.einsum("nki,nki->nk", d0, g.u)
        disc = du**2 - np.einsum("nki,nki->nk", d0, d0) + g.l**2
        s = -1.0 if self.links_along_rail else 1.0
        with np.errstate(invalid="ignore"):
            return du + s * np.sqrt(np.where(disc >= 0, disc, np.nan))

    def tool_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Identification Jacobian of the tool pose by the implicit function theorem.

        ``d(dw, beta)/dtheta = -F_x^{-1} F_theta``; the tool point
        ``T = N(beta) + R (t - n)`` then moves by
        ``dN/dbeta dbeta - [R (t - n)]x dw`` plus the direct terms of the
        chain-3 and tool parameters.  Returns shape (n_poses, 6, P); see
        :meth:`Machine.tool_jacobian`.
        """
        q = self.check_q(q)
        n = q.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        st = poses.state
        R, beta = st.R, st.beta
        _, Fx, k = self._constraints(q, g, R, beta)
        P = self.n_params
        # direct motion of N per parameter (n, 3, P): chain 3's O, w, lhat, r
        dNt = np.zeros((n, 3, P))
        o = _O3
        dNt[:, :, o : o + 3] = np.eye(3)
        dNt[:, :, o + 3 : o + 5] = g.rlen[:, None, None] * _d_rotate_d_axis(g.w, beta, g.lhat) @ g.dw
        rot = _rotation_matrix(g.w, beta)
        dNt[:, :, o + 5 : o + 7] = g.rlen[:, None, None] * rot @ g.dlhat
        dNt[:, :, o + 7] = rotate_about(g.w, beta, g.lhat)
        # ... and every platform point moves by -R dn for the U centre n
        dNt[:, :, o + 12 : o + 15] = -R
        Ft = np.zeros((n, 4, P))
        d1, d2 = k.d[:, 0], k.d[:, 1]
        Ft[:, 0] = np.einsum("ni,nip->np", d1, dNt)
        Ft[:, 1] = np.einsum("ni,nip->np", d2, dNt)
        Ft[:, 2] = np.einsum("ni,nip->np", g.r2, dNt)
        # chain 1: a (3), B (3), u tilts (2), l
        Ft[:, 0, 0:3] = np.einsum("nj,njk->nk", d1, R)
        Ft[:, 0, 3:6] = -d1
        Ft[:, 0, 6:8] = -q[:, 0, None] * np.einsum("nj,njk->nk", d1, g.du[:, 0])
        Ft[:, 0, 8] = -g.l[:, 0]
        # chain 2: a (3), B (3), u tilts (2), r tilts (2), l
        o2 = _O2
        Ft[:, 1, o2 : o2 + 3] = np.einsum("nj,njk->nk", d2, R)
        Ft[:, 2, o2 : o2 + 3] = np.einsum("nj,njk->nk", g.r2, R)
        Ft[:, 1, o2 + 3 : o2 + 6] = -d2
        Ft[:, 2, o2 + 3 : o2 + 6] = -g.r2
        Ft[:, 1, o2 + 6 : o2 + 8] = -q[:, 1, None] * np.einsum("nj,njk->nk", d2, g.du[:, 1])
        Ft[:, 2, o2 + 6 : o2 + 8] = -q[:, 1, None] * np.einsum("nj,njk->nk", g.r2, g.du[:, 1])
        Ft[:, 2, o2 + 8 : o2 + 10] = np.einsum("nj,njk->nk", d2, g.dr2)
        Ft[:, 1, o2 + 10] = -g.l[:, 1]
        # chain 3's U joint: F3 = Rot(w, beta) k1 . R k2
        Ft[:, 3, o + 3 : o + 5] = np.einsum("ni,nij,njk->nk", k.v, _d_rotate_d_axis(g.w, beta, g.k1), g.dw)
        Ft[:, 3, o + 8 : o + 10] = np.einsum("ni,nij,njk->nk", k.v, rot, g.dk1)
        Ft[:, 3, o + 10 : o + 12] = np.einsum("ni,nij,njk->nk", k.k1b, R, g.dk2)
        dx = -np.linalg.solve(Fx, Ft)  # (n, 4, P): rows dw (3), dbeta
        mt = np.einsum("nij,nj->ni", R, g.t - g.n)
        J = np.empty((n, 6, P))
        J[:, :3] = dNt + k.dN[:, :, None] * dx[:, 3:4] - skew(mt) @ dx[:, :3]
        J[:, :3, _OT:] += R
        J[:, 3:] = dx[:, :3]
        return J

    # ------------------------------------------------------------------ output
    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """Machine file of the geometry ``nominal + theta``, same kind and keys."""
        g = self.geometry_arrays(theta)
        f = format_toml_value
        out = [f"kind = {f(self.kind)}", f"name = {f(self.name)}"]
        if not self.links_along_rail:
            out.append('assembly = "against_rail"')
        out.append("")
        for i in range(2):
            out += [
                "[[chain]]",
                f"joints = {f(_JOINTS[i])}",
                f"rail_origin = {f(g['rail_origin'][i])}",
                f"rail_direction = {f(g['rail_direction'][i])}",
            ]
            if i == 1:
                out.append(f"revolute_axis = {f(g['revolute_axis'])}")
            out += [f"link_length = {f(g['link_length'][i])}", f"sphere_center = {f(g['sphere_center'][i])}", ""]
        out += [
            "[[chain]]",
            'joints = "RU"',
            f"base_point = {f(g['base_point'])}",
            f"base_axis = {f(g['base_axis'])}",
            f"link_direction = {f(g['link_direction'])}",
            f"link_length = {f(g['center_link_length'])}",
            f"universal_axis_link = {f(g['universal_axis_link'])}",
            f"universal_axis_platform = {f(g['universal_axis_platform'])}",
            f"universal_center = {f(g['universal_center'])}",
            "",
            "[tool]",
            f"point = {f(g['tool_point'])}",
            "",
        ]
        return "\n".join(out) + common_toml(self, self.tolerance_groups)


# ---------------------------------------------------------------- helpers
def _rotation_matrix(w: NDArray, beta: NDArray) -> NDArray:
    """``Rot(w, beta)`` as matrices (n, 3, 3)."""
    return so3_exp(w * beta[:, None])
