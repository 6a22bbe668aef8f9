"""The redundantly actuated 2T1R spatial parallel module (RASPM).

Topology (docs/redundant.md): every revolute axis is parallel to the base
``y`` axis and every chain moves in a plane ``y = const``, so the chains'
structure constrains the three out-of-plane motions and the platform keeps
three degrees of freedom: translation in ``x`` and ``z`` (2T) and a rotation
``phi`` about ``y`` (1R).  A chain is one platform revolute joint (centre
``a``, platform frame) driven by one or more sliders; a slider is an
actuated prismatic joint on a fixed rail (``C = B + q u``) with a link of
length ``l`` from the slider's revolute joint to the platform joint.  The
example module has chains 1 and 2 of type P-R-R (one slider each) and
chain 3 with two sliders sharing one coaxial platform joint (a five-bar):
chain 3 sets the translation of its joint, chains 1 and 2 both set the
rotation, so 4 actuators drive 3 DOF with one redundant actuation and the
rotation is decoupled from the planar translation.

Per slider ``k`` (attached to the platform joint ``a_k`` of its chain) the
compatibility condition is

    f_k = (|p + R(phi) a_k - B_k - q_k u_k|^2 - l_k^2) / 2 = 0      (planar x-z vectors)

with the closed-form inverse ``q_k = IK_k(x)``.  Three of the four conditions
(the ``nonredundant`` actuators) fix the pose ``x = (p_x, p_z, phi)``;
:meth:`Raspm.forward` solves those (the model of the corresponding
non-redundant module) and :meth:`Raspm.compatibility` returns what the other
actuators violate, ``IK_r(x) - q_r``, which is zero only for a geometrically
perfect module.

Error parameters (in-plane, mm or rad): per chain ``platform_joint.{x,z}``;
per slider ``rail_origin.{x,z}`` (the component along the rail is the
actuator's zero offset), ``rail_direction.tilt`` (in-plane rotation of the
rail about ``y``), ``link_length``; and ``tool.point.{x,z}``.  24 for the
example module.  Out-of-plane components (``y``) do not enter the planar
kinematics and carry no parameter.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..io.machine_file import TomlTable, format_toml_value
from ..params import ParamLayout, ParamSpec
from .base import Machine, MeasurementNoise, ToolPoses
from .common import common_toml, read_noise, read_q_limits, read_tolerance
from .tolerance import tolerance_vector

__all__ = ["Raspm", "RASPM_TOLERANCE_DEFAULTS", "PlanarState", "rot2", "drot2"]

#: Documented one-sigma defaults of the ``[tolerance]`` table (mm or rad).
RASPM_TOLERANCE_DEFAULTS: dict[str, float] = {
    "platform_joint": 0.05,
    "rail_origin": 0.05,
    "rail_direction": 1.0e-4,
    "link_length": 0.05,
    "tool_point": 0.05,
}

_TOL = 1e-11  # mm; Newton step at which a pose counts as solved
_MAXIT = 100
N_DOF = 3


def rot2(phi: NDArray) -> NDArray:
    """In-plane part of ``R_y(phi)`` acting on ``(x, z)``: shape ``phi.shape + (2, 2)``."""
    c, s = np.cos(phi), np.sin(phi)
    return np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], -2)


def drot2(phi: NDArray) -> NDArray:
    """``d rot2 / d phi``."""
    c, s = np.cos(phi), np.sin(phi)
    return np.stack([np.stack([-s, c], -1), np.stack([-c, -s], -1)], -2)


def _rot_y(phi: NDArray) -> NDArray:
    c, s = np.cos(phi), np.sin(phi)
    z, o = np.zeros_like(phi), np.ones_like(phi)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


@dataclass(frozen=True)
class PlanarState:
    """Solved planar poses: ``x[:, 0:2]`` platform origin (x, z) mm, ``x[:, 2]`` phi rad."""

    x: NDArray


@dataclass(frozen=True)
class _Geometry:
    a: NDArray  # (n, m, 2) platform joint of each slider's chain, platform frame
    B: NDArray  # (n, m, 2) rail origins
    u: NDArray  # (n, m, 2) rail directions
    du: NDArray  # (n, m, 2) d u / d tilt
    l: NDArray  # (n, m) link lengths
    t: NDArray  # (n, 2) tool point, platform frame


@dataclass(frozen=True, eq=False)
class Raspm(Machine):
    """A redundantly actuated 2T1R module: nominal geometry, parameters, kinematics.

    Parameters
    ----------
    platform_joint : ndarray, shape (n_chains, 3)
        Platform revolute-joint centre of each chain, platform frame, mm.
    slider_chain : tuple of int
        0-based chain of each slider (actuator), in actuator order.
    rail_origin, rail_direction : ndarray, shape (m, 3)
        Per slider, base frame, mm / unit vector normal to ``y``.
    link_length : ndarray, shape (m,)
        mm.
    links_against_rail : ndarray of bool, shape (m,)
        Assembly branch of each slider: True when the link points from the
        slider against the rail direction.
    tool_point : ndarray, shape (3,)
        mm, platform frame.
    nonredundant : tuple of int
        0-based actuators whose positions fix the pose in :meth:`forward`.
    pose_range : ndarray, shape (3, 2) or None
        Planar translation ``x``, ``z`` (mm) and rotation ``phi`` (rad) ranges.
    """

    kind = "RASPM-2T1R"

    platform_joint: NDArray
    slider_chain: tuple
    rail_origin: NDArray
    rail_direction: NDArray
    link_length: NDArray
    links_against_rail: NDArray
    tool_point: NDArray
    nonredundant: tuple = (0, 2, 3)
    name: str = "RASPM"
    noise: MeasurementNoise = field(default_factory=MeasurementNoise)
    q_limits: NDArray | None = None
    pose_range: NDArray | None = None
    tolerance_groups: dict = field(default_factory=lambda: dict(RASPM_TOLERANCE_DEFAULTS))
    source: str = "<memory>"

    def __post_init__(self) -> None:
        m = len(self.slider_chain)
        if len(self.nonredundant) != N_DOF or len(set(self.nonredundant)) != N_DOF:
            raise InputError(f"{self.source}: nonredundant: expected {N_DOF} distinct actuators, got {self.nonredundant}")
        if m < N_DOF:
            raise InputError(f"{self.source}: a 2T1R module needs at least {N_DOF} actuators, got {m}")
        specs: list[ParamSpec] = []
        ja = np.zeros((len(self.platform_joint), 2), dtype=int)  # column of platform_joint.{x,z} per chain
        sl = np.zeros((m, 4), dtype=int)  # columns of rail_origin.x, .z, tilt, link_length per slider
        for c in range(len(self.platform_joint)):
            ja[c] = len(specs), len(specs) + 1
            specs += [ParamSpec(f"chain{c + 1}.platform_joint.{x}", "mm", "platform_joint") for x in "xz"]
            local = [k for k in range(m) if self.slider_chain[k] == c]
            for j, k in enumerate(local):
                s = f"chain{c + 1}.slider{j + 1}"
                sl[k] = np.arange(len(specs), len(specs) + 4)
                specs += [ParamSpec(f"{s}.rail_origin.{x}", "mm", "rail_origin") for x in "xz"]
                specs += [ParamSpec(f"{s}.rail_direction.tilt", "rad", "rail_direction"), ParamSpec(f"{s}.link_length", "mm", "link_length")]
        tcol = np.array([len(specs), len(specs) + 1])
        specs += [ParamSpec(f"tool.point.{x}", "mm", "tool_point") for x in "xz"]
        object.__setattr__(self, "layout", ParamLayout(tuple(specs)))
        object.__setattr__(self, "tolerance", tolerance_vector(specs, self.tolerance_groups))
        object.__setattr__(self, "_cols", (ja, sl, tcol))

    # ----------------------------------------------------------------- set-up
    @property
    def n_actuators(self) -> int:
        return len(self.slider_chain)

    @property
    def n_dof(self) -> int:
        return N_DOF

    @property
    def redundant(self) -> tuple[int, ...]:
        """0-based actuators outside the non-redundant subset."""
        return tuple(k for k in range(self.n_actuators) if k not in self.nonredundant)

    @property
    def redundancy(self) -> "Raspm":
        """The RASPM itself: one redundant drive and every drive's inverse kinematics in closed form."""
        return self

    @property
    def actuator_box_reachable(self) -> bool:
        """False: the redundant actuators are fixed by the others, not free within ``q_limits``."""
        return False

    def offset_index(self) -> NDArray:
        """Parameter indices whose change moves one rail origin along its rail (zero offsets), per actuator.

        Returns the indices of ``rail_origin.x`` / ``rail_origin.z`` (whichever
        component lies most along the rail), shape (m,).
        """
        _, sl, _ = self._cols
        along_z = np.abs(self.rail_direction[:, 2]) >= np.abs(self.rail_direction[:, 0])
        return np.where(along_z, sl[:, 1], sl[:, 0])

    @classmethod
    def from_toml(cls, doc: TomlTable, path: str) -> "Raspm":
        doc.reject_unknown({"kind", "name", "chain", "tool", "nonredundant", "measurement", "workspace", "tolerance", "pose_range"})
        chains = doc.array_of_tables("chain")
        pj, sc, B, u, l, against = [], [], [], [], [], []
        for c, ch in enumerate(chains):
            ch.reject_unknown({"platform_joint", "slider"})
            pj.append(ch.vector("platform_joint"))
            for sd in ch.array_of_tables("slider"):
                sd.reject_unknown({"rail_origin", "rail_direction", "link_length", "links_against_rail"})
                d = sd.vector("rail_direction", unit=True)
                if abs(d[1]) > 1e-9:
                    raise sd.error("rail_direction", f"expected a direction normal to the revolute axes (y component 0), got {d.tolist()}")
                sc.append(c)
                B.append(sd.vector("rail_origin"))
                u.append(d)
                l.append(sd.number("link_length", positive=True))
                v = sd.data.get("links_against_rail", True)
                if not isinstance(v, bool):
                    raise sd.error("links_against_rail", f"expected true or false, got {v!r}")
                against.append(v)
        m = len(sc)
        nr = doc.data.get("nonredundant", [1, 3, 4][:m] if m >= 4 else list(range(1, m + 1)))
        if not isinstance(nr, list) or len(nr) != N_DOF or any(isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= m for k in nr) or len(set(nr)) != N_DOF:
            raise doc.error("nonredundant", f"expected {N_DOF} distinct actuator numbers from 1 to {m}, got {nr!r}")
        tool = doc.table("tool")
        tool.reject_unknown({"point"})
        pr = doc.table("pose_range", required=False)
        pose_range = None
        if pr is not None:
            pr.reject_unknown({"x", "z", "rotation"})
            pose_range = np.array([pr.vector(k, 2) for k in ("x", "z", "rotation")])
            for k, (lo, hi) in zip(("x", "z", "rotation"), pose_range):
                if lo >= hi:
                    raise pr.error(k, f"expected [min, max] with min < max, got {[lo, hi]}")
        return cls(
            platform_joint=np.array(pj), slider_chain=tuple(sc), rail_origin=np.array(B), rail_direction=np.array(u),
            link_length=np.array(l), links_against_rail=np.array(against), tool_point=tool.vector("point"),
            nonredundant=tuple(k - 1 for k in nr), name=doc.string("name", "RASPM"), noise=read_noise(doc),
            q_limits=read_q_limits(doc, m), pose_range=pose_range,
            tolerance_groups=read_tolerance(doc, RASPM_TOLERANCE_DEFAULTS), source=path,
        )

    def _theta_rows(self, theta: ArrayLike | None, n: int) -> NDArray:
        theta = self.check_theta(theta, n)
        return np.broadcast_to(theta, (n, self.n_params)) if theta.ndim == 1 else theta

    def _geometry(self, theta: NDArray) -> _Geometry:
        """Planar geometry for theta of shape (n, P)."""
        ja, sl, tcol = self._cols
        xz = [0, 2]
        ch = np.array(self.slider_chain)
        a = self.platform_joint[ch][:, xz][None] + theta[:, ja[ch]]
        B = self.rail_origin[:, xz][None] + theta[:, sl[:, :2]]
        tilt = theta[:, sl[:, 2]]
        R = rot2(tilt)  # (n, m, 2, 2)
        u0 = self.rail_direction[:, xz]
        u = np.einsum("nkij,kj->nki", R, u0)
        du = np.einsum("nkij,kj->nki", drot2(tilt), u0)
        l = self.link_length[None] + theta[:, sl[:, 3]]
        t = self.tool_point[xz][None] + theta[:, tcol]
        return _Geometry(a=a, B=B, u=u, du=du, l=l, t=t)

    # ------------------------------------------------------------ kinematics
    def _joint_vectors(self, x: NDArray, g: _Geometry):
        """Platform joints ``A`` (n, m, 2), ``R a`` and ``dR/dphi a``."""
        Ra = np.einsum("nij,nkj->nki", rot2(x[:, 2]), g.a)
        dRa = np.einsum("nij,nkj->nki", drot2(x[:, 2]), g.a)
        return x[:, None, :2] + Ra, Ra, dRa

    def _ik(self, x: NDArray, g: _Geometry):
        """Closed-form inverse kinematics and its pose Jacobian.

        Returns ``q`` (n, m) mm (NaN out of reach), ``J_a = dq/dx`` (n, m, 3)
        and ``d = A - C`` (n, m, 2).
        """
        A, _, dRa = self._joint_vectors(x, g)
        e = A - g.B
        eu = np.einsum("nki,nki->nk", e, g.u)
        disc = eu**2 - np.einsum("nki,nki->nk", e, e) + g.l**2
        s = np.where(self.links_against_rail, 1.0, -1.0)[None]
        with np.errstate(invalid="ignore"):
            q = eu + s * np.sqrt(np.where(disc >= 0, disc, np.nan))
        d = e - q[..., None] * g.u
        du_ = np.einsum("nki,nki->nk", d, g.u)  # df/dq = -d.u
        Ja = np.empty(q.shape + (3,))
        Ja[..., :2] = d / du_[..., None]
        Ja[..., 2] = np.einsum("nki,nki->nk", d, dRa) / du_
        return q, Ja, d

    def inverse_planar(self, x: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """Actuator positions (n, m) mm for planar poses ``x`` (n, 3): ``(p_x mm, p_z mm, phi rad)``.

        This is what a controller using geometry ``theta`` commands for a
        desired pose: all m actuators, so they are mutually compatible only
        when ``theta`` is the true geometry.  NaN where a link cannot reach.
        """
        x = np.atleast_2d(np.asarray(x, dtype=float))
        return self._ik(x, self._geometry(self._theta_rows(theta, x.shape[0])))[0]

    def ik_jacobian(self, x: ArrayLike, theta: ArrayLike | None = None) -> tuple[NDArray, NDArray]:
        """``q = IK(x)`` and the actuation Jacobian ``J_a = dq/dx``, shape (n, m, 3)."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        q, Ja, _ = self._ik(x, self._geometry(self._theta_rows(theta, x.shape[0])))
        return q, Ja

    def ik_parameter_jacobian(self, x: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """``G = dIK/dtheta`` at fixed pose, shape (n, m, P) (mm per unit of each parameter)."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        n = x.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        q, _, d = self._ik(x, g)
        R = rot2(x[:, 2])
        du_ = np.einsum("nki,nki->nk", d, g.u)
        ja, sl, _ = self._cols
        ch = np.array(self.slider_chain)
        G = np.zeros((n, self.n_actuators, self.n_params))
        for k in range(self.n_actuators):
            # dq/dtheta = (df/dtheta) / (d.u), f = (|d|^2 - l^2)/2
            G[:, k, ja[ch[k]]] += np.einsum("ni,nij->nj", d[:, k], R) / du_[:, k, None]
            G[:, k, sl[k, :2]] += -d[:, k] / du_[:, k, None]
            G[:, k, sl[k, 2]] += -q[:, k] * np.einsum("ni,ni->n", d[:, k], g.du[:, k]) / du_[:, k]
            G[:, k, sl[k, 3]] += -g.l[:, k] / du_[:, k]
        return G

    def fit_pose(
        self, q: ArrayLike, theta: ArrayLike | None, weights: ArrayLike, *, x0: NDArray | None = None
    ) -> tuple[NDArray, NDArray]:
        """Pose minimising ``sum_k w_k (IK_k(x) - q_k)^2``: the restrained-equilibrium pose.

        With ``w_k`` the actuated-joint stiffnesses this is the elastic
        equilibrium of a module whose deformations live at the actuated
        joints (deformation ``delta_k = IK_k(x) - q_k``, internal force
        ``w_k delta_k`` in the null space of ``J_a^T``); with ``w`` zero
        outside the non-redundant subset it is the non-redundant forward
        kinematics.  Gauss-Newton, whose fixed points are exactly the points
        where ``J_a^T W (IK(x) - q) = 0``.

        Parameters
        ----------
        q : array_like, shape (n, m)
            Commanded actuator positions, mm.
        theta : array_like, shape (P,) or (n, P)
        weights : array_like, shape (m,) or (n, m)
            Non-negative; only ratios matter.
        x0 : ndarray, shape (n, 3), optional
            Start; the nominal home by default.

        Returns
        -------
        x : ndarray, shape (n, 3)
            Planar poses (NaN rows where the solve failed).
        ok : ndarray of bool, shape (n,)
        """
        q = self.check_q(q)
        n = q.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        w = np.broadcast_to(np.asarray(weights, dtype=float), (n, self.n_actuators))
        x = np.zeros((n, 3)) + (self._home_x() if x0 is None else x0)
        done = np.zeros(n, dtype=bool)
        for _ in range(_MAXIT):
            qi, Ja, _ = self._ik(x, g)
            r = qi - q
            Jw = Ja * w[..., None]
            H = np.einsum("nki,nkj->nij", Jw, Ja)
            grad = np.einsum("nki,nk->ni", Jw, r)
            bad = ~np.isfinite(grad).all(axis=1) | ~np.isfinite(H).all(axis=(1, 2))
            dx = np.zeros((n, 3))
            good = ~bad
            if good.any():
                dx[good] = -np.linalg.solve(H[good], grad[good][..., None])[..., 0]
            # cap steps far from the solution (the start may be hundreds of mm away)
            size = np.abs(dx[:, :2]).max(axis=1) / 50.0 + np.abs(dx[:, 2]) / 0.1
            dx *= np.minimum(1.0, 1.0 / np.maximum(size, 1e-300))[:, None]
            x = np.where(bad[:, None], x * 0.9 + 0.1 * self._home_x(), x + dx)
            done = good & (np.abs(dx[:, :2]).max(axis=1) < _TOL) & (np.abs(dx[:, 2]) < _TOL * 1e-3)
            if done.all():
                break
        return x, done

    def _home_x(self) -> NDArray:
        if self.pose_range is not None:
            return self.pose_range.mean(axis=1)
        return np.zeros(3)

    def nonredundant_weights(self) -> NDArray:
        w = np.zeros(self.n_actuators)
        w[list(self.nonredundant)] = 1.0
        return w

    def forward_planar(self, q: ArrayLike, theta: ArrayLike | None = None, *, x0: NDArray | None = None):
        """Planar pose from the non-redundant subset of actuators: ``(x (n, 3), ok (n,))``."""
        return self.fit_pose(q, theta, self.nonredundant_weights(), x0=x0)

    def compatible_q(self, q: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """``q`` with the redundant drives set to the inverse kinematics of the non-redundant pose, mm.

        What a controller commands for that pose: the redundant drives follow
        the nominal model, they are not free (see :meth:`Machine.compatible_q`).
        Rows whose pose cannot be solved are returned unchanged.
        """
        q = self.check_q(q)
        x, ok = self.forward_planar(q, theta)
        out = q.copy()
        r = list(self.redundant)
        out[np.ix_(ok, r)] = self.inverse_planar(x[ok], theta)[:, r] if ok.any() else out[np.ix_(ok, r)]
        return out

    def compatibility(self, q: ArrayLike, theta: ArrayLike | None = None) -> NDArray:
        """What each actuator violates at the non-redundant pose: ``IK(x) - q``, shape (n, m), mm.

        Zero (to round-off) on the non-redundant actuators; on the others it
        is the incompatibility a geometric error leaves, which a real
        redundant module absorbs by restrained deformation.
        """
        q = self.check_q(q)
        x, _ = self.forward_planar(q, theta)
        return self.inverse_planar(x, theta) - q

    def tool_from_planar(self, x: NDArray, theta: ArrayLike | None = None) -> tuple[NDArray, NDArray]:
        """Tool point (n, 3) mm and rotation (n, 3, 3) of planar poses."""
        n = x.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        t2 = x[:, :2] + np.einsum("nij,nj->ni", rot2(x[:, 2]), g.t)
        pos = np.column_stack([t2[:, 0], np.full(n, self.tool_point[1]), t2[:, 1]])
        return pos, _rot_y(x[:, 2])

    def forward(self, q: ArrayLike, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> ToolPoses:
        """Forward kinematics of the corresponding non-redundant module.

        Parameters
        ----------
        q : array_like, shape (n_poses, m)
            Commanded actuator positions, mm; only the ``nonredundant`` ones are used.
        theta : array_like, shape (P,) or (n_poses, P), optional
        guess : ToolPoses, optional
            Warm start (its ``state``).

        Returns
        -------
        ToolPoses
            ``state`` is a :class:`PlanarState`.
        """
        q = self.check_q(q)
        x0 = guess.state.x if guess is not None and isinstance(guess.state, PlanarState) else None
        x, ok = self.forward_planar(q, theta, x0=x0)
        _, Ja = self.ik_jacobian(x, theta)
        Js = Ja[:, list(self.nonredundant)]
        with np.errstate(invalid="ignore"):
            cond = np.linalg.cond(np.where(np.isfinite(Js), Js, 0.0))
        singular = ok & (cond > 1e10)
        msgs = tuple(
            "" if o and not s else ("singular pose" if s else "forward kinematics did not converge (pose unreachable?)")
            for o, s in zip(ok, singular)
        )
        pos, R = self.tool_from_planar(np.where(np.isfinite(x), x, 0.0), theta)
        return ToolPoses(position=pos, rotation=R, success=ok & ~singular, message=msgs, state=PlanarState(x=x))

    def planar_jacobian(self, q: ArrayLike, theta: ArrayLike | None, x: NDArray) -> NDArray:
        """``dx/dtheta`` of the non-redundant pose, shape (n, 3, P): ``-J_s^-1 G_s``."""
        _, Ja = self.ik_jacobian(x, theta)
        G = self.ik_parameter_jacobian(x, theta)
        s = list(self.nonredundant)
        # q_s = IK_s(x(theta), theta) held fixed: J_s dx + G_s dtheta = 0
        return -np.linalg.solve(Ja[:, s], G[:, s])

    def tool_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Identification Jacobian of the non-redundant model, shape (n, 6, P).

        Rows: tool x, y (zero), z; small rotation about x (zero), y (``dphi``), z (zero).
        """
        q = self.check_q(q)
        x = poses.state.x
        dx = self.planar_jacobian(q, theta, x)
        return self.tool_jacobian_from_planar(x, theta, dx)

    def actuator_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """``d(tool pose)/dq`` of the non-redundant model, shape (n, 6, m), analytic.

        ``IK_s(x) = q_s`` for the non-redundant drives gives ``dx/dq_s = J_s^-1``;
        the redundant drives are not read (zero columns).  Replaces the
        finite differences of the base class (8 forward solves per call).
        """
        q = self.check_q(q)
        x = poses.state.x
        n = x.shape[0]
        _, Ja = self.ik_jacobian(x, theta)
        s = list(self.nonredundant)
        dx = np.zeros((n, 3, self.n_actuators))
        dx[:, :, s] = np.linalg.inv(Ja[:, s])
        g = self._geometry(self._theta_rows(theta, n))
        dRt = np.einsum("nij,nj->ni", drot2(x[:, 2]), g.t)
        J = np.zeros((n, 6, self.n_actuators))
        J2 = dx[:, :2] + dRt[:, :, None] * dx[:, 2:3]
        J[:, 0], J[:, 2], J[:, 4] = J2[:, 0], J2[:, 1], dx[:, 2]
        return J

    def tool_jacobian_from_planar(self, x: NDArray, theta: ArrayLike | None, dx: NDArray) -> NDArray:
        """Tool-pose Jacobian (n, 6, P) from a planar-pose Jacobian ``dx`` (n, 3, P)."""
        n = x.shape[0]
        g = self._geometry(self._theta_rows(theta, n))
        _, _, tcol = self._cols
        dRt = np.einsum("nij,nj->ni", drot2(x[:, 2]), g.t)
        J = np.zeros((n, 6, self.n_params))
        J2 = dx[:, :2] + dRt[:, :, None] * dx[:, 2:3]
        J2[:, :, tcol] += rot2(x[:, 2])
        J[:, 0], J[:, 2], J[:, 4] = J2[:, 0], J2[:, 1], dx[:, 2]
        return J

    # ---------------------------------------------------------------- sampling
    def sample_planar(self, n: int, rng: np.random.Generator) -> NDArray:
        """``n`` planar poses drawn uniformly in ``pose_range``."""
        if self.pose_range is None:
            raise InputError(f"{self.source}: the machine file has no [pose_range]; it is needed to draw poses")
        lo, hi = self.pose_range[:, 0], self.pose_range[:, 1]
        return lo + (hi - lo) * rng.random((n, 3))

    def sample_q(self, n: int, rng: np.random.Generator) -> NDArray:
        """Compatible actuator vectors of ``n`` nominal poses drawn in ``pose_range``.

        Independent uniform draws of four actuators would almost never be
        compatible (the module would jam), so poses are drawn instead.
        """
        if self.pose_range is None:
            return super().sample_q(n, rng)
        return self.inverse_planar(self.sample_planar(n, rng))

    # ------------------------------------------------------------------ output
    def geometry_arrays(self, theta: ArrayLike | None = None) -> dict[str, NDArray]:
        """The machine file's arrays of ``nominal + theta`` (theta of shape (P,))."""
        theta = self.check_theta(theta)
        g = self._geometry(theta[None])
        ja, _, _ = self._cols
        pj = self.platform_joint.copy()
        pj[:, [0, 2]] += theta[ja]
        B = self.rail_origin.copy()
        B[:, [0, 2]] = g.B[0]
        u = np.zeros_like(self.rail_direction)
        u[:, [0, 2]] = g.u[0]
        t = self.tool_point.copy()
        t[[0, 2]] = g.t[0]
        return {"platform_joint": pj, "rail_origin": B, "rail_direction": u, "link_length": g.l[0], "tool_point": t}

    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """Machine file of the geometry ``nominal + theta``, same kind and keys."""
        g = self.geometry_arrays(theta)
        f = format_toml_value
        out = [f"kind = {f(self.kind)}", f"name = {f(self.name)}", f"nonredundant = {f([k + 1 for k in self.nonredundant])}", ""]
        for c in range(len(self.platform_joint)):
            out += ["[[chain]]", f"platform_joint = {f(g['platform_joint'][c])}", ""]
            for k in (k for k in range(self.n_actuators) if self.slider_chain[k] == c):
                out += [
                    "[[chain.slider]]",
                    f"rail_origin = {f(g['rail_origin'][k])}",
                    f"rail_direction = {f(g['rail_direction'][k])}",
                    f"link_length = {f(g['link_length'][k])}",
                    f"links_against_rail = {f(bool(self.links_against_rail[k]))}",
                    "",
                ]
        out += ["[tool]", f"point = {f(g['tool_point'])}", ""]
        if self.pose_range is not None:
            out += ["[pose_range]"] + [f"{k} = {f(v)}" for k, v in zip(("x", "z", "rotation"), self.pose_range)] + [""]
        return "\n".join(out) + common_toml(self, self.tolerance_groups)
