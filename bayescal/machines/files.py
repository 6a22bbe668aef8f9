"""Machine files in and out: read one of any kind with its tables, write a calibrated machine as one or several files.

:func:`load_machine` reads the geometry (by its kind, :data:`bayescal.machines.KINDS`)
and the tables every kind may carry: ``[instrument]`` (section 4),
``[effect.*]`` (section 7), ``[calibration]`` and ``[discrepancy]`` (section 8).

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

import os
from pathlib import Path

from numpy.typing import ArrayLike

from ..discrepancy.table import read_discrepancy
from ..effects.stored import calibration_tables_toml, effect_tables_toml, machine_file_text, read_effect_tables
from ..io.answers import write_files_atomic, write_text_atomic
from ..io.machine_file import TomlTable, parse_toml_text, read_toml
from ..prediction.record import check_record, read_calibration
from .base import Machine, machine_from_table
from .framed import InstrumentFrame, instrument_toml, read_instrument
from .hybrid import machine_files_text

__all__ = ["load_machine", "machine_from_text", "write_calibrated_machine_files", "written_as_modules"]

#: Tables of a machine file read here, around the geometry its kind reads.
_TABLES = ("effect", "instrument", "calibration", "discrepancy")


def _build(doc: TomlTable, path: str) -> Machine:
    # docs/formats.md section 4: an optional [instrument] table (the recordings' frame) for every kind;
    # [effect.<name>] tables (section 7) are read for every kind alike, after the geometry
    frame = read_instrument(doc, path)
    geometry = type(doc)({k: v for k, v in doc.data.items() if k not in _TABLES}, doc.path, doc.prefix)
    machine = machine_from_table(geometry, path)
    if "effect" in doc.data:
        machine = machine.with_effects(read_effect_tables(doc, machine))
    if "calibration" in doc.data or "discrepancy" in doc.data:
        # the calibration's uncertainty and model discrepancy, for bayescal predict (docs/formats.md section 8)
        record = read_calibration(doc, path)
        if record is not None:
            check_record(record, path)
        machine = machine.with_calibration(record, read_discrepancy(doc, path, machine))
    return machine if frame is None else InstrumentFrame(machine, frame, fit=False)


def load_machine(path: str | os.PathLike) -> Machine:
    """Read a machine file (docs/formats.md section 1) of any shipped kind.

    Raises
    ------
    MachineFileError
        Naming the file, the key and what was expected.
    """
    return _build(read_toml(path), str(path))


def machine_from_text(text: str, path: str = "<memory>") -> Machine:
    """Build a machine from machine-file text (as written by ``Machine.to_toml``)."""
    return _build(TomlTable(parse_toml_text(text, path), path, ""), path)


def written_as_modules(machine: Machine) -> bool:
    """Whether ``machine`` (possibly in an instrument frame) is written as a main file plus module files."""
    return bool(machine.inside.written_modules)


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
    if not written_as_modules(machine):
        return [write_text_atomic(path, header + machine_file_text(machine, theta))]
    th = machine.check_theta(theta)
    frame = machine.instrument_frame
    files = machine_files_text(path, machine.inside, th[machine.n_frame:])
    # the main file carries what belongs to the whole machine: its [effect.*] tables and its [instrument] frame
    extra = []
    if machine.effects:
        extra.append(effect_tables_toml(tuple(machine.effects)))
    if frame is not None and frame.n_stations == 1:
        extra.append(instrument_toml(frame.frame_at(th[: frame.n_params])))
    if tables := calibration_tables_toml(machine).strip("\n"):
        extra.append(tables)
    if extra or header:
        main, text = files[0]
        files[0] = (main, header + "\n\n".join([text.rstrip("\n")] + [e.rstrip("\n") for e in extra]) + "\n")
    # one unit, the main file renamed last (bayescal.io.answers.write_files_atomic)
    write_files_atomic(files[1:] + files[:1])
    return [p for p, _ in files]
