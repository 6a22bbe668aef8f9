"""Machine files and recordings written by hand from the contract of docs/formats.md, by a program that is not bayescal.

This module is the "independent party" of the format tests: it imports nothing from
bayescal. Its kinematics are the spec's own equations (docs/formats.md sections 1 and 5)
solved with numpy, its TOML and CSV are written as text, in the variants another
program could plausibly produce and the spec allows (column order, optional columns,
unit suffixes, CRLF, a UTF-8 BOM, trailing whitespace, integers for floats, ...).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

# ---------------------------------------------------------------- rotations


def rotvec_to_matrix(w) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis times angle, rad), Rodrigues' formula."""
    w = np.asarray(w, float)
    th = float(np.linalg.norm(w))
    if th < 1e-14:
        return np.eye(3)
    k = w / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * kx + (1 - math.cos(th)) * kx @ kx


def matrix_to_rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (angles well below pi here)."""
    c = (np.trace(r) - 1) / 2
    th = math.acos(max(-1.0, min(1.0, c)))
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if th < 1e-12:
        return v / 2
    return v * th / (2 * math.sin(th))


def rpy_matrix(rpy) -> np.ndarray:
    """R = Rz(y) Ry(p) Rx(r), URDF's fixed-axis convention (docs/formats.md section 5)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def homogeneous(r: np.ndarray, t) -> np.ndarray:
    t4 = np.eye(4)
    t4[:3, :3] = r
    t4[:3, 3] = t
    return t4


# ---------------------------------------------------------------- 3-PRS (section 1)


@dataclass(frozen=True)
class Chain:
    rail_origin: tuple
    rail_direction: tuple
    revolute_axis: tuple
    link_length: float
    sphere_center: tuple


@dataclass(frozen=True)
class Prs3:
    chains: tuple
    tool: tuple = (0.0, 0.0, -100.0)
    name: str = "spindle head A"
    sigma_position: float = 0.005
    sigma_angle: float = 5.0e-5
    q_limits: tuple = ((450.0, 550.0),) * 3
    extra: dict = field(default_factory=dict)


def prs3_nominal() -> Prs3:
    """The section-1 example, the two more chains at 120 and 240 degrees about z."""
    chains = []
    for k in range(3):
        a = 2 * math.pi * k / 3
        c, s = math.cos(a), math.sin(a)
        chains.append(Chain((300 * c, 300 * s, 0.0), (0.0, 0.0, 1.0), (-s, c, 0.0), 400.0, (150 * c, 150 * s, 0.0)))
    return Prs3(tuple(chains))


def prs3_perturbed(m: Prs3, seed: int, scale: float = 1.0) -> Prs3:
    """A 'true' machine: every key of the machine file moved by a few hundredths of a mm / mrad."""
    rng = np.random.default_rng(seed)
    chains = []
    for ch in m.chains:
        u = np.asarray(ch.rail_direction) + rng.normal(0, 2e-4 * scale, 3)
        r = np.asarray(ch.revolute_axis) + rng.normal(0, 2e-4 * scale, 3)
        chains.append(
            Chain(
                tuple(np.asarray(ch.rail_origin) + rng.normal(0, 0.05 * scale, 3)),
                tuple(u / np.linalg.norm(u)),
                tuple(r / np.linalg.norm(r)),
                ch.link_length + rng.normal(0, 0.05 * scale),
                tuple(np.asarray(ch.sphere_center) + rng.normal(0, 0.05 * scale, 3)),
            )
        )
    return replace(m, chains=tuple(chains), tool=tuple(np.asarray(m.tool) + rng.normal(0, 0.05 * scale, 3)))


def _prs3_equations(m: Prs3, q, x):
    p, rot = x[:3], rotvec_to_matrix(x[3:])
    out = []
    for qi, ch in zip(q, m.chains):
        c = np.asarray(ch.rail_origin) + qi * np.asarray(ch.rail_direction)
        a = p + rot @ np.asarray(ch.sphere_center)
        d = a - c
        out += [np.linalg.norm(d) - ch.link_length, d @ np.asarray(ch.revolute_axis)]
    return np.array(out)


def prs3_pose(m: Prs3, q) -> tuple[np.ndarray, np.ndarray]:
    """Platform pose (p, R) by Newton on the section-1 equations (numerical Jacobian)."""
    q = np.asarray(q, float)
    # the platform hangs below the sliders: z = q - sqrt(l^2 - 150^2) on the symmetric branch
    x = np.array([0.0, 0.0, q.mean() - math.sqrt(400.0**2 - 150.0**2), 0.0, 0.0, 0.0])
    for _ in range(60):
        f = _prs3_equations(m, q, x)
        jac = np.empty((6, 6))
        for j in range(6):
            dx = np.zeros(6)
            dx[j] = 1e-7
            jac[:, j] = (_prs3_equations(m, q, x + dx) - _prs3_equations(m, q, x - dx)) / 2e-7
        step = np.linalg.solve(jac, -f)
        x += step
        if np.max(np.abs(step)) < 1e-12:
            break
    assert np.max(np.abs(_prs3_equations(m, q, x))) < 1e-9
    return x[:3], rotvec_to_matrix(x[3:])


def prs3_tool(m: Prs3, q) -> tuple[np.ndarray, np.ndarray]:
    """Tool point (mm) and platform rotation, base frame."""
    p, rot = prs3_pose(m, q)
    return p + rot @ np.asarray(m.tool), rot


def prs3_tool_poses(m: Prs3, q) -> tuple[np.ndarray, np.ndarray]:
    """Tool points (n, 3; mm) and platform rotations (n, 3, 3) of ``m`` at each row of ``q``."""
    poses = [prs3_tool(m, qi) for qi in q]
    return np.array([p for p, _ in poses]), np.array([r for _, r in poses])


def _v(x, fmt="{:.9g}") -> str:
    return "[" + ", ".join(fmt.format(float(c)) for c in x) + "]"


def prs3_toml(
    m: Prs3,
    *,
    variant: str = "plain",
    instrument=None,
    effects: str = "",
    measurement: bool = True,
    workspace: bool = True,
) -> str:
    """The machine file of section 1, written as text.

    variant: "plain" (spec order, floats), "shuffled" (keys in another order, integers
    where a value is whole, comments, inline array of tables avoided), "inline"
    (the [tool] table as a dotted key).
    """
    lines = []
    if variant == "shuffled":
        lines += ["# written by another program", f'name = "{m.name}"', 'kind = "3-PRS"', ""]
    else:
        lines += ['kind = "3-PRS"', f'name = "{m.name}"', ""]

    def num(x):
        x = float(x)
        return str(int(x)) if variant == "shuffled" and x == int(x) else f"{x:.12g}"

    def vec(v):
        return "[" + ", ".join(num(c) for c in v) + "]"

    for ch in m.chains:
        keys = [
            ("rail_origin", vec(ch.rail_origin)),
            ("rail_direction", vec(ch.rail_direction)),
            ("revolute_axis", vec(ch.revolute_axis)),
            ("link_length", num(ch.link_length)),
            ("sphere_center", vec(ch.sphere_center)),
        ]
        if variant == "shuffled":
            keys = keys[::-1]
        lines.append("[[chain]]")
        lines += [f"{k} = {v}" + ("   # mm" if variant == "shuffled" else "") for k, v in keys]
        lines.append("")
    if variant == "inline":
        lines.append(f"tool.point = {vec(m.tool)}")
    else:
        lines += ["[tool]", f"point = {vec(m.tool)}"]
    lines.append("")
    if measurement:
        lines += ["[measurement]", f"sigma_position = {m.sigma_position}", f"sigma_angle = {m.sigma_angle}", ""]
    if workspace:
        lines += ["[workspace]", "q_limits = [" + ", ".join(vec(lim) for lim in m.q_limits) + "]", ""]
    if instrument is not None:
        origin, rv = instrument
        lines += ["[instrument]", f"origin = {vec(origin)}", f"rotation_vector = {vec(rv)}", ""]
    if effects:
        lines.append(effects)
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- serial (section 5)


@dataclass(frozen=True)
class Joint:
    type: str
    origin: tuple
    rpy: tuple
    axis: tuple


@dataclass(frozen=True)
class Serial:
    joints: tuple
    tool_point: tuple | None
    tool_rpy: tuple | None = None
    name: str = "two-axis positioner"
    q_limits: tuple = ()
    sigma_position: float = 0.005
    sigma_angle: float = 5.0e-5


def positioner_nominal() -> Serial:
    """A tilt-rotary positioner (tilt about x, then the table about z) with a prismatic lift."""
    joints = (
        Joint("prismatic", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
        Joint("revolute", (0.0, 0.0, 200.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0)),
        Joint("revolute", (0.0, 0.0, 80.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    )
    return Serial(joints, (120.0, 30.0, 50.0), None, q_limits=((0.0, 100.0), (-1.2, 1.2), (-3.0, 3.0)))


def serial_perturbed(m: Serial, seed: int) -> Serial:
    rng = np.random.default_rng(seed)
    joints = []
    for j in m.joints:
        ax = np.asarray(j.axis) + rng.normal(0, 5e-4, 3)
        joints.append(
            Joint(
                j.type,
                tuple(np.asarray(j.origin) + rng.normal(0, 0.05, 3)),
                tuple(np.asarray(j.rpy) + rng.normal(0, 5e-4, 3)),
                tuple(ax / np.linalg.norm(ax)),
            )
        )
    return replace(m, joints=tuple(joints), tool_point=tuple(np.asarray(m.tool_point) + rng.normal(0, 0.05, 3)))


def serial_transform(m: Serial, q) -> np.ndarray:
    """T_1 ... T_n Trans(tool.point) Rot(tool.rpy), T_i = Trans(origin) Rot(rpy) M(q_i)."""
    t = np.eye(4)
    for qi, j in zip(q, m.joints):
        t = t @ homogeneous(rpy_matrix(j.rpy), j.origin)
        ax = np.asarray(j.axis, float)
        if j.type == "revolute":
            t = t @ homogeneous(rotvec_to_matrix(ax * qi), np.zeros(3))
        else:
            t = t @ homogeneous(np.eye(3), ax * qi)
    return t @ homogeneous(rpy_matrix(m.tool_rpy or (0.0, 0.0, 0.0)), m.tool_point or (0.0, 0.0, 0.0))


def serial_toml(m: Serial, *, variant: str = "plain", name: str | None = None, measurement: bool = True) -> str:
    """The serial machine file of section 5; no [tool] table when ``m.tool_point`` is None."""
    lines = ['kind = "serial"', f'name = "{name or m.name}"', ""]
    for j in m.joints:
        keys = [("type", f'"{j.type}"'), ("origin", _v(j.origin, "{:.12g}")), ("rpy", _v(j.rpy, "{:.12g}")),
                ("axis", _v(j.axis, "{:.12g}"))]
        if variant == "shuffled":
            keys = keys[::-1]
        lines += ["[[joint]]"] + [f"{k} = {v}" for k, v in keys] + [""]
    if m.tool_point is not None:
        lines += ["[tool]", f"point = {_v(m.tool_point, '{:.12g}')}"]
        if m.tool_rpy is not None:
            lines.append(f"rpy = {_v(m.tool_rpy, '{:.12g}')}")
        lines.append("")
    if measurement:
        lines += ["[measurement]", f"sigma_position = {m.sigma_position}", f"sigma_angle = {m.sigma_angle}", ""]
    if m.q_limits:
        lines += ["[workspace]", "q_limits = [" + ", ".join(_v(lim, "{:.12g}") for lim in m.q_limits) + "]", ""]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- recordings (sections 2, 4, 6)


def draw_q(limits, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo = np.array([lim[0] for lim in limits])
    hi = np.array([lim[1] for lim in limits])
    return lo + (hi - lo) * rng.uniform(0.05, 0.95, (n, len(limits)))


def write_csv(path, header: list[str], rows: list[list], *, crlf=False, bom=False, trailing_ws=False,
              final_newline=True, fmt="{:.10g}") -> None:
    """CSV as text: the spec's one header row and one row per pose, in the variant asked for."""
    nl = "\r\n" if crlf else "\n"
    pad = "  " if trailing_ws else ""

    def cell(v):
        return v if isinstance(v, str) else fmt.format(float(v))

    text = ",".join(header) + pad + nl
    text += nl.join(",".join(cell(v) for v in row) + pad for row in rows)
    if final_newline:
        text += nl
    data = text.encode("utf-8")
    if bom:
        data = b"\xef\xbb\xbf" + data
    path.write_bytes(data)


def pose_rows(q, points, rots=None, *, dof=6, sigma=0.0, seed=0, frame=None, units=None):
    """Columns name -> values of a pose recording (section 2 and 4), noise added.

    frame: (origin, rotation_vector) of the instrument in the base frame; the recording
    is then in the instrument frame, p_inst = R^T (p_base - origin).
    units: dict column -> (new column name, factor) for unit-suffixed columns.
    """
    rng = np.random.default_rng(seed)
    n = len(q)
    cols = {f"q{i + 1}": q[:, i] for i in range(q.shape[1])}
    pts = np.array(points, float)
    rr = None if rots is None else np.array(rots, float)
    if frame is not None:
        rf = rotvec_to_matrix(frame[1])
        pts = (pts - np.asarray(frame[0])) @ rf
        if rr is not None:
            rr = np.einsum("ji,njk->nik", rf, rr)
    pts = pts + rng.normal(0, sigma, pts.shape)
    cols.update(x=pts[:, 0], y=pts[:, 1], z=pts[:, 2])
    if dof == 6:
        rv = np.array([matrix_to_rotvec(rotvec_to_matrix(rng.normal(0, sigma * 1e-2, 3)) @ r) for r in rr])
        cols.update(rx=rv[:, 0], ry=rv[:, 1], rz=rv[:, 2])
    elif dof == 5:
        ax = rr[:, :, 2] + rng.normal(0, sigma * 1e-2, (n, 3))
        ax /= np.linalg.norm(ax, axis=1, keepdims=True)
        cols.update(nx=ax[:, 0], ny=ax[:, 1], nz=ax[:, 2])
    for old, (new, factor) in (units or {}).items():
        cols[new] = cols.pop(old) * factor
    return cols


def rows_of(cols: dict, order: list[str] | None = None):
    header = order or list(cols)
    return header, [[cols[h][i] if not isinstance(cols[h], list) else cols[h][i] for h in header]
                    for i in range(len(next(iter(cols.values()))))]


# ---------------------------------------------------------------- effect tables (section 7)


def effect_table(name: str, params: dict[str, float], *, comments=True, extra: dict | None = None) -> str:
    """[effect.<name>] with quoted dotted parameter names, as in section 7's example."""
    lines = [f"[effect.{name}]"]
    for k, v in params.items():
        lines.append(f'"{k}" = {v!r}' + ("   # written by hand" if comments else ""))
    for k, v in (extra or {}).items():
        lines.append(f"{k} = {v}")
    return "\n".join(lines) + "\n"
