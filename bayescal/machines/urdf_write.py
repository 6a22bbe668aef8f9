"""A calibrated serial chain written as a URDF file (``bayescal identify --write-urdf``).

The URDF holds the chain's kinematics as calibrated, in URDF's units (metres,
radians), so that ROS tools, simulators and yourdfpy predict what bayescal
predicts:

* links ``base_link``, ``link1`` ... ``link<m>`` (link ``k`` is the frame after
  joint ``k``, as :attr:`Serial.weight_body_names` names it) and ``tool``;
* one joint per ``[[joint]]`` (its name kept when the machine has names, e.g.
  from a URDF; ``joint<i>`` otherwise), ``revolute`` or ``prismatic``, with the
  calibrated ``origin`` (zero offsets folded in: a revolute joint's origin
  rotated by ``Rot(axis, offset)``, a prismatic joint's translated by
  ``offset * axis``) and the calibrated unit ``axis``;
* mimic joints as ``<mimic joint=... multiplier=... offset=...>``, converted to
  URDF's units (a prismatic joint's positions in metres);
* the tool point and orientation as a fixed joint ``tool_joint`` to the link ``tool``.

Joint limits are the machine file's ``q_limits`` (a mimic joint's are its
driver's, mapped); a revolute joint without them is written ``continuous``.
URDF requires ``effort`` and ``velocity`` in ``<limit>``; bayescal does not
know them and writes ``0``.  Not written: what a URDF cannot carry or
bayescal does not know: inertias (and so the links' masses), meshes, the
``[effect.*]``, ``[instrument]``, ``[measurement]`` and ``[tolerance]`` tables
(``--write-machine`` keeps those).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from .base import Machine
from .serial import Serial

__all__ = ["serial_part", "urdf_text", "write_calibrated_urdf"]

_MM_PER_M = 1000.0


def serial_part(machine: Machine, theta: ArrayLike | None = None, *, what: str = "a URDF") -> tuple[Serial, NDArray]:
    """The serial chain under any views (instrument frame, effect parameters) and its part of ``theta``.

    Parameters
    ----------
    machine : Machine
        A serial machine, possibly in an instrument frame or with effects.
    theta : array_like, shape (P,), optional
        ``machine``'s parameters (mm, rad); zeros if omitted.
    what : str
        Named in the error for another kind.

    Raises
    ------
    InputError
        When the geometry is not a serial chain (a URDF describes a tree of
        joints, not a parallel mechanism or a stack of modules).
    """
    th = machine.check_theta(theta)
    m = machine
    while True:
        inner, idx = m.geometry_part
        if inner is m:
            break
        m, th = inner, th[idx]
    if m.serial_chain is None:
        raise InputError(f"{what} describes a serial chain; {m.source} is a {m.kind} machine (kind = \"serial\" only)")
    return m, th


def _fmt(v) -> str:
    """Numbers at full precision (repr round-trips a double), space-separated; -0.0 written 0.0."""
    return " ".join(repr(float(x) + 0.0) for x in np.atleast_1d(v))


def _scale(joint_type: str) -> float:
    """mm (bayescal) per URDF unit of a joint's position."""
    return _MM_PER_M if joint_type == "prismatic" else 1.0


def _unique(name: str, taken: set) -> str:
    out, k = name, 1
    while out in taken:
        k += 1
        out = f"{name}_{k}"
    taken.add(out)
    return out


def _limits(chain: Serial, i: int) -> tuple[float, float] | None:
    """Joint ``i``'s limits in bayescal units: its actuator's ``q_limits`` row, or its driver's mapped (mimic)."""
    if chain.q_limits is None:
        return None
    drive = i if chain.mimic[i] is None else chain.mimic[i][0]
    lo, hi = chain.q_limits[chain.actuated_joints.index(drive)]
    if chain.mimic[i] is None:
        return float(lo), float(hi)
    _, k, o = chain.mimic[i]
    a, b = k * lo + o, k * hi + o
    return float(min(a, b)), float(max(a, b))


def urdf_text(machine: Machine, theta: ArrayLike | None = None) -> str:
    """The URDF (XML text) of the serial chain ``nominal + theta``, in metres and radians.

    Parameters
    ----------
    machine : Machine
        A serial machine (possibly in an instrument frame or with effects, which
        are not written).
    theta : array_like, shape (P,), optional
        Geometric errors of ``machine`` to fold in (mm, rad); zeros if omitted.

    Returns
    -------
    str
        A URDF whose forward kinematics from ``base_link`` to ``tool`` is the
        chain's tool frame, for actuator positions in URDF units (prismatic in m).

    Raises
    ------
    InputError
        For a machine that is not a serial chain.
    """
    chain, th = serial_part(machine, theta)
    g = chain.geometry_arrays(th)
    names = chain.joint_names or tuple(f"joint{i + 1}" for i in range(chain.n_joints))
    robot = ET.Element("robot", name=chain.name)
    robot.append(ET.Comment(f" written by bayescal from {chain.source}: the calibrated kinematics (metres, radians); "
                            "no inertias, meshes or effects "))
    ET.SubElement(robot, "link", name="base_link")
    parent = "base_link"
    for i, jt in enumerate(chain.joint_type):
        lim = _limits(chain, i)
        kind = "continuous" if jt == "revolute" and lim is None else jt
        joint = ET.SubElement(robot, "joint", name=names[i], type=kind)
        ET.SubElement(joint, "parent", link=parent)
        ET.SubElement(joint, "child", link=f"link{i + 1}")
        ET.SubElement(joint, "origin", xyz=_fmt(g["origin"][i] / _MM_PER_M), rpy=_fmt(g["rpy"][i]))
        ET.SubElement(joint, "axis", xyz=_fmt(g["axis"][i]))
        if kind != "continuous":
            attrs = {"effort": "0", "velocity": "0"}  # required by URDF; unknown to bayescal
            if lim is not None:
                attrs |= {"lower": _fmt(lim[0] / _scale(jt)), "upper": _fmt(lim[1] / _scale(jt))}
            ET.SubElement(joint, "limit", attrs)
        if chain.mimic[i] is not None:
            d, k, o = chain.mimic[i]
            # q_i[urdf] = k (S_d / S_i) q_d[urdf] + o / S_i, with S the mm per URDF unit
            ET.SubElement(joint, "mimic", joint=names[d], multiplier=_fmt(k * _scale(chain.joint_type[d]) / _scale(jt)),
                          offset=_fmt(o / _scale(jt)))
        ET.SubElement(robot, "link", name=f"link{i + 1}")
        parent = f"link{i + 1}"
    tool = ET.SubElement(robot, "joint", name=_unique("tool_joint", set(names)), type="fixed")
    ET.SubElement(tool, "parent", link=parent)
    ET.SubElement(tool, "child", link="tool")
    ET.SubElement(tool, "origin", xyz=_fmt(g["tool_point"] / _MM_PER_M), rpy=_fmt(g["tool_rpy"]))
    ET.SubElement(robot, "link", name="tool")
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def write_calibrated_urdf(path, machine: Machine, theta: ArrayLike | None = None) -> Path:
    """Write :func:`urdf_text` of ``nominal + theta`` to ``path`` atomically (temporary file and rename).

    Parameters
    ----------
    path : path
        The URDF file to write.
    machine : Machine
        A serial machine (possibly in an instrument frame or with effects).
    theta : array_like, shape (P,), optional
        Geometric errors (mm, rad), e.g. ``IdentificationResult.theta``; zeros if omitted.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    InputError
        For a machine that is not a serial chain; nothing is written then.
    """
    from ..io.answers import write_text_atomic

    return write_text_atomic(path, urdf_text(machine, theta))
