"""What several commands read from their arguments: the recording's model and name lists."""

from __future__ import annotations

import argparse

from ..io import Recording, read_recording
from ..machines import Machine, load_machine
from ..measurement import MeasurementModel, check_recording_solves


def name_list(text: str) -> list[str]:
    """Comma-separated names (``"a, b,,c"`` -> ``["a", "b", "c"]``)."""
    return [s.strip() for s in text.split(",") if s.strip()]


def free_arg(text: str) -> str | list[str]:
    """``--free``: ``"auto"``, ``"all"`` or a list of parameter names."""
    return text if text in ("auto", "all") else name_list(text)


def recording_model(args: argparse.Namespace) -> tuple[Machine, Recording, MeasurementModel]:
    """Machine file, recording and measurement model of ``args.machine`` / ``args.recording`` (``args.dof``).

    Raises a BayescalError naming the recording's file and line when the
    machine cannot assemble one of its poses at the nominal geometry.
    """
    machine = load_machine(args.machine)
    rec = read_recording(args.recording)
    model = MeasurementModel.from_recording(machine, rec, dof=getattr(args, "dof", None))
    check_recording_solves(model, rec)
    return machine, rec, model
