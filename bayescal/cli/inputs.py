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


def recording_model(args: argparse.Namespace, *, constraints: bool = False) -> tuple[Machine, Recording, MeasurementModel]:
    """Machine file, recording and measurement model of ``args.machine`` / ``args.recording`` (``args.dof``).

    Raises a BayescalError naming the recording's file and line when the
    machine cannot assemble one of its poses at the nominal geometry.  A
    constraint recording (FORMATS.md section 6, a ``measure`` column) gives a
    :class:`~bayescal.constraint_model.ConstraintModel` when the command
    takes one (``constraints=True``), and a clear error otherwise.
    """
    machine = load_machine(args.machine)
    from ..io.constraints import is_constraint_recording

    if is_constraint_recording(args.recording):
        from ..constraint_model import ConstraintModel
        from ..errors import InputError
        from ..io.constraints import read_constraints

        if not constraints:
            raise InputError(
                f"{args.recording}: a constraint recording (distances, heights, ballbar); this command takes "
                "recordings of measured poses only (use bayescal identify)"
            )
        crec = read_constraints(args.recording)
        return machine, crec, ConstraintModel.from_recording(machine, crec, dof=getattr(args, "dof", None))
    rec = read_recording(args.recording)
    model = MeasurementModel.from_recording(machine, rec, dof=getattr(args, "dof", None))
    check_recording_solves(model, rec)
    return machine, rec, model
