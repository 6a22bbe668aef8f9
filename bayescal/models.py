"""The measurement model of any recording: measured poses or measured relations.

The one place that knows which model goes with which recording; every
consumer (diagnosis, comparison, grids) asks here and then sees only the
measurement-model interface (:mod:`bayescal.measurement`).
"""

from __future__ import annotations

import os

from .io import Recording, read_recording
from .io.constraints import ConstraintRecording, is_constraint_recording, read_constraints
from .machines.base import Machine

__all__ = ["read_any_recording", "model_from_recording"]


def read_any_recording(path: str | os.PathLike, *, text: str | None = None) -> Recording | ConstraintRecording:
    """Read a recording CSV: a constraint recording (a ``measure`` column, docs/formats.md section 6) or measured poses.

    Which of the two it is, :func:`~bayescal.io.constraints.is_constraint_recording` decides (from
    the header, as CSV); the reader of that kind then reports any error with file, line and column.

    Parameters
    ----------
    path : path-like
        The CSV file; with ``text``, only the name messages give.
    text : str, optional
        The file's content, when it does not come from ``path`` (a comparison file holds it).

    Returns
    -------
    Recording or ConstraintRecording
    """
    if is_constraint_recording(path, text=text):
        return read_constraints(path, text=text)
    return read_recording(path, text=text)


def model_from_recording(machine: Machine, rec: Recording | ConstraintRecording, *, dof: int | None = None, check: bool = True):
    """The measurement model of ``rec``: a :class:`~bayescal.constraints.model.ConstraintModel` for measured
    relations, a :class:`~bayescal.measurement.MeasurementModel` for measured poses.

    ``check`` rows (a ``role`` column, docs/formats.md section 8) are left out: the model is of the
    ``fit`` rows, the rows anything is identified from.

    Raises a BayescalError naming the recording's file and line when the
    machine cannot assemble one of its poses at the nominal geometry (for
    measured poses only with ``check``; a constraint recording is always checked).
    """
    if isinstance(rec, ConstraintRecording):
        from .constraints.model import ConstraintModel, check_pivot_readings

        check_pivot_readings(rec)  # a pivot per reading leaves nothing to identify the geometry from
        return ConstraintModel.from_recording(machine, rec, dof=dof)
    from .measurement import MeasurementModel, check_recording_solves

    if rec.is_check.any():
        # docs/formats.md section 8: check rows are never used to identify anything
        import numpy as np

        rec = rec.subset(np.flatnonzero(~rec.is_check))
    model = MeasurementModel.from_recording(machine, rec, dof=dof)
    if check:
        check_recording_solves(model, rec)
    return model
