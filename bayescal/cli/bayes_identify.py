"""The probabilistic methods of ``bayescal identify``: --method kalman | mcmc (options and run)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import InputError
from .outputs import say, write_json, write_report

__all__ = ["add_arguments", "check_method_options", "run_bayes", "METHODS"]

METHODS = ("kalman", "mcmc")


def add_arguments(p) -> None:
    g = p.add_argument_group("kalman and mcmc")
    g.add_argument("--variant", choices=("ekf", "ukf"), default="ekf", help="kalman: extended or unscented filter (default ekf)")
    g.add_argument(
        "--process-noise", type=float, default=0.0,
        help="kalman: random-walk std per pose, as a fraction of each prior std (default 0: static parameters)",
    )
    g.add_argument("--steps", type=int, default=1000, help="mcmc: steps per walker incl. burn-in (default 1000)")
    g.add_argument("--walkers", type=int, help="mcmc: number of walkers (default 2 x parameters + 2)")
    g.add_argument("--seed", type=int, default=0, help="mcmc: random seed (default 0)")
    g.add_argument(
        "--surrogate", choices=("none", "linear"), default="none",
        help="mcmc: 'linear' samples the model linearised at the MAP (fast; checked and reported)",
    )
    g.add_argument("--posterior", metavar="PATH", help="mcmc: write the posterior (arviz DataTree) as NetCDF")
    g.add_argument("--checkpoint", metavar="PATH.npz",
                   help="mcmc: save the chain and random state here every --checkpoint-every steps (atomically)")
    g.add_argument("--checkpoint-every", type=int, default=100, metavar="N", help="mcmc: steps between checkpoints (default 100)")
    g.add_argument("--resume", action="store_true",
                   help="mcmc: continue the chain saved in --checkpoint up to --steps (same result as an uninterrupted "
                   "run with the same --seed)")
    g.add_argument(
        "--progress", action=argparse.BooleanOptionalAction, default=None,
        help="mcmc: show a progress bar (default: when stderr is a terminal)",
    )


#: Options that act only with one method: (dest, option, method, is it given?).
_METHOD_OPTIONS = (
    ("posterior", "--posterior", "mcmc", lambda v: v is not None),
    ("walkers", "--walkers", "mcmc", lambda v: v is not None),
    ("surrogate", "--surrogate", "mcmc", lambda v: v != "none"),
    ("checkpoint", "--checkpoint", "mcmc", lambda v: v is not None),
    ("resume", "--resume", "mcmc", bool),
    ("variant", "--variant", "kalman", lambda v: v != "ekf"),
    ("process_noise", "--process-noise", "kalman", lambda v: v != 0.0),
)


def check_method_options(args) -> None:
    """Refuse, before any work, an option of one method given with another (it would be silently ignored)."""
    for dest, option, method, given in _METHOD_OPTIONS:
        if args.method != method and given(getattr(args, dest, None)):
            raise InputError(f"{option} goes with --method {method}; it does nothing with --method {args.method}")


def run_bayes(args, machine, model, free, check=None, outliers=None, session=None, noise=None) -> int:
    """Run kalman or mcmc; ``outliers`` (an OutlierHandling of a robust MAP pass) weights the poses and is reported."""
    from . import EXIT_FAILED, EXIT_OK
    from .effect_options import with_fitted_effects
    from .instrument import instrument_report, judge, refusal_note, write_calibrated_files
    from ..bayes.kalman import kalman_filter
    from ..bayes.mcmc import sample_posterior, write_posterior

    if args.method != "mcmc" and (args.checkpoint or args.resume):
        raise InputError("--checkpoint and --resume go with --method mcmc")
    if args.resume and not args.checkpoint:
        raise InputError("--resume needs --checkpoint PATH (the checkpoint to continue)")
    base_model = model
    if outliers is not None:
        model = outliers.weighted_model(model)  # the robust MAP pass's weights (docs/outliers.md)
    if args.method == "kalman":
        res = kalman_filter(model, variant=args.variant, free=free, process_noise=args.process_noise)
    else:
        if args.steps < 20:
            # fewer steps cannot even estimate an autocorrelation time
            raise InputError(f"--steps: expected at least 20, got {args.steps}")
        res = sample_posterior(
            model, free=free, n_steps=args.steps, n_walkers=args.walkers, seed=args.seed,
            progress=sys.stderr.isatty() if args.progress is None else args.progress, surrogate=args.surrogate,
            checkpoint=args.checkpoint, checkpoint_every=args.checkpoint_every, resume=args.resume,
        )
    answer, outlier_text = res.to_dict(), ""
    if outliers is not None:
        from ..identify.robust import map_system

        outliers = outliers.retested(base_model, res, map_system(res))
        answer.update(outliers.to_dict())
        outlier_text = outliers.report()
    extra, plaus = judge(machine, base_model, res, check)  # instrument frame and plausibility
    answer.update(extra)
    from ..prediction.recording import held_out_report, score_held_out

    # the noise and the leave-one-out factor of the MAP the method started from (the same model and prior)
    scale, kappa = (1.0, 1.0) if noise is None else (noise.noise_scale, noise.variance_factor)
    held_out = (score_held_out(res, session, noise_scale=scale, variance_factor=kappa)
                if session is not None and not args.fit_effects else {})
    answer.update(held_out)
    if noise is not None:
        answer.update(noise.noise_dict())
    write_json(args, answer)  # before printing: a closed stdout (`| head`) must not cost the answer
    if args.method == "mcmc" and args.posterior and res.success:
        write_posterior(res, args.posterior)
        say(args, f"wrote {args.posterior} (posterior draws, NetCDF)")
    write_calibrated_files(args, with_fitted_effects(machine, base_model, res), res, plaus)
    write_report(args, "identify", res, machine=machine, model=base_model, answer_extra=extra)
    made = []
    if args.figures:
        from ..plots.bayes import plot_filter_history, plot_pair, plot_trace, plot_trace_pages

        out = Path(args.figures)
        out.mkdir(parents=True, exist_ok=True)
        if args.method == "kalman":
            made = [plot_filter_history(res, out / "kalman_history.png")]
        elif res.success:
            made = [plot_trace(res, out / "mcmc_trace.png"), *plot_trace_pages(res, out), plot_pair(res, out / "mcmc_pair.png")]
    if not args.quiet:
        print(res.report())
        if noise is not None:
            print(noise.noise_report())
        print(instrument_report(extra, plaus))
        if outlier_text:
            print(outlier_text)
        if text := held_out_report(held_out):
            print(text)
        if made:
            print("\nfigures: " + ", ".join(str(m) for m in made))
    if (args.write_machine or getattr(args, "posterior", None)) and not res.success and not args.quiet:
        print("\nnot writing outputs: the identification did not succeed")
    if (note := refusal_note(args, res, plaus)) and not args.quiet:
        print("\n" + note)
    return EXIT_OK if res.success and plaus.plausible else EXIT_FAILED
