"""``bayescal predict``: every row of a new recording from a calibrated machine, with a 90 % region, scored by role.

The calibrated machine (geometry, effects, model discrepancy, and the
covariance of its calibration in ``[calibration]``) is held fixed with its
uncertainty.  Only what belongs to the session is fitted, on the ``fit``
rows: the instrument frame of each station with ``frame="fit"``, and the
mountings of the body sensors (a calibrated machine holds none).  Every row
gets its predictive mean and covariance (:mod:`bayescal.prediction.engine`),
its position error and whether it lies inside its 90 % region
(:mod:`bayescal.prediction.score`); a body sensor's reading is a measured
row like the tool's, predicted through the same engine and scored by its
tilt error (:mod:`bayescal.prediction.sensor_score`).  The summary scores
the ``check`` rows (no fit has seen them) and the ``fit`` rows apart.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..contract import scale_noise
from ..errors import InputError
from ..geometry import so3_log
from ..io.recording import Recording
from ..machines.base import Machine
from .engine import FitRowsJoint, PredictiveRows, predictive_rows
from .row_tests import ROW_TEST_ALPHA, RowGroupTest, row_group_tests  # noqa: F401  (their home before)
from .score import REGION_LEVEL, score_rows, summarise
from .sensor_score import sensor_report_lines
from ..notebook import ShowsReport

__all__ = ["PredictionResult", "predict_recording"]


@dataclass(frozen=True)
class PredictionResult(ShowsReport):
    """The answer of :func:`predict_recording` (docs/formats.md section 8).

    Attributes
    ----------
    machine_name : str
    rows : tuple of dict
        Per row: ``line``, ``station``, ``role``, ``measured``, ``predicted``,
        ``std`` (one sigma per measured component: the position's x, y, z in mm, then the orientation's
        small rotation about x, y, z (6-DOF) or the tool axis's two tangential directions (5-DOF), rad),
        ``error_position_mm``,
        ``inside_90``; or ``error`` (why it could not be predicted).  With body sensors also
        ``sensors``: per body, the recorded and predicted reading (the recording's units), the
        one-sigma ``std`` of its two tilt rows (rad), ``error_tilt_rad`` and ``inside_90``
        (:mod:`bayescal.prediction.sensor_score`).
    summary : dict
        ``{"check": {...}, "fit": {...}}``: counts, mean / median / p95
        position error (mm), coverage of the 90 % regions; with body sensors, per role a
        ``sensors`` block: per body the same of the tilt error (rad) and the sensor's ``sigma_tilt_rad``.
    frames : dict
        The session's fitted frames (``{}`` for ``frame="base"``).
    notes : tuple of str
        What the prediction took as known, in words.
    """

    machine_name: str
    rows: tuple[dict, ...]
    summary: dict
    frames: dict
    notes: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        """The JSON answer of ``bayescal predict`` (docs/formats.md section 8), in JSON's own types.

        ``bayescal.io.answers.json_text(result.to_dict())`` is the command's ``--json`` file, byte for byte.
        """
        from ..io.answers import to_jsonable

        return to_jsonable({"machine": self.machine_name, "rows": list(self.rows), "summary": self.summary,
                            **self.frames, "notes": list(self.notes), "region_level": REGION_LEVEL})

    def report(self) -> str:
        lines = [f"bayescal prediction with '{self.machine_name}'"]
        for role in ("check", "fit"):
            s = self.summary.get(role)
            if not s or not s["n"] and not s["n_failed"]:
                continue
            if s["n"]:
                lines.append(
                    f"  {role:<6} {s['n']:>5} rows: position error mean {s['mean_error_position_mm']:.4g} mm, median "
                    f"{s['median_error_position_mm']:.4g}, p95 {s['p95_error_position_mm']:.4g}; inside the 90 % "
                    f"region: {100 * s['coverage_90']:.1f} %")
            if s["n_failed"]:
                lines.append(f"  {role:<6} {s['n_failed']:>5} rows not predicted (see their 'error' in the JSON)")
            lines += sensor_report_lines(s.get("sensors", {}), role)
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)


def predict_recording(machine: Machine, rec: Recording, *, frame: str = "base", dof: int | None = None) -> PredictionResult:
    """Predict every row of ``rec`` from the calibrated ``machine`` (module docstring).

    Parameters
    ----------
    machine : Machine
        As loaded from a calibrated machine file (``bayescal.machines.files.load_machine``):
        its ``calibration`` record gives the parameters' covariance and noise
        scale, its ``discrepancy`` the model discrepancy (either may be absent).
    rec : Recording
        With an optional ``station`` and ``role`` column.
    frame : {"base", "fit"}
        ``fit``: each station's instrument frame is fitted on its ``fit`` rows,
        the machine held fixed.
    dof : int, optional
        6, 5 or 3; default: what the recording holds.

    Returns
    -------
    PredictionResult
    """
    from ..instrument.plausibility import frame_answer

    session, notes = _session(machine, rec, dof, frame)
    fm, model = session.model.machine, session.model
    errors = session.row_errors()
    usable = np.array([e is None for e in errors])
    fit_rows = ~rec.is_check & usable
    disc = machine.discrepancy
    if disc is not None:
        try:
            disc.raw_inputs(model)
        except InputError as exc:
            errors = [str(exc)] * rec.n_poses
            usable[:] = False
            fit_rows[:] = False
    names = fm.layout.names
    n_session = fm.n_frame if frame == "fit" else 0
    theta = np.zeros(fm.n_params)
    frame_free: list[int] = []
    frames = {}
    if n_session:
        fitted = [k for k, label in enumerate(fm.stations) if label not in session.unfitted_stations]
        frame_free = [6 * k + c for k in fitted for c in range(6)]
        if not frame_free:
            raise _no_frame_to_fit(rec)
        theta, fit_ok = _fit_frames(model.without_sensors(), theta, frame_free, fit_rows, disc)
        if not fit_ok:
            raise InputError(f"{rec.path}: the instrument frame(s) could not be fitted on the fit rows")
        free = np.zeros(fm.n_params, dtype=bool)
        free[:n_session] = True
        frames = frame_answer(fm, theta, free, None)
        if session.unfitted_stations and "frames" in frames:
            frames = {"frames": {k: v for k, v in frames["frames"].items() if k not in session.unfitted_stations}}
    sensor_free = _sensor_index(model)
    if sensor_free.size:
        theta = _fit_mountings(model, theta, sensor_free, fit_rows, rec)
    C, machine_index, noise_factor, kappa, note, eff = _machine_covariance(machine, fm, names, disc)
    if note:
        notes.append(note)
    extra = _effect_columns(machine, rec, (dof, frame, model), theta, eff) if eff else None
    # the calibration's noise scale and leave-one-out factor are the tool rows' (the sensors' sigma is the file's)
    td = model.tool_dof
    per_row = lambda v, s=1.0: np.r_[np.broadcast_to(v, (td,)), np.broadcast_to(s, (model.dof - td,))]  # noqa: E731
    kw = dict(machine_index=machine_index, noise_factor=per_row(noise_factor), discrepancy=disc,
              extra_columns=extra, **_session_parameters(model, frame_free, sensor_free))
    pr = _predict_with_row_tests(model, (theta, C, usable, fit_rows), kw, lambda t, s: per_row(kappa * t, s), notes)
    for i in np.flatnonzero(usable & ~pr.success):
        errors[i] = f"cannot be predicted: {pr.message[i] or 'the pose does not solve'}"
    failed = np.array([e is not None for e in errors])
    rows, scores, sensors = _scored_rows(model, theta, pr, rec, errors, failed)
    summary = {role: summarise(scores, mask, failed) for role, mask in (("check", rec.is_check), ("fit", ~rec.is_check))}
    if sensors is not None:
        for role, mask in (("check", rec.is_check), ("fit", ~rec.is_check)):
            summary[role]["sensors"] = sensors.summary(mask, failed)
    if disc is None:
        notes.append("no [discrepancy] in the machine file: the prediction is the kinematic model's")
    return PredictionResult(machine.name, tuple(rows), summary, frames, tuple(notes))


def _session(machine, rec, dof, frame):
    """The session of every row, with the recording's body sensors as measurements where they can be predicted.

    A sensor's mounting is the session's, not the machine's (a calibrated file holds none): it is fitted on
    the fit rows, so without any the sensors are read as channels only, and a note says so.
    """
    from ..instrument.prepare import prepare_session
    from ..sensors import sensor_readings
    from ..sensors.mounts import sensor_base

    # the columns are checked even where the sensors are not predicted (a body the machine lacks, an incomplete
    # x/y/z set, a zero or NaN reading): a base sensor gives the gravity-driven effects their per-pose gravity
    readings = sensor_readings(dict(rec.aux), rec.path, rec.lines, tuple(sensor_base(machine.inside).sensor_bodies))
    bodies = [b for b in readings if b != "base"]
    notes = []
    predicted = bool(bodies) and bool(np.any(~rec.is_check))
    if bodies and not predicted:
        notes.append(f"the sensor reading(s) on {', '.join(map(repr, bodies))} are not predicted: their mountings are "
                     "fitted on the fit rows, and the recording has none")
    session = prepare_session(machine, rec, dof=dof, frame=frame, strict=False, sensors=predicted)
    return session, notes


def _session_parameters(model, frame_free: list[int], sensor_free: np.ndarray) -> dict:
    """:func:`predictive_rows`' ``session_index`` and ``session_prior_std``: the frames, then the mountings.

    Each with the estimator it was fitted by: the frames least squares (no prior, :func:`_fit_frames`), the
    mountings MAP under their tolerance (:func:`_fit_mountings`), whose prior decides what the fit rows do not
    see, and so does its variance there. The engine takes them as one estimator (the least squares of the fit
    rows stacked on the prior's rows); the two fits made in turn are that estimator because an instrument frame
    moves no tilt reading and a mounting no tool point (their columns share no row).
    """
    index = np.array(list(frame_free) + sensor_free.tolist(), dtype=int)
    if not index.size:
        return {"session_index": None}
    tol = np.asarray(model.machine.tolerance, dtype=float)
    return {"session_index": index, "session_prior_std": np.r_[np.full(len(frame_free), np.inf), tol[sensor_free]]}


def _sensor_index(model) -> np.ndarray:
    """The model machine's body-sensor parameters (mountings and up's level: appended last), as indices."""
    k = 0 if model.sensors is None else model.sensors.n_params
    return np.arange(model.n_params - k, model.n_params)


def _fit_mountings(model, theta, sensor_free, fit_rows, rec):
    """The sensors' mountings (and up's level) fitted on the fit rows' tilt rows, the machine held fixed.

    MAP under the machine file's ``sensor_mount`` / ``base_level`` tolerances: a column's sensor mounting and
    the level of up are one direction to such a sensor, the prior splits it as identify's fit does.
    """
    from ..identify.gauss_newton import identify

    fit_idx = np.flatnonzero(fit_rows)
    sub = model.subset(fit_idx)
    ok = np.flatnonzero(sub.predict(theta).success)
    res = identify(sub.subset(ok), method="map", free=sensor_free.tolist(), theta0=theta)
    if not res.success:
        raise InputError(f"{rec.path}: the body sensors' mountings could not be fitted on the fit rows "
                         f"({res.message or 'the fit did not converge'})")
    return res.theta


def _predict_usable(model, theta, C, usable, fit_rows, **kw) -> PredictiveRows:
    """:func:`predictive_rows` of the usable rows, NaN (not successful) elsewhere."""
    n = model.n_poses
    pr = PredictiveRows(np.full((n, model.dof), np.nan), np.full((n, model.dof, model.dof), np.nan),
                        np.zeros(n, dtype=bool), ("",) * n)
    idx = np.flatnonzero(usable)
    if not idx.size:
        return pr
    if kw.get("extra_columns") is not None:
        kw = {**kw, "extra_columns": kw["extra_columns"][idx]}
    got = predictive_rows(model.subset(idx), theta, C, fit_rows=fit_rows[idx], **kw)
    mean, cov, ok = pr.mean.copy(), pr.cov.copy(), pr.success.copy()
    mean[idx], cov[idx], ok[idx] = got.mean, got.cov, got.success
    msgs = list(pr.message)
    for k, i in enumerate(idx):
        msgs[i] = got.message[k]
    j = got.joint
    if j is None:  # no row solved
        return PredictiveRows(mean, cov, ok, tuple(msgs))
    base, U = np.full((n,) + j.base.shape[1:], np.nan), np.full((n,) + j.U.shape[1:], np.nan)
    base[idx], U[idx] = j.base, j.U
    return PredictiveRows(mean, cov, ok, tuple(msgs), FitRowsJoint(base, U, j.W))


def _sensor_scores(model, theta, pr, rec, predicted):
    """The body sensors' scores (:mod:`bayescal.prediction.sensor_score`) of the rows ``predicted``; None without sensors."""
    from ..sensors import predicted_readings
    from .sensor_score import score_sensor_rows

    S = model.sensors
    if S is None:
        return None
    td = model.tool_dof
    raw = np.stack([np.column_stack([np.asarray(rec.aux[f"accel.{b}.{a}"], dtype=float) for a in "xyz"])
                    for b in S.bodies], axis=1)
    unit = np.full(raw.shape, np.nan)
    idx = np.flatnonzero(predicted)
    if idx.size:
        sub = model.subset(idx)
        unit[idx] = predicted_readings(sub.machine, sub.sensors, sub.q, theta)
    # the tilt rows' sigma as the prediction weighed them (a rescaled sigma_tilt in a held-out score)
    sigma = float(np.median(np.asarray(model.row_sigma)[:, td:])) if model.n_poses else S.row_sigma(
        model.machine.noise.sigma_tilt)
    return score_sensor_rows(S, raw, unit, pr.mean[:, td:], pr.cov[:, td:, td:], sigma)


def _fit_frames(model, theta, frame_free, fit_rows, disc):
    """Least squares of the session's frames on the fit rows, the machine held fixed (the discrepancy's mean removed)."""
    from ..identify.gauss_newton import identify

    fit_idx = np.flatnonzero(fit_rows)
    if fit_idx.size == 0:
        raise InputError("predict --frame fit: no fit rows to fit the instrument frame(s) on")
    sub = model.subset(fit_idx)
    pred = sub.predict(theta)
    ok = np.flatnonzero(pred.success)
    sub = sub.subset(ok)
    free = list(frame_free)
    for _ in range(2 if disc is not None else 1):
        target = sub
        if disc is not None:
            p = sub.predict(theta)
            dmean, _, _ = disc.rows(sub, theta, p)
            target = replace(sub, y_measured=sub.y_measured - dmean)
        res = identify(target, method="ls", free=free, theta0=theta)
        if not res.success:
            return theta, False
        theta = res.theta
    return theta, True


def _machine_covariance(machine, fm, names, disc):
    """Covariance over the machine's parameters the record holds (and the discrepancy's weights), their indices, c."""
    from ..discrepancy import weight_names

    record = machine.calibration
    pos = {n: i for i, n in enumerate(names)}
    wnames = weight_names(disc.n_features) if disc is not None else ()
    if record is None:
        k = len(wnames)
        note = ("no [calibration] in the machine file: its parameters are taken as exact; the intervals carry the "
                "instrument noise" + (" and the discrepancy's prior" if disc is not None else ""))
        return np.eye(k) if k else np.zeros((0, 0)), np.zeros(0, dtype=int), 1.0, 1.0, note, ()
    from ..machines.framed import is_frame_parameter
    from .record import covariance_with_prior, effect_parameter_names, unknown_parameters_message

    # the machine's own parameters (a session's instrument frame is fitted, not calibrated): those the record
    # lacks keep their prior, the tolerance (bayescal.prediction.record.covariance_with_prior)
    own = [n for n in machine.layout.names if n in pos and not is_frame_parameter(n)]
    geo = [n for n in record.names if n in pos] + [n for n in own if n not in set(record.names)]
    # the effect tables' parameters the record holds: their columns come from the effects (_effect_columns)
    eff = [n for n in record.names if n in set(effect_parameter_names(machine.effects))]
    tol = np.asarray(fm.tolerance, dtype=float)
    # weights the record lacks: N(0, I); effect parameters are all in the record (no prior needed)
    prior = [tol[pos[n]] for n in geo] + [1.0] * (len(eff) + len(wnames))
    C, missing = covariance_with_prior(record, geo + eff + list(wnames), prior, machine.source)
    notes = []
    lost = [n for n in record.names if n not in pos and n not in set(eff) and not n.startswith("discrepancy.")]
    if lost:
        notes.append(f"{len(lost)} parameter(s) of [calibration] are not this machine's and were left out: "
                     f"{', '.join(lost[:4])}")
    if unheld := [n for n in missing if n in set(geo)]:
        notes.append(unknown_parameters_message(machine.source, unheld))
    note = "; ".join(notes)
    return (C, np.array([pos[n] for n in geo], dtype=int), float(record.noise_scale) ** 2,
            float(record.variance_factor), note, tuple(eff))


def _predict_with_row_tests(model, args, kw, factor, notes: list) -> PredictiveRows:
    """The usable rows' prediction, each row group widened where its fit rows say so (:func:`row_group_tests`).

    ``factor(t, s)`` is the per-component variance factor with ``t`` on the tool's rows and ``s`` (one per sensor
    row) on the sensors'; each widening adds its note.
    """
    pr = _predict_usable(model, *args, variance_factor=factor(1.0, 1.0), **kw)
    tests = row_group_tests(model, pr, args[3])
    if not any(t.widen > 1.0 for t in tests):
        return pr
    notes.extend(t.note() for t in tests if t.widen > 1.0)
    tool, sensors = tests[0].widen, np.repeat([t.widen for t in tests[1:]], 2)
    return _predict_usable(model, *args, variance_factor=factor(tool, sensors if sensors.size else 1.0), **kw)


def _effect_columns(machine, rec, session_args, theta, names) -> np.ndarray:
    """d rows / d (effect parameter) of every row, by central differences of the whole session, shape (n, dof, m).

    Each of ``names`` (``effect.<effect>.<parameter>``) is moved by a hundredth of its calibrated std either
    way in the machine's ``[effect.*]`` table and the session rebuilt as :func:`predict_recording` builds it
    (the effects reach the rows through the actuators, the tool's offset and the body sensors alike), the
    session's parameters ``theta`` held. Rows that fail either way are NaN (they fail unperturbed too).
    An effect's rows are smooth in its parameters (a compliance times a load): the difference is exact to
    O(h^2), far below the std it multiplies.
    """
    dof, frame, model = session_args
    record = machine.calibration
    std = dict(zip(record.names, record.std))
    cols = np.full((model.n_poses, model.dof, len(names)), np.nan)
    for k, name in enumerate(names):
        h = 0.01 * std[name] if std[name] > 0 else 0.0
        if h == 0.0:
            cols[:, :, k] = 0.0
            continue
        ys = []
        for sign in (1.0, -1.0):
            moved = machine.with_effects(_moved_tables(machine.effects, name, sign * h))
            got, _ = _session(moved, rec, dof, frame)
            pred = got.model.predict(theta)
            ys.append(np.where(np.asarray(pred.success)[:, None], pred.y, np.nan))
        cols[:, :, k] = (ys[0] - ys[1]) / (2 * h)
    return cols


def _moved_tables(effects, name: str, step: float) -> tuple:
    """``effects`` (StoredEffect) with parameter ``name`` (``effect.<effect>.<parameter>``) moved by ``step``."""
    out = []
    for st in effects:
        values = tuple((k, v + step if f"effect.{st.name}.{k}" == name else v) for k, v in st.values)
        out.append(replace(st, values=values))
    return tuple(out)


def _rows(rec, model, pr, scores, errors, sensors=None) -> list[dict]:
    measured, predicted = _in_recording_terms(rec, model, pr)
    std = pr.std
    out = []
    stations = rec.station or ("",) * rec.n_poses
    roles = rec.role or ("fit",) * rec.n_poses
    lines = rec.lines
    for i in range(rec.n_poses):
        row = {"line": int(lines[i]), "station": stations[i] if rec.station is not None else None, "role": roles[i],
               "measured": measured[i]}
        if errors[i] is not None:
            row["error"] = errors[i]
        else:
            row.update({"predicted": predicted[i], "std": std[i].tolist(),
                        "error_position_mm": float(scores.error_position[i]), "inside_90": bool(scores.inside[i])})
            if sensors is not None:
                row["sensors"] = sensors.row(i)
        out.append(row)
    return out


def _in_recording_terms(rec, model, pr):
    """Measured and predicted values as the recording writes them: position, then rotation vector or tool axis."""
    measured = [rec.position[i].tolist() for i in range(rec.n_poses)]
    predicted = [pr.mean[i, :3].tolist() for i in range(rec.n_poses)]
    if model.dof == 6 and rec.rotvec is not None:
        # the model's rows are log(R R_meas^T): the predicted rotation is exp(row) R_meas
        from ..geometry import so3_exp

        R_meas = so3_exp(rec.rotvec)
        ok = np.all(np.isfinite(pr.mean[:, 3:]), axis=1)
        rv = np.full((rec.n_poses, 3), np.nan)
        if ok.any():
            rv[ok] = so3_log(so3_exp(pr.mean[ok, 3:]) @ R_meas[ok])
        for i in range(rec.n_poses):
            measured[i] += rec.rotvec[i].tolist()
            predicted[i] += rv[i].tolist()
    elif model.dof == 5:
        # the rows are t_k . n on a tangent basis t_k of the measured axis: the predicted axis, to first order,
        # is the measured one moved by sum_k y_k t_k
        n_meas = rec.axis if rec.axis is not None else so3_exp_z(rec.rotvec)
        T = model._tangent
        n_pred = n_meas + np.einsum("nk,nkj->nj", pr.mean[:, 3:], T)
        n_pred = n_pred / np.linalg.norm(n_pred, axis=1, keepdims=True)
        for i in range(rec.n_poses):
            measured[i] += np.asarray(n_meas[i], dtype=float).tolist()
            predicted[i] += n_pred[i].tolist()
    return measured, predicted


def so3_exp_z(rotvec) -> np.ndarray:
    """The third column (tool axis) of the rotations ``exp(rotvec)``, shape (n, 3)."""
    from ..geometry import so3_exp

    return so3_exp(np.asarray(rotvec, dtype=float))[:, :, 2]


def score_held_out(cal, session, *, effects=None) -> dict:
    """The ``check`` rows of a calibration's own recording, predicted and scored as ``predict`` scores them.

    Parameters
    ----------
    cal : Calibration
        Fitted on the session's ``fit`` rows (its frames are the session's); its noise scale, discrepancy,
        joint covariance and variance factor are used.
    session : bayescal.instrument.prepare.Session
    effects : tuple of StoredEffect, optional
        Effects fitted with the geometry (``--fit-effects``): the check rows are
        predicted with them at their fitted values (their parameters' uncertainty
        is not carried).

    Returns
    -------
    dict
        ``{"check": {"summary": {...}, "rows": [...]}}``, or ``{}`` when the
        recording has no ``check`` row.
    """
    cov = cal.joint_covariance if cal.joint_covariance is not None else cal.result.covariance
    return score_held_out_result(cal.result, session, effects=effects, covariance=cov,
                                 discrepancy=cal.discrepancy_model, noise_scale=cal.noise_scale,
                                 variance_factor=cal.variance_factor)


def score_held_out_result(res, session, *, effects=None, covariance=None, discrepancy=None,
                          noise_scale: float = 1.0, variance_factor: float = 1.0) -> dict:
    """:func:`score_held_out` of any identification result (a Kalman or MCMC answer: its covariance as it is).

    Parameters
    ----------
    res : bayescal.contract.Result
        Fitted on the session's ``fit`` rows.
    session : bayescal.instrument.prepare.Session
    effects : tuple of StoredEffect, optional
        As :func:`score_held_out`.
    covariance : ndarray, optional
        Of the free parameters (and a discrepancy's weights); default ``res.covariance``.
    discrepancy : Discrepancy, optional
        A model discrepancy fitted with the geometry.
    noise_scale : float
        Factor on the recording's sigma.
    variance_factor : float
        The leave-one-out factor on the predictive covariance.

    Returns
    -------
    dict
        As :func:`score_held_out`.
    """
    from ..measurement import MeasurementModel

    rec = session.recording
    if not rec.is_check.any():
        return {}
    idx = np.flatnonzero(rec.is_check)
    model_all = session.model
    if effects:
        model_all = MeasurementModel.from_recording(model_all.machine.with_effects(tuple(effects)), rec,
                                                    dof=model_all.tool_dof)
    # the check rows' tool poses and body-sensor readings are predicted and scored, each row with its noise as
    # the fit weighed it (a sigma_tilt rescaled on the sensors' own rows, then the calibration's scale)
    model = model_all.subset(idx)
    tilt_scale = float(((res.extras or {}).get("tilt_noise") or {}).get("scale_used", 1.0))
    if model.sensors is not None and tilt_scale != 1.0:
        from ..identify.calibrate import with_tilt_scale

        model = with_tilt_scale(model, tilt_scale)
    scale = float(noise_scale)
    if scale != 1.0:
        model = scale_noise(model, scale)
    sub_rec = rec.subset(idx)
    P = model.n_params
    theta, free = np.asarray(res.theta, dtype=float), np.asarray(res.free, dtype=bool)
    cov = res.covariance if covariance is None else covariance
    disc = discrepancy
    if theta.size != P:
        # parameters beyond the machine's (fitted effects): their block of the covariance leaves, their values act
        keep = np.flatnonzero(free)
        inner = keep < P
        n_w = 0 if disc is None else disc.n_features
        sel = np.concatenate([np.flatnonzero(inner), keep.size + np.arange(n_w)])
        cov = None if cov is None else np.asarray(cov)[np.ix_(sel, sel)]
        theta, free = theta[:P], free[:P]
    if not res.success or cov is None:
        why = "the calibration did not succeed" if not res.success else "the method gives no covariance"
        errors = [why] * idx.size
        pr = PredictiveRows(np.full((idx.size, model.dof), np.nan), np.full((idx.size, model.dof, model.dof), np.nan),
                            np.zeros(idx.size, dtype=bool), ("",) * idx.size)
    else:
        td = model.tool_dof  # the leave-one-out factor is the tool rows' (as predict applies it)
        pr = predictive_rows(model, theta, cov, machine_index=np.flatnonzero(free), discrepancy=disc,
                             variance_factor=np.r_[np.full(td, float(variance_factor)), np.ones(model.dof - td)])
        errors = [None if ok else f"cannot be predicted: {m}" for ok, m in zip(pr.success, pr.message)]
    failed = np.array([e is not None for e in errors])
    rows, scores, sensors = _scored_rows(model, theta, pr, sub_rec, errors, failed)
    every = np.ones(idx.size, dtype=bool)
    summary = summarise(scores, every, failed)
    if sensors is not None:
        summary["sensors"] = sensors.summary(every, failed)
    return {"check": {"summary": summary, "rows": rows}}


def _scored_rows(model, theta, pr, rec, errors, failed):
    """Every row's answer, the tool rows' scores and the body sensors' (None without), of a prediction ``pr``."""
    td = model.tool_dof
    tool = model.without_sensors()
    tool_pr = PredictiveRows(pr.mean[:, :td], pr.cov[:, :td, :td], pr.success, pr.message)
    scores = score_rows(tool.y_measured, tool_pr.mean, tool_pr.cov)
    sensors = _sensor_scores(model, theta, pr, rec, ~failed)
    return _rows(rec, tool, tool_pr, scores, errors, sensors), scores, sensors


def held_out_report(answer: dict) -> str:
    """The report line of :func:`score_held_out`'s answer ("" without check rows)."""
    c = answer.get("check")
    if not c:
        return ""
    s = c["summary"]
    if not s["n"]:
        return f"  held out        {s['n_failed']} check rows, none predicted"
    lines = [f"  held out        {s['n']} check rows: position error mean {s['mean_error_position_mm']:.4g} mm, median "
             f"{s['median_error_position_mm']:.4g}, p95 {s['p95_error_position_mm']:.4g}; inside their 90 % region "
             f"{100 * s['coverage_90']:.1f} %"]
    for b, t in s.get("sensors", {}).items():
        if t["n"]:
            lines.append(f"  held out        sensor on {b!r}: tilt error mean {1e3 * t['mean_error_tilt_rad']:.4g} mrad, "
                         f"p95 {1e3 * t['p95_error_tilt_rad']:.4g} (sigma {1e3 * t['sigma_tilt_rad']:.3g}); inside "
                         f"their 90 % region {100 * t['coverage_90']:.1f} %")
    return "\n".join(lines)


def _no_frame_to_fit(rec: Recording) -> InputError:
    """The error of ``--frame fit`` when no station has the fit poses to align its frame (each needs 3, 2 with orientations)."""
    from ..errors import RecordingError

    need = rec.frame_fit_poses
    fit = ~rec.is_check
    counts = np.bincount(rec.station_index[fit], minlength=len(rec.stations))
    if rec.station is None:
        return RecordingError(rec.path, None, None, f"--frame fit: {int(counts[0])} fit row(s); at least {need} are "
                              "needed to fit the instrument frame")
    shown = ", ".join(f"{s!r} {int(c)}" for s, c in list(zip(rec.stations, counts))[:6])
    more = f" and {len(rec.stations) - 6} more" if len(rec.stations) > 6 else ""
    return RecordingError(rec.path, None, "station", f"--frame fit: no station has the {need} fit rows needed to fit "
                          f"its instrument frame (fit rows per station: {shown}{more})")
