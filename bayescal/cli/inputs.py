"""What several commands read from their arguments: the recording's model and name lists.

The parsers' pieces here (:func:`add_frame_argument`, the name lists) import no numpy; the library is
imported by the functions that read the files (issue 31: ``COMMAND --help`` builds its parser only).
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..io import Recording
    from ..machines import Machine
    from ..measurement import MeasurementModel


def name_list(text: str) -> list[str]:
    """Comma-separated names (``"a, b,,c"`` -> ``["a", "b", "c"]``)."""
    return [s.strip() for s in text.split(",") if s.strip()]


def bound_args(texts) -> dict[str, tuple[float, float]] | None:
    """``--bound NAME=LO:HI`` (repeatable) as ``{name: (lo, hi)}``; an empty side (``NAME=:0.1``) is open.

    Raises
    ------
    InputError
        Naming the argument that is not ``NAME=LO:HI`` with numbers (``inf`` and ``-inf`` allowed).
    """
    if not texts:
        return None
    from ..errors import InputError

    out = {}
    for text in texts:
        name, eq, rng = text.partition("=")
        lo, colon, hi = rng.partition(":")
        try:
            if not (eq and colon and name.strip()):
                raise ValueError
            pair = (float(lo) if lo.strip() else None, float(hi) if hi.strip() else None)
        except ValueError:
            raise InputError(f"--bound {text!r}: expected NAME=LO:HI in the parameter's unit, e.g. "
                             "--bound chain1.link_length=-0.1:0.1 (an empty side is open: NAME=0:)") from None
        if name.strip() in out:
            raise InputError(f"--bound: '{name.strip()}' given twice")
        out[name.strip()] = pair
    return out


def free_arg(text: str) -> str | list[str]:
    """``--free``: ``"auto"``, ``"all"`` or a list of parameter names."""
    return text if text in ("auto", "all") else name_list(text)


def recording_model(args: argparse.Namespace, *, constraints: bool = False) -> tuple[Machine, Recording, MeasurementModel]:
    """Machine file, recording and measurement model of ``args.machine`` / ``args.recording`` (``args.dof``).

    Raises a BayescalError naming the recording's file and line when the
    machine cannot assemble one of its poses at the nominal geometry.  A
    constraint recording (docs/formats.md section 6, a ``measure`` column) gives a
    :class:`~bayescal.constraints.model.ConstraintModel` when the command
    takes one (``constraints=True``), and a clear error otherwise.
    With ``args.frame`` (``--frame base|fit``) see :func:`instrument_inputs`.
    """
    if hasattr(args, "frame"):
        machine, rec, model, _ = instrument_inputs(args, constraints=constraints)
        return machine, rec, model
    from ..io import read_recording
    from ..machines.files import load_machine
    from ..measurement import MeasurementModel, check_recording_solves

    machine = load_machine(args.machine)
    constrained = _constraint_inputs(args, machine, constraints)
    if constrained is not None:
        return constrained
    from ..instrument.prepare import fit_size_check

    rec = read_recording(args.recording, check_size=fit_size_check(machine, dof=getattr(args, "dof", None),
                                                                   path=args.recording))
    if rec.is_check.any():  # docs/formats.md section 8: check rows are never identified from
        import numpy as np

        rec = rec.subset(np.flatnonzero(~rec.is_check))
    model = MeasurementModel.from_recording(machine, rec, dof=getattr(args, "dof", None))
    check_recording_solves(model, rec)
    return machine, rec, model


def _constraint_inputs(args: argparse.Namespace, machine: Machine, constraints: bool):
    """``(machine, recording, ConstraintModel)`` for a constraint recording (docs/formats.md section 6), else None."""
    from ..io.constraints import is_constraint_recording

    if not is_constraint_recording(args.recording):
        return None
    from ..constraints.model import load_constraint_model
    from ..errors import InputError

    if not constraints:
        raise InputError(
            f"{args.recording}: a constraint recording (distances, heights, ballbar); this command takes "
            "recordings of measured poses only (use bayescal identify)"
        )
    frame = getattr(args, "frame", "base")
    try:
        crec, model = load_constraint_model(machine, args.recording, frame=frame, dof=getattr(args, "dof", None))
    except InputError as e:
        if frame == "fit" and str(e).startswith("frame fit:"):
            raise InputError("--" + str(e).replace("use the base frame", "drop --frame fit")) from None
        raise
    return model.calibrated_machine, crec, model


# ---------------------------------------------------------------- instrument frame (docs/formats.md section 4)
FRAME_HELP = (
    "frame of the recording: 'base' (default: the machine's base frame, or the machine file's [instrument] "
    "frame) or 'fit' (an unknown instrument frame, fitted with the geometry; docs/real-instruments.md)"
)


def add_frame_argument(p) -> None:
    """``--frame base|fit`` for commands that read a recording."""
    p.add_argument("--frame", choices=("base", "fit"), default="base", help=FRAME_HELP)


def instrument_inputs(args: argparse.Namespace, *, constraints: bool = False):
    """Machine, recording (its ``fit`` rows), model of those rows and the rigid-transform check, with ``args.frame``.

    A constraint recording gives ``(machine, recording, ConstraintModel, None)``
    when ``constraints`` (see :func:`recording_model`).

    Units are checked (RecordingError for positions that look like metres,
    angles like degrees).  With ``--frame base``, a recording that a rigid
    transform explains far better than the tolerances gets a warning on
    stderr suggesting ``--frame fit`` (unless ``--quiet``).  ``check`` rows
    (docs/formats.md section 8) are left out: :func:`instrument_session` keeps them.
    """
    return inputs_with_session(args, constraints=constraints)[:4]


def inputs_with_session(args: argparse.Namespace, *, constraints: bool = False):
    """As :func:`instrument_inputs`, plus the :class:`~bayescal.instrument.prepare.Session` (None for constraints)."""
    from ..machines.files import load_machine

    machine = load_machine(args.machine)
    constrained = _constraint_inputs(args, machine, constraints)
    if constrained is not None:
        return (*constrained, None, None)
    session = instrument_session(args, machine).with_fitted_stations()
    # the machine bound to the fit rows' stations (a command that rebuilds the model from the recording it gets)
    fit_model = session.fit_model
    return fit_model.machine, session.fit_recording, fit_model, session.check, session


def instrument_session(args: argparse.Namespace, machine=None):
    """The :class:`~bayescal.instrument.prepare.Session` of ``args.recording`` (every row, with its role)."""
    import sys

    from ..instrument.prepare import fit_size_check, prepare_session
    from ..io import read_recording
    from ..machines.files import load_machine

    machine = load_machine(args.machine) if machine is None else machine
    rec = read_recording(args.recording, check_size=fit_size_check(
        machine, dof=getattr(args, "dof", None), frame=getattr(args, "frame", "base"), path=args.recording))
    session = prepare_session(machine, rec, dof=getattr(args, "dof", None), frame=getattr(args, "frame", "base"))
    from ..io.recording import near_reserved_columns

    warnings = near_reserved_columns(rec) + ([] if session.check is None or not session.check.warning()
                                             else [session.check.warning()])
    for warning in [] if getattr(args, "quiet", False) else warnings:
        print(f"bayescal {args.command}: warning: {warning}", file=sys.stderr)
    return session
