"""The diagnosis as the front door calls it: a machine file or Machine, and a recording path or Recording."""

from __future__ import annotations

import os

from ..machines import Machine
from ..machines.files import load_machine
from ..models import read_any_recording
from .core import diagnose as diagnose_model

__all__ = ["diagnose_files"]


def diagnose_files(machine: str | os.PathLike | Machine, recording, **options):
    """:func:`bayescal.api.diagnose` (the front door documents its parameters): files or objects in, a Diagnosis out."""
    m = machine if isinstance(machine, Machine) else load_machine(machine)
    rec = read_any_recording(recording) if isinstance(recording, (str, os.PathLike)) else recording
    return diagnose_model(m, rec, **options)
