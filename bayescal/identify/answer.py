"""The whole answer of ``bayescal identify``, as the library gives it: one function, so both say the same.

A calibration's JSON answer (docs/formats.md section 3) is the fit's keys
(:meth:`IdentificationResult.to_dict`), the model's own nuisance answers
(a ballbar recording's fitted pivots), the instrument frame and the
plausibility verdict (:func:`bayescal.instrument.plausibility.judge_fit`),
and the scores of the recording's held-out ``check`` rows
(:func:`bayescal.prediction.recording.score_held_out`).  The command line
writes ``json_text(cal.to_dict())`` of what :func:`identify_answer`
returns; a notebook gets the same bytes.
"""

from __future__ import annotations

from dataclasses import replace

from ..instrument.plausibility import judge_fit, refuse_implausible
from ..prediction.recording import score_held_out

__all__ = ["identify_answer", "calibration_answer", "refuse_implausible"]


def identify_answer(cal, machine, model, *, check=None, session=None, effects=None) -> tuple:
    """``cal`` with every key of the identify answer in its result, the frame's and the held-out keys apart.

    Parameters
    ----------
    cal : bayescal.identify.calibrate.Calibration
    machine : Machine
        The machine calibrated (in its instrument frame, if one was fitted).
    model : Model
        The model ``cal`` was fitted on (its ``fit`` rows).
    check : FrameCheck, optional
        The rigid-transform check of a base-frame recording.
    session : bayescal.instrument.prepare.Session, optional
        Its ``check`` rows are predicted and scored.
    effects : tuple of StoredEffect, optional
        Effects fitted with the geometry (``--fit-effects``), applied to the check rows.

    Returns
    -------
    (Calibration, dict, dict)
        The calibration with ``plausibility`` set and the answer's keys in ``result.extras``; the
        frame and plausibility keys; the held-out keys (``{}`` without check rows).
    """
    res = cal.result
    frame, plaus = judge_fit(machine, model, res, check)
    held = score_held_out(cal, session, effects=effects) if session is not None else {}
    extras = {**res.extras, **model.answer_extras(res.theta), **frame, **held}
    out = replace(cal, result=replace(res, extras=extras), plausibility=plaus)
    return out, frame, held


def calibration_answer(model, machine, *, method: str, session=None, check=None, **options) -> tuple:
    """A deterministic method's calibration with the whole identify answer, and the machine it writes.

    Parameters
    ----------
    model : Model
        The ``fit`` rows' model (an effect model when ``options["fit_effects"]``).
    machine : Machine
        The machine calibrated (in its instrument frame, if one was fitted).
    method : {"ls", "ridge", "tsvd", "map"}
    session, check
        As for :func:`identify_answer`.
    **options
        Of :func:`bayescal.identify.calibrate.calibrate`.

    Returns
    -------
    (Calibration, dict, dict)
        As :func:`identify_answer`; the calibration's ``machine`` is ``machine`` carrying the effect
        tables at their fitted values when they were fitted with the geometry.
    """
    from ..effects.joint_model import with_fitted_effects
    from .calibrate import calibrate

    cal = calibrate(model, method=method, **options)
    written = with_fitted_effects(machine, model, cal.result)
    effects = tuple(written.effects) if options.get("fit_effects") else None
    cal, frame, held = identify_answer(cal, machine, model, check=check, session=session, effects=effects)
    return replace(cal, machine=written), frame, held
