"""The front door: the few verbs a notebook user needs, each the command line's own policy.

.. code-block:: python

    import bayescal

    s = bayescal.load("machine.toml", "recording.csv", frame="fit")   # units, frame(s), stations, roles checked
    cal = bayescal.calibrate(s, method="map", discrepancy="auto")     # what `bayescal identify` runs
    cal.report(); cal.parameters["chain1.link_length"].std
    cal.write_machine("calibrated.toml")
    p = bayescal.predict("calibrated.toml", "new.csv", frame="fit")  # what `bayescal predict` runs
    p.summary["check"]["coverage_90"]
    g = bayescal.grid(s, nodes=9)                                      # what `bayescal grid` runs
    g.write_csv("grid.csv"); g.grid.std

    plan = bayescal.plan("machine.toml", 24, criterion="I")             # what `bayescal plan` runs
    cmp = bayescal.compare("machine.toml", methods="ls,map", trials=200)  # what `bayescal compare` runs

``bayescal identify``, ``predict``, ``grid``, ``diagnose``, ``plan`` and ``compare`` call the
same functions, so a study gets the number a user gets.
"""

from __future__ import annotations

import os

from .io.recording import Recording
from .machines.base import Machine

__all__ = ["load", "load_klipper", "calibrate", "predict", "grid", "diagnose", "plan", "compare", "simulate_session",
           "compensate", "plan_next_session"]


def _machine(machine) -> Machine:
    from .machines.files import load_machine

    return machine if isinstance(machine, Machine) else load_machine(machine)


def _recording(recording) -> Recording:
    from .io import read_recording

    return recording if isinstance(recording, Recording) else read_recording(recording)


def load(machine: str | os.PathLike | Machine, recording: str | os.PathLike | Recording, *, frame: str = "base",
         dof: int | None = None):
    """A machine file and a recording, checked and made into a model, as every command makes them.

    Parameters
    ----------
    machine : path or Machine
        Machine file (docs/formats.md sections 1, 5, 7).
    recording : path or Recording or ConstraintRecording
        Recording CSV (sections 2, 4, 8: per-pose sigma, unit suffixes, ``station`` and ``role`` columns), or a
        constraint recording (section 6), read or not.
    frame : {"base", "fit"}
        ``fit``: an instrument frame per station, fitted with the geometry.
    dof : int, optional
        6, 5 or 3 (default: what the recording holds).

    Returns
    -------
    bayescal.instrument.prepare.Session or bayescal.constraints.model.ConstraintModel
        ``.fit_model`` (the rows to identify from), ``.check_model`` (held-out rows), ``.machine``, ``.check``
        (the rigid-transform check: ``check.fires`` suggests ``frame="fit"``); a constraint recording
        (section 6: heights, distances, ballbar radii) gives its model, which :func:`calibrate` takes as well.
    """
    from .instrument.prepare import fit_size_check, prepare_session

    machine = _machine(machine)
    from .io.constraints import ConstraintRecording

    if isinstance(recording, ConstraintRecording):
        from .constraints.model import load_constraint_model

        return load_constraint_model(machine, recording, frame=frame, dof=dof)[1]
    if isinstance(recording, (str, os.PathLike)):
        from .io import read_recording
        from .io.constraints import is_constraint_recording

        if is_constraint_recording(recording):
            from .constraints.model import load_constraint_model

            return load_constraint_model(machine, recording, frame=frame, dof=dof)[1]
        # a recording too large to fit is refused once its header is read, before its cells are parsed
        recording = read_recording(recording, check_size=fit_size_check(machine, dof=dof, frame=frame,
                                                                         path=str(recording)))
    recording = _recording(recording)
    _warn_near_reserved(recording)
    return prepare_session(machine, recording, dof=dof, frame=frame).with_fitted_stations()


def _warn_near_reserved(recording) -> None:
    """A :class:`~bayescal.errors.BayescalWarning` per channel named like a reserved column (``sigma_postion``)."""
    import warnings

    from .errors import BayescalWarning
    from .io.recording import near_reserved_columns

    for message in near_reserved_columns(recording):
        warnings.warn(message, BayescalWarning, stacklevel=3)


def load_klipper(config: str | os.PathLike, **options):
    """A Klipper delta printer's config and saved DELTA_CALIBRATE as machine and recording, as ``bayescal klipper``.

    .. code-block:: python

        k = bayescal.load_klipper("printer.cfg")
        cal = bayescal.calibrate(bayescal.load(k.machine, k.recording), method="map", free="all")
        k.write("calib/")                       # the two files `bayescal klipper --out calib/` writes

    Parameters
    ----------
    config : path
        ``printer.cfg`` with its SAVE_CONFIG block.
    **options
        ``sigma_height``, ``sigma_distance`` (mm) of :func:`bayescal.klipper.setup.load_klipper`.

    Returns
    -------
    bayescal.klipper.setup.KlipperSetup
        ``machine``, ``recording``, ``write(out)``, ``to_dict()``, ``report(out)``.
    """
    from .klipper.setup import load_klipper as _load_klipper

    return _load_klipper(config, **options)


def calibrate(data, *, method: str = "map", **options):
    """Identify a recording's errors as ``bayescal identify`` does (method, outliers, prior scale, noise, discrepancy).

    ``bayescal identify`` calls the same functions: ``json_text(calibrate(...).to_dict())`` is its ``--json`` file.

    Parameters
    ----------
    data : Session or MeasurementModel
        From :func:`load` (its ``check`` rows are then scored as ``identify`` scores them), or a model.
    method : {"map", "ridge", "tsvd", "ls", "kalman", "mcmc"}
    **options
        Of :func:`bayescal.identify.calibrate.calibrate`: ``lam``, ``k``, ``free``, ``fix``, ``bounds``, ``rule``,
        ``prior_scale``, ``robust``, ``noise``, ``discrepancy``, ``discrepancy_inputs``, ``fit_effects``, ...;
        for kalman and mcmc, of :func:`bayescal.identify.probabilistic.calibrate_bayes`: ``free``, ``fix``,
        ``bounds`` (mcmc), ``noise``, ``robust``, ``variant``, ``process_noise`` (kalman), ``steps``, ``walkers``, ``seed``,
        ``surrogate``, ``checkpoint``, ``resume``, ``ess`` (mcmc: stop at that bulk and tail ESS), ``fit_effects``.  With ``fit_effects=True`` (map,
        mcmc) the machine file's ``[effect.*]`` parameters are identified with the geometry.

    Returns
    -------
    bayescal.identify.calibrate.Calibration or bayescal.identify.probabilistic.BayesCalibration
        ``report()``, ``to_dict()``, ``write_machine(path)``; a ``Calibration`` has ``parameters`` by
        name; with a session holding ``check`` rows, ``to_dict()["check"]`` holds their scores.
    """
    from .contract import Model
    from .errors import InputError
    from .identify.probabilistic import BAYES_METHODS, calibrate_bayes
    from .instrument.prepare import Session

    if not isinstance(data, (Session, Model)):
        raise InputError(f"calibrate: expected what bayescal.load returns (or a measurement model), got "
                         f"{type(data).__name__} {data!r:.80}; for files: bayescal.calibrate(bayescal.load(machine, "
                         "recording))")
    session = data if isinstance(data, Session) else None
    model = data.fit_model if session is not None else data
    machine = model.calibrated_machine
    if options.get("fit_effects"):
        from .effects.joint_model import joint_effects_model

        model = joint_effects_model(model, None if session is None else session.fit_recording, method=method)
    if session is not None:
        from .outliers import recording_lines

        # the outlier test names poses by their line in the recording file (held-out rows skipped)
        options.setdefault("lines", recording_lines(model.n_poses, session.fit_recording))
    check = None if session is None else session.check
    from .constants import DETERMINISTIC_METHODS

    if method not in DETERMINISTIC_METHODS + BAYES_METHODS:
        raise InputError(f"method: expected one of {', '.join(DETERMINISTIC_METHODS + BAYES_METHODS)}, got {method!r}")
    if method in BAYES_METHODS:
        return calibrate_bayes(model, method=method, machine=machine, check=check, session=session, **options)
    from .identify.answer import calibration_answer

    return calibration_answer(model, machine, method=method, session=session, check=check, **options)[0]


def predict(machine: str | os.PathLike | Machine, recording: str | os.PathLike | Recording, *, frame: str = "base",
            dof: int | None = None):
    """Predict every row of a recording from a calibrated machine, as ``bayescal predict`` does.

    ``bayescal predict`` calls this function: ``json_text(predict(...).to_dict())`` is its ``--json`` file.

    Parameters
    ----------
    machine : path or Machine
        A calibrated machine file (``write_machine``, ``identify --write-machine``): its ``[calibration]``
        covariance and ``[discrepancy]`` are used when present.
    recording : path or Recording
        Rows to predict (docs/formats.md section 8: ``role = check`` rows are never fitted, only scored).
    frame : {"base", "fit"}
        ``fit``: each station's instrument frame is fitted on its ``fit`` rows, the machine held fixed.
    dof : int, optional
        6, 5 or 3 (default: what the recording holds).

    Returns
    -------
    bayescal.prediction.recording.PredictionResult
        ``rows``, ``summary`` (per role: mean, median, p95 position error in mm, ``coverage_90``),
        ``to_dict()``, ``report()``.
    """
    from .prediction.recording import predict_recording

    return predict_recording(_machine(machine), _recording(recording), frame=frame, dof=dof)


def grid(data, **options):
    """Identify a recording's errors and span a compensation grid with its std, as ``bayescal grid`` does.

    ``bayescal grid`` calls :func:`bayescal.bayes.recording_grid.recording_grid` with its options:
    ``json_text(grid(...).to_dict())`` is its ``--json`` file.

    Parameters
    ----------
    data : Session or Model
        From :func:`load` (its ``fit`` rows are used), or a measurement or constraint model.
    **options
        Of :func:`~bayescal.bayes.recording_grid.recording_grid`: ``method`` ("map", "kalman", "mcmc"),
        ``free``, ``nodes``, ``space`` ("auto", "actuator", "tool"), ``ranges``, ``aux``, ``steps``,
        ``surrogate``, ``seed``, ``ess``, ``fit_effects``.

    Returns
    -------
    bayescal.bayes.recording_grid.GridAnswer
        ``grid.correction`` and ``grid.std`` at every node (mm), ``to_dict()``, ``report()``,
        ``write_csv(path)``, ``write_nc_csv(path)`` (tool space).
    """
    from .bayes.recording_grid import recording_grid
    from .errors import refuse_unknown_options

    refuse_unknown_options("grid", options, recording_grid)
    return recording_grid(data, **options)


def diagnose(machine: str | os.PathLike | Machine, recording, **options):
    """Locate a model mismatch, name the missing physics, model it, as ``bayescal diagnose`` does.

    Parameters
    ----------
    machine : path or Machine
        Machine file (docs/formats.md sections 1, 5, 7) or a machine.
    recording : path or Recording or ConstraintRecording
        A pose or constraint recording (sections 2, 4, 6, 8).
    **options
        ``frame`` (``"base"`` or ``"fit"``: one instrument frame per station fitted with the geometry, as
        ``--frame fit``; its keys are in ``to_dict()``), and those of :func:`bayescal.diagnose.core.diagnose`:
        ``effects``, ``seed``, ``n_folds``, ``effect_settings``.

    Returns
    -------
    bayescal.diagnose.result.Diagnosis
        ``verdict``, ``effects``, ``report()``, ``to_dict()`` (what ``bayescal diagnose --json`` writes).
    """
    from .diagnose.verb import diagnose_files

    return diagnose_files(machine, recording, **options)


def plan(machine: str | os.PathLike | Machine, n: int, **options):
    """Choose ``n`` measurement poses (or probe heights, distances) by information, as ``bayescal plan`` does.

    Parameters
    ----------
    machine : path or Machine
        Machine file with ``[workspace] q_limits`` (docs/formats.md section 1) or a machine.
    n : int
        Poses or relations to plan.
    **options
        Of :func:`bayescal.design.verb.plan_files`: ``measure`` ("pose", "height", "distance"),
        ``criterion``, ``frame``, ``seed``, ``repeats``, ``method``, and the pose options (``dof``,
        ``n_candidates``, ``certify``, ...) or the relation options (``given``, ``centre``, ``radius``, ...).

    Returns
    -------
    PosePlan or RelationPlan
        ``q`` (poses), ``report()``, ``to_dict()`` (what ``bayescal plan --json`` writes).
    """
    from .design.verb import plan_files

    return plan_files(machine, n, **options)


def compare(machine: str | os.PathLike | Machine, **options):
    """Compare identification methods by Monte Carlo on machines drawn from the tolerances, as ``bayescal compare``.

    Parameters
    ----------
    machine : path or Machine
        Nominal machine file with ``[workspace] q_limits`` or a machine.
    **options
        Of :func:`bayescal.compare.verb.compare_files`: ``methods`` (``"ls,ridge:lam=auto,map"``),
        ``trials``, ``recording``, ``dof``, ``poses``, ``alpha``, ``out``, ``seed``, ``workers``, ...

    Returns
    -------
    bayescal.compare.result.Comparison
        ``report()``, ``to_dict()`` (what ``bayescal compare --json`` writes), per-method errors.
    """
    from .compare.verb import compare_files

    return compare_files(machine, **options)


def simulate_session(machine: str | os.PathLike | Machine, n: int | None = None, **options):
    """A simulated recording with its truth, as ``bayescal simulate`` writes it.

    (Not ``bayescal.simulate``: that name is the module of the simulation's pieces,
    :mod:`bayescal.simulate`.)

    Parameters
    ----------
    machine : path or Machine
        Nominal machine file or machine; its ``[effect.*]`` tables and ``[discrepancy]`` act on the
        simulated machine.
    n : int, optional
        Poses drawn within ``q_limits`` (readings per circle with ``ballbar``).
    **options
        Of :func:`bayescal.simulated.simulate_files`: ``seed`` (required), ``dof``, ``poses_file``,
        ``tolerance_scale``, ``effects``, ``aux``, ``ballbar``, ``pivot``, ``planes``.

    Returns
    -------
    bayescal.simulated.SimulatedSession
        ``recording``, ``truth``, ``write(out, truth=None)`` (the three files of the command), ``report(out)``.
    """
    from .simulated import simulate_files

    return simulate_files(machine, n, **options)


def compensate(**options):
    """Build a bilinear compensation grid from measured errors (or read one) and evaluate it, as ``bayescal compensate``.

    Parameters
    ----------
    **options
        Of :func:`bayescal.compensation.compensate_files`: ``errors`` (an x,z,ex,ez table, mm) with
        ``x_range``, ``z_range`` (mm), ``n``, ``node_std`` (mm); or ``grid`` (a grid CSV); and ``evaluate``
        (fresh points' errors).

    Returns
    -------
    bayescal.compensation.Compensation
        ``grid`` (``report()``, :func:`bayescal.compensation.write_grid`), ``evaluation`` (what ``--json`` writes).
    """
    from .compensation import compensate_files

    return compensate_files(**options)


def plan_next_session(machine: str | os.PathLike | Machine, recording, n: int, *, condition: str | None = None,
                      **options):
    """Plan the second session that separates a diagnosis' effects from the geometry, as ``bayescal plan --separate``.

    The recording is diagnosed (:func:`diagnose`, same options); where the
    written geometry is confounded with the selected effects, the second
    sessions under changed conditions are weighed
    (:mod:`bayescal.diagnose.separate`) and ``n`` of the recording's poses
    are chosen, one at a time, for the best one (or ``condition``).

    Parameters
    ----------
    machine : path or Machine
    recording : path or Recording
        A pose recording (docs/formats.md sections 2, 4, 8).
    n : int
        Poses of the second session.
    condition : str, optional
        ``payload``, ``temperature``, ``tilt_1`` or ``tilt_2`` (default: the one forecast to help most).
    **options
        As :func:`diagnose` (``effects``, ``seed``, ``frame``, ...).

    Returns
    -------
    bayescal.diagnose.separate.SessionPlan
        ``q``, ``channels``, ``to_csv()`` (a pose file, docs/formats.md E7), ``report()``, ``to_dict()``.

    Raises
    ------
    InputError
        Nothing to separate (no effect selected, the written geometry not
        confounded, no condition helps), or ``condition`` not among those
        forecast to help.
    """
    from .errors import InputError

    d = diagnose(machine, recording, **options)
    where = d.recording or "the recording"
    if d.confound is None:
        raise InputError(f"{where}: the diagnosis selected no effect (verdict {d.verdict}); there is nothing to "
                         "separate from the geometry, plan poses with 'bayescal plan' alone")
    if not d.confound.confounded:
        raise InputError(f"{where}: the written geometry is not confounded with {', '.join(d.selected)} "
                         f"({d.confound.tool_std_um:.1f} um against {d.confound.geometric_tool_std_um:.1f} um of a "
                         "geometry-only calibration); no second session is needed")
    sessions = {x.key: x for x in d.confound.next_sessions}
    if not sessions:
        raise InputError(f"{where}: no second session under a changed payload, mounting tilt or temperature is "
                         f"forecast to cut the written geometry's uncertainty ({d.confound.tool_std_um:.1f} um) by "
                         "a fifth; state the effects' inputs instead (diagnose --effect-input)")
    if condition is not None and condition not in sessions:
        raise InputError(f"--condition {condition}: expected one of {', '.join(sessions)} (the conditions forecast "
                         f"to help on {where})")
    return sessions[condition or next(iter(sessions))].plan(n)
