"""Write a calibrated machine as machine files: one file, or a hybrid in docs/formats.md section 5's file-per-module form.

One place for what ``--write-machine`` of every command and
:meth:`bayescal.diagnose.calibrated.CalibratedMachine.write` write, so that
a library user and the command line produce the same files: every kind is
one file with its ``[effect.*]`` and ``[instrument]`` tables; a hybrid
machine puts each module in ``<stem>.m<k>.toml`` beside the main file (the
form any reader of docs/formats.md section 5 reads; bayescal's own inline form is not in
the contract), and its ``[effect.*]`` and ``[instrument]`` tables go into
the main file.  The files of a hybrid are written as one unit, the main
file renamed last (:func:`bayescal.io.answers.write_files_atomic`).
"""

from __future__ import annotations

from pathlib import Path

from numpy.typing import ArrayLike

from ..io.answers import write_files_atomic, write_text_atomic
from .base import Machine

__all__ = ["write_calibrated_machine_files", "written_as_modules"]


def written_as_modules(machine: Machine) -> bool:
    """Whether ``machine`` (possibly in an instrument frame) is written as a main file plus module files."""
    from .framed import InstrumentFrame
    from .hybrid import Hybrid

    return isinstance(machine.machine if isinstance(machine, InstrumentFrame) else machine, Hybrid)


def write_calibrated_machine_files(path, machine: Machine, theta: ArrayLike | None = None, *,
                                   header: str = "") -> list[Path]:
    """Write ``nominal + theta`` of ``machine`` (its effects and instrument frame kept) to ``path``.

    Parameters
    ----------
    path : path
        The machine file (TOML) to write; module files of a hybrid go beside it.
    machine : Machine
        Any kind, possibly in an instrument frame or with effects.
    theta : array_like, shape (P,), optional
        Geometric errors (mm, rad) to fold in; zeros if omitted.
    header : str
        Comment lines (each starting with ``#``) put at the top of the main file.

    Returns
    -------
    list of Path
        The files written, the main file first.
    """
    from ..effects.stored import calibration_tables_toml, effect_tables_toml, machine_file_text
    from .framed import InstrumentFrame, instrument_toml
    from .hybrid import machine_files_text

    if not written_as_modules(machine):
        return [write_text_atomic(path, header + machine_file_text(machine, theta))]
    th = machine.check_theta(theta)
    framed = isinstance(machine, InstrumentFrame)
    inner = machine.machine if framed else machine
    files = machine_files_text(path, inner, th[machine.n_frame:] if framed else th)
    # the main file carries what belongs to the whole machine: its [effect.*] tables and its [instrument] frame
    extra = []
    if machine.effects:
        extra.append(effect_tables_toml(tuple(machine.effects)))
    if framed and machine.n_stations == 1:
        extra.append(instrument_toml(machine.frame_at(th)))
    if tables := calibration_tables_toml(machine).strip("\n"):
        extra.append(tables)
    if extra or header:
        main, text = files[0]
        files[0] = (main, header + "\n\n".join([text.rstrip("\n")] + [e.rstrip("\n") for e in extra]) + "\n")
    # one unit, the main file renamed last (bayescal.io.answers.write_files_atomic)
    write_files_atomic(files[1:] + files[:1])
    return [p for p, _ in files]
