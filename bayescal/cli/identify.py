"""``bayescal identify``: identify geometric errors from a recording.

The parser imports no numpy (issue 31): its choices come from :mod:`bayescal.constants`, and the
library is imported by :func:`run`.
"""

from __future__ import annotations

import argparse

from ..constants import DEFAULT_RULE, DETERMINISTIC_METHODS, PRIOR_SCALES, RULE_NAMES
from ..errors import InputError
from . import SUMMARIES
from .bayes_identify import METHODS, add_arguments, bayes_options, check_method_options, run_bayes
from .effect_options import joint_effects_model
from .inputs import add_frame_argument, bound_args, free_arg, inputs_with_session, name_list
from .instrument import add_force_argument, instrument_report, refusal_note, write_calibrated_files
from .outlier_options import add_outlier_arguments, outlier_kwargs
from .outputs import add_output_options, write_json, write_report

HELP = """\
Identify the geometric errors of a machine from a recording of measured poses.

The recording (CSV, see docs/formats.md) holds commanded actuator positions
q1..qN and the measured tool point x, y, z, plus either a rotation vector rx,
ry, rz (6-DOF) or a tool axis nx, ny, nz (5-DOF), or nothing more (position
only). With --free auto (default) the combinations the measurement cannot
separate are found by SVD and named in the report: ls fixes enough parameters
at nominal to be well posed (ballbar pivots and other nuisance parameters
kept); ridge, tsvd, map and kalman estimate every parameter the measurement
sees and let the prior decide those combinations (fixing them made a MAP
calibration from a ballbar worse than the nominal machine; docs/delta.md).

Methods: map (the default: the MAP estimate under the [tolerance] prior,
with its Laplace covariance), ls (Gauss-Newton least squares), ridge
(Tikhonov towards nominal; --lam 1 is the MAP estimate under the machine
file's tolerance prior), tsvd (least squares on the k best-determined
directions), kalman (a recursive EKF/UKF, one update per pose, with the
uncertainty after each pose), mcmc (emcee posterior, refused unless
converged). See docs/bayes.md.

--lam auto / --k auto choose the regularisation from the data by a rule
(--rule): cv (K-fold cross-validation over held-out poses), lcurve (L-curve
corner), gcv (generalised cross-validation), discrepancy (residual matches
the instrument sigma), evidence (marginal likelihood, empirical Bayes),
risk (Bayes decision under the evidence prior for the squared error: for k,
keep the singular directions with s^2 > lambda_evidence), success (Bayes
decision for "tool-point error within 10 % of the best candidate's", by
Monte Carlo over the posterior, the prior scale integrated over a hyperprior:
log-normal around the tolerances, sd ln 2, within 0.3-6 times them; the
default for lambda), targets (the default for k: a compromise calibrated on
the recording's own design, by simulating data sets from it at 0.5-4 times
the tolerances, so that the success probability stays within 3 points of
the attainable, the mean ratio to the best near its least and the ratio
above 1.40 in at most 10 % of cases; a few seconds).  The report
prints the chosen value and what every other rule picks ("<- used" marks
the rule applied); --figures DIR draws the rule curves.  See
docs/regularisation.md.

--method map multiplies every tolerance of the prior by one factor estimated
from the data (the evidence), so that the intervals hold when the machine is
better or worse than its tolerances say, when the recording has at least
three measured components per parameter or the machine file states no
noise (no [measurement] table: the sigmas are weights, and the factor sets
the geometry's spread against the noise); otherwise the tolerances are used
as they are, and the report says so ("prior scale: ..." line).
--prior-scale tolerance|empirical chooses explicitly (tolerance: MAP = ridge
with --lam 1).

A machine file with [effect.<name>] tables (written by diagnose
--write-machine) has those effects applied at their stored values, driven by
the recording's auxiliary channels and measurement order: only the geometry
is identified, and --write-machine keeps the tables (docs/formats.md section 7).
With --fit-effects (--method map or mcmc) the effects' parameters are
unknowns too, under the effects' own priors, started at the stored values:
the MAP and its covariance, or the posterior, are joint, so the geometry's
intervals carry the effects' uncertainty; --write-machine writes the
refitted tables (docs/bayes.md, "Effects sampled with the geometry").

Every pose is tested for being an outlier (a gross error no model of the
machine explains: a beam break, a mistyped value), with a test that accounts
for the number of poses; flagged poses are named by CSV line in the report
and the JSON "outliers".  By default (--robust auto) a recording with flagged
poses is refitted by Student-t IRLS, which down-weights them. See
docs/outliers.md.
"""

EXAMPLES = """\
examples:
  bayescal identify examples/prs3/recording.csv --machine examples/prs3/machine.toml
  bayescal identify rec.csv --machine m.toml --method ridge --lam 1 --json answer.json
  bayescal identify rec.csv --machine m.toml --method tsvd --k 25 --dof 5 --write-machine calibrated.toml
  bayescal identify rec.csv --machine m.toml --method ridge --lam auto --figures figs/
  bayescal identify rec.csv --machine m.toml --method tsvd --k auto --rule gcv --json answer.json
  bayescal identify rec.csv --machine m.toml --method map --json map.json
  bayescal identify rec.csv --machine m.toml --method kalman --variant ukf --figures figs/
  bayescal identify rec.csv --machine m.toml --method mcmc --surrogate linear --progress --posterior post.nc --figures figs/
  bayescal identify rec.csv --machine m.toml --method map --robust t --json answer.json
"""


def register(sub) -> None:
    p = sub.add_parser(
        "identify", help=SUMMARIES["identify"], description=HELP, epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recording", help="recording CSV (docs/formats.md section 2)")
    p.add_argument("--machine", required=True, help="machine file TOML (docs/formats.md section 1)")
    p.add_argument("--method", choices=DETERMINISTIC_METHODS + METHODS, default="map",
                   help="solver (default: map, the MAP estimate under the tolerance prior with its Laplace covariance)")
    p.add_argument(
        "--lam", type=_lam_arg, metavar="LAM|auto",
        help="ridge parameter, dimensionless (1 = MAP under the tolerance prior), or 'auto'",
    )
    p.add_argument("--k", type=_k_arg, metavar="K|auto", help="number of singular values tsvd keeps, or 'auto'")
    p.add_argument(
        "--rule", choices=RULE_NAMES, help="rule for --lam auto / --k auto (default: " + ", ".join(
            f"{m} {r}" for m, r in DEFAULT_RULE.items()) + ")",
    )
    p.add_argument("--figures", metavar="DIR", help="write figures into DIR: the rule curves (with auto), the kalman history, the mcmc trace and pair plots")
    p.add_argument("--dof", type=int, choices=(6, 5, 3), help="use only this much of the measurement (default: all)")
    p.add_argument(
        "--free", default="auto",
        help="parameters to identify: 'auto' (default: ls the identifiable set; methods with a prior every parameter "
             "the measurement sees), 'all', or comma-separated names",
    )
    _add_parameter_arguments(p)
    p.add_argument(
        "--prior-scale", choices=PRIOR_SCALES, default=None,
        help="map: the prior's scale: 'empirical' (one factor on the machine file's tolerances, estimated from the "
             "data) or 'tolerance' (the tolerances as they are); default: empirical with at least 3 measured "
             "components per parameter or with no stated noise (no [measurement] table), else tolerance",
    )
    p.add_argument(
        "--fit-effects", action="store_true",
        help="map, mcmc: fit the machine file's [effect.*] parameters jointly with the geometry, under the effects' "
             "priors, instead of holding them at their stored values",
    )
    p.add_argument(
        "--noise", choices=("auto", "stated"), default="auto",
        help="the instrument noise: 'auto' (default) tests the stated sigma by the fit's chi-square and, where the "
             "data contradict it, uses the estimated scale (intervals widen for residuals larger than stated; a sigma "
             "stated far too large no longer leaves the calibration to the prior); 'stated' tests and reports only",
    )
    p.add_argument(
        "--discrepancy", choices=("off", "auto", "on"), default="off",
        help="a model discrepancy: a smooth function of the inputs (actuators, auxiliary channels) added to the tool "
             "pose for what the kinematic model leaves out, fitted off what the geometry explains; 'auto' keeps it "
             "where the marginal likelihood supports it, 'on' always; the calibrated machine carries it "
             "(docs/discrepancy.md). Default off; suggested when the residuals are larger than the noise",
    )
    p.add_argument("--discrepancy-inputs", metavar="NAMES",
                   help="comma-separated inputs of the discrepancy: q1, q2, ... and auxiliary channels of the recording "
                        "(default: every actuator and every channel that varies)")
    p.add_argument("--max-iter", type=int, default=50, help="Gauss-Newton iterations at most (default 50)")
    p.add_argument("--json", metavar="PATH", help="write the answer as JSON (docs/formats.md section 3)")
    p.add_argument("--write-machine", metavar="PATH", help="write the calibrated machine file")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    p.add_argument(
        "--write-klipper", metavar="PATH",
        help="linear-delta only: write the calibrated geometry in Klipper's keys (delta_radius, angle, arm_length, "
        "position_endstop) as a block to paste into printer.cfg above its SAVE_CONFIG block",
    )
    p.add_argument(
        "--write-urdf", metavar="PATH",
        help="serial machines only: write the calibrated chain as a URDF file (metres, radians; mimic joints kept), "
        "written when --write-machine would be",
    )
    add_frame_argument(p)
    add_force_argument(p)
    add_arguments(p)
    add_outlier_arguments(p)
    add_output_options(p)
    p.set_defaults(func=run)


def _lam_arg(text: str):
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0 or 'auto', got {text!r}") from None


def _k_arg(text: str):
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer or 'auto', got {text!r}") from None


def _check_options(args) -> None:
    """Options that do not go together, refused before anything is read (exit 2), not ignored."""
    check_method_options(args)  # e.g. --posterior with a method other than mcmc
    if args.discrepancy != "off" and args.method not in ("map", "ridge"):
        raise InputError(f"--discrepancy goes with --method map or ridge: the geometry's prior decides what the "
                         f"discrepancy may take (got --method {args.method})")
    if args.discrepancy_inputs and args.discrepancy == "off":
        raise InputError("--discrepancy-inputs goes with --discrepancy auto or on")
    if args.discrepancy_inputs:
        names = name_list(args.discrepancy_inputs)
        if not names or len(set(names)) != len(names):
            raise InputError(f"--discrepancy-inputs {args.discrepancy_inputs}: expected distinct comma-separated names "
                             "(q1, q2, ... or auxiliary channels)")


def _check_method_arguments(args) -> None:
    """Each method's own options: required where the method needs them, refused with another method."""
    if args.method == "ridge" and args.lam is None:
        raise InputError("--lam is required with --method ridge (try --lam 1: MAP under the tolerance prior, or --lam auto)")
    if args.method == "tsvd" and args.k is None:
        raise InputError("--k is required with --method tsvd (a number, or --k auto)")
    if args.method != "mcmc" and (args.checkpoint or args.resume):
        raise InputError("--checkpoint and --resume go with --method mcmc")
    # options of another method are refused, not ignored (kalman and mcmc too)
    if args.prior_scale is not None and args.method != "map":
        raise InputError("--prior-scale goes with --method map")
    if args.lam is not None and args.method != "ridge":
        raise InputError(f"--lam goes with --method ridge (got --method {args.method})")
    if args.k is not None and args.method != "tsvd":
        raise InputError(f"--k goes with --method tsvd (got --method {args.method})")


def _add_parameter_arguments(p) -> None:
    """``--fix`` and ``--bound``: parameters held by name and kept inside bounds."""
    p.add_argument(
        "--fix", metavar="NAMES",
        help="comma-separated parameter names held at nominal (not identified, zero variance), as lmfit's "
             "vary=False; with --free auto the identifiable set is chosen among the others",
    )
    p.add_argument(
        "--bound", action="append", metavar="NAME=LO:HI",
        help="keep a parameter's error inside [LO, HI], in its unit (lmfit's min/max; repeatable; an empty side is "
             "open, e.g. --bound effect.deflection.compliance=0:): ls, ridge and map stay inside and name a "
             "parameter that ends on a bound (no std: the others' covariance is conditional on it), mcmc samples "
             "the posterior truncated there; tsvd and kalman refuse bounds",
    )


def run(args) -> int:
    from ..identify.answer import calibration_answer
    from ..identify.probabilistic import calibrate_bayes
    from . import EXIT_FAILED, EXIT_OK

    _check_options(args)
    machine, rec, model, check, session = inputs_with_session(args, constraints=True)
    if args.write_klipper and machine.kind != "linear-delta":
        raise InputError(f"--write-klipper: Klipper's delta keys describe a linear-delta machine; {args.machine} is a {machine.kind}")
    if args.write_urdf:
        from ..machines.urdf_write import serial_part

        serial_part(machine, what="--write-urdf: a URDF")  # InputError (exit 2) for other kinds, before any fit
    free = free_arg(args.free)
    fix = name_list(args.fix) if args.fix is not None else None
    bounds = bound_args(args.bound)
    _check_method_arguments(args)
    if args.fit_effects:
        model = joint_effects_model(args, machine, rec, model)
    okw = outlier_kwargs(args, rec, model.n_poses)
    if args.method in METHODS:
        if args.rule:
            raise InputError("--rule goes with --method ridge --lam auto or --method tsvd --k auto")
        # the noise test, the outliers, the filter or sampler and the whole answer: one library call
        answer = calibrate_bayes(model, method=args.method, free=free, fix=fix, bounds=bounds, max_iter=args.max_iter, noise=args.noise,
                                 fit_effects=args.fit_effects, machine=machine, check=check, session=session,
                                 **okw, **bayes_options(args))
        return run_bayes(args, machine, answer)
    auto = (args.method == "ridge" and args.lam == "auto") or (args.method == "tsvd" and args.k == "auto")
    if not auto and (args.rule or args.figures):
        raise InputError("--rule and --figures go with --lam auto, --k auto, --method kalman or --method mcmc")
    if args.fit_effects and args.prior_scale == "empirical":
        # one factor estimated for every prior would rescale the effects' priors with the geometry's tolerances
        raise InputError("--prior-scale empirical does not go with --fit-effects: the effects' priors are not "
                         "the machine file's tolerances (use --prior-scale tolerance)")
    # method dispatch, outliers, the prior scale and the noise check: one library call (bayescal.identify.calibrate)
    # ... and the whole answer (pivots, instrument frame, plausibility, held-out rows), as bayescal.calibrate gives it
    cal, extra, held_out = calibration_answer(
        model, machine, method=args.method, session=session, check=check, lam=args.lam, k=args.k, free=free,
        fix=fix, bounds=bounds, rule=args.rule, prior_scale=args.prior_scale, max_iter=args.max_iter, noise=args.noise,
        fit_effects=args.fit_effects, discrepancy=args.discrepancy,
        discrepancy_inputs=name_list(args.discrepancy_inputs) if args.discrepancy_inputs else None, **okw)
    res, choice, plaus = cal.result, cal.choice, cal.plausibility
    # the answers are written before anything is printed, so that a reader of stdout that
    # goes away early (`| head`) cannot cost the JSON or the calibrated machine file
    write_json(args, cal.to_dict())
    write_calibrated_files(args, cal.machine_with_record(), res, plaus)
    write_report(args, "identify", res, machine=machine, model=model, choice=choice, answer_extra=extra)
    path = None
    if choice is not None and args.figures:
        from ..plots.regularisation import plot_choice

        path = plot_choice(choice, f"{args.figures}/regularisation_{args.method}.png")
    if not args.quiet:
        _print_answer(args, machine, cal, extra, held_out, path)
    return EXIT_OK if res.success and plaus.plausible else EXIT_FAILED


def _print_answer(args, machine, cal, extra: dict, held_out, figure) -> None:
    """The answer on stdout: the identification, noise, discrepancy, held-out rows, outliers, frame and notes."""
    from ..prediction.recording import held_out_report

    res, handling, choice, plaus = cal.result, cal.handling, cal.choice, cal.plausibility
    print(res.report())
    print(cal.noise_report())
    if text := cal.discrepancy_report():
        print(text)
    if text := held_out_report(held_out):
        print(text)
    print(handling.report())
    print(instrument_report(extra, plaus))
    if machine.effects:
        how = "fitted with the geometry (--fit-effects)" if args.fit_effects else "applied at their stored values"
        print(f"\neffects {how} ({args.machine}): {', '.join(e.name for e in machine.effects)}")
    if "prior_scale_note" in res.extras:
        print("\n" + res.extras["prior_scale_note"])
    if "prior_scale" in res.extras:
        print(f"\nprior scale: {res.extras['prior_scale']:.3g} x the machine file's tolerances "
              f"(estimated from the data; --prior-scale tolerance to use them as they are)")
    if choice is not None:
        print("\n" + choice.report())
    if figure is not None:
        print(f"\nwrote {figure}")
    if args.write_machine and not res.success:
        print(f"\nnot writing {args.write_machine}: the identification did not succeed")
    if note := refusal_note(args, res, plaus):
        print("\n" + note)
    if args.write_klipper and not (res.success and plaus.plausible):
        print(f"\nnot writing {args.write_klipper}: the identification did not succeed or is not plausible")
    if args.write_urdf and not (res.success and (plaus.plausible or args.force)):
        print(f"\nnot writing {args.write_urdf}: the identification did not succeed or is not plausible (--force)")
