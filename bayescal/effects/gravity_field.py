"""Gravity per pose and the weights a serial chain carries: what the gravity-driven effects share.

* The gravity direction of each pose: the effect's ``gravity`` input (a base-frame
  direction, ``[0, 0, -1]`` by default) or, when the recording has a base
  sensor (columns ``accel.base.x``, ``.y``, ``.z``, docs/formats.md section 8), the
  sensor's reading at that pose.  Only the direction is used.  An
  accelerometer at rest reads the specific force, which points *up*; a sensor
  whose readings point away from the stated direction on most poses is
  therefore read with the opposite sign.  The sensor's axes are taken as the
  base frame's up to the small mounting tilt the effects fit
  (``gravity.tilt_1``, ``gravity.tilt_2``).
* The masses and centres of mass of a serial chain's links: stated
  (``link_mass_kg``, ``link_com_mm``), else the machine file's (a URDF's
  ``<inertial>``), else unknown; unknown masses sit at the links' middles
  (half-way from the link frame's origin to the next joint, or to the tool
  point on the last link).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..machines.base import Machine

__all__ = ["BASE_SENSOR", "gravity_per_pose", "sensor_bodies", "tilt_basis", "tilted_gravity", "serial_part", "chain_masses",
           "link_middles", "check_masses"]

#: The recording columns of a base tilt sensor (docs/formats.md section 8).
BASE_SENSOR = ("accel.base.x", "accel.base.y", "accel.base.z")


def gravity_per_pose(aux: dict, down0: NDArray, n: int) -> tuple[NDArray, bool]:
    """The gravity direction of every pose, (n, 3), and whether it comes from a base sensor.

    Parameters
    ----------
    aux : dict of str to ndarray
        The recording's channels; ``accel.base.x/y/z`` give each pose its own direction.
    down0 : ndarray, shape (3,)
        The stated (or default) unit direction, base frame.
    n : int
        Number of poses.

    Raises
    ------
    InputError
        Some but not all of the three sensor columns, or a reading of zero length.
    """
    have = [c for c in BASE_SENSOR if c in aux]
    if not have:
        return np.broadcast_to(down0, (n, 3)).copy(), False
    if len(have) < 3:
        missing = [c for c in BASE_SENSOR if c not in aux]
        raise InputError(f"base tilt sensor: column(s) {', '.join(missing)} missing beside {', '.join(have)}; expected all three")
    v = np.column_stack([np.asarray(aux[c], float) for c in BASE_SENSOR])
    norm = np.linalg.norm(v, axis=1)
    bad = np.flatnonzero(~(np.isfinite(norm) & (norm > 0)))
    if bad.size:
        raise InputError(f"base tilt sensor: pose {bad[0] + 1} reads {v[bad[0]].tolist()}; expected a non-zero vector")
    d = v / norm[:, None]
    # an accelerometer at rest reads the specific force (up); the columns may hold either convention
    if np.median(d @ down0) < 0:
        d = -d
    return d, True


def tilt_basis(down: NDArray) -> NDArray:
    """Two unit vectors normal to ``down`` (3,): the base axes it is most perpendicular to, orthogonalised, (2, 3)."""
    keep = [i for i in range(3) if i != int(np.argmax(np.abs(down)))]
    out: list[NDArray] = []
    for k in keep:
        e = np.eye(3)[k] - down * down[k]
        for o in out:
            e = e - o * (o @ e)
        out.append(e / np.linalg.norm(e))
    return np.array(out)


def tilted_gravity(down: NDArray, basis: NDArray, tilt: NDArray) -> tuple[NDArray, NDArray]:
    """Per-pose gravity ``d = normalise(down + t_1 e_1 + t_2 e_2)`` and ``d d / d t``.

    Parameters
    ----------
    down : ndarray, shape (n, 3)
        Each pose's unit direction before the tilt.
    basis : ndarray, shape (2, 3)
        ``e_1``, ``e_2`` (:func:`tilt_basis` of the mean direction).
    tilt : ndarray, shape (2,)
        Tangents of the tilt (rad at small angles).

    Returns
    -------
    d : ndarray, shape (n, 3)
    dd : ndarray, shape (n, 3, 2)
    """
    v = down + np.asarray(tilt, float) @ basis
    nv = np.linalg.norm(v, axis=1)
    d = v / nv[:, None]
    dd = (basis.T[None] - d[:, :, None] * (d @ basis.T)[:, None, :]) / nv[:, None, None]
    return d, dd


def serial_part(machine: Machine, theta) -> tuple[object, NDArray | None]:
    """The serial chain whose geometry ``machine`` describes (unwrapping a fitted frame) and its part of ``theta``; (None, None) otherwise."""
    inner, idx = machine.geometry_part
    if inner.serial_chain is None:
        return None, None
    if theta is None:
        return inner, None
    return inner, np.asarray(theta, float)[..., np.asarray(idx)]


def sensor_bodies(chain, aux: dict) -> tuple[str, ...]:
    """The bodies of ``chain`` carrying a tilt sensor in ``aux`` (``accel.<body>.x``; the base apart), channel order."""
    from ..sensors.columns import SENSOR_COLUMN

    out = []
    for key in aux:
        m = SENSOR_COLUMN.fullmatch(key)
        if m and m["axis"] == "x" and m["body"] != "base" and m["body"] in chain.sensor_bodies and m["body"] not in out:
            out.append(m["body"])
    return tuple(out)


def link_middles(chain) -> NDArray:
    """Each link's middle in its own frame, (m, 3), mm: half-way to the next joint's origin (the tool point on the last link)."""
    nxt = np.concatenate([chain.origin[1:], chain.tool_point[None]], axis=0)
    return 0.5 * nxt


def check_masses(mass, com, n_bodies: int, who: str) -> tuple[NDArray, NDArray]:
    """Stated link masses (kg, >= 0, nan: unknown) and centres of mass (mm, default: the link origins) checked against the chain."""
    mass = np.asarray(mass, float).reshape(-1)
    known = ~np.isnan(mass)
    if (not mass.size or np.any(np.isinf(mass)) or np.any(mass[known] < 0)
            or not (np.any(mass[known] > 0) or np.any(~known))):
        raise InputError(f"{who} link_mass_kg: expected masses in kg, >= 0 (nan: unknown, fitted) and not all zero, "
                         f"got {mass.tolist()}")
    com_a = np.zeros((mass.size, 3)) if com is None else np.asarray(com, float)
    if com_a.size != 3 * mass.size or not np.all(np.isfinite(com_a)):
        raise InputError(f"{who} link_com_mm: expected {mass.size} centres of mass [x, y, z] in mm "
                         f"(one per entry of link_mass_kg), got {np.asarray(com).tolist()}")
    if n_bodies is not None and mass.size != n_bodies:
        raise InputError(f"{who} link_mass_kg: {mass.size} masses for the {n_bodies} links of this serial chain; "
                         "expected one per link (every moving joint, mimic joints included), base outward")
    return mass, com_a.reshape(-1, 3)


def chain_masses(machine: Machine, chain, link_mass, link_com, who: str) -> tuple[NDArray | None, NDArray, str]:
    """Masses (kg, or None when unknown), centres of mass (mm, link frames) of a chain's links and where they come from.

    Stated masses first (a ``nan`` entry: that link's mass unknown, its
    centre at the link's middle unless stated), else the machine file's
    (:attr:`Machine.body_inertials`, a URDF's ``<inertial>``), else unknown
    with the centres at the links' middles (:func:`link_middles`).
    """
    m = len(chain.joint_type)
    if link_mass is not None:
        mass, com = check_masses(link_mass, link_com, m, who)
        if link_com is None:
            com[np.isnan(mass)] = link_middles(chain)[np.isnan(mass)]  # an unknown link's weight at its middle
        return mass, com, "link_mass_kg stated" + (" (nan: unknown)" if np.isnan(mass).any() else "")
    known = chain.body_inertials
    if known is not None:
        return np.asarray(known.mass_kg, float), np.asarray(known.com_mm, float).reshape(-1, 3), known.source
    return None, link_middles(chain), "unknown"


def gravity_loads(chain, q: NDArray, theta, mass: NDArray, com: NDArray, down: NDArray, payload_kg: NDArray) -> NDArray:
    """Generalised gravity force on every actuator of a serial chain, by virtual work, shape (n, N).

    ``tau_i = g d . (sum_b m_b dx_b / dq_i + m_L dx_t / dq_i)`` with ``x_b``
    each link's centre of mass, ``x_t`` the tool point (payload), ``d`` each
    pose's gravity direction: positive when gravity pushes ``q_i`` up.  N on
    a slider (``q`` in mm), N mm per rad on a revolute joint (times 1e-3: N m).

    Parameters
    ----------
    chain : Serial
    q : ndarray, shape (n, N)
    theta : ndarray or None
        The chain's geometric errors.
    mass : ndarray, shape (m,)
        kg per link.
    com : ndarray, shape (m, 3)
        mm, link frames.
    down : ndarray, shape (n, 3)
        Unit gravity direction per pose.
    payload_kg : ndarray, shape (n,)
    """
    poses = chain.forward(q, theta)
    wb = chain.weight_bodies(q, theta, poses)
    Rc = np.einsum("nbij,bj->nbi", wb.rotation, com)
    Jx = wb.jacobian[:, :, :3] + np.cross(wb.jacobian[:, :, 3:], Rc[:, :, :, None], axisa=2, axisb=2, axisc=2)
    K = np.einsum("b,nbkm->nkm", mass, Jx) + payload_kg[:, None, None] * chain.actuator_jacobian(q, theta, poses)[:, :3]
    return 9.80665 * np.einsum("nk,nkm->nm", down, K)
