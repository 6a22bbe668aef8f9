"""``simulate`` as a user gets it: a recording, its truth and the true machine file, as ``bayescal simulate`` writes them.

:func:`simulate_files` is what the command line runs (and
:func:`bayescal.simulate_session` in a notebook).  It applies the command's policy: a machine file's
``[effect.*]`` tables and ``[discrepancy]`` act on the simulated machine,
concealed effects and recorded channels, a pose file's poses checked against
``q_limits``, a ballbar session instead of poses, the tolerances scaled.
The answer carries the three files' texts, so a notebook writes the bytes
the command writes.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError, RecordingError
from .machines.base import Machine

__all__ = ["SimulatedSession", "simulate_files", "read_poses_file"]


@dataclass(frozen=True)
class SimulatedSession:
    """A simulated recording with its truth.

    Attributes
    ----------
    recording : Recording or ConstraintRecording
        What the instrument read (docs/formats.md section 2; section 6 for a ballbar session).
    recording_csv : str
        Its file's text.
    truth : dict
        The drawn errors, seed and concealed effects (the truth JSON).
    truth_machine_toml : str
        The true machine file (with the nominal machine's ``[effect.*]`` tables).
    what : str
        What was recorded, for the report (``"36 poses, 6-DOF"``).
    nominal_error_mm : tuple of float, or None
        RMS and largest position error of the nominal model on the poses (mm); None for a ballbar session.
    """

    recording: object
    recording_csv: str
    truth: dict
    truth_machine_toml: str
    what: str
    nominal_error_mm: tuple[float, float] | None

    def report(self, out: str | os.PathLike, truth: str | os.PathLike | None = None) -> str:
        """What the command prints after :meth:`write` with the same paths."""
        out = Path(out)
        truth = Path(truth) if truth is not None else out.with_suffix(".truth.json")
        if self.nominal_error_mm is None:
            return f"wrote {out} ({self.what}), truth {truth}"
        rms, big = self.nominal_error_mm
        return (f"wrote {out} ({self.what}), truth {truth} and {truth.with_suffix('.toml')}\n"
                f"position error of the nominal model on these poses: RMS {rms:.4f} mm, max {big:.4f} mm")

    def write(self, out: str | os.PathLike, truth: str | os.PathLike | None = None) -> tuple[Path, Path, Path]:
        """Write the recording to ``out``, the truth JSON to ``truth`` (default ``out`` with ``.truth.json``) and
        the true machine beside it (suffix ``.toml``), as one unit; the three paths."""
        from .io.answers import json_text, write_files_atomic

        out = Path(out)
        truth = Path(truth) if truth is not None else out.with_suffix(".truth.json")
        paths = (out, truth, truth.with_suffix(".toml"))
        # one unit: the recording never stands beside the truth of another run (bayescal.io.answers)
        write_files_atomic([(paths[0], self.recording_csv), (paths[1], json_text(self.truth)),
                            (paths[2], self.truth_machine_toml)])
        return paths


def read_poses_file(path: str | os.PathLike, n_actuators: int) -> np.ndarray:
    """The commanded poses of a plan CSV: columns ``q1..qN`` (any order, other columns ignored), rows in order.

    Parameters
    ----------
    path : path
        A pose file (docs/formats.md E7: what ``bayescal plan --out`` writes).
    n_actuators : int
        The machine's actuators; a column ``q<k>`` beyond them is refused.

    Returns
    -------
    ndarray, shape (n_poses, n_actuators)
        Actuator positions (mm, rad).
    """
    from .io.recording import parse_table, read_csv_rows

    path = str(path)
    want = [f"q{i + 1}" for i in range(n_actuators)]
    header, col, rows = read_csv_rows(path, None, f"a pose file with columns {','.join(want)}")
    missing = [c for c in want if c not in col]
    if missing:
        raise RecordingError(path, 1, None, f"columns {', '.join(missing)} missing; expected {','.join(want)} (and e.g. pose_id)")
    extra = [c for c in header if re.fullmatch(r"q\d+", c) and c not in want]
    if extra:
        # a plan of a machine with more actuators: its q4 was ignored, silently
        raise RecordingError(path, 1, extra[0], f"an actuator column beyond the machine's {n_actuators} actuators; "
                             f"expected {','.join(want)} (a pose file of another machine?)")
    if not rows:
        raise RecordingError(path, 2, None, "no data rows")
    for i, r in enumerate(rows):
        if len(r) != len(header):
            raise RecordingError(path, i + 2, None, f"{len(r)} cells, expected {len(header)} (one per header column)")
    return parse_table(path, want, [[r[col[c]] for c in want] for r in rows])


def _poses(machine: Machine, n, poses_file, effects, aux, ballbar, source) -> tuple[int, np.ndarray | None]:
    """``(n, q)``: the number of poses and the pose file's poses (None: drawn within q_limits)."""
    q = None
    if poses_file is not None:
        if ballbar is not None:
            raise InputError("ballbar (--ballbar) drives circles about its pivot; it does not take poses_file "
                             "(--poses-file; give n, --poses, the readings per circle)")
        q = read_poses_file(poses_file, machine.n_actuators)
        if machine.q_limits is not None:
            # a recording outside q_limits is refused by every consumer: refuse it here, naming the line
            from .io.recording import check_q_limits

            check_q_limits(str(poses_file), q, machine.q_limits, machine_path=source)
        if n is not None and n != q.shape[0]:
            raise InputError(f"n (--poses) {n} but {poses_file} holds {q.shape[0]} poses; give one of them")
        if effects or aux:
            raise InputError("poses_file (--poses-file) cannot be combined with effects (--effect) or aux (--aux) "
                             "yet; simulate them with n poses")
        n = q.shape[0]
    if n is None:
        raise InputError("give n (--poses N, poses drawn within q_limits) or poses_file (--poses-file CSV, planned "
                         "poses)")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InputError(f"n (--poses): expected a positive whole number, got {n!r}")
    return int(n), q


def simulate_files(machine: str | os.PathLike | Machine, n: int | None = None, *, seed: int, dof: int = 6,
                   poses_file: str | os.PathLike | None = None, tolerance_scale: float = 1.0,
                   effects: tuple[str, ...] | list[str] = (), aux: tuple[str, ...] | list[str] = (),
                   ballbar: float | None = None, pivot=None,
                   planes: tuple[str, ...] | list[str] | None = None) -> SimulatedSession:
    """Simulate a measurement session as ``bayescal simulate`` does.

    Parameters
    ----------
    machine : path or Machine
        Nominal machine (docs/formats.md section 1); its ``[effect.*]`` tables and ``[discrepancy]`` act on
        the simulated machine, driven by the channels recorded.
    n : int, optional
        Poses drawn within ``q_limits`` (or readings per ballbar circle); from ``poses_file`` if not given.
    seed : int
        Seeds the errors, the poses and the noise.
    dof : {6, 5, 3}
        What the instrument measures.
    poses_file : path, optional
        Commanded poses to simulate at (a plan's CSV, docs/formats.md E7).
    tolerance_scale : float
        The true machine is drawn from the tolerances times this (> 0).
    effects : list of str
        ``NAME[:MAGNITUDE]`` of effects to conceal (docs/diagnose.md).
    aux : list of str
        Channels to record: ``time_s``, ``temp_C``, ``payload_kg``.
    ballbar : float, optional
        Record a ballbar session of this radius (mm) instead: ``n`` readings per circle about ``pivot``
        (X, Y, Z in mm; default the tool at the middle of q_limits), one circle per plane of ``planes``
        (``xy``, ``xz``, ``yz``; default ``xy``).

    Returns
    -------
    SimulatedSession
        Nothing is written until :meth:`SimulatedSession.write`.
    """
    if not isinstance(machine, Machine):
        from .machines.files import load_machine

        machine = load_machine(machine)
    source = machine.source
    effects, aux = list(effects), list(aux)
    if ballbar is None and (pivot is not None or planes is not None):
        # options of a ballbar session, ignored without one
        name = "pivot" if pivot is not None else "planes"
        raise InputError(f"--{name} (keyword {name}) goes with --ballbar RADIUS (keyword ballbar); it does nothing for "
                         "a recording of poses")
    n, q = _poses(machine, n, poses_file, effects, aux, ballbar, source)
    if isinstance(tolerance_scale, bool) or not isinstance(tolerance_scale, (int, float)) or not tolerance_scale > 0 \
            or not np.isfinite(tolerance_scale):
        raise InputError(f"tolerance_scale (--tolerance-scale): expected a positive number, got {tolerance_scale!r}")
    if ballbar is not None:
        return _ballbar(machine, n, seed, dof, tolerance_scale, effects, aux, ballbar, pivot, planes)
    return _poses_session(machine, n, q, seed, dof, tolerance_scale, effects, aux)


def _poses_session(machine, n, q, seed, dof, tolerance_scale, effects, aux) -> SimulatedSession:
    from .effects.stored import machine_file_text
    from .io.recording import recording_to_csv
    from .simulate import simulate_recording

    # a machine file's [effect.*] tables act on the simulated machine, driven by the recorded channels
    stored = []
    if machine.effects:
        from .effects.stored import StoredEffectsTransform

        stored = [StoredEffectsTransform(machine, machine.effects)]
    if machine.discrepancy is not None:
        # a calibrated machine's model discrepancy moves its simulated tool as it moves the real one
        from .discrepancy.model import DiscrepancyTransform

        stored.append(DiscrepancyTransform(machine.discrepancy))
    tolerance = machine.tolerance * tolerance_scale
    if effects or aux:
        from .effects.simulate import parse_effect_spec, simulate_with_effects

        specs = [parse_effect_spec(s) for s in effects]
        sim = simulate_with_effects(machine, n, seed=seed, dof=dof, effects=specs, record=aux, tolerance=tolerance,
                                    extra=stored)
    else:
        sim = simulate_recording(machine, n, seed=seed, dof=dof, tolerance=tolerance, q=q, effects=stored)
    err = np.linalg.norm(sim.recording.position - machine.forward(sim.recording.q).position, axis=1)
    # the truth machine with its [effect.*] and [discrepancy], not the calibration's uncertainty (this is the truth,
    # not an estimate)
    return SimulatedSession(sim.recording, recording_to_csv(sim.recording),
                            {"machine": machine.name, "dof": dof, **sim.truth_dict()},
                            machine_file_text(machine.with_calibration(None, machine.discrepancy), sim.theta_true),
                            f"{n} poses, {dof}-DOF", (float(np.sqrt(np.mean(err**2))), float(err.max())))


def _ballbar(machine, n, seed, dof, tolerance_scale, effects, aux, radius, pivot, planes) -> SimulatedSession:
    """A ballbar session: circles about a pivot, read as distances (a constraint recording)."""
    from .constraints.simulate import simulate_ballbar
    from .io.constraints import constraints_to_csv

    if effects or aux or dof != 6:
        raise InputError("ballbar (--ballbar) records distances to a pivot; it does not take effects (--effect), "
                         "aux (--aux) or dof (--dof)")
    if pivot is not None:
        if isinstance(pivot, str):
            try:
                pivot = [float(v) for v in pivot.split(",")]
            except ValueError:
                pivot = []
        if len(pivot) != 3:
            raise InputError(f"pivot (--pivot): expected X,Y,Z in mm, got {pivot!r}")
    sim = simulate_ballbar(machine, radius, n_points=n, pivot=pivot, planes=tuple(planes or ("xy",)), seed=seed,
                           tolerance=machine.tolerance * tolerance_scale)
    return SimulatedSession(sim.recording, constraints_to_csv(sim.recording),
                            {"machine": machine.name, "measure": "ballbar", **sim.truth_dict(machine)},
                            machine.to_toml(sim.theta_true), f"{sim.recording.n_rows} ballbar readings of {radius:g} mm",
                            None)
