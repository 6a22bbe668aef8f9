"""Name, model and verify: fit each effect with the geometry, keep what the evidence and cross-validation support.

Decision rule (docs/diagnose.md):

1. The geometric model is fitted as the MAP estimate under the tolerance
   prior (ridge, lam = 1, every parameter free).
2. Each applicable effect is fitted jointly with the geometry.  Evidence =
   log Bayes factor by the Laplace approximation, with the noise variance
   scaled by ``max(1, chi2 / (N - edf))`` of the richer model (so that an
   understated instrument noise does not turn into false detections), minus
   a look-elsewhere penalty for parameters chosen by a search (the pitch).
   Out of sample: K-fold leave-poses-out position RMS.
3. Greedy forward selection: add the effect with the largest evidence while
   it is decisive (> ln 100, Jeffreys) AND the cross-validated RMS improves.
   A fit whose parameters are physically impossible (a compliance, dead
   band or screw expansion more than 3 sigma below zero:
   :meth:`bayescal.effects.Effect.nonphysical`) is never a detection: the
   effect is skipped with the reason, and a combination that needs it is
   not formed.
4. Verdict: the first selected effect when the final model explains the data
   (chi-square p > 0.001) or most (>= 80 %) of the excess chi-square of the
   geometric model; ``"unexplained"`` when effects were found but a large
   structured excess remains, or none was found and either the geometric
   model fails the chi-square test (p < 0.001) or the location tests find
   a significant dependence (Holm, family-wise 1 %); ``"none"`` otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property, partial
from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2 as chi2_dist

from ..contract import scale_noise, whiten
from ..effects import EFFECTS, get_effect
from ..effects.base import Effect, Features
from ..effects.model import (COARSE_START_POSES, EffectFit, actuator_residual, effect_residual, fit_map,
                             linear_fold_residuals)
from ..errors import InputError, KinematicsError
from ..identify.noise import distinct_measurements
from ..io.recording import Recording
from ..machines.base import Machine
from ..effects.base import approach_direction
from ..measurement import MeasurementModel
from ..models import model_from_recording
from ..outliers import recording_lines
from ..outliers.screen import (
    complete_screen,
    first_round,
    retest_with_candidates,
    retest_with_discrepancy,
    retest_with_effects,
)
from ..progress import report
from ..sensors.columns import is_body_measurement
from .confound import geometry_confound, written_tool_jacobian
from .separate import separating_sessions
from .discrepancy import try_discrepancy
from .locate import locate
from .tilt_noise import sensor_noise, tilt_scale_with_effects
from .noise import NoiseSettling, noise_test, settle_overstated_noise, with_tool_noise_scale
from .result import Diagnosis, EffectTrial, ParameterValue

__all__ = ["diagnose", "DECISIVE", "P_MISMATCH", "EXPLAINED_FRACTION"]

#: Decisive evidence, nats (Jeffreys: a Bayes factor above 100).
DECISIVE = float(np.log(100.0))
#: Chi-square p-value below which the model does not explain the data to within the noise.
P_MISMATCH = 1e-3
#: Share of the geometric model's excess chi-square an effect must explain to be named while misfit remains.
EXPLAINED_FRACTION = 0.8


@dataclass(frozen=True)
class _Candidate:
    effect: Effect
    features: Features
    penalty: float


#: Poses from which a cross-validation fold's fit is one Gauss-Newton step from the full fit
#: (:func:`~bayescal.effects.model.linear_fold_residuals`) instead of a refit.  On the 3-PRS recording of
#: benchmarks/diagnose_speed.py (backlash concealed, 6-DOF) the two CV RMS differ by at most 1.1e-3 of
#: themselves at 200 poses, 6.5e-4 at 1,000 and 1.7e-5 at 3,000 (every candidate; they shrink like the
#: step's square), while a refit costs 10 to 40 times as much; from here the difference is far below what
#: separates candidates and the refits are most of the diagnosis' time.
LINEAR_CV_POSES = 2_000


def _cv_rms(model: MeasurementModel, cands: list[_Candidate], folds: list[NDArray], theta0, eta0,
            system: tuple | None = None) -> float:
    """K-fold leave-poses-out position RMS (mm): fit on the other folds, predict the held-out poses.

    From :data:`LINEAR_CV_POSES` poses on, each fold's fit is linearised at the full fit ``theta0, eta0``
    (whose whitened system ``system`` the caller may have: :attr:`EffectFit.system`).
    """
    n = model.n_poses
    if n >= LINEAR_CV_POSES:
        eta = np.zeros(0) if eta0 is None else eta0
        res = linear_fold_residuals(model, [(c.effect, c.features) for c in cands], theta0, eta, folds, system)
        return float(np.sqrt(sum(float(np.sum(r[:, :3] ** 2)) for r in res) / sum(len(t) for t in folds)))
    sq, count = 0.0, 0
    for test in folds:
        train = np.setdiff1d(np.arange(n), test)
        tr = model.subset(train)
        # features are per solved pose: a row's poses are model.poses_of(row) (a distance has two)
        ptr, pte = model.poses_of(train), model.poses_of(test)
        fit = fit_map(tr, [(c.effect, c.features.subset(ptr)) for c in cands], theta0=theta0, eta0=eta0)
        r = effect_residual(model.subset(test), [(c.effect, c.features.subset(pte)) for c in cands], fit.theta, fit.eta)
        sq += float(np.sum(r[:, :3] ** 2))
        count += len(test)
    return float(np.sqrt(sq / count))


def _sensor_noise(machine: Machine, recording: Recording, model: MeasurementModel):
    """``(machine, model)`` with ``sigma_tilt`` rescaled where the geometry-only fit's tilt rows contradict it
    (:func:`bayescal.diagnose.tilt_noise.sensor_noise`)."""
    return sensor_noise(machine, recording, model)[:2]


def _scale2(fit: EffectFit) -> float:
    return max(1.0, fit.chi2 / max(fit.n_rows - fit.edf, 1.0))


def _evidence(rich: EffectFit, poor: EffectFit, penalty: float) -> float:
    s2 = _scale2(rich)
    return rich.log_evidence(s2) - poor.log_evidence(s2) - penalty


def _params(fit: EffectFit, name: str) -> tuple[ParameterValue, ...]:
    s2 = _scale2(fit)
    std = fit.std_eta(s2)
    sl = dict(fit.effect_slices)[name]
    return tuple(
        ParameterValue(p.name, float(v), float(s), p.unit)
        for p, v, s in zip(fit.params[sl], fit.eta[sl], std[sl])
    )


def _nonphysical(fit: EffectFit, cands: list["_Candidate"]) -> str | None:
    """Why a (joint) fit puts some effect's parameters outside their physical range, or None."""
    std = fit.std_eta(_scale2(fit))
    sl = dict(fit.effect_slices)
    for c in cands:
        k = sl[c.effect.name]
        why = c.effect.nonphysical(fit.params[k], fit.eta[k], std[k])
        if why is not None:
            return f"{c.effect.name}: {why}" if len(cands) > 1 else why
    return None


def _chi2_test(fit: EffectFit, excluded_rows: int = 0) -> tuple[float, float]:
    # rows of excluded outliers carry no weight: they add nothing to chi2, nor to its expectation
    dof = max(fit.n_rows - excluded_rows - fit.edf, 1.0)
    return dof, float(chi2_dist.sf(fit.chi2, dof))


def diagnose(
    machine: Machine,
    recording: Recording,
    *,
    effects: list[str] | None = None,
    seed: int = 0,
    n_folds: int = 5,
    n_perm: int | None = None,
    effect_settings: dict[str, dict] | None = None,
    _screen=None, _disc_retested: bool = False, _noise: NoiseSettling | None = None, _tilt: float | None = None,
    _warm: dict | None = None, _pretested: bool = False, _geometric=None, _judge: bool = False,
) -> Diagnosis:
    """Locate a model mismatch, name the missing physics, model it and verify it out of sample.

    Parameters
    ----------
    machine : Machine
        Nominal machine (its ``[measurement]`` noise is the yardstick). Effects it carries
        (``[effect.*]`` tables) are not applied: every effect is fitted afresh with the geometry.
    recording : Recording or ConstraintRecording
        Rows in measurement order: poses (docs/formats.md section 2) or distances, heights and ballbar
        readings (section 6), on whose poses the effects act (a distance's pose a, then its pose b).
    effects : list of str, optional
        Effects to try (forced: an effect that cannot be modelled is an
        error).  Default: every effect of the library that applies.
    seed : int
        Seeds the cross-validation folds and the blocks of the location tests.
    n_folds : int
        Folds of the leave-poses-out cross-validation.
    n_perm : int, optional
        Not used (the location tests use exact permutation moments, :mod:`bayescal.diagnose.dependence`).
    effect_settings : dict of str to dict, optional
        Inputs of effects by name (e.g. ``{"joint_compliance": {"gravity":
        [1, 0, 0]}}`` for a machine mounted on its side), over those the
        machine file states in its ``[effect.<name>]`` tables, key by key;
        documented defaults otherwise.

    Returns
    -------
    Diagnosis

    Raises
    ------
    InputError
        Unknown effect names, a forced effect that needs a missing channel,
        too few poses for a forced effect or for cross-validation.
    """
    again = dict(effects=effects, seed=seed, n_folds=n_folds, n_perm=n_perm, effect_settings=effect_settings, _tilt=_tilt)
    s = _setup(machine, recording, effects, effect_settings, n_folds, _screen or _geometric, _noise, tilt=_tilt)
    g = _geometric_stage(s, seed)
    if s.noise is None:
        s = _noise_tested(s, g)
        if s.noise.rescaled:  # a noise stated too large: the whole diagnosis at the scale the residuals support
            return diagnose(machine, recording, **again, _noise=s.noise)
    again["_noise"] = s.noise  # a rerun (outliers retested) keeps the noise tested once
    cands, skipped = _candidates(s, g)
    if _screen is None:
        s, restart, _pretested = _screened_by_candidates(s, g, cands, _noise)
        if restart is not None:
            return diagnose(machine, recording, **{**again, **restart})
    folds = _folds(s.kept, seed, n_folds)
    cv0 = _cv_rms(s.model, [], folds, g.fit0.theta, None)
    tried: dict = {}  # every fit with effects, by the effects' names: where a rerun's fits start
    single = _single_trials(s.model, cands, skipped, folds, g.fit0, _warm, tried)
    selected, cur_fit, cur_cv = _forward_selection(s, cands, single, folds, g.fit0, cv0, _warm, tried)
    v = _verdict(s, g, selected, cur_fit)
    if _tilt is None and (rerun := _tilt_rerun(s, selected, cur_fit, machine, recording, again)) is not None:
        return rerun
    again["_warm"] = tried  # an outlier rerun starts its fits from this pass's (large recordings, _start)
    if _screen is None or _pretested or _judge:
        final, s = _judged_by_final_model(s, selected, cur_fit, _pretested)
        if final is not None:  # with no effect selected, the geometric screen: its pass's final model judges too
            return diagnose(machine, recording, **again, _screen=final, _disc_retested=_disc_retested,
                            _judge=not selected)
    disc_trial, final_model = _discrepancy_trial(s, g, v, recording, selected, cur_fit, folds, cur_cv, seed)
    if not _disc_retested and (final := _discrepancy_retested(s, recording, selected, cur_fit, disc_trial)) is not None:
        return diagnose(machine, recording, **again, _screen=final, _disc_retested=True)
    found = _Found(cands, tuple(skipped), single, selected, cur_fit, cv0, cur_cv, disc_trial, final_model)
    return _diagnosis(s, g, v, found, recording, seed)


def _outliers_retested(s: "_Setup", selected: list, cur_fit: EffectFit, keep_same: bool = False):
    """The screen to diagnose again with, when the outliers judged against the final model are other poses; else None.

    The screen judged the poses by the geometric model alone, or by every candidate effect linearised
    (:func:`_outliers_pretested`; docs/outliers.md, "In the diagnosis").  With no effect selected the final model
    is the geometry: a screen from the candidates gives way to the geometric one it replaced.
    """
    if s.screen is None:
        return None
    if not selected:
        return None if s.screen.replaced is None else complete_screen(s.base_model, s.screen.replaced)
    return retest_with_effects(s.base_model, [(c.effect, c.features) for c in selected], cur_fit, s.screen,
                               keep_same=keep_same)


def _judged_by_final_model(s: "_Setup", selected: list, cur_fit: EffectFit, pretested: bool):
    """``(screen, s)``: the screen to diagnose again with when the final model names other poses (else None), and
    ``s``, whose screen is the final model's test when that names the poses of a screen from the candidates (the
    answer's outlier test is then the final model's, as after a rerun)."""
    final = _outliers_retested(s, selected, cur_fit, keep_same=pretested)
    if final is None or not np.array_equal(final.excluded, s.screen.excluded):
        return final, s
    return None, replace(s, screen=final)


def _discrepancy_retested(s: "_Setup", recording, selected: list, cur_fit: EffectFit, disc_trial):
    """The screen to diagnose again with when the kept discrepancy explains poses the screen took out; else None.

    Poses the discrepancy explains are physics, not gross errors: the outliers are judged against it.
    """
    if disc_trial is None or not disc_trial.kept or s.screen is None:
        return None
    plain = _final_model(s.machine, recording, s.base_model, selected, cur_fit, s.settings, None)
    return retest_with_discrepancy(plain, cur_fit.theta, disc_trial.fit, s.screen) if plain is not None else None


def _screened_by_candidates(s: "_Setup", g: "_Geometric", cands: list, noise) -> tuple:
    """``(s, restart, pretested)``: the first pass's setup, the keywords of the pass to run instead (or None), and
    whether its screen is now the candidates' (:func:`_outliers_pretested`).

    Where the screen's first round flagged poses (``s.screen`` not complete) the candidates judge every pose at
    once, at the first round's fit (its deletion test needs no round without a gross pose to see it): where
    they explain them all, the pass goes on with nothing excluded, and the screen's later rounds are never run
    (at 100,000 poses a refit and a test, 6 s of CPU, and the first pass's stages again, 5 s); where they name
    poses, the pass starts again with those out, as after the test at the complete screen; where they cannot
    judge, the screen is completed and the pass starts from it as any other.  The final model judges the poses
    again in every case (:func:`_judged_by_final_model`).
    """
    first = s.screen is not None and not s.screen.complete
    judged = _outliers_pretested(s, g, cands, first)
    if not first:
        return s, (None if judged is None else dict(_screen=judged, _pretested=True)), False
    if judged is None:  # too many stand out against the candidates too, or a candidate cannot be linearised
        return s, dict(_geometric=complete_screen(s.base_model, s.screen), _noise=noise), False
    if not judged.excluded.any():
        return replace(s, screen=judged), None, True
    # gross poses even against the candidates: out of every fit, the noise tested without them
    return s, dict(_screen=judged, _pretested=True, _noise=noise), False


def _outliers_pretested(s: "_Setup", g: "_Geometric", cands: list, keep_same: bool = False) -> object:
    """The screen to diagnose with when the poses judged against every candidate effect, linearised at the
    geometric fit, are other poses than the geometric screen's; else None (no screen, no candidate).  With
    ``keep_same`` (a first round, :func:`_screened_by_candidates`) that screen whatever it names.

    The final model judges the poses again (:func:`_outliers_retested`): this spares the pass of fits that a
    retest naming other poses would make again, where the candidates and the final model agree.
    """
    if s.screen is None or not cands:
        return None
    return retest_with_candidates(s.base_model, [(c.effect, c.features) for c in cands], g.fit0.theta, s.screen,
                                  keep_same=keep_same)


def _folds(kept: NDArray, seed: int, n_folds: int) -> list[NDArray]:
    """The cross-validation folds over the kept poses (excluded poses are never held out: their residual would be
    the gross error, not the model's)."""
    perm = kept[np.random.default_rng(seed).permutation(kept.size)]
    return [np.sort(perm[i::n_folds]) for i in range(n_folds)]


def _discrepancy_trial(s, g, v, recording, selected, cur_fit, folds, cur_cv, seed):
    """The last step (bayescal/diagnose/discrepancy.py): a mismatch no effect explains is modelled all the same.

    Returns the discrepancy trial (None when there is no mismatch to model) and the final model.
    """
    located_sig = g.location.strongest is not None and g.location.strongest.significant
    disc_trial, final_model = None, _final_model(s.machine, recording, s.model, selected, cur_fit, s.settings, s.screen)
    if (v.p_final < P_MISMATCH or located_sig) and final_model is not None:
        disc_trial = try_discrepancy(final_model, cur_fit.theta, folds, cur_cv, location=g.location,
                                     units=s.machine.actuator_units, seed=seed)
    return disc_trial, final_model


def _tilt_rerun(s: "_Setup", selected, cur_fit: EffectFit, machine, recording, again: dict):
    """The diagnosis again at the tilt rows' own scale with the effects selected, where it keeps them; else None.

    The geometry-only fit's tilt misfit may be the physics now modelled, not the sensors' noise
    (bayescal/diagnose/tilt_noise.py).  The rerun is kept where the sensors at their own noise still support
    what was found; an effect that the precise tilt rows push out of its physical range (unknown link masses
    fitted at the links' middles) is the effect's simplification showing, and the first diagnosis stands.
    """
    if s.tilt_scale == 1.0 or not selected:
        return None
    tilt = tilt_scale_with_effects(s.model, [(c.effect, c.features) for c in selected], cur_fit, s.tilt_scale)
    if tilt >= 0.5 * s.tilt_scale:
        return None
    rerun = diagnose(machine, recording, **{**again, "_tilt": tilt})
    return rerun if set(rerun.selected) >= {c.effect.name for c in selected} else None


def _noise_tested(s: "_Setup", g: "_Geometric") -> "_Setup":
    """``s`` with the stated noise tested on the geometric fit (bayescal.diagnose.noise), rescaled where overstated."""
    n_out = 0 if s.screen is None else int(s.screen.excluded.sum()) * s.model.dof
    return replace(s, noise=settle_overstated_noise(s.base_model, noise_test(s.model, g.fit0, n_out)))


@dataclass(frozen=True)
class _Found:
    """What the stages of a diagnosis found: the effects tried and kept, the final fit, the discrepancy trial."""

    cands: list  # of _Candidate
    skipped: tuple
    single: dict
    selected: list  # of _Candidate
    fit: EffectFit
    cv0: float  # cross-validated RMS of the geometry alone
    cv: float  # ... with the selected effects
    disc_trial: object  # DiscrepancyTrial or None
    final_model: object  # the model with the selected effects, or None


def _diagnosis(s: _Setup, g: _Geometric, v: _Verdict, f: _Found, recording: Recording, seed: int) -> Diagnosis:
    """The answer: the verdict (the discrepancy's where it is kept and no effect explained the mismatch)."""
    disc_trial, cur_fit, cur_cv = f.disc_trial, f.fit, f.cv
    kept_disc = disc_trial is not None and disc_trial.kept
    verdict, message = v.verdict, v.message
    if kept_disc:
        cur_cv = disc_trial.rms_cv_after
        if verdict == "unexplained":
            verdict, message = _with_discrepancy(f.selected, disc_trial)
    return Diagnosis(
        verdict=verdict,
        effects=_trials(f.cands, f.single, f.selected, cur_fit, f.cv0),
        selected=tuple(c.effect.name for c in f.selected),
        location=g.location,
        skipped=f.skipped,
        chi2_geometric=g.fit0.chi2,
        chi2_final=cur_fit.chi2,
        dof_geometric=v.dof_geometric,
        dof_final=v.dof_final,
        p_geometric=v.p_geometric,
        p_final=v.p_final,
        rms_cv_geometric=f.cv0,
        rms_cv_final=cur_cv,
        # expected per-pose position RMS of pure noise: the position rows' sigmas (3 for a pose, 1 for a
        # distance), per row as the recording states them (not the exclusion weights of outliers)
        rms_noise=float(np.sqrt(np.mean(np.sum(np.asarray(s.base_model.row_sigma)[:, :3] ** 2, axis=1)))),
        n_poses=s.model.n_poses,
        dof=s.model.tool_dof,  # the tool's DOF (body sensors' tilt rows apart)
        machine_name=s.machine.name,
        recording=recording.path,
        seed=seed,
        message=message,
        # the machine's parameters only (a model's own nuisance parameters, ballbar pivots, follow them); the
        # written geometry is the final fit's, corrected by the joint fit with the discrepancy when it is kept
        theta_final=(disc_trial.theta if kept_disc else cur_fit.theta)[: s.machine.n_params],
        theta_geometric=g.fit0.theta[: s.machine.n_params],
        effect_settings={k: dict(val) for k, val in s.settings.items()},
        outliers=s.screen,
        confound=_confound(s, g, f.selected, cur_fit, g.fit0),
        discrepancy=disc_trial,
        record=_record(s.machine, f.final_model, cur_fit, disc_trial),
        frame=_frame(s.machine, g.fit0),
        noise=s.noise,
    )


def _frame(machine: Machine, fit0: EffectFit) -> dict:
    """The answer's frame keys of a fitted instrument frame: the geometric fit's (the diagnosis' start)."""
    frame = machine.instrument_frame
    if frame is None or not frame.fit:
        return {}
    from ..instrument.plausibility import frame_answer

    return frame_answer(machine, fit0.theta, np.ones(fit0.theta.size, dtype=bool), fit0.covariance)


@dataclass(frozen=True)
class _Setup:
    """What every stage of a diagnosis works on: the model (outliers down-weighted) and the effects to try."""

    machine: Machine
    model: MeasurementModel
    base_model: MeasurementModel  # before the outlier screen's weights
    screen: object  # OutlierScreen or None
    kept: NDArray  # poses not excluded as gross errors
    aux: dict
    lib: list
    forced: bool
    settings: dict
    path: str
    noise: NoiseSettling | None  # the stated noise's test and the factor on the tool rows' sigma (None: not yet tested)
    tilt_scale: float = 1.0  # the factor on the stated sigma_tilt the diagnosis runs at


def _setup(machine: Machine, recording: Recording, effects, effect_settings, n_folds: int, screen,
           noise: NoiseSettling | None = None, tilt: float | None = None) -> _Setup:
    """The geometry-only model of ``recording`` with its sensors' noise tested and gross errors screened."""
    if isinstance(n_folds, bool) or not isinstance(n_folds, (int, np.integer)) or n_folds < 2:
        raise InputError(f"n_folds: expected a whole number >= 2 (folds of the cross-validation), got {n_folds!r}")
    # the inputs the machine file states in its [effect.<name>] tables, overridden key by key by those given: the
    # command line and a notebook's bayescal.diagnose(...) on the same file use the same inputs
    settings = {e.name: dict(e.settings) for e in machine.effects if e.settings}
    # the diagnosis starts from the geometry: effects a machine file carries ([effect.*]) are fitted afresh
    machine = machine.with_effects(())
    names = list(EFFECTS) if effects is None else list(dict.fromkeys(effects))
    for name, given in (effect_settings or {}).items():
        settings[name] = {**settings.get(name, {}), **given}
    lib = [get_effect(n, **settings.get(n, {})) for n in names]  # raises on unknown names and settings
    model = model_from_recording(machine, recording, check=False)
    # tilt given: the scale the fit with the effects supported (a rerun), else tested on the geometry-only fit
    machine, model, tilt_scale = sensor_noise(machine, recording, model, tilt)
    n = model.n_poses
    if n < 2 * n_folds:
        raise InputError(f"{recording.path}: {n} poses; the diagnosis needs at least {2 * n_folds} (cross-validation in {n_folds} folds)")
    # copied rows add rows but no information: they would leave a chi-square of 0 called "noise explains it"
    n_distinct = distinct_measurements(model)
    if n_distinct < 2 * n_folds:
        raise InputError(
            f"{recording.path}: {n} rows but only {n_distinct} distinct ({n - n_distinct} repeat an earlier row exactly, "
            f"commanded and measured values alike); the diagnosis needs at least {2 * n_folds} distinct measurements "
            f"(cross-validation in {n_folds} folds)"
        )
    # a noise stated far too large hides every effect below it: the diagnosis reruns at the scale the residuals
    # support (bayescal.diagnose.noise; tested on the first run's geometric fit, in diagnose)
    model = with_tool_noise_scale(model, 1.0 if noise is None else noise.scale)
    # gross errors are not physics (docs/outliers.md): flagged poses leave every fit and test
    base_model = model
    if screen is None:
        try:
            # the first round alone where it flags a few poses: the candidate effects judge them before the
            # screen's later rounds (diagnose, _screened_by_candidates); otherwise the screen is complete here
            screen = first_round(model, lines=recording_lines(n, recording))
            if not screen.test.flagged.any() or screen.test.too_many:
                screen = complete_screen(model, screen)
        except (KinematicsError, InputError):
            screen = None  # the nominal machine cannot solve the recording: the geometric fit says so
    if screen is not None:
        model = screen.weighted_model(model)
    kept = np.arange(n) if screen is None else np.flatnonzero(~screen.excluded)
    return _Setup(machine, model, base_model, screen, kept, dict(recording.aux), lib, effects is not None, settings,
                  recording.path, noise, tilt_scale)


@dataclass(frozen=True)
class _Geometric:
    """The geometry-only fit, the actuator-space residual and where the mismatch sits.

    The location tests run when :attr:`location` is first asked for: a pass that ends in a rerun (outliers
    retested, the noise or the tilt rows rescaled) never asks, and at 100,000 poses they cost 43 s of CPU.
    """

    fit0: EffectFit
    dq_res: NDArray
    locate: Callable[[], object]  # the location tests, run once on demand
    inputs: tuple  # the model's effect_inputs at fit0: (machine, theta, poses)

    @cached_property
    def location(self):
        """The :class:`~bayescal.diagnose.locate.Location` of the geometric fit's residuals."""
        return self.locate()


def _geometric_stage(s: _Setup, seed: int) -> _Geometric:
    model = s.model
    try:
        fit0 = s.screen.fit if s.screen is not None and s.screen.fit is not None else fit_map(model)
    except KinematicsError as exc:
        raise InputError(
            f"{s.path}: the machine {s.machine.source} cannot solve this recording at its nominal geometry "
            f"({exc}); expected a recording taken on this machine (check the machine file)"
        ) from exc
    pred0 = model.predict(fit0.theta)
    dq_res = actuator_residual(model, fit0.theta, fit0.residual, pred0)
    if s.screen is not None:
        # per-pose least squares undoes the exclusion's scaling: an excluded pose's gross error must not
        # reach the actuator-space tests (periodogram, pitch search); zero is "no actuator error"
        dq_res[s.screen.excluded] = 0.0
    direction = approach_direction(model.pose_q, model.pose_order)[: model.n_poses]
    # a body sensor's reading is a measurement of the outcome, not a condition: no channel to locate a mismatch on
    channels = {k: v for k, v in s.aux.items() if not is_body_measurement(k)}
    rw, region = whiten(model, fit0.residual), model.region(pred0)
    where = partial(locate, model.q, rw, dq_res, channels, region, seed=seed, direction=direction,
                    units=s.machine.actuator_units)
    return _Geometric(fit0, dq_res, where, model.effect_inputs(fit0.theta, pred0))


def _candidates(s: _Setup, g: _Geometric) -> tuple[list[_Candidate], list[tuple[str, str]]]:
    """The effects that can be modelled on this recording, and why each of the others cannot."""
    model, machine, n = s.model, s.machine, s.model.n_poses
    # effects act on every solved pose (a distance row has two), in time order, with its row's channels
    pose_aux = _pose_aux(s)
    cands: list[_Candidate] = []
    skipped: list[tuple[str, str]] = []
    for eff in s.lib:
        why = eff.not_applicable(machine, s.aux)
        if why is None:
            f = _features(s, g, eff, pose_aux)
            why = eff.inadmissible(f)
        if why is None:
            k = len(eff.params(machine, f))
            if n < eff.min_poses(k):
                why = f"too few poses: {n} for {k} parameters (at least {eff.min_poses(k)} needed)"
        if why is not None:
            if s.forced:
                raise InputError(f"{s.path}: effect {eff.name} was asked for (--effects) but cannot be modelled: {why}")
            skipped.append((eff.name, why))
            continue
        cands.append(_Candidate(eff, f, eff.occam_penalty(f, model.q)))
    return cands, skipped


def _pose_aux(s: _Setup) -> dict:
    """The recording's channels per solved pose of the model (a distance row has two poses)."""
    return {k: np.asarray(v)[s.model.pose_row] for k, v in s.aux.items()}


def _features(s: _Setup, g: _Geometric, eff: Effect, pose_aux: dict) -> Features:
    """The effect's features for the model's poses under the channels ``pose_aux``, refined by the geometric fit."""
    model = s.model
    eff_machine, eff_theta, eff_poses = g.inputs
    if eff.features_at_nominal:
        f = eff.features(eff_machine, model.pose_q, np.zeros_like(np.asarray(eff_theta, float)), pose_aux,
                         model.pose_order, None if eff.needs_poses else eff_poses)
    else:
        f = eff.features(eff_machine, model.pose_q, eff_theta, pose_aux, model.pose_order, eff_poses)
    return eff.refine(f, model.q, g.dq_res)


#: Poses from which the diagnosis takes two shortcuts that move its answer only within the fits' stop tests
#: (docs/diagnose.md "Large recordings"); below, nothing changes.  (1) A rerun of the diagnosis (the outliers
#: judged against the final model were other poses) starts each fit from the first pass's fit of the same
#: effects, without the coarse start: the poses changed are a few of many, so that fit is within a few steps of
#: the rerun's optimum.  From the coarse start instead, the fit of a quarter of the rows walks away to its own
#: optimum and the full fit crawls back (at 100,000 poses on the speed benchmark's recording the rerun's
#: joint-compliance fit took 20, 13 and 14 iterations, as the first pass's; 7 from the first pass's fit).
#: (2) A candidate's cross-validation linearises the folds at the fit's own whitened system
#: (:attr:`EffectFit.system`) instead of solving the poses again there: the two differ by round-off.
LARGE_POSES = COARSE_START_POSES


def _start(warm: dict | None, names: tuple, n_params: int, n_poses: int, theta0, eta0=None) -> dict:
    """``fit_map``'s start for the effects ``names``: ``theta0, eta0``, or in a rerun of a large recording the
    earlier pass's fit of the same effects (:data:`LARGE_POSES`), with no coarse start."""
    prev = None if warm is None or n_poses < LARGE_POSES else warm.get(names)
    if prev is None or prev.eta.size != n_params:
        return dict(theta0=theta0, eta0=eta0)
    return dict(theta0=prev.theta, eta0=prev.eta, coarse=False)


def _single_trials(model, cands: list[_Candidate], skipped: list, folds, fit0: EffectFit, warm: dict | None = None,
                   tried: dict | None = None) -> dict:
    """Each candidate fitted alone with the geometry: ``{name: (fit, evidence, CV RMS)}``.

    A candidate whose fit fails or needs non-physical values leaves ``cands`` for ``skipped``.  Each fit starts
    from the geometric fit, or from ``warm``'s (:func:`_start`); ``tried`` collects the fits by ``(name,)``.
    """
    single: dict[str, tuple[EffectFit, float, float]] = {}
    total = len(cands)
    for i, c in enumerate(list(cands), 1):
        report(lambda: f"fitting candidate effect {i} of {total} ({c.effect.name})")
        try:
            fit, ev, cv, why = _single_trial(model, c, folds, fit0, warm)
        except KinematicsError as exc:
            # the fitted effect moved a pose out of the workspace: it cannot be the explanation
            fit, why = None, f"fit failed: {exc}"
        if fit is not None and tried is not None:
            tried[(c.effect.name,)] = fit
        if why is not None:
            skipped.append((c.effect.name, why))
            cands.remove(c)
            continue
        single[c.effect.name] = (fit, ev, cv)
    return single


def _single_trial(model, c: _Candidate, folds, fit0: EffectFit, warm: dict | None):
    """``c`` fitted alone with the geometry: ``(fit, evidence, CV RMS, None)``, or ``(fit, None, None, why)`` when
    its values are inadmissible or non-physical.  KinematicsError when a pose fails."""
    k = len(c.effect.params(model.machine, c.features))
    large = model.n_poses >= LARGE_POSES
    fit = fit_map(model, [(c.effect, c.features)], **_start(warm, (c.effect.name,), k, model.n_poses, fit0.theta),
                  keep_system=large)
    system, fit = fit.system, replace(fit, system=None)  # the system is rows x parameters: kept no longer than needed
    why = c.effect.inadmissible(c.features, fit.eta) or _nonphysical(fit, [c])
    if why is not None:
        return fit, None, None, why
    return fit, _evidence(fit, fit0, c.penalty), _cv_rms(model, [c], folds, fit.theta, fit.eta, system), None


def _combined(s: _Setup, selected: list[_Candidate], c: _Candidate, cur_fit: EffectFit, warm: dict | None = None,
              tried: dict | None = None):
    """``c`` fitted together with the effects already selected: (fit, evidence), or None when that fails.

    The fit starts from ``cur_fit`` and ``c``'s start values, or from ``warm``'s (:func:`_start`); ``tried``
    collects it by the effects' names.
    """
    combo = selected + [c]
    names = tuple(x.effect.name for x in combo)
    eta0 = np.concatenate([cur_fit.eta, [p.start_value for p in c.effect.params(s.machine, c.features)]])
    try:
        fit = fit_map(s.model, [(x.effect, x.features) for x in combo],
                      **_start(warm, names, eta0.size, s.model.n_poses, cur_fit.theta, eta0))
    except KinematicsError:
        return None
    if tried is not None:
        tried[names] = fit
    sl = dict(fit.effect_slices)[c.effect.name]
    if c.effect.inadmissible(c.features, fit.eta[sl]) is not None or _nonphysical(fit, combo) is not None:
        return None  # a combination that needs non-physical values of any member is no explanation
    return fit, _evidence(fit, cur_fit, c.penalty)


def _forward_selection(s: _Setup, cands, single, folds, fit0: EffectFit, cv0: float, warm: dict | None = None,
                       tried: dict | None = None):
    """Greedy forward selection: the most evident effect while it is decisive and lowers the CV RMS.

    ``warm`` and ``tried`` as for :func:`_combined`.
    """
    selected: list[_Candidate] = []
    cur_fit, cur_cv = fit0, cv0
    remaining = list(cands)
    while remaining:
        best = None
        for c in remaining:
            report(lambda: f"forward selection: {len(selected)} selected, trying {c.effect.name}")
            if not selected:
                fit, ev, cv = single[c.effect.name]
            elif single[c.effect.name][1] < DECISIVE:
                continue  # not decisive alone: not worth a combined fit
            else:
                both = _combined(s, selected, c, cur_fit, warm, tried)
                if both is None:
                    continue
                (fit, ev), cv = both, None
            if ev > DECISIVE and (best is None or ev > best[2]):
                best = (c, fit, ev, cv)
        if best is None:
            break
        c, fit, ev, cv = best
        if cv is None:
            try:
                cv = _cv_rms(s.model, selected + [c], folds, fit.theta, fit.eta)
            except KinematicsError:
                cv = np.inf
        if not cv < cur_cv:
            break
        selected.append(c)
        remaining.remove(c)
        cur_fit, cur_cv = fit, cv
    return selected, cur_fit, cur_cv


@dataclass(frozen=True)
class _Verdict:
    verdict: str
    message: str
    dof_geometric: float
    p_geometric: float
    dof_final: float
    p_final: float


def _verdict(s: _Setup, g: _Geometric, selected: list[_Candidate], cur_fit: EffectFit) -> _Verdict:
    """The verdict before the discrepancy: the first selected effect if it explains the excess chi-square."""
    n_out = 0 if s.screen is None else int(s.screen.excluded.sum()) * s.model.dof
    dof0, p0 = _chi2_test(g.fit0, n_out)
    dof_f, p_f = _chi2_test(cur_fit, n_out)
    excess = g.fit0.chi2 - dof0
    explained = (g.fit0.chi2 - cur_fit.chi2) / excess if excess > 0 else 1.0
    message = ""
    if selected:
        if p_f > P_MISMATCH or explained >= EXPLAINED_FRACTION:
            verdict = selected[0].effect.name
        else:
            verdict = "unexplained"
            message = (
                f"{', '.join(c.effect.name for c in selected)} explain(s) only {100 * explained:.0f}% of the excess "
                f"chi-square; a structured mismatch remains (final chi-square p = {p_f:.2g})"
            )
    else:
        loc = g.location.strongest
        verdict = "unexplained" if p0 < P_MISMATCH or (loc is not None and loc.significant) else "none"
    return _Verdict(verdict, message, dof0, p0, dof_f, p_f)


def _with_discrepancy(selected: list[_Candidate], disc_trial) -> tuple[str, str]:
    """Verdict and message when a kept model discrepancy explains what the effects left unexplained."""
    if not selected:
        return "discrepancy", ("no effect of the library explains the located mismatch; a model discrepancy does, "
                               f"out of sample (it resembles {disc_trial.resembles})")
    return selected[0].effect.name, (f"{', '.join(c.effect.name for c in selected)} and a model discrepancy together "
                                     "explain the mismatch out of sample")


def _confound(s: _Setup, g: _Geometric, selected: list[_Candidate], cur_fit: EffectFit, fit0: EffectFit):
    """How the selected effects and the geometry are confounded (None without effects or poses to average over),
    and, where they are, the second sessions that would separate them."""
    if not selected:
        return None
    effects = [c.effect for c in selected]
    try:
        conf = geometry_confound(s.machine, s.model.q, cur_fit, fit0, effects, noise_scale2=_scale2(cur_fit),
                                 keep=s.kept)
        if not conf.confounded:
            return conf
        G, n = written_tool_jacobian(s.machine, s.model.q, cur_fit.theta[: s.machine.n_params], s.kept)
    except KinematicsError:
        return None  # nothing to average over; the answer's written_geometry is then null
    nxt = separating_sessions(s.model, effects, cur_fit, lambda e, aux: _features(s, g, e, aux), _pose_aux(s), G, n,
                              noise_scale2=_scale2(cur_fit))
    return replace(conf, next_sessions=nxt)


def _trials(cands: list[_Candidate], single: dict, selected: list[_Candidate], cur_fit: EffectFit, cv0: float) -> tuple:
    """Every effect tried, most evident first (docs/formats.md section 3)."""
    sel_names = [c.effect.name for c in selected]
    trials = []
    for c in cands:
        name = c.effect.name
        fit, ev, cv = single[name]
        params = _params(cur_fit if name in sel_names else fit, name)
        note = "; ".join(filter(None, ["look-elsewhere penalty %.1f nats" % c.penalty if c.penalty else "",
                                       c.effect.model_note(c.features)]))
        trials.append(EffectTrial(name, name in sel_names, float(ev), params, cv0, cv, note))
    trials.sort(key=lambda t: -t.evidence)
    return tuple(trials)


def _stored(selected, fit: EffectFit, settings: dict) -> tuple:
    """The selected effects at their fitted values, as machine-file tables."""
    from ..effects.stored import StoredEffect

    out = []
    for c in selected:
        name = c.effect.name
        params = _params(fit, name)
        out.append(StoredEffect(
            name, tuple((p.name, float(p.value)) for p in params), tuple(p.unit for p in params), source="<diagnosis>",
            settings=tuple((k, np.asarray(v, float).tolist() if np.ndim(v) else float(v))
                           for k, v in settings.get(name, {}).items())))
    return tuple(out)


def _final_model(machine, recording, model, selected, fit: EffectFit, settings, screen):
    """The final model's recording with its effects applied at their fitted values (and the outliers' weights).

    None for recordings a discrepancy does not model (constraint recordings: a row is not one pose).
    """
    if np.asarray(model.pose_q).shape[0] != model.n_poses:
        return None
    if not selected:
        return model
    try:
        m = model_from_recording(machine.with_effects(_stored(selected, fit, settings)), recording, check=False)
    except (KinematicsError, InputError):
        return None
    return screen.weighted_model(m) if screen is not None else m


def _record(machine, final_model, fit: EffectFit, disc_trial):
    """The ``[calibration]`` record the calibrated machine carries (its covariance, noise scale, variance factor).

    The selected effects' parameters are in it, jointly with the geometry: a prediction through a fitted effect
    (a tip sensor's tilt under bending) is no surer than its parameters (``predict`` propagates them).
    """
    from ..discrepancy import weight_names
    from ..prediction.loo import loo_variance_factor
    from ..prediction.record import record_from_result

    P = machine.n_params
    if disc_trial is not None and disc_trial.kept:
        f = disc_trial.fit
        scale = float(np.sqrt(f.noise_factor))
        extra, cov = weight_names(f.discrepancy.n_features), f.covariance
        disc = f.discrepancy
    else:
        if fit.covariance is None:
            return None
        scale2 = _scale2(fit)
        scale, extra, cov, disc = float(np.sqrt(scale2)), (), fit.covariance[:P, :P] * scale2, None
    kappa = 1.0
    if final_model is not None:
        scaled = scale_noise(final_model, scale)
        theta = disc_trial.theta[:P] if disc is not None else fit.theta[:P]
        try:
            kappa, _ = loo_variance_factor(scaled, theta, cov, machine_index=np.arange(P), discrepancy=disc)
        except (np.linalg.LinAlgError, ValueError, KinematicsError):
            kappa = 1.0
    eff = tuple(f"effect.{e}.{p.name}" for e, sl in fit.effect_slices for p in fit.params[sl])
    joint = _with_effect_block(cov, fit, P, len(extra)) if eff and fit.covariance is not None else None
    names = tuple(machine.layout.names) + (eff if joint is not None else ())
    free = np.ones(len(names), dtype=bool)
    if joint is None:
        joint = cov if extra else cov[:P, :P]
    return record_from_result(machine.base_machine(), names, free, None if extra else joint, noise_scale=scale,
                              method="diagnose", extra_names=extra, extra_cov=joint if extra else None,
                              variance_factor=kappa, effect_names=names[P:])


def _with_effect_block(cov: NDArray, fit: EffectFit, P: int, W: int) -> NDArray | None:
    """The covariance over ``[geometry (P), effect parameters (K), discrepancy weights (W)]``.

    ``cov`` is over the geometry and the weights (the discrepancy's joint fit, effects held at their values) or the
    geometry alone; ``fit.covariance`` is the effects' joint fit over ``[geometry, effects]``. Given the geometry,
    the effects are ``eta = B g + e`` with ``B = C_eg C_gg^-1`` and ``e`` of the conditional covariance
    ``C_ee - B C_ge`` (the effects' fit, scaled by its noise; the fit's nuisance parameters marginalised out):
    the joint covariance of ``(g, w, B g + e)`` is
    positive semi-definite by construction and keeps the trade between an effect and the geometry (a compliance
    against a link length). None when the effects' fit does not give it.
    """
    K = len(fit.params)
    full = fit.covariance * _scale2(fit)
    if K == 0 or full.shape[0] < P + K:
        return None
    # the fit's vector is [geometry (P), the model's nuisance parameters (body sensors' mountings), effects (K)]:
    # the marginal over the geometry and the effects is their block
    keep = np.r_[np.arange(P), full.shape[0] - K + np.arange(K)]
    C = full[np.ix_(keep, keep)]
    try:
        B = np.linalg.solve(C[:P, :P], C[:P, P:]).T
    except np.linalg.LinAlgError:
        return None
    Ce = C[P:, P:] - B @ C[:P, P:]
    Ce = 0.5 * (Ce + Ce.T)
    D = np.asarray(cov, dtype=float)[: P + W, : P + W]  # geometry then weights
    out = np.zeros((P + K + W,) * 2)
    order = np.r_[np.arange(P), P + K + np.arange(W)]  # where D's rows go
    out[np.ix_(order, order)] = D
    cross = B @ D[:P, :]  # cov(eta, (g, w))
    out[P:P + K, order] = cross
    out[order, P:P + K] = cross.T
    out[P:P + K, P:P + K] = B @ D[:P, :P] @ B.T + Ce
    return out if np.all(np.isfinite(out)) else None
