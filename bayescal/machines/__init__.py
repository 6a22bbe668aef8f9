"""Kinematic families.  ``load_machine`` reads a machine file of any shipped kind."""

from __future__ import annotations

import os

from ..errors import MachineFileError
from ..io.machine_file import TomlTable, read_toml
from .base import Machine, MeasurementNoise, ToolPoses
from .check import MachineCheckError, check_machine
from .linear_delta import LinearDelta
from .framed import Frame, InstrumentFrame, read_instrument
from .prs3 import Prs3
from .raspm import Raspm
from .rupus_prs import RupusPrs
from .hybrid import Hybrid, write_machine_files
from .serial import Serial

__all__ = [
    "Machine", "ToolPoses", "MeasurementNoise", "Prs3", "RupusPrs", "Raspm", "Serial", "Hybrid", "LinearDelta", "KINDS",
    "load_machine", "machine_from_text", "write_machine_files", "check_machine", "MachineCheckError", "InstrumentFrame",
    "Frame",
]

#: Machine kinds by the ``kind`` string of the machine file.
KINDS: dict[str, type[Machine]] = {
    Prs3.kind: Prs3, RupusPrs.kind: RupusPrs, Raspm.kind: Raspm, Serial.kind: Serial, Hybrid.kind: Hybrid,
    LinearDelta.kind: LinearDelta,
}


def _build(doc, path: str) -> Machine:
    kind = doc.string("kind")
    if kind not in KINDS:
        raise MachineFileError(path, "kind", f"unknown kind {kind!r}; expected one of: {', '.join(KINDS)}")
    # docs/formats.md section 4: an optional [instrument] table (the recordings' frame) for every kind;
    # [effect.<name>] tables (section 7) are read for every kind alike, after the geometry
    frame = read_instrument(doc, path)
    extra = ("effect", "instrument", "calibration", "discrepancy")
    geometry = type(doc)({k: v for k, v in doc.data.items() if k not in extra}, doc.path, doc.prefix)
    machine = KINDS[kind].from_toml(geometry, path)
    if "effect" in doc.data:
        from ..effects.stored import read_effect_tables

        machine = machine.with_effects(read_effect_tables(doc, machine))
    if "calibration" in doc.data or "discrepancy" in doc.data:
        # the calibration's uncertainty and model discrepancy, for bayescal predict (docs/formats.md section 8)
        from ..discrepancy.table import read_discrepancy
        from ..prediction.record import check_record, read_calibration

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
    from ..io.machine_file import parse_toml_text

    return _build(TomlTable(parse_toml_text(text, path), path, ""), path)
