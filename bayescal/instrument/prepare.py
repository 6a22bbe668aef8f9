"""The measurement model of a recording in the base frame, a known instrument frame, or a fitted one."""

from __future__ import annotations

import numpy as np

from ..errors import InputError, RecordingError
from ..io.recording import Recording
from ..machines.base import Machine
from ..machines.framed import InstrumentFrame, base_machine
from ..measurement import MeasurementModel, check_recording_solves
from .alignment import FrameCheck, check_frame, frame_start
from .units import check_recording_units

__all__ = ["FRAMES", "prepare_model", "station_frames"]

#: ``--frame`` choices: the recording is in the base frame (or the machine file's known
#: ``[instrument]`` frame), or in an unknown instrument frame fitted with the geometry.
FRAMES = ("base", "fit")


def prepare_model(
    machine: Machine, rec: Recording, *, dof: int | None = None, frame: str = "base"
) -> tuple[Machine, MeasurementModel, FrameCheck | None]:
    """Check a recording's units and build its measurement model, with the instrument frame asked for.

    Parameters
    ----------
    machine : Machine
        As loaded (it carries a known ``[instrument]`` frame if its file has one).
    rec : Recording
    dof : int, optional
        6, 5 or 3; default: what the recording holds.
    frame : {"base", "fit"}
        ``"base"``: the recording is in the machine's base frame (or its
        known instrument frame).  ``"fit"``: in an unknown instrument frame,
        fitted with the geometry, started from the closed-form alignment
        (:func:`~bayescal.instrument.alignment.frame_start`).

    Returns
    -------
    machine : Machine
        The machine the model uses (an :class:`InstrumentFrame` with six
        frame parameters first for ``"fit"``).
    model : MeasurementModel
        With the recording's per-pose noise, if it has any.
    check : FrameCheck or None
        For ``"base"``: whether a rigid transform explains the recording far
        better than the tolerances (then suggest ``--frame fit``; the
        command line warns on stderr).

    Raises
    ------
    RecordingError
        Units that look wrong (:func:`check_recording_units`), a pose the
        nominal machine cannot assemble, or (``"base"``) a recording the
        check refuses (:attr:`FrameCheck.refuses`: more than 100 times
        what the tolerances explain, and rigidly explained).
    """
    if frame not in FRAMES:
        raise InputError(f"frame: expected one of {', '.join(FRAMES)}, got {frame!r}")
    rec.check_machine(machine.n_actuators, machine.q_limits, machine.source, machine.actuator_units)
    check_recording_units(machine, rec)
    check = None
    if frame == "fit":
        machine = station_frames(machine, rec, dof=dof)
    else:
        check = check_frame(machine, rec)
        if check is not None and check.refuses:
            # metres off, tens of degrees turned: no calibration in the base frame can mean anything
            raise RecordingError(rec.path, None, None, check.message())
    model = MeasurementModel.from_recording(machine, rec, dof=dof)
    try:
        check_recording_solves(model, rec)
    except RecordingError as exc:
        if check is None or not check.fires:
            raise
        # started from poses measured in another frame, the kinematics land nowhere: say why
        raise RecordingError(rec.path, None, None, check.message()) from exc
    return machine, model, check


def station_frames(machine: Machine, rec: Recording, *, dof: int | None = None) -> InstrumentFrame:
    """A fitted instrument frame per station of ``rec`` (FORMATS.md section 8), each started by its own alignment.

    One station (no ``station`` column, or one label) gives the single frame
    of section 4 (parameters ``frame.origin.x`` ...); several give six
    parameters each (``frame.<station>.origin.x`` ...), bound to the
    recording's poses.

    Raises
    ------
    RecordingError
        A station with too few poses to align a frame (at least 3 points, or
        2 with orientations), naming the station.
    """
    base = base_machine(machine)
    stations = rec.stations
    idx = rec.station_index
    need = 3 if rec.dof == 3 else 2
    frames = []
    for k, label in enumerate(stations):
        rows = np.flatnonzero(idx == k)
        if rows.size < need:
            raise RecordingError(rec.path, int(rec.lines[rows[0]]) if rows.size else None, "station",
                                 f"station {label!r} has {rows.size} pose(s); at least {need} are needed to fit its frame")
        frames.append(frame_start(machine, rec.subset(rows), dof=dof))
    if len(stations) == 1:
        return InstrumentFrame(base, frames[0], fit=True)
    return InstrumentFrame(base, frames[0], fit=True, stations=stations, frames0=tuple(frames), pose_station=idx)
