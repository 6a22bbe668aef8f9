"""The probabilistic methods of ``bayescal identify``: --method kalman | mcmc (options and run)."""

from __future__ import annotations

import argparse
import sys

from ..constants import BAYES_METHODS as METHODS
from ..errors import InputError
from .outputs import say, write_json, write_report

__all__ = ["add_arguments", "check_method_options", "bayes_options", "run_bayes", "METHODS"]



def add_arguments(p) -> None:
    g = p.add_argument_group("kalman and mcmc")
    g.add_argument("--variant", choices=("ekf", "ukf"), default="ekf", help="kalman: extended or unscented filter (default ekf)")
    g.add_argument(
        "--process-noise", type=float, default=0.0,
        help="kalman: random-walk std per pose, as a fraction of each prior std (default 0: static parameters)",
    )
    g.add_argument("--steps", type=int, default=1000, help="mcmc: steps per walker incl. burn-in (default 1000)")
    g.add_argument("--ess", type=float, metavar="N",
                   help="mcmc: stop as soon as every convergence check passes with bulk and tail ESS >= N (checked as "
                        "the chain grows by a tenth; --steps is then the most steps; e.g. 4000); default: run --steps")
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
        help="mcmc: show a progress bar (default: when stderr is a terminal); --no-progress also silences the "
             "progress lines a long fit writes on stderr (docs/cli.md, Limits)",
    )


#: Options that act only with one method: (dest, option, method, is it given?).
_METHOD_OPTIONS = (
    ("posterior", "--posterior", "mcmc", lambda v: v is not None),
    ("walkers", "--walkers", "mcmc", lambda v: v is not None),
    ("ess", "--ess", "mcmc", lambda v: v is not None),
    ("steps", "--steps", "mcmc", lambda v: v != 1000),  # given with map it was ignored, silently (a probe found it)
    ("checkpoint_every", "--checkpoint-every", "mcmc", lambda v: v != 100),
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


def bayes_options(args) -> dict:
    """The options of ``args.method`` for :func:`bayescal.identify.probabilistic.calibrate_bayes`."""
    if args.method == "kalman":
        return {"variant": args.variant, "process_noise": args.process_noise}
    return {"steps": args.steps, "walkers": args.walkers, "seed": args.seed, "surrogate": args.surrogate,
            "progress": sys.stderr.isatty() if args.progress is None else args.progress,
            "checkpoint": args.checkpoint, "checkpoint_every": args.checkpoint_every, "resume": args.resume,
            "ess": args.ess}


def run_bayes(args, machine, answer) -> int:
    """Write and print the answer of kalman or mcmc (:class:`bayescal.identify.probabilistic.BayesCalibration`)."""
    from . import EXIT_FAILED, EXIT_OK
    from .instrument import instrument_report, refusal_note, write_calibrated_files
    from ..bayes.mcmc import write_posterior
    from ..prediction.recording import held_out_report

    res, plaus = answer.result, answer.plausibility
    write_json(args, answer.to_dict())  # before printing: a closed stdout (`| head`) must not cost the answer
    if args.method == "mcmc" and args.posterior and res.success:
        write_posterior(res, args.posterior)
        say(args, f"wrote {args.posterior} (posterior draws, NetCDF)")
    write_calibrated_files(args, answer.machine, res, plaus)
    write_report(args, "identify", res, machine=machine, model=answer.model, answer_extra=answer.frame)
    made = []
    if args.figures:
        from ..plots.bayes import plot_filter_history, plot_pair, plot_trace, plot_trace_pages

        from ..io.safe_paths import output_folder

        out = output_folder(args.figures, "--figures")
        if args.method == "kalman":
            made = [plot_filter_history(res, out / "kalman_history.png")]
        elif res.success:
            made = [plot_trace(res, out / "mcmc_trace.png"), *plot_trace_pages(res, out), plot_pair(res, out / "mcmc_pair.png")]
    if not args.quiet:
        print(res.report())
        if answer.noise is not None:
            print(answer.noise.noise_report())
        print(instrument_report(answer.frame, plaus))
        print(answer.handling.report())
        if text := held_out_report(answer.held_out):
            print(text)
        if made:
            print("\nfigures: " + ", ".join(str(m) for m in made))
    if (args.write_machine or getattr(args, "posterior", None)) and not res.success and not args.quiet:
        print("\nnot writing outputs: the identification did not succeed")
    if (note := refusal_note(args, res, plaus)) and not args.quiet:
        print("\n" + note)
    return EXIT_OK if res.success and plaus.plausible else EXIT_FAILED
