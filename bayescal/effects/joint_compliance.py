"""Joint compliance: the actuated joints yield under the gravity load of platform and payload."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..machines.base import ActuatorUnit, Machine, ToolPoses
from .base import Effect, EffectParam, Features
from .conditions import second_payload, tilted_mounting
from .gravity_field import gravity_per_pose, link_middles, serial_part, tilt_basis, tilted_gravity

__all__ = ["JointCompliance", "actuator_loads", "gravity_direction", "compliance_prior_scale", "GRAVITY", "DEFAULT_GRAVITY_DIRECTION"]

#: Standard gravity, m/s^2.
GRAVITY = 9.80665
#: Gravity in the base frame of a machine mounted upright (rails along +z pointing up), unit vector.
DEFAULT_GRAVITY_DIRECTION = (0.0, 0.0, -1.0)


def _unit(v, what: str) -> NDArray:
    v = np.asarray(v, float).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) == 0:
        raise InputError(f"{what}: expected a non-zero 3-vector, got {v.tolist()}")
    return v / np.linalg.norm(v)


def compliance_prior_scale(unit: ActuatorUnit) -> float:
    """A slider's compliance prior (um/N) to this drive's unit (``unit.compliance``): 1, or 100 on a joint.

    The reference arm of :attr:`ActuatorUnit.per_um` is ``r = 1 / per_um`` m
    (100 mm on a joint).  A force ``F`` there is a torque ``F r``, which
    turns a joint of compliance ``c`` by ``c F r`` and moves the point by
    ``c F r^2``; as compliant as a slider of ``c_s`` um/N when ``c = c_s /
    r^2``, i.e. ``per_um ** 2`` urad/(N m) per um/N (um/m^2 = urad/m).
    Weight deflections ``c m g`` scale alike.
    """
    return float(unit.per_um) ** 2


def _tilt_basis(down: NDArray) -> NDArray:
    """Two unit vectors normal to ``down``: the base axes it is most perpendicular to, orthogonalised, (2, 3)."""
    keep = [i for i in range(3) if i != int(np.argmax(np.abs(down)))]
    out = []
    for k in keep:
        e = np.eye(3)[k] - down * down[k]
        for o in out:
            e = e - o * (o @ e)
        out.append(e / np.linalg.norm(e))
    return np.array(out)


def gravity_direction(down0: NDArray, tilt: NDArray) -> tuple[NDArray, NDArray]:
    """Gravity direction tilted from ``down0`` and its derivative by the two tilts.

    ``d = normalise(down0 + t_1 e_1 + t_2 e_2)`` with ``e_1, e_2`` the unit
    vectors normal to ``down0`` along the base axes it is most perpendicular
    to (for ``down0 = -z``: ``e_1 = x``, ``e_2 = y``), so ``t_k`` is the
    tangent of the tilt towards ``e_k`` (rad at small angles), exact at any
    tilt below 90 degrees.

    Returns
    -------
    d : ndarray, shape (3,)
    dd : ndarray, shape (3, 2)
        ``d d / d t_k``.
    """
    E = _tilt_basis(down0)
    v = down0 + np.asarray(tilt, float) @ E
    nv = np.linalg.norm(v)
    d = v / nv
    dd = (E.T - np.outer(d, d @ E.T)) / nv
    return d, dd


def actuator_loads(
    machine: Machine, q: NDArray, theta: NDArray, poses: ToolPoses, mass_kg: NDArray, *, down=DEFAULT_GRAVITY_DIRECTION,
    point: str = "origin",
) -> NDArray:
    """Generalised forces on the actuators of a weight ``m g`` at the platform origin (or the tool point), by virtual work.

    For every motion the actuators can make, ``f . dq = F . dx``, with ``dx``
    the displacement of the point the weight acts at (``J dq``, ``J`` from
    :meth:`Machine.actuator_jacobian`): ``f = J_x^T F``, ``J_x = J_t + [w]x
    (x - tool)``, i.e. the tool-point wrench ``(F, (x - tool) x F)`` mapped
    by ``J^T``.

    Parameters
    ----------
    mass_kg : ndarray, shape (n_poses,)
        kg.
    down : (3,)
        Gravity direction in the base frame (unit vector).
    point : {"origin", "tool"}
        Where the weight acts: the platform origin (``poses.state.p``; the
        tool point on kinds whose state has none) or the tool point.

    Returns
    -------
    ndarray, shape (n_poses, n_actuators), N mm per ``q`` unit
        Generalised gravity force on each actuator coordinate (positive:
        gravity pushes ``q_i`` up): a force in N on a slider (``q`` in mm),
        a torque in N mm on a revolute joint (``q`` in rad; times
        ``ActuatorUnit.load_scale`` gives N m).
    """
    J = machine.actuator_jacobian(q, theta, poses)
    F = np.asarray(mass_kg, float)[:, None] * GRAVITY * _unit(down, "down")[None, :]
    x = _platform_origin(poses) if point == "origin" else poses.position
    M = np.cross(x - poses.position, F)
    return np.einsum("nki,nk->ni", J[:, :3], F) + np.einsum("nki,nk->ni", J[:, 3:], M)


def _platform_origin(poses: ToolPoses) -> NDArray:
    p = getattr(poses.state, "p", None)
    return np.asarray(p, float) if p is not None else poses.position


class JointCompliance(Effect):
    """Actuated joints (screw, nut, bearings, slider, drive train) yield under the gravity load they carry.

    Physics: the platform's weight ``m_p g`` acts at its centre of mass
    ``x_c = p + R c`` (``c`` in the platform frame, from the platform origin
    ``p``: the machine's platform frame origin, or the tool point on kinds
    without one) and a payload ``m_L g`` (channel ``payload_kg``) at the
    tool point ``x_t``.  By virtual work the gravity force on actuator
    coordinate ``q_i`` is the derivative of ``g . sum(m x)`` by ``q_i``, and
    a drive of compliance ``c_i`` gives way by ``c_i`` times it:

        dq_i = w_i d . (dx_c / dq_i) + c_i m_L g d . (dx_t / dq_i),
        dx_c / dq_i = J_t,i + omega_i x (x_c - x_t),    w_i = c_i m_p g

    with ``(J_t,i, omega_i)`` column ``i`` of
    :meth:`Machine.actuator_jacobian` (tool-point velocity and platform
    angular velocity per unit of ``q_i``) and ``d`` the unit gravity
    direction in the base frame.  ``dq_i > 0`` when gravity pulls the slider
    towards larger ``q_i``.

    Units follow the drive (:attr:`Machine.actuator_unit_info`).  The
    generalised force ``m g d . dx/dq_i`` is a force (N) on a slider
    (``dx/dq_i`` in mm/mm) and a torque on a revolute joint (``dx/dq_i`` in
    mm/rad, so N mm, i.e. ``1e-3`` N m; ``ActuatorUnit.load_scale``): a
    joint's compliance ``c_i`` is its deflection per joint torque, urad/(N m)
    (``1 / c_i`` is its torsional stiffness), and ``dq_i = 1e-6 c_i tau_i``
    rad with ``tau_i`` in N m.  The same formula thus holds for both, only
    the numbers' units differ: ``dq_i [mm] = 1e-3 c_i [um/N] F_i [N]``;
    ``dq_i [rad] = 1e-9 c_i [urad/(N m)] tau_i [N mm]``.

    What the data identify, hence the parameters (names, units), in two
    sets that depend only on whether the recording has a ``payload_kg``
    channel:

    * without it: ``weight_deflection.q<i>`` (um, ``>= 0``), ``w_i = c_i
      m_p g``, how far drive ``i`` would give way under the whole platform
      weight on its axis (prior ``0 +- 300 um``): mass and compliance appear
      only as this product; on a revolute joint urad/m, its deflection per
      metre of the weight's lever arm (prior ``0 +- 30,000 urad/m``, 3 mrad
      at 100 mm);
    * with it: ``compliance.q<i>`` (um/N, ``>= 0``, prior ``0 +- 1``; on a
      revolute joint urad/(N m), prior ``0 +- 100``, a torsional stiffness of
      1e4 N m/rad: the joint that lets a point 100 mm from its axis give way
      1 um/N, as the slider's prior; ``ActuatorUnit.per_um`` squared) and
      ``platform_mass`` (kg, ``>= 0``, prior ``0 +- 100``, or centred on a
      stated mass with 2 % width), ``w_i = c_i m_p g`` (the payload's
      changing load fixes ``c_i``; the platform's then fixes ``m_p``);
    * both: ``com.x``, ``com.y``, ``com.z`` (mm, platform frame): the
      platform's centre of mass from the platform origin (prior ``0 +-
      200 mm``, or a stated one +- 5 mm), and ``gravity.tilt_1``,
      ``gravity.tilt_2`` (tangent of the tilt, "rad"): ``d = normalise(d0 +
      t_1 e_1 + t_2 e_2)`` (:func:`gravity_direction`), the mounting's tilt
      from ``d0`` (prior ``0 +- 0.5``, 27 degrees, when ``d0`` is the
      default; ``0 +- 0.02`` when the gravity direction is stated).  Tilts
      of 45 degrees are found from an upright start when the deflections
      are tens of um; otherwise they are reported near their prior.

    Sign rule: ``w_i``, ``c_i``, ``m_p >= 0`` (a drive gives way in the
    direction it is pushed); the tilt keeps ``d`` in the half space of
    ``d0``, so flipping both the direction and the deflections is not a
    second solution, and a fit needing a negative value beyond 3 sigma is
    rejected as non-physical.  ``d0`` must therefore be right to within 90
    degrees (upright by default).

    Identifiability: the pose-independent part of the sag is exactly an
    actuator zero offset.  It is told apart from the geometry only through
    the physics tying it to the pose-dependent part (``c_i`` from the
    payload, then ``m_p``, ``c``, ``d``), and on a 3-PRS that tie is weak:
    at 4 um noise and 160 poses the data alone leave the constant sag
    uncertain by 40-65 um, the platform mass by about 20 kg, so the
    geometry "without gravity" is uncertain by tens of um at the tool
    whatever the priors (studies/compliance_identifiability.py; 1,000
    poses take a quarter to 40 % off, a tenth of the noise two thirds).
    The fit writes the MAP under the tolerance prior, and the diagnosis
    reports that uncertainty and the parameters that trade off
    (:mod:`bayescal.diagnose.confound`, :meth:`confound_note`); stating the
    mass, centre of mass and mounting (below) pins it to a few um.  The
    fit starts ``platform_mass`` at the stated mass, else 30 kg (weight
    deflections at 0.5 um/N under 30 kg): at zero the bilinear load has no
    gradient and Gauss-Newton stalls (:attr:`EffectParam.start`).

    Inputs with documented defaults (constructor arguments,
    :attr:`settings_keys`; proposed machine-file keys of the same names in
    the ``[effect.joint_compliance]`` table): ``gravity`` (default ``[0, 0,
    -1]``, ``d0`` in the base frame, an upright machine; give the mounting's
    direction for machines mounted on a wall or tilted), ``payload_offset``
    (default ``[0, 0, 0]`` mm, platform frame, the payload's centre of mass
    from the tool point: a spindle's tool hangs at the tool point),
    ``platform_mass_kg`` and ``platform_com_mm`` (default unknown).  Hidden
    assumptions: only the drives yield (links, joints and frame rigid; their
    compliance shows as apparent drive compliance to first order); small
    deflections (the load is evaluated at the undeflected pose: the
    second-order change of the load with the deflection is below 1e-3 of
    it for deflections under 0.1 % of the mechanism's size); on a
    redundantly actuated machine the load is shared among the drives in a
    statically indeterminate way, and the model puts it on the drives its
    forward kinematics reads.  Usual size on machine tools: ball-screw
    drives 0.002-0.02 um/N (50-500 N/um axial stiffness); with links,
    spherical joints and a lightweight frame the apparent compliance at the
    actuator reaches 0.05-1 um/N; platforms of 10-200 kg.  Revolute
    drives: robot and positioner joints 1-10 urad/(N m) (stiffness 1e5-1e6
    N m/rad), harmonic-drive wrists 10-100 urad/(N m).

    **Known loads: link weights.**  On a serial chain the links between the
    drives (an arm's upper arm and forearm, a positioner's turntable housing)
    weigh too, and load every drive nearer the base; on an arm they dominate
    the shoulder and elbow torques.  The machine's weight bodies
    (:meth:`Machine.weight_bodies`: on a serial chain link ``k`` in the frame
    after joint ``k``; on other kinds the platform alone) carry them.  When
    their masses are known, from the inputs ``link_mass_kg`` (kg, one per
    body, base outward) and ``link_com_mm`` (mm, ``[[x, y, z], ...]``, each
    in its body's frame from its origin; default: at the origins), or else
    from the machine file (a URDF's ``<inertial>`` elements,
    :attr:`Machine.body_inertials`), the gravity load on every drive is
    computed exactly from all bodies and the payload,

        tau_i = g d . (sum_b m_b dx_b / dq_i) + m_L g d . (dx_t / dq_i),
        dx_b / dq_i = v_b,i + w_b,i x (R_b c_b),    dq_i = c_i tau_i,

    and the parameters are ``compliance.q<i>`` (um/N or urad/(N m), as
    above, starting at 0.5 um/N, 50 urad/(N m)), ``mass.<body>`` (kg,
    ``>= 0``, prior ``0 +- 100``, started at 20 kg) for every body whose
    stated mass is ``nan`` (not known: fitted, at the link's middle on a
    serial chain unless ``link_com_mm`` places it) and ``gravity.tilt_1``,
    ``gravity.tilt_2``, with or without a payload channel: the known loads
    fix the compliances.  The last body is then the platform (its mass the
    last entry of ``link_mass_kg``), so ``platform_mass_kg`` and
    ``platform_com_mm`` are not stated with it.  Without known masses the
    model is the platform-and-payload one above, and on a chain of several
    links the trial's note says that the link weights are left out: their
    loads then show as biased compliances and weight deflections.
    """

    name = "joint_compliance"
    summary = "actuators yield under the gravity load of platform (unknown mass and centre of mass) and payload (payload_kg)"
    magnitude_unit = "um/N"  # urad/(N m) on a revolute drive (the parameter's own unit)
    default_magnitude = 0.5
    needs_poses = True
    settings_keys = ("gravity", "payload_offset", "platform_mass_kg", "platform_com_mm", "link_mass_kg", "link_com_mm")

    #: Prior one-sigma of a weight deflection (um), a compliance (um/N), the platform mass (kg), a
    #: centre-of-mass coordinate (mm), a gravity tilt; on a revolute drive the first two times
    #: :func:`compliance_prior_scale` (urad/m, urad/(N m)).
    WEIGHT_PRIOR_UM = 300.0
    COMPLIANCE_PRIOR = 1.0
    MASS_PRIOR_KG = 100.0
    COM_PRIOR_MM = 200.0
    TILT_PRIOR = 0.5
    #: Where the fit starts a link mass stated unknown (nan in ``link_mass_kg``), kg.
    LINK_MASS_START_KG = 20.0

    def __init__(self, *, gravity=None, payload_offset=(0.0, 0.0, 0.0), platform_mass_kg: float | None = None,
                 platform_com_mm=None, link_mass_kg=None, link_com_mm=None):
        """
        Parameters
        ----------
        gravity : (3,), optional
            Gravity direction ``d0`` in the base frame (normalised).  None
            (default): ``[0, 0, -1]``, an upright mounting, assumed to within
            the tilt prior ``0 +- 0.5``; stated: known to ``0 +- 0.02``.
        payload_offset : (3,)
            Payload's centre of mass from the tool point, platform frame, mm.
        platform_mass_kg : float, optional
            Stated mass of the platform (and everything that moves with it
            but the payload), kg: the prior of ``platform_mass`` is then
            centred on it with a 2 % width.  None (default): unknown, prior
            ``0 +- 100 kg``.  Simulation uses it (30 kg when None).
        platform_com_mm : (3,), optional
            Stated centre of mass of the platform (platform frame, from its
            origin), mm: prior centred on it, 5 mm wide.  None (default):
            unknown, prior ``0 +- 200 mm``.
        link_mass_kg : (n_bodies,), optional
            Stated mass of every weight body of the machine
            (:meth:`Machine.weight_bodies`: a serial chain's links base
            outward, the last one carrying the tool), kg.  None (default):
            the machine file's (a URDF's ``<inertial>``), else unknown (the
            platform-only model).
        link_com_mm : (n_bodies, 3) or (3 n_bodies,), optional
            Their centres of mass, each in its body's frame from its origin,
            mm; only with ``link_mass_kg``.  None (default): at the origins.
        """
        self.gravity_stated = gravity is not None
        self.down = _unit(DEFAULT_GRAVITY_DIRECTION if gravity is None else gravity, "joint_compliance gravity")
        if platform_com_mm is None:
            self.stated_com = None
        else:
            com = np.asarray(platform_com_mm, float).reshape(-1)
            if com.shape != (3,) or not np.all(np.isfinite(com)):
                raise InputError(f"joint_compliance platform_com_mm: expected a 3-vector in mm, got {com.tolist()}")
            self.stated_com = com
        off = np.asarray(payload_offset, float).reshape(-1)
        if off.shape != (3,) or not np.all(np.isfinite(off)):
            raise InputError(f"joint_compliance payload_offset: expected a 3-vector in mm, got {off.tolist()}")
        self.payload_offset = off
        if platform_mass_kg is not None and not (np.isfinite(platform_mass_kg) and platform_mass_kg > 0):
            raise InputError(f"joint_compliance platform_mass_kg: expected a positive mass in kg, got {platform_mass_kg!r}")
        self.stated_mass_kg = None if platform_mass_kg is None else float(platform_mass_kg)
        self.platform_mass_kg = 30.0 if platform_mass_kg is None else float(platform_mass_kg)
        self.link_mass, self.link_com = None, None
        if link_mass_kg is None:
            if link_com_mm is not None:
                raise InputError("joint_compliance link_com_mm: given without link_mass_kg; state the links' masses too")
            return
        mass = np.asarray(link_mass_kg, float).reshape(-1)
        # NaN: a mass not known, fitted (mass.<body>); the others >= 0 and, with none unknown, not all zero
        known = ~np.isnan(mass)
        if (not mass.size or np.any(np.isinf(mass)) or np.any(mass[known] < 0)
                or not (np.any(mass[known] > 0) or np.any(~known))):
            raise InputError(f"joint_compliance link_mass_kg: expected masses in kg, >= 0 (nan: unknown, fitted) and not "
                             f"all zero, got {mass.tolist()}")
        if platform_mass_kg is not None or platform_com_mm is not None:
            raise InputError("joint_compliance: link_mass_kg and platform_mass_kg/platform_com_mm both given; with link masses "
                             "the last body is the platform: give its mass and centre of mass as the last entries of "
                             "link_mass_kg and link_com_mm")
        self.link_com_stated = link_com_mm is not None
        com = np.zeros((mass.size, 3)) if link_com_mm is None else np.asarray(link_com_mm, float)
        if com.size != 3 * mass.size or not np.all(np.isfinite(com)):
            raise InputError(f"joint_compliance link_com_mm: expected {mass.size} centres of mass [x, y, z] in mm "
                             f"(one per entry of link_mass_kg), got {np.asarray(link_com_mm).tolist()}")
        self.link_mass, self.link_com = mass, com.reshape(-1, 3)

    def known_inertials(self, machine: Machine) -> tuple[NDArray, NDArray, str] | None:
        """Masses (kg), centres of mass (mm) of the machine's weight bodies and where they come from, or None (unknown).

        Stated ``link_mass_kg`` first, else the machine file's
        (:attr:`Machine.body_inertials`).  InputError when their number is
        not the machine's number of weight bodies, or when platform inputs
        are stated beside masses from the machine file.
        """
        names = machine.weight_body_names
        if self.link_mass is not None:
            mass, com, src = self.link_mass, self.link_com, "link_mass_kg, link_com_mm stated"
        else:
            known = machine.body_inertials
            if known is None:
                return None
            if self.stated_mass_kg is not None or self.stated_com is not None:
                raise InputError(f"joint_compliance: platform_mass_kg/platform_com_mm stated, but {known.source} gives every "
                                 "moving link's mass (the last link is the platform); state link_mass_kg and link_com_mm instead")
            mass, com, src = np.asarray(known.mass_kg, float), np.asarray(known.com_mm, float), known.source
        if mass.size != len(names):
            raise InputError(f"joint_compliance link_mass_kg: {mass.size} masses for the {len(names)} weight bodies of this "
                             f"{machine.kind} machine ({', '.join(names)}); expected one per body, base outward")
        return mass, com, src

    def implied_settings(self, machine: Machine) -> dict:
        """The link masses the machine file gives (a URDF's), as inputs, so that a file written without the URDF keeps them."""
        if self.link_mass is not None or machine.body_inertials is None:
            return {}
        known = machine.body_inertials
        return {"link_mass_kg": np.asarray(known.mass_kg, float).tolist(), "link_com_mm": np.asarray(known.com_mm, float).tolist()}

    def model_note(self, features: Features) -> str:
        """Which loads the model has (the links' and from where, or the platform's only) and where gravity comes from."""
        note = self._load_note(features)
        if features.const.get("sensor"):
            note = "; ".join(filter(None, [note, "gravity per pose from the base sensor (accel.base.*)"]))
        return note

    @staticmethod
    def _load_note(features: Features) -> str:
        if features.const.get("known") and features.const.get("fitted_bodies"):
            return (f"gravity loads of all {features.const['n_bodies']} weight bodies ({features.const['source']}); "
                    f"masses fitted for {', '.join(features.const['fitted_bodies'])} (stated unknown)")
        if features.const.get("known"):
            return f"gravity loads of all {features.const['n_bodies']} weight bodies known ({features.const['source']})"
        if features.const.get("n_bodies", 1) > 1:
            return ("link weights left out (only the last body's weight and the payload load the drives): state "
                    "link_mass_kg and link_com_mm, or give a URDF with <inertial> elements")
        return ""

    def separating_conditions(self, aux: dict) -> tuple:
        """A heavier payload (a known load), and the mounting tilted either way (gravity turned against the machine)."""
        return (second_payload(aux), tilted_mounting(self.down, 0), tilted_mounting(self.down, 1))

    def confound_note(self) -> str:
        """The constant sag is a zero offset; which inputs, stated, would pin it."""
        head = ("joint_compliance: the pose-independent part of the sag is exactly an actuator zero offset "
                "(rail_origin along the rail); the data fix it only through the sag's pose-dependent part")
        if self.link_mass is not None:
            return head + " and the stated link masses (link_mass_kg, link_com_mm), which fix every load."
        unstated = [k for k, v in (("platform_mass_kg", self.stated_mass_kg), ("platform_com_mm", self.stated_com),
                                   ("gravity", self.gravity_stated or None)) if v is None]
        if not unstated:
            return head + " and the stated platform_mass_kg, platform_com_mm and gravity (to 2 %, 5 mm and 0.02)."
        return (head + f". Stating {', '.join(unstated)} (inputs of [effect.joint_compliance], diagnose "
                "--effect-input joint_compliance.KEY=VALUE) pins it; on a chain of moving links, link_mass_kg and "
                "link_com_mm (or a URDF with <inertial> elements) state every load.")

    def features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, order, poses: ToolPoses | None) -> Features:
        if poses is None:
            poses = machine.forward(q, theta)
        known = self.known_inertials(machine)
        if known is not None:
            return self._known_features(machine, q, theta, aux, poses, known)
        n = q.shape[0]
        J = machine.actuator_jacobian(q, theta, poses)
        R = np.asarray(poses.rotation, float)
        # the payload point and the platform origin, as offsets from the tool point (base frame, mm)
        payload_arm = np.einsum("nij,j->ni", R, self.payload_offset)
        origin_arm = _platform_origin(poses) - poses.position
        # the payload compliances are parameters whenever the channel is recorded (also at a constant
        # payload: then weakly determined, at their prior if it is zero), so that the parameter set
        # depends only on which channels a recording has, as machine-file effect tables need
        has_payload = "payload_kg" in aux
        down, sensor = gravity_per_pose(aux, self.down, q.shape[0])  # a base sensor gives each pose its own
        mass = np.asarray(aux["payload_kg"], float) if has_payload else np.zeros(n)
        # q units per (compliance unit x N mm per q unit): 1e-3 (um/N x N -> mm), 1e-9 (urad/(N m) x N mm -> rad)
        units = machine.actuator_unit_info
        scale = np.array([u.small_to_q * u.load_scale for u in units])
        # a load per unit weight (mm/mm, or mm/rad: the lever arm) as the equivalent force at the reference arm
        # 1 / per_um m (100 mm on a joint): what "no gravity load" compares with
        arm = np.array([u.load_scale * u.per_um for u in units])
        return Features(
            {"Jt": J[:, :3], "w": J[:, 3:], "R": R, "origin_arm": origin_arm, "payload_arm": payload_arm, "payload_kg": mass,
             "down": down},
            {"down": self.down, "basis": tilt_basis(self.down), "sensor": sensor, "has_payload": has_payload, "scale": scale, "arm": arm, "known": False,
             "n_bodies": len(machine.weight_body_names)},
        )

    def _known_features(self, machine: Machine, q: NDArray, theta: NDArray, aux: dict, poses: ToolPoses, known) -> Features:
        """Features of the known-load model: ``K_i = sum_b m_b dx_b / dq_i`` (kg mm per q unit) and the payload's lever."""
        mass, com, source = known
        # gravity acts in the machine's base frame: a view with nuisance parameters (an instrument frame) is
        # evaluated on the machine it wraps
        inner, idx = machine.geometry_part
        if inner is not machine:
            theta = np.asarray(theta, float)[..., idx]
            poses = inner.forward(q, theta)
        wb = inner.weight_bodies(q, theta, poses)
        Rc = np.einsum("nbij,bj->nbi", wb.rotation, com)
        Jx = wb.jacobian[:, :, :3] + np.cross(wb.jacobian[:, :, 3:], Rc[:, :, :, None], axisa=2, axisb=2, axisc=2)
        unknown = np.flatnonzero(np.isnan(mass))  # stated as nan: fitted, mass.<body>
        if unknown.size and not getattr(self, "link_com_stated", True):
            # an unknown link's weight sits at its middle unless its centre of mass is stated
            chain, _ = serial_part(inner, None)
            if chain is not None:
                com = np.array(com, float)
                com[unknown] = link_middles(chain)[unknown]
                Rc = np.einsum("nbij,bj->nbi", wb.rotation, com)
                Jx = wb.jacobian[:, :, :3] + np.cross(wb.jacobian[:, :, 3:], Rc[:, :, :, None], axisa=2, axisb=2, axisc=2)
        K = np.einsum("b,nbkm->nkm", np.nan_to_num(mass), Jx)
        J = inner.actuator_jacobian(q, theta, poses)
        payload_arm = np.einsum("nij,j->ni", np.asarray(poses.rotation, float), self.payload_offset)
        has_payload = "payload_kg" in aux
        down, sensor = gravity_per_pose(aux, self.down, q.shape[0])  # a base sensor gives each pose its own
        n = q.shape[0]
        units = machine.actuator_unit_info
        return Features(
            {"K": K, "Jt": J[:, :3], "w": J[:, 3:], "payload_arm": payload_arm,
             "payload_kg": np.asarray(aux["payload_kg"], float) if has_payload else np.zeros(n), "down": down,
             "Rb": Jx[:, unknown]},
            {"down": self.down, "basis": tilt_basis(self.down), "sensor": sensor, "has_payload": has_payload, "known": True,
             "total_mass": float(np.nansum(mass)) + self.LINK_MASS_START_KG * unknown.size,
             "fitted_bodies": tuple(machine.weight_body_names[b] for b in unknown),
             "scale": np.array([u.small_to_q * u.load_scale for u in units]),
             "arm": np.array([u.load_scale * u.per_um for u in units]), "n_bodies": len(mass), "source": source},
        )

    def params(self, machine: Machine, features: Features) -> tuple[EffectParam, ...]:
        units = machine.actuator_unit_info
        # a stated direction, or a base sensor's per pose, is known to within the mounting's small tilt
        tilt_sd = 0.02 if (self.gravity_stated or (features is not None and features.const.get("sensor"))) else self.TILT_PRIOR
        if features is not None and features.const.get("known"):
            # the loads are known: the compliances (started off zero, where the tilts have no gradient), the masses
            # stated unknown (nan; started off zero too) and the mounting
            return tuple(
                [EffectParam(f"compliance.q{i + 1}", u.compliance, self.COMPLIANCE_PRIOR * compliance_prior_scale(u), lower=0.0,
                             start=self.default_magnitude * compliance_prior_scale(u)) for i, u in enumerate(units)]
                + [EffectParam(f"mass.{b}", "kg", self.MASS_PRIOR_KG, lower=0.0, start=self.LINK_MASS_START_KG)
                   for b in features.const["fitted_bodies"]]
                + [EffectParam(f"gravity.tilt_{k}", "rad", tilt_sd) for k in (1, 2)])
        if features is not None and features.const["has_payload"]:
            out = [EffectParam(f"compliance.q{i + 1}", u.compliance, self.COMPLIANCE_PRIOR * compliance_prior_scale(u), lower=0.0)
                   for i, u in enumerate(units)]
            # the mass starts at a typical platform's (the stated one, else 30 kg), not at zero: there the
            # platform's load c_i m_p g has no gradient in c_i nor m_p, and Gauss-Newton crawls out of that
            # saddle for tens of iterations or stops in it (studies/compliance_identifiability.py, docs/diagnose.md)
            if self.stated_mass_kg is None:
                out.append(EffectParam("platform_mass", "kg", self.MASS_PRIOR_KG, lower=0.0, start=self.platform_mass_kg))
            else:
                out.append(EffectParam("platform_mass", "kg", 0.02 * self.stated_mass_kg, prior_mean=self.stated_mass_kg,
                                       lower=0.0, start=self.stated_mass_kg))
        else:
            # likewise the weight deflections start at 0.5 um/N under 30 kg: at zero the centre of mass and
            # the tilt have no gradient
            start = self.default_magnitude * self.platform_mass_kg * GRAVITY
            out = [EffectParam(f"weight_deflection.q{i + 1}", u.weight, self.WEIGHT_PRIOR_UM * compliance_prior_scale(u), lower=0.0,
                               start=start * compliance_prior_scale(u))
                   for i, u in enumerate(units)]
        if self.stated_com is None:
            out += [EffectParam(f"com.{x}", "mm", self.COM_PRIOR_MM) for x in "xyz"]
        else:
            out += [EffectParam(f"com.{x}", "mm", 5.0, prior_mean=float(v)) for x, v in zip("xyz", self.stated_com)]
        out += [EffectParam(f"gravity.tilt_{k}", "rad", tilt_sd) for k in (1, 2)]
        return tuple(out)

    # the pieces of the model, per pose and actuator (see the class docstring)
    def _terms(self, features: Features, eta: NDArray):
        eta = np.asarray(eta, float)
        Jt, w, R = features.per_pose["Jt"], features.per_pose["w"], features.per_pose["R"]
        m = Jt.shape[2]
        if features.const["has_payload"]:
            c, mp = eta[:m], eta[m]
            W = c * mp * GRAVITY  # weight deflections c_i m_p g, um (urad/m)
            k = m + 1
        else:
            c, mp = np.zeros(m), 0.0
            W = eta[:m]
            k = m
        com = eta[k : k + 3]
        d, dd = self._gravity(features, eta[k + 3 : k + 5])
        arm_c = features.per_pose["origin_arm"] + np.einsum("nij,j->ni", R, com)  # x_c - x_t
        Jc = Jt + np.cross(w, arm_c[:, :, None], axisa=1, axisb=1, axisc=1)  # (n, 3, m): d x_c / d q
        Jl = Jt + np.cross(w, features.per_pose["payload_arm"][:, :, None], axisa=1, axisb=1, axisc=1)
        phi = np.einsum("nk,nkm->nm", d, Jc)  # (n, m)
        psi = np.einsum("nk,nkm->nm", d, Jl)
        load = GRAVITY * features.per_pose["payload_kg"]  # N
        return k, W, c, mp, d, dd, Jc, Jl, phi, psi, load

    @staticmethod
    def _gravity(features: Features, tilt: NDArray) -> tuple[NDArray, NDArray]:
        """Each pose's gravity direction (n, 3) at the tilts, and its derivative (n, 3, 2)."""
        return tilted_gravity(features.per_pose["down"], features.const["basis"], tilt)

    def _known_terms(self, features: Features, eta: NDArray):
        eta = np.asarray(eta, float)
        K, Jt, w = features.per_pose["K"], features.per_pose["Jt"], features.per_pose["w"]
        m = K.shape[2]
        F = len(features.const["fitted_bodies"])
        c = eta[:m]
        if F:
            K = K + np.einsum("f,nfkm->nkm", eta[m : m + F], features.per_pose["Rb"])
        d, dd = self._gravity(features, eta[m + F : m + F + 2])
        Jl = Jt + np.cross(w, features.per_pose["payload_arm"][:, :, None], axisa=1, axisb=1, axisc=1)
        load = GRAVITY * features.per_pose["payload_kg"]  # N
        # generalised gravity force per drive, N mm per q unit: links and platform, then the payload
        tau = GRAVITY * np.einsum("nk,nkm->nm", d, K) + load[:, None] * np.einsum("nk,nkm->nm", d, Jl)
        dtau = GRAVITY * np.einsum("nkt,nkm->nmt", dd, K) + load[:, None, None] * np.einsum("nkt,nkm->nmt", dd, Jl)
        return m, c, tau, dtau

    def delta_q(self, features: Features, eta: NDArray) -> NDArray:
        if features.const.get("known"):
            _, c, tau, _ = self._known_terms(features, eta)
            return features.const["scale"][None, :] * c[None, :] * tau
        _, W, c, _, _, _, _, _, phi, psi, load = self._terms(features, eta)
        return features.const["scale"][None, :] * (W[None, :] * phi + c[None, :] * load[:, None] * psi)

    def delta_q_jacobian(self, features: Features, eta: NDArray) -> NDArray:
        if features.const.get("known"):
            m, c, tau, dtau = self._known_terms(features, eta)
            F = len(features.const["fitted_bodies"])
            s = features.const["scale"]
            J = np.zeros((tau.shape[0], m, m + F + 2))
            ar = np.arange(m)
            J[:, ar, ar] = s[None, :] * tau
            if F:
                d, _ = self._gravity(features, np.asarray(eta, float)[m + F : m + F + 2])
                J[:, :, m : m + F] = (s * c)[None, :, None] * GRAVITY * np.einsum("nk,nfkm->nmf", d, features.per_pose["Rb"])
            J[:, :, m + F :] = (s * c)[None, :, None] * dtau
            return J
        k, W, c, mp, d, dd, Jc, Jl, phi, psi, load = self._terms(features, eta)
        n, m = phi.shape
        J = np.zeros((n, m, len(np.asarray(eta))))
        ar = np.arange(m)
        s = features.const["scale"]
        if features.const["has_payload"]:
            J[:, ar, ar] = s[None, :] * (mp * GRAVITY * phi + load[:, None] * psi)
            J[:, :, m] = s[None, :] * c[None, :] * GRAVITY * phi
        else:
            J[:, ar, ar] = s[None, :] * phi
        # d phi_i / d com = R^T (d x omega_i): d . (omega x R c) = c . R^T (d x omega)
        dxw = np.cross(d[:, :, None], features.per_pose["w"], axisa=1, axisb=1, axisc=1)  # (n, 3, m)
        J[:, :, k : k + 3] = (s * W)[None, :, None] * np.einsum("nji,njm->nmi", features.per_pose["R"], dxw)
        dphi = np.einsum("nkt,nkm->nmt", dd, Jc)  # (n, m, 2)
        dpsi = np.einsum("nkt,nkm->nmt", dd, Jl)
        J[:, :, k + 3 : k + 5] = s[None, :, None] * (W[None, :, None] * dphi + (c[None, :] * load[:, None])[:, :, None] * dpsi)
        return J

    def inadmissible(self, features: Features, eta: NDArray | None = None) -> str | None:
        # e.g. the RU-PUS-PRS: its platform origin is the centre of the passive post's universal joint, so
        # a weight there loads only the post; with a centre of mass off it the drives would carry its moment,
        # but that load is bilinear in the deflections and the offset and vanishes at the prior (no start
        # for the fit).  Compare the dimensionless loads (actuator force per unit of weight; on a joint its
        # torque per unit of weight over the reference arm, 100 mm) with 1e-3.
        m = features.per_pose["Jt"].shape[2]
        if features.const.get("known"):
            # the loads per unit of the bodies' total weight (their lever arms), against the same 1e-3
            F = len(features.const["fitted_bodies"])
            tau = self._known_terms(features, np.concatenate([np.ones(m), np.full(F, self.LINK_MASS_START_KG), np.zeros(2)]))[2]
            lever = tau * features.const["arm"][None, :] / (GRAVITY * features.const["total_mass"])
            mass = features.per_pose["payload_kg"]
            if lever.size and np.max(np.abs(lever)) <= 1e-3 and not (mass.size and np.ptp(mass) > 0):
                return "the actuators carry no gravity load at any pose (under 0.1 % of the bodies' weight) and no changing payload_kg is recorded"
            return None
        zero = np.zeros(m + 5 + (1 if features.const["has_payload"] else 0))
        phi, psi = self._terms(features, zero)[8:10]
        arm = features.const["arm"][None, :]
        phi, psi = phi * arm, psi * arm
        mass = features.per_pose["payload_kg"]
        payload = bool(mass.size and np.ptp(mass) > 0 and psi.size and np.max(np.abs(psi)) > 1e-3)
        if phi.size and np.max(np.abs(phi)) <= 1e-3 and not payload:
            return ("the actuators carry no gravity load at any pose (under 0.1 % of the weight at the platform origin, "
                    "or of its torque at 100 mm on a revolute joint: it acts at a passive joint or on the joint's axis) "
                    "and no changing payload_kg is recorded")
        return None

    def simulated_values(self, machine: Machine, features: Features, magnitude: float, rng) -> NDArray:
        """Compliances ``magnitude`` (um/N, urad/(N m) on a revolute drive; +-40 %) under the platform mass and centre of mass of the constructor, no tilt."""
        m = machine.n_actuators
        c = magnitude * rng.uniform(0.6, 1.4, m)
        if features.const.get("known"):
            F = len(features.const["fitted_bodies"])
            return np.concatenate([c, self.LINK_MASS_START_KG * rng.uniform(0.5, 1.5, F), np.zeros(2)])
        com = np.zeros(3) if self.stated_com is None else self.stated_com
        if features.const["has_payload"]:
            out = [c, [self.platform_mass_kg], com, np.zeros(2)]
        else:
            out = [c * self.platform_mass_kg * GRAVITY, com, np.zeros(2)]
        return np.concatenate(out)
