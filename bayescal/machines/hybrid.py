"""Hybrid machines: modules of any kind stacked on one another (docs/formats.md section 5).

A ``kind = "hybrid"`` file lists ``[[module]]`` tables in actuator order, each
with ``role`` and either ``file`` (a machine file of any kind, relative to the
hybrid file) or an inline ``[module.machine]`` table holding the same keys
(the form :meth:`Hybrid.to_toml` writes, so that a calibrated hybrid machine
is one self-contained file).

* ``role = "tool"``: the first tool module sits on the base; each further tool
  module sits on the previous tool module's tool frame (its tool point, with
  its platform or tool-frame orientation).
* ``role = "table"``: the same stacking for the modules carrying the
  workpiece; the measurement is the tool frame relative to the last table
  module's tool frame.

So with tool modules ``T_1 ... T_a`` and table modules ``B_1 ... B_c`` (each
the module's tool frame in its own base frame), the measured pose is

    M = (B_1 ... B_c)^-1 (T_1 ... T_a).

A module may itself be a hybrid machine, down to :data:`MAX_NESTING` levels;
a module file that includes itself, directly or through other module files,
is refused naming the cycle.

Actuators are numbered through the modules in file order.  Parameters are the
modules' own, prefixed ``m<k>.`` with ``k`` the module's position in the file
(``m1.chain1.link_length``, ``m2.joint1.offset``); tolerances are those of the
module files.  ``[measurement]`` and ``[workspace]`` belong to the hybrid file
(``q_limits`` defaults to the modules' own limits, concatenated).

Weight bodies (:meth:`Machine.weight_bodies`, joint_compliance's loads): the
default, the measured platform alone.  The modules' own bodies (a serial
module's links) are not composed through the stack yet, so a hybrid's
link masses cannot be stated; the platform's weight is taken in the measured
(table) frame, as before.

The Jacobian is the chain rule of the module Jacobians: a module's twist in
its base frame is carried to the stack's base by the rotation of the modules
below it, and a twist of a table module enters with the opposite sign.
"""

from __future__ import annotations

import os
import re
import tomllib
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..io.machine_file import TomlTable, format_toml_value, read_toml
from ..params import ParamLayout, ParamSpec
from .base import Machine, MeasurementNoise, ToolPoses, machine_from_table
from .common import common_toml, read_noise, read_q_limits

__all__ = ["Hybrid", "ROLES", "MAX_NESTING", "write_machine_files"]

ROLES = ("tool", "table")

#: Hybrid machines nested deeper than this (a hybrid module holding a hybrid module ...) are refused:
#: no real machine stacks that many, and each level costs every prediction a composition.
MAX_NESTING = 32

#: The hybrid files being read, outermost first, as (real path, path as given): a module file
#: already on this stack includes itself, which would recurse without end.
_READING: ContextVar[tuple] = ContextVar("bayescal_hybrid_reading", default=())


@dataclass(frozen=True)
class _HybridState:
    position: NDArray  # (n, k, 3) each module's tool point in its own base frame
    rotation: NDArray  # (n, k, 3, 3) each module's tool-frame orientation in its base frame
    modules: tuple  # the modules' own states


def _compose(Rs: list[NDArray], ps: list[NDArray], n: int):
    """Product of frames ``(R_1, p_1) ... (R_k, p_k)`` for n poses (identity if none); also the
    rotation before each factor and the origin after it (each module's tool point in the stack's base)."""
    R = np.broadcast_to(np.eye(3), (n, 3, 3))
    p = np.zeros((n, 3))
    before, after = [], []
    for Rk, pk in zip(Rs, ps):
        before.append(R)
        p = p + np.einsum("nij,nj->ni", R, pk)
        R = R @ Rk
        after.append(p)
    return R, p, before, after


def _table_tool_default(doc: TomlTable) -> TomlTable:
    """A serial table module without ``[tool]``: its tool frame is its last joint frame.

    docs/formats.md section 5 measures the tool "relative to the table's last frame"; bayescal
    reads that as the table module's tool frame (``T_1 ... T_n Trans(tool.point)
    Rot(tool.rpy)``). A table written with the other reading (the last joint frame) needs
    no ``[tool]``, and with none the two readings agree, so it may be left out.
    """
    if doc.data.get("kind") != "serial" or doc.has("tool"):
        return doc
    return type(doc)({**doc.data, "tool": {"point": [0.0, 0.0, 0.0]}}, doc.path, doc.prefix)


def _refuse_cycle(mt: TomlTable, f: Path) -> None:
    """MachineFileError (key ``file``) when module file ``f`` is one of the hybrid files being read."""
    stack = _READING.get()
    real = os.path.realpath(f)
    for i, (r, _) in enumerate(stack):
        if r == real:
            loop = " -> ".join([shown for _, shown in stack[i:]] + [str(f)])
            what = "includes itself" if i == len(stack) - 1 else "is part of a cycle of module files"
            raise mt.error("file", f"{f} {what} ({loop}); expected a module file that is not one of the files including it")


#: Tables a machine file may carry around its geometry (docs/formats.md sections 4, 7, 8): in a hybrid they
#: describe the whole machine and live in its main file.
_MAIN_FILE_TABLES = ("effect", "instrument", "calibration", "discrepancy")


def _read_modules(doc: TomlTable, path: str) -> tuple[list, list]:
    """The modules and roles of the ``[[module]]`` tables, each module built by its own kind."""
    modules, roles = [], []
    for mt in doc.array_of_tables("module"):
        mt.reject_unknown({"file", "role", "machine"})
        role = mt.string("role")
        if role not in ROLES:
            raise mt.error("role", f"expected \"tool\" or \"table\", got {role!r}")
        if mt.has("file") == mt.has("machine"):
            raise mt.error("file", "expected either file = \"module.toml\" or an inline [module.machine] table")
        if mt.has("file"):
            f = Path(mt.string("file"))
            f = f if f.is_absolute() else Path(path).parent / f
            _refuse_cycle(mt, f)
            # named from the key that points there: "nope.toml: file not found" did not say which file asked for it
            if not f.exists():
                raise mt.error("file", f"{f}: file not found; expected a module's machine file (TOML)")
            if not f.is_file():
                from ..io.safe_paths import file_kind

                raise mt.error("file", f"{f}: is {file_kind(f.stat().st_mode)}, not a regular file; expected a module's "
                               "machine file (TOML)")
            sub, sub_path = read_toml(f), str(f)
        else:
            sub, sub_path = mt.table("machine"), path
        for key in _MAIN_FILE_TABLES:
            if sub.has(key):
                raise mt.error("file" if mt.has("file") else "machine",
                               f"a module has a [{key}] table; expected it in the hybrid machine's own file ({path}): "
                               "effects, the instrument frame and the calibration belong to the whole machine")
        if role == "table":
            sub = _table_tool_default(sub)
        modules.append(machine_from_table(sub, sub_path))  # a module is geometry: its machine's tables are the main file's
        roles.append(role)
    return modules, roles


@dataclass(frozen=True, eq=False)
class Hybrid(Machine):
    """Modules stacked with roles ``tool`` and ``table``.

    Parameters
    ----------
    modules : tuple of Machine
        In file (actuator) order.
    roles : tuple of str
        ``"tool"`` or ``"table"`` per module; at least one ``"tool"``.
    name, noise, q_limits, source
        As for the other kinds; ``q_limits`` covers all actuators.
    """

    kind = "hybrid"

    modules: tuple
    roles: tuple
    name: str = "hybrid machine"
    noise: MeasurementNoise = field(default_factory=MeasurementNoise)
    q_limits: NDArray | None = None
    source: str = "<memory>"

    def __post_init__(self) -> None:
        specs, tol, qsl, tsl = [], [], [], []
        q0 = t0 = 0
        for k, m in enumerate(self.modules):
            specs += [ParamSpec(f"m{k + 1}.{s.name}", s.unit, f"m{k + 1}.{s.group}") for s in m.layout]
            tol.append(np.asarray(m.tolerance, dtype=float))
            qsl.append(slice(q0, q0 + m.n_actuators))
            tsl.append(slice(t0, t0 + m.n_params))
            q0, t0 = q0 + m.n_actuators, t0 + m.n_params
        object.__setattr__(self, "layout", ParamLayout(tuple(specs)))
        object.__setattr__(self, "tolerance", np.concatenate(tol))
        object.__setattr__(self, "_qsl", tuple(qsl))
        object.__setattr__(self, "_tsl", tuple(tsl))
        object.__setattr__(self, "_tools", tuple(k for k, r in enumerate(self.roles) if r == "tool"))
        object.__setattr__(self, "_tables", tuple(k for k, r in enumerate(self.roles) if r == "table"))

    @property
    def n_actuators(self) -> int:
        return sum(m.n_actuators for m in self.modules)

    @property
    def written_modules(self) -> tuple[Machine, ...]:
        """The modules: each written to a file of its own (docs/formats.md section 5)."""
        return tuple(self.modules)

    @property
    def actuator_units(self) -> tuple[str, ...]:
        return tuple(u for m in self.modules for u in m.actuator_units)

    @property
    def actuator_box_reachable(self) -> bool:
        """The box is the product of the modules' boxes: all reachable only if each module's is."""
        return all(m.actuator_box_reachable for m in self.modules)

    # ----------------------------------------------------------------- set-up
    @classmethod
    def from_toml(cls, doc: TomlTable, path: str) -> "Hybrid":
        """Read ``[[module]]`` tables (``file`` relative to this file, or inline ``[module.machine]``).

        Raises MachineFileError for a module file that includes itself (the
        cycle named) and for hybrid machines nested deeper than :data:`MAX_NESTING`.
        """
        doc.reject_unknown({"kind", "name", "module", "measurement", "workspace"})
        stack = _READING.get()
        if len(stack) >= MAX_NESTING:
            raise doc.error("module", f"hybrid machines nested more than {MAX_NESTING} levels deep (from "
                                      f"{stack[0][1]}); expected at most {MAX_NESTING}")
        token = _READING.set(stack + ((os.path.realpath(path), path),))
        try:
            modules, roles = _read_modules(doc, path)
        finally:
            _READING.reset(token)
        if "tool" not in roles:
            raise doc.error("module", "expected at least one module with role = \"tool\" (the one carrying the measured tool)")
        n_act = sum(m.n_actuators for m in modules)
        q_limits = read_q_limits(doc, n_act)
        if q_limits is None and all(m.q_limits is not None for m in modules):
            q_limits = np.concatenate([m.q_limits for m in modules])
        return cls(
            modules=tuple(modules), roles=tuple(roles), name=doc.string("name", "hybrid machine"),
            noise=read_noise(doc), q_limits=q_limits, source=path,
        )

    def split_theta(self, theta: ArrayLike | None, n: int | None = None) -> list[NDArray]:
        """``theta`` cut into the modules' parameter vectors (``(P_k,)`` or ``(n, P_k)``)."""
        theta = self.check_theta(theta, n)
        return [theta[..., sl] for sl in self._tsl]

    # ------------------------------------------------------------ kinematics
    def _module_poses(self, state: _HybridState, k: int) -> ToolPoses:
        n = state.position.shape[0]
        return ToolPoses(state.position[:, k], state.rotation[:, k], np.ones(n, bool), ("",) * n, state.modules[k])

    def _measured(self, pos: NDArray, rot: NDArray):
        """Compose the stacks: tool and table frames in the base, and the measured pose."""
        Rt, pt, before_t, after_t = _compose([rot[:, k] for k in self._tools], [pos[:, k] for k in self._tools], pos.shape[0])
        Rb, pb, before_b, after_b = _compose([rot[:, k] for k in self._tables], [pos[:, k] for k in self._tables], pos.shape[0])
        RbT = np.swapaxes(Rb, 1, 2)
        p = np.einsum("nij,nj->ni", RbT, pt - pb)
        return p, RbT @ Rt, (Rt, pt, before_t, after_t), (Rb, pb, before_b, after_b)

    def forward(self, q: ArrayLike, theta: ArrayLike | None = None, *, guess: ToolPoses | None = None) -> ToolPoses:
        """Tool pose relative to the table: each module's forward kinematics, then the stacks composed.

        Parameters
        ----------
        q : array_like, shape (n_poses, n_actuators)
            All modules' actuators in file order (mm or rad per module).
        theta : array_like, shape (P,) or (n_poses, P), optional
        guess : ToolPoses, optional
            An earlier solution of this machine (its modules' states are the warm starts).
        """
        q = self.check_q(q)
        n = q.shape[0]
        ths = self.split_theta(theta, n)
        warm = guess is not None and isinstance(guess.state, _HybridState) and guess.state.position.shape[0] == n
        poses = []
        for k, m in enumerate(self.modules):
            g = self._module_poses(guess.state, k) if warm else None
            poses.append(m.forward(q[:, self._qsl[k]], ths[k], guess=g))
        pos = np.stack([p.position for p in poses], axis=1)
        rot = np.stack([p.rotation for p in poses], axis=1)
        p, R, _, _ = self._measured(pos, rot)
        success = np.all([pp.success for pp in poses], axis=0)
        msgs = []
        for i in range(n):
            bad = [f"module m{k + 1} ({self.modules[k].kind}): {pp.message[i]}" for k, pp in enumerate(poses) if not pp.success[i]]
            msgs.append("; ".join(bad))
        state = _HybridState(position=pos, rotation=rot, modules=tuple(pp.state for pp in poses))
        return ToolPoses(position=p, rotation=R, success=success, message=tuple(msgs), state=state)

    def _chain_rule(self, blocks: list[NDArray], state: _HybridState) -> NDArray:
        """Module Jacobian blocks (each in its module's base frame) to the measured pose's."""
        _, _, (Rt, pt, before_t, after_t), (Rb, pb, before_b, after_b) = self._measured(state.position, state.rotation)
        RbT = np.swapaxes(Rb, 1, 2)
        out = []
        for k, Jk in enumerate(blocks):
            if self.roles[k] == "tool":
                j = self._tools.index(k)
                RA, end, ref = before_t[j], after_t[j], pt
            else:
                j = self._tables.index(k)
                RA, end, ref = before_b[j], after_b[j], pb
            w = RA @ Jk[:, 3:]
            dp = RA @ Jk[:, :3] + np.cross(w, (ref - end)[:, :, None], axis=1)
            J = np.empty_like(Jk)
            if self.roles[k] == "tool":
                J[:, :3], J[:, 3:] = RbT @ dp, RbT @ w
            else:
                J[:, :3] = -RbT @ (dp + np.cross(w, (pt - pb)[:, :, None], axis=1))
                J[:, 3:] = -RbT @ w
            out.append(J)
        return np.concatenate(out, axis=2)

    def tool_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Chain rule of the module Jacobians; shape (n_poses, 6, P), see :meth:`Machine.tool_jacobian`.

        For a module with base-frame twist ``(dp_k, w_k)`` under modules of
        rotation ``R_A``: ``w = R_A w_k`` and ``dp = R_A dp_k + w x (p - c_k)``
        (``c_k`` the module's tool point, ``p`` the top of its stack); in the
        table frame a tool module's twist is rotated by ``R_B^T`` and a table
        module's enters as ``-R_B^T w`` and ``-R_B^T (dp + w x (p_tool - p_table))``.
        """
        q = self.check_q(q)
        st = poses.state
        ths = self.split_theta(theta, q.shape[0])
        blocks = [
            m.tool_jacobian(q[:, self._qsl[k]], ths[k], self._module_poses(st, k)) for k, m in enumerate(self.modules)
        ]
        return self._chain_rule(blocks, st)

    def actuator_jacobian(self, q: ArrayLike, theta: ArrayLike | None, poses: ToolPoses) -> NDArray:
        """Chain rule of the modules' actuator Jacobians; shape (n_poses, 6, n_actuators)."""
        q = self.check_q(q)
        st = poses.state
        ths = self.split_theta(theta, q.shape[0])
        blocks = [
            m.actuator_jacobian(q[:, self._qsl[k]], ths[k], self._module_poses(st, k)) for k, m in enumerate(self.modules)
        ]
        return self._chain_rule(blocks, st)

    def guess_from_measurement(
        self, q: NDArray, position: NDArray, rotation: NDArray | None = None, axis: NDArray | None = None
    ) -> ToolPoses | None:
        """Warm starts for the modules that want one, from the measured pose.

        Each such module's own tool pose is what the measurement implies when
        the other modules are at their nominal poses (the nominal orientation
        stands in for an unmeasured one); the module then builds its start
        from that as from a measurement of its own.  None when no module
        wants a start (serial modules are closed-form).
        """
        q = self.check_q(q)
        n = q.shape[0]
        cold = self.forward(q)
        st = cold.state
        Rm = cold.rotation if rotation is None else np.asarray(rotation, dtype=float)
        Rt, pt, _, _ = _compose([st.rotation[:, k] for k in self._tools], [st.position[:, k] for k in self._tools], n)
        Rb, pb, _, _ = _compose([st.rotation[:, k] for k in self._tables], [st.position[:, k] for k in self._tables], n)
        # the stacks' tops as the measurement sees them (the other stack nominal)
        top = {
            "tool": (Rb @ Rm, pb + np.einsum("nij,nj->ni", Rb, position)),
            "table": (Rt @ np.swapaxes(Rm, 1, 2), pt - np.einsum("nij,nj->ni", Rt @ np.swapaxes(Rm, 1, 2), position)),
        }
        pos, rot = st.position.copy(), st.rotation.copy()
        states, any_guess = list(st.modules), False
        for k, m in enumerate(self.modules):
            order = self._tools if self.roles[k] == "tool" else self._tables
            j = order.index(k)
            RA, pA, _, _ = _compose([st.rotation[:, i] for i in order[:j]], [st.position[:, i] for i in order[:j]], n)
            RB, pB, _, _ = _compose([st.rotation[:, i] for i in order[j + 1 :]], [st.position[:, i] for i in order[j + 1 :]], n)
            Rtop, ptop = top[self.roles[k]]
            # top = A T_k B  =>  T_k = A^-1 top B^-1
            Rk = np.swapaxes(RA, 1, 2) @ Rtop @ np.swapaxes(RB, 1, 2)
            pk = np.einsum("nji,nj->ni", RA, ptop - pA - np.einsum("nij,nj->ni", Rtop @ np.swapaxes(RB, 1, 2), pB))
            g = m.guess_from_measurement(q[:, self._qsl[k]], pk, Rk if rotation is not None else None, None)
            if g is not None:
                any_guess = True
                pos[:, k], rot[:, k], states[k] = g.position, g.rotation, g.state
        if not any_guess:
            return None
        state = _HybridState(position=pos, rotation=rot, modules=tuple(states))
        return ToolPoses(position=np.asarray(position, float), rotation=Rm, success=np.ones(n, bool), message=("",) * n, state=state)

    # ------------------------------------------------------------------ output
    def to_toml(self, theta: ArrayLike | None = None) -> str:
        """One self-contained hybrid file of ``nominal + theta``: each module inline as ``[module.machine]``."""
        f = format_toml_value
        out = ['kind = "hybrid"', f"name = {f(self.name)}", ""]
        for k, (m, role) in enumerate(zip(self.modules, self.roles)):
            doc = tomllib.loads(m.to_toml(self.split_theta(theta)[k]))
            out += ["[[module]]", f"role = {f(role)}", ""] + _toml_table(doc, "module.machine", array=False)
        return "\n".join(out) + common_toml(self, {})


def machine_files_text(path, machine: Machine, theta: ArrayLike | None = None) -> list[tuple[Path, str]]:
    """The files of :func:`write_machine_files` as ``(path, text)``, the main file first, without writing them."""
    path = Path(path)
    if not machine.written_modules:
        return [(path, machine.to_toml(theta))]
    f = format_toml_value
    out = ['kind = "hybrid"', f"name = {f(machine.name)}", ""]
    modules = []
    for k, (m, role) in enumerate(zip(machine.modules, machine.roles)):
        sub = path.with_name(f"{path.stem}.m{k + 1}.toml")
        modules += machine_files_text(sub, m, machine.split_theta(theta)[k])
        out += ["[[module]]", f"file = {f(sub.name)}", f"role = {f(role)}", ""]
    return [(path, "\n".join(out) + common_toml(machine, {}))] + modules


def write_machine_files(path, machine: Machine, theta: ArrayLike | None = None) -> list[Path]:
    """Write the machine file of ``nominal + theta`` in the file-per-module form of docs/formats.md section 5.

    For a hybrid machine, each module goes to ``<stem>.m<k>.toml`` beside
    ``path`` (recursively for nested hybrids) and ``path`` lists them with
    ``file = "..."``, the form docs/formats.md section 5 specifies, which any
    implementation of that format reads.  Any other kind is written as
    :meth:`Machine.to_toml`.  The files are written as one unit
    (:func:`bayescal.io.answers.write_files_atomic`): all of them complete
    beside their targets first, then renamed, the module files before the
    main file.

    Parameters
    ----------
    path : path
        The machine file to write.
    machine : Machine
    theta : array_like, shape (P,), optional
        Geometric errors to fold in (e.g. ``IdentificationResult.theta``).

    Returns
    -------
    list of Path
        The files written, the main file first.
    """
    from ..io.answers import write_files_atomic

    files = machine_files_text(path, machine, theta)
    write_files_atomic(files[1:] + files[:1])  # the main file last: it never lists a module not yet written
    return [p for p, _ in files]


_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(k: str) -> str:
    return k if _BARE_KEY.match(k) else format_toml_value(k)


def _toml_table(d: dict, header: str, *, array: bool) -> list[str]:
    """A parsed TOML table written under ``header`` (sub-tables and arrays of tables follow it)."""
    lines = [f"[[{header}]]" if array else f"[{header}]"]
    subs = []
    for k, v in d.items():
        if isinstance(v, dict):
            subs.append((k, v, False))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            subs += [(k, x, True) for x in v]
        else:
            lines.append(f"{_key(k)} = {format_toml_value(v)}")
    lines.append("")
    for k, v, arr in subs:
        lines += _toml_table(v, f"{header}.{_key(k)}", array=arr)
    return lines
