"""The diagnosis as the front door calls it: a machine file or Machine, and a recording path or Recording."""

from __future__ import annotations

import os

from ..errors import InputError, refuse_unknown_options
from ..io.recording import Recording
from ..machines import Machine
from ..machines.files import load_machine
from ..models import read_any_recording
from .core import diagnose as diagnose_model

__all__ = ["diagnose_files"]


def diagnose_files(machine: str | os.PathLike | Machine, recording, *, frame: str = "base", **options):
    """:func:`bayescal.api.diagnose` (the front door documents its parameters): files or objects in, a Diagnosis out.

    A pose recording is prepared as every command prepares it
    (:func:`bayescal.instrument.prepare.prepare_session`: units checked, the
    ``check`` rows left out, one instrument frame per station with
    ``frame="fit"``); a constraint recording sees no frame.
    """
    refuse_unknown_options("diagnose", options, diagnose_files, diagnose_model)
    m = machine if isinstance(machine, Machine) else load_machine(machine)
    rec = read_any_recording(recording) if isinstance(recording, (str, os.PathLike)) else recording
    if isinstance(rec, Recording):
        from ..instrument.prepare import prepare_session

        session = prepare_session(m, rec, frame=frame).with_fitted_stations()
        m, rec = session.fit_model.machine, session.fit_recording
    elif frame != "base":
        raise InputError(f"frame {frame}: {rec.path} is a constraint recording; distances and ballbar radii do not see "
                         "an instrument frame, and heights are measured along the base z axis (docs/formats.md "
                         "section 6): use the base frame")
    return diagnose_model(m, rec, **options)
