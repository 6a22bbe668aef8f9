"""A serial chain from a URDF file (``urdf``, ``base_link``, ``tip_link`` in a serial machine file).

The file is parsed by ``yourdfpy`` (a maintained URDF parser); this module only
walks the joints between two links and converts them to bayescal's units.

Supported: ``revolute``, ``continuous`` (both revolute actuators, q in rad),
``prismatic`` (q in mm; URDF's metres are converted) and ``fixed`` joints (folded
into the next moving joint's origin and rpy, or into the tool after the last
one).  ``<mimic joint="..." multiplier="..." offset="..."/>`` is honoured: the
joint moves by ``multiplier * q_driver + offset`` and is no actuator (the
multiplier and offset are converted to mm where a prismatic joint is
involved); its driver must be a moving joint of the same chain and no mimic
joint itself.  Refused with a message naming the joint: ``floating`` and
``planar`` joints (not one actuator each), a mimic joint whose driver is off
the chain, and files that are no tree (a link that is the child of two
joints, joints forming a cycle).  Ignored: visual and collision elements,
``dynamics``, ``safety_controller``, ``calibration`` (the URDF
``calibration`` reference positions are not zero offsets), transmissions.

``<inertial>`` elements give the moving links' weights (joint_compliance's
loads): link ``k`` of the chain (in the frame after moving joint ``k``, the
URDF child link of that joint) carries its own mass and that of every link
hanging from it through joints other than the chain's next moving joint:
fixed joints (folded exactly), and moving joints off the chain (a gripper's
fingers, a head on a torso) folded at their zero position.  Each centre of
mass is the ``<inertial><origin>`` carried into link ``k``'s frame (m to mm),
the link's the mass-weighted mean.  A link without ``<inertial>`` weighs
nothing (URDF's convention); a chain none of whose moving links has a mass
gives no inertials (unknown).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..errors import MachineFileError
from ..geometry import rpy_from_matrix

__all__ = ["UrdfChain", "chain_from_urdf"]

_M_TO_MM = 1000.0
_REVOLUTE = ("revolute", "continuous")


@dataclass(frozen=True)
class UrdfChain:
    """The moving joints between two links, in mm and rad.

    Attributes
    ----------
    joint_type : tuple of str
        ``"revolute"`` (also for URDF ``continuous``) or ``"prismatic"``.
    origin, rpy, axis : ndarray, shape (m, 3)
        As the ``[[joint]]`` keys; fixed joints before a moving joint are folded in.
    tail : (ndarray (3, 3), ndarray (3,))
        Rotation and translation (mm) of ``tip_link`` in the last moving joint's frame.
    q_limits : ndarray, shape (m, 2) or None
        From the URDF ``<limit>`` elements (rad or mm) when every moving joint has
        one (``continuous`` joints have none).
    names : tuple of str
        The URDF joint names, base outward.
    mimic : tuple
        Per moving joint: None (an actuator) or ``(d, multiplier, offset)``
        in bayescal's units (``d`` the 0-based index of the driving joint in
        the chain; offset mm or rad), as :class:`~bayescal.machines.serial.Serial` takes it.
    link_mass : ndarray, shape (m,) or None
        Mass of each moving link with what hangs from it (kg), None when no
        moving link has an ``<inertial>`` mass.
    link_com : ndarray, shape (m, 3) or None
        Its centre of mass in the frame after moving joint ``k``, mm.
    links : tuple of (str, int, ndarray (3, 3))
        Every link from ``base_link`` to ``tip_link``: its name, the moving
        joint ``k`` (0-based) whose frame it is fixed to (-1: the base) and
        its orientation in that frame (fixed joints folded); what a body
        sensor named after a URDF link is read on (docs/formats.md section 8).
    """

    joint_type: tuple
    origin: NDArray
    rpy: NDArray
    axis: NDArray
    tail: tuple
    q_limits: NDArray | None
    names: tuple
    link_mass: NDArray | None = None
    link_com: NDArray | None = None
    mimic: tuple = ()
    links: tuple = ()


def chain_from_urdf(urdf_path: str | Path, base_link: str, tip_link: str, *, path: str = "") -> UrdfChain:
    """Read the joints from ``base_link`` to ``tip_link`` of a URDF file.

    Parameters
    ----------
    urdf_path : path
        The URDF file (relative paths are resolved by the caller against the machine file).
    base_link, tip_link : str
        Link names; ``base_link`` must be an ancestor of ``tip_link``.
    path : str
        The machine file, for error messages.

    Raises
    ------
    MachineFileError
        Naming the machine file, the key (``urdf``, ``base_link``, ``tip_link``)
        and, for an unsupported joint, its URDF name and type.
    """

    urdf_path = Path(urdf_path)
    robot = _load(urdf_path, path)
    chain = _joints_between(robot, base_link, tip_link, urdf_path, path)
    types, origin, rpy, axis, lim, moving = [], [], [], [], [], []
    pending = np.eye(4)  # fixed transforms not yet folded into a moving joint (mm)
    links = [(base_link, -1, np.eye(3))]
    for j in chain:
        T = _transform_mm(j.origin)
        _check_origin(j, T, urdf_path, path)
        if j.type == "fixed":
            pending = pending @ T
            # a link after fixed joints only: fixed to the last moving joint's frame (the base before any)
            links.append((j.child, len(types) - 1, pending[:3, :3].copy()))
            continue
        if j.type not in _REVOLUTE + ("prismatic",):
            raise MachineFileError(path, "urdf", f"joint {j.name!r} is of type {j.type!r}; supported: revolute, continuous, prismatic, fixed")
        T = pending @ T
        pending = np.eye(4)
        a = np.array(j.axis if j.axis is not None else [1.0, 0.0, 0.0], dtype=float)  # URDF default axis is x
        if not (np.all(np.isfinite(a)) and np.linalg.norm(a) > 0):
            raise MachineFileError(path, "urdf", f"joint {j.name!r} has a zero axis")
        types.append("revolute" if j.type in _REVOLUTE else "prismatic")
        origin.append(T[:3, 3])
        rpy.append(rpy_from_matrix(T[:3, :3]))
        axis.append(a / np.linalg.norm(a))
        moving.append(j)
        links.append((j.child, len(types) - 1, np.eye(3)))
        scale = _M_TO_MM if j.type == "prismatic" else 1.0
        if j.type == "continuous" or j.limit is None or j.limit.lower is None or j.limit.upper is None:
            lim.append(None)
        else:
            lim.append((scale * float(j.limit.lower), scale * float(j.limit.upper)))
    if not types:
        raise MachineFileError(path, "tip_link", f"no revolute, continuous or prismatic joint between {base_link!r} and {tip_link!r}")
    mimic = _mimic_entries(moving, path)
    lim = [li for li, mi in zip(lim, mimic) if mi is None]  # limits per actuator: mimic joints have none
    ok = all(li is not None and li[0] < li[1] for li in lim)
    mass, com = _link_inertials(robot, moving, path, urdf_path)
    return UrdfChain(
        joint_type=tuple(types), origin=np.array(origin), rpy=np.array(rpy), axis=np.array(axis),
        tail=(pending[:3, :3], pending[:3, 3]), q_limits=np.array(lim, dtype=float) if ok else None,
        names=tuple(j.name for j in moving), link_mass=mass, link_com=com, mimic=mimic, links=tuple(links),
    )


def _load(urdf_path: Path, path: str):
    """The parsed URDF (yourdfpy), after a strict XML parse; MachineFileError (key ``urdf``) otherwise."""
    import yourdfpy

    from ..io.safe_paths import MAX_TOML_BYTES, read_input_bytes

    if not urdf_path.exists():
        raise MachineFileError(path, "urdf", f"file not found: {urdf_path}")
    if not urdf_path.is_file():  # a folder, a FIFO or a device (/dev/zero) would block or never end
        raise MachineFileError(path, "urdf", f"{urdf_path} is not a regular file; expected a URDF file")
    # read once, as an input of the run: no output of the run (--write-urdf) may replace it
    data = read_input_bytes(urdf_path, "a URDF file", limit=MAX_TOML_BYTES,
                            error=lambda message: MachineFileError(path, "urdf", f"{urdf_path}: {message}"))
    try:
        # yourdfpy recovers from malformed XML (and only logs it); a machine description must be
        # well-formed, so the file is first parsed strictly by lxml (which yourdfpy builds on)
        from lxml import etree

        root = etree.fromstring(data, etree.XMLParser(recover=False))
        duplicate = _duplicate_name(root)
        bad = _bad_number(root)
        if bad is not None:
            raise MachineFileError(path, "urdf", f"{urdf_path.name} line {bad}")
        if duplicate is None:
            return yourdfpy.URDF.load(
                io.BytesIO(data), build_scene_graph=False, load_meshes=False,
                build_collision_scene_graph=False, load_collision_meshes=False,
            )
    except MachineFileError:
        raise
    except Exception as exc:  # yourdfpy raises lxml, ValueError, KeyError... for malformed files
        raise MachineFileError(path, "urdf", f"{urdf_path} is not a readable URDF file ({type(exc).__name__}: {exc})") from exc
    # yourdfpy keeps one element per name: a second joint 'j1' silently replaced the first (and broke the chain)
    tag, name = duplicate
    raise MachineFileError(path, "urdf", f"{urdf_path.name} has two <{tag}> elements named {name!r}; expected unique names")


#: The numeric attributes of a joint the chain is read from, with how many numbers each holds.
_JOINT_NUMBERS = (("origin", "xyz", 3), ("origin", "rpy", 3), ("axis", "xyz", 3), ("limit", "lower", 1),
                  ("limit", "upper", 1), ("mimic", "multiplier", 1), ("mimic", "offset", 1))


def _bad_number(root) -> str | None:
    """``"N: <joint 'j2'> <origin rpy>: ..."`` for the first joint attribute that is not its count of numbers, else None.

    yourdfpy's own failure for ``rpy="0 0"`` was an IndexError naming neither the joint nor the line.
    """
    for joint in root.findall("joint"):
        for tag, attr, count in _JOINT_NUMBERS:
            for element in joint.findall(tag):
                text = element.get(attr)
                if text is None:
                    continue
                try:
                    values = [float(v) for v in text.split()]
                except ValueError:
                    values = None
                if values is None or len(values) != count:
                    what = "a number" if count == 1 else f"{count} numbers separated by spaces"
                    return (f"{element.sourceline}: joint {joint.get('name')!r}, <{tag} {attr}=...>: expected {what}, "
                            f"got {text!r}")
    return None


def _duplicate_name(root) -> tuple[str, str] | None:
    """The first ``(tag, name)`` that two ``<joint>`` or two ``<link>`` elements of the robot share, else None."""
    for tag in ("joint", "link"):
        seen: set = set()
        for element in root.findall(tag):
            name = element.get("name")
            if name in seen:
                return tag, name
            seen.add(name)
    return None


def _joints_between(robot, base_link: str, tip_link: str, urdf_path: Path, path: str) -> list:
    """The URDF joints from ``base_link`` down to ``tip_link``, base outward.

    The walk goes up from the tip by each link's parent joint; a URDF is a
    tree, so a link with two parent joints or a cycle of joints (which would
    make the walk endless) is refused by name.
    """
    links = set(robot.link_map)
    for key, link in (("base_link", base_link), ("tip_link", tip_link)):
        if link not in links:
            raise MachineFileError(path, key, f"link {link!r} not in {urdf_path.name}; links: {', '.join(sorted(links))}")
    by_child: dict = {}
    for j in robot.joint_map.values():
        if j.child in by_child:
            raise MachineFileError(path, "urdf", f"link {j.child!r} of {urdf_path.name} is the child of two joints "
                                                 f"({by_child[j.child].name!r}, {j.name!r}); a URDF is a tree")
        by_child[j.child] = j
    _check_no_cycle(by_child, tip_link, urdf_path, path)
    chain, link = [], tip_link
    while link != base_link:
        if link not in by_child:
            raise MachineFileError(path, "base_link", f"{base_link!r} is not an ancestor of tip_link {tip_link!r} in {urdf_path.name}")
        j = by_child[link]
        chain.append(j)
        link = j.parent
    chain.reverse()
    return chain


def _check_no_cycle(by_child: dict, tip_link: str, urdf_path: Path, path: str) -> None:
    """Refuse joints that form a cycle anywhere in the file (a walk up from a link on it would never end).

    A cycle through the base link (its tip joined back to it) left the chain's walk from the tip finite, and
    was read.  Every link is walked up by its parent joints once (links already walked end a walk), so the
    check is linear in the number of links; the tip's walk comes first, so a cycle above it is named from it.
    """
    done: set = set()
    for start in [tip_link, *by_child]:
        walk, on_walk, link = [], set(), start
        while link in by_child and link not in done:
            if link in on_walk:
                loop = walk[walk.index(link):]
                names = [by_child[x].name for x in loop]
                raise MachineFileError(
                    path, "urdf", f"the joints {', '.join(repr(n) for n in names)} of {urdf_path.name} form a cycle "
                    f"(links {' <- '.join(loop + [link])}); a URDF is a tree")
            walk.append(link)
            on_walk.add(link)
            link = by_child[link].parent
        done.update(walk)


def _check_origin(joint, T: NDArray, urdf_path: Path, path: str) -> None:
    """Refuse a joint origin that is not finite or lies beyond :data:`~bayescal.limits.MAX_FILE_NUMBER` mm."""
    from ..limits import MAX_FILE_NUMBER

    if not np.all(np.isfinite(T)) or np.any(np.abs(T[:3, 3]) > MAX_FILE_NUMBER):
        raise MachineFileError(path, "urdf", f"joint {joint.name!r} of {urdf_path.name} has the origin "
                               f"xyz [{', '.join(f'{v / _M_TO_MM:.6g}' for v in T[:3, 3])}] m (rpy giving "
                               f"{'a finite' if np.all(np.isfinite(T[:3, :3])) else 'a non-finite'} rotation); expected "
                               f"finite numbers, a translation of at most {MAX_FILE_NUMBER / _M_TO_MM:g} m")


def _mimic_entries(moving: list, path: str) -> tuple:
    """``(driver index, multiplier, offset)`` per moving joint in bayescal's units (mm, rad), None for actuators."""
    index = {j.name: k for k, j in enumerate(moving)}
    scale = [_M_TO_MM if j.type == "prismatic" else 1.0 for j in moving]
    out = []
    for k, j in enumerate(moving):
        if j.mimic is None:
            out.append(None)
            continue
        if j.mimic.joint not in index:
            raise MachineFileError(path, "urdf", f"joint {j.name!r} mimics {j.mimic.joint!r}, which is not a moving joint "
                                                 f"between base_link and tip_link; expected one of {', '.join(index)}")
        d = index[j.mimic.joint]
        mult = 1.0 if j.mimic.multiplier is None else float(j.mimic.multiplier)
        off = 0.0 if j.mimic.offset is None else float(j.mimic.offset)
        # q_k[urdf] = mult q_d[urdf] + off, and q[bayescal] = scale q[urdf] (mm for prismatic joints)
        out.append((d, mult * scale[k] / scale[d], off * scale[k]))
    for k, j in enumerate(moving):
        if out[k] is None:
            continue
        d = out[k][0]
        if d == k:
            raise MachineFileError(path, "urdf", f"joint {j.name!r} mimics itself; expected the joint that drives it")
        if out[d] is not None:
            raise MachineFileError(path, "urdf", f"joint {j.name!r} mimics {moving[d].name!r}, which mimics "
                                                 f"{moving[out[d][0]].name!r}; the driving joint must be no mimic joint itself")
        if not np.all(np.isfinite(out[k][1:])):
            raise MachineFileError(path, "urdf", f"joint {j.name!r}: mimic multiplier and offset must be finite numbers")
    return tuple(out)


def _transform_mm(origin) -> NDArray:
    """A URDF ``<origin>`` (4x4, metres) in mm; the identity when absent."""
    T = np.array(origin if origin is not None else np.eye(4), dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):  # a huge origin overflows to inf: refused by _check_origin
        T[:3, 3] *= _M_TO_MM
    return T


def _link_inertials(robot, moving: list, path: str, urdf_path: Path) -> tuple[NDArray | None, NDArray | None]:
    """Mass (kg) and centre of mass (mm, frame after moving joint k) of each moving link with what hangs from it."""
    chain_joints = {j.name for j in moving}
    by_parent: dict[str, list] = {}
    for j in robot.joint_map.values():
        by_parent.setdefault(j.parent, []).append(j)
    mass = np.zeros(len(moving))
    moment = np.zeros((len(moving), 3))
    for k, joint in enumerate(moving):
        stack = [(joint.child, np.eye(4))]  # link, its frame in link k's frame (mm)
        while stack:
            link, T = stack.pop()
            inertial = robot.link_map[link].inertial
            if inertial is not None and inertial.mass is not None and not (np.isfinite(inertial.mass) and inertial.mass >= 0):
                raise MachineFileError(path, "urdf", f"link {link!r} of {urdf_path.name} has mass {inertial.mass!r}; expected kg >= 0")
            if inertial is not None and inertial.mass:
                c = T @ _transform_mm(inertial.origin)[:, 3]
                mass[k] += float(inertial.mass)
                moment[k] += float(inertial.mass) * c[:3]
            for j in by_parent.get(link, []):
                if j.name not in chain_joints:  # the next moving joint of the chain starts link k + 1
                    stack.append((j.child, T @ _transform_mm(j.origin)))  # off-chain motion at its zero position
    if not np.any(mass > 0):
        return None, None
    com = np.divide(moment, mass[:, None], out=np.zeros_like(moment), where=mass[:, None] > 0)
    return mass, com
