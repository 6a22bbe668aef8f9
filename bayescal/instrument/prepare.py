"""The measurement model of a recording in the base frame, a known instrument frame, or fitted ones (per station).

Roles (docs/formats.md section 8): only ``fit`` rows are ever identified from;
``check`` rows are held out.  :func:`prepare_session` builds one model of
every row (so that all rows share the machine, its stations and frames) and
gives the ``fit`` and ``check`` parts; :func:`prepare_model` gives the
``fit`` part, which is what every command that identifies anything uses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import InputError, RecordingError
from ..io.recording import Recording
from ..limits import check_fit_memory
from ..machines.base import Machine
from ..machines.framed import Frame, InstrumentFrame
from ..measurement import MeasurementModel, check_recording_solves
from .alignment import FrameCheck, check_frame, frame_start
from ..progress import report
from .units import check_recording_units

__all__ = ["fit_size_check", "FRAMES", "Session", "prepare_model", "prepare_session", "station_frames"]

#: ``--frame`` choices: the recording is in the base frame (or the machine file's known
#: ``[instrument]`` frame), or in an unknown instrument frame fitted with the geometry.
FRAMES = ("base", "fit")


@dataclass(frozen=True)
class Session:
    """A recording's model with its roles.

    Attributes
    ----------
    machine : Machine
        The machine the model uses (with the stations' fitted frames for ``frame="fit"``).
    model : MeasurementModel
        Every row of the recording.
    recording : Recording
    check : FrameCheck or None
        The rigid-transform check of the ``fit`` rows (base frame only).
    unfitted_stations : tuple of str
        Stations with too few ``fit`` rows (none; or, for ``predict``, fewer than a frame needs): their
        frames cannot be fitted, their rows not predicted.
    """

    machine: Machine
    model: MeasurementModel
    recording: Recording
    check: FrameCheck | None = None
    unfitted_stations: tuple[str, ...] = ()

    @property
    def fit_rows(self) -> np.ndarray:
        return ~self.recording.is_check

    @property
    def fit_model(self) -> MeasurementModel:
        """The model of the ``fit`` rows (all rows when the recording has no ``role`` column)."""
        rows = self.fit_rows
        return self.model if rows.all() else self.model.subset(np.flatnonzero(rows))

    @property
    def fit_recording(self) -> Recording:
        rows = self.fit_rows
        return self.recording if rows.all() else self.recording.subset(np.flatnonzero(rows))

    @property
    def check_model(self) -> MeasurementModel | None:
        """The model of the ``check`` rows, or None when there are none."""
        rows = self.recording.is_check
        return self.model.subset(np.flatnonzero(rows)) if rows.any() else None

    def with_fitted_stations(self) -> "Session":
        """This session, refused when a station has no ``fit`` rows (its frame could not be fitted).

        Raises
        ------
        RecordingError
            Naming the recording and the station.
        """
        if self.unfitted_stations:
            raise RecordingError(self.recording.path, None, "station", f"station {self.unfitted_stations[0]!r} has no "
                                 "fit rows; its frame cannot be fitted (give it fit rows, or leave its rows out)")
        return self

    def row_errors(self) -> list[str | None]:
        """Per row, why it cannot be predicted from this session (its station has no ``fit`` row), else None."""
        if not self.unfitted_stations or self.recording.station is None:
            return [None] * self.recording.n_poses
        bad = set(self.unfitted_stations)
        return [f"station {s!r} has too few fit rows to fit its frame" if s in bad else None for s in self.recording.station]


def fit_size_check(machine: Machine, *, dof: int | None = None, frame: str = "base", stations: int = 1,
                   path: str = "") -> Callable[[int, int], None]:
    """The memory check of a fit of a recording, for :func:`bayescal.io.read_recording`'s ``check_size``.

    The returned function takes the recording's poses and measured
    components per pose and refuses (InputError, through
    :func:`bayescal.limits.check_fit_memory`) a fit whose arrays would not fit
    in the memory budget: ``dof`` (when given) components per pose, the
    machine's parameters and, for ``frame="fit"``, six per station.
    :func:`prepare_session` checks the same once more with the stations the
    recording has.
    """
    n_params = machine.n_params + (6 * stations if frame == "fit" else 0)

    def check(n_poses: int, row_dof: int) -> None:
        check_fit_memory(n_poses * (dof or row_dof), n_params, f"{path}: identifying" if path else "identifying")

    return check


def prepare_session(
    machine: Machine, rec: Recording, *, dof: int | None = None, frame: str = "base", strict: bool = True,
    sensors: bool = True,
) -> Session:
    """Check a recording's units and build the model of all its rows, with the instrument frame(s) asked for.

    Parameters
    ----------
    machine : Machine
        As loaded (it carries a known ``[instrument]`` frame if its file has one).
    rec : Recording
    dof : int, optional
        6, 5 or 3; default: what the recording holds.
    frame : {"base", "fit"}
        ``"base"``: the recording is in the machine's base frame (or its
        known instrument frame).  ``"fit"``: in unknown instrument frames, one
        per station (docs/formats.md section 8), fitted with the geometry, each
        started from the closed-form alignment of its station's ``fit`` rows.
    strict : bool
        Refuse a recording with a pose the nominal machine cannot solve
        (``predict`` reports such rows instead).
    sensors : bool
        Body sensors as measurements (:meth:`MeasurementModel.from_recording`);
        ``predict`` reads them as auxiliary channels only.

    Raises
    ------
    InputError
        (``strict``) A recording whose fit would not fit in the memory budget
        (:func:`bayescal.limits.check_fit_memory`), before anything is solved.
    RecordingError
        Units that look wrong (:func:`check_recording_units`), a pose the
        nominal machine cannot assemble (``strict``), or (``"base"``) a
        recording the check refuses (:attr:`FrameCheck.refuses`: more than
        100 times what the tolerances explain, and rigidly explained).
    """
    if frame not in FRAMES:
        raise InputError(f"frame: expected one of {', '.join(FRAMES)}, got {frame!r}")
    rec.check_machine(machine.n_actuators, machine.q_limits, machine.source, machine.actuator_units)
    if strict:
        # before any pose is solved: a recording whose fit cannot fit in memory ends now, not minutes later
        fit_size_check(machine, dof=dof, frame=frame, stations=len(rec.stations), path=rec.path)(rec.n_poses, rec.dof)
    check_recording_units(machine, rec)
    fit_rec = rec.subset(np.flatnonzero(~rec.is_check)) if rec.is_check.any() else rec
    check, unfitted = None, ()
    if frame == "fit":
        machine, unfitted = station_frames(machine, rec, dof=dof, lenient=not strict)
    else:
        check = _base_frame_check(machine, fit_rec)
    model = MeasurementModel.from_recording(machine, rec, dof=dof, sensors=sensors)
    if strict:
        report(lambda: f"solving the nominal kinematics at {rec.n_poses:,} poses")
        usable = np.ones(rec.n_poses, dtype=bool)
        if unfitted and rec.station is not None:
            usable = np.array([st not in unfitted for st in rec.station])
        try:
            if usable.all():
                check_recording_solves(model, rec)
            elif usable.any():
                keep = np.flatnonzero(usable)
                check_recording_solves(model.subset(keep), rec.subset(keep))
        except RecordingError as exc:
            if check is None or not check.fires:
                raise
            # started from poses measured in another frame, the kinematics land nowhere: say why
            raise RecordingError(rec.path, None, None, check.message()) from exc
    return Session(machine, model, rec, check, unfitted)


def _base_frame_check(machine: Machine, rec: Recording) -> FrameCheck | None:
    """The rigid-transform check of a recording said to be in the base frame, per station when it has several.

    Several stations in the base frame are legitimate (sessions of one frame), but a station measured in its own
    instrument frame would otherwise pass unnoticed: no one rigid transform explains two stations at once.
    """
    subsets = [rec]
    if len(rec.stations) > 1:
        idx = rec.station_index
        subsets = [rec.subset(np.flatnonzero(idx == k)) for k in range(len(rec.stations))
                   if np.count_nonzero(idx == k) >= 3]
    first = None
    for k, sub in enumerate(subsets):
        check = check_frame(machine, sub)
        if check is None:
            continue
        where = f"station {sub.station[0]!r}: " if len(subsets) > 1 and sub.station else ""
        if check.refuses:
            # metres off, tens of degrees turned: no calibration in the base frame can mean anything
            raise RecordingError(rec.path, None, None, where + check.message())
        if first is None or (check.fires and not first.fires):
            first = check
    return first


def prepare_model(
    machine: Machine, rec: Recording, *, dof: int | None = None, frame: str = "base"
) -> tuple[Machine, MeasurementModel, FrameCheck | None]:
    """The machine, the model of the recording's ``fit`` rows, and the frame check (:func:`prepare_session`).

    Returns
    -------
    machine : Machine
        The machine the model uses (an :class:`InstrumentFrame` with six
        frame parameters per station first for ``"fit"``).
    model : MeasurementModel
        Of the ``fit`` rows, with the recording's per-pose noise, if it has any.
    check : FrameCheck or None
        For ``"base"``: whether a rigid transform explains the recording far
        better than the tolerances (then suggest ``--frame fit``; the
        command line warns on stderr).
    """
    s = prepare_session(machine, rec, dof=dof, frame=frame)
    if s.unfitted_stations:
        raise RecordingError(rec.path, None, "station", f"station {s.unfitted_stations[0]!r} has no fit rows; its "
                             "frame cannot be fitted (give it fit rows, or leave its rows out)")
    return s.machine, s.fit_model, s.check


def station_frames(machine: Machine, rec: Recording, *, dof: int | None = None,
                   lenient: bool = False) -> tuple[InstrumentFrame, tuple[str, ...]]:
    """A fitted instrument frame per station of ``rec`` (docs/formats.md section 8), each started by its own alignment.

    One station (no ``station`` column, or one label) gives the single frame
    of section 4 (parameters ``frame.origin.x`` ...); several give six
    parameters each (``frame.<station>.origin.x`` ...), bound to the
    recording's poses.  Each start uses the station's ``fit`` rows only.

    Returns
    -------
    (InstrumentFrame, tuple of str)
        The frames, and the stations without ``fit`` rows (their start is
        the identity; their rows cannot be predicted).

    Raises
    ------
    RecordingError
        A station with too few ``fit`` poses to align a frame (at least 3
        points, or 2 with orientations), naming the station.
    """
    base = machine.base_machine()
    stations = rec.stations
    idx = rec.station_index
    fit = ~rec.is_check
    need = rec.frame_fit_poses
    frames, unfitted = [], []
    for k, label in enumerate(stations):
        rows = np.flatnonzero((idx == k) & fit)
        if rows.size == 0:
            unfitted.append(label)
            frames.append(Frame.identity())
            continue
        if rows.size < need and lenient:
            unfitted.append(label)  # predict: its rows say why, the others are predicted
            frames.append(Frame.identity())
            continue
        if rows.size < need:
            raise _too_few_fit_poses(rec, label, rows, need)
        frames.append(frame_start(machine, rec.subset(rows), dof=dof))
    if len(stations) == 1:
        return InstrumentFrame(base, frames[0], fit=True), tuple(unfitted)
    framed = InstrumentFrame(base, frames[0], fit=True, stations=stations, frames0=tuple(frames), pose_station=idx)
    return framed, tuple(unfitted)


def _too_few_fit_poses(rec: Recording, label: str, rows, need: int) -> RecordingError:
    """The error for a station (or a recording without a ``station`` column) too small to align a frame."""
    line = int(rec.lines[rows[0]]) if rows.size else None
    what = "orientations" if need == 2 else "positions only"
    if rec.station is None:
        return RecordingError(rec.path, line, None, f"{rows.size} fit pose(s); at least {need} ({what}) are needed to "
                              "fit the instrument frame (--frame fit)")
    return RecordingError(rec.path, line, "station", f"station {label!r} has {rows.size} fit pose(s); at least {need} "
                          f"({what}) are needed to fit its frame")
