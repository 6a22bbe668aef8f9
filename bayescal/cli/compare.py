"""``bayescal compare``: compare identification methods statistically (Monte Carlo)."""

from __future__ import annotations

import argparse
import sys

from ..constants import COMPARE_METHODS, METRICS
from . import SUMMARIES
from .outputs import add_output_options, say, write_json, write_report

HELP = """\
Compare identification methods by Monte Carlo on simulated machines.  Per
trial: a true machine drawn from the tolerances, poses within q_limits,
instrument noise; every method identifies on the same data; the output
error (RMS and max position error, RMS angle error) is evaluated on fresh
poses.  The report gives per method the error distribution, paired
differences with bootstrap confidence intervals, Wilcoxon signed-rank tests
between every pair with Holm's correction, win rates, and failures counted
separately (docs/compare.md explains how to read it).

Methods: registry names, comma separated, options after a colon
(ridge:lam=0.1, tsvd:k=20; several options separated by ';').  Registered:
{methods}
A method of your own, added in Python with bayescal.compare.register_method,
is compared in that Python session (bayescal.compare.compare_methods); this
command knows the methods above.

With --recording CSV every trial re-measures what that recording measured
(its poses, or the distance pairs, heights and ballbar circles of a
constraint recording, docs/formats.md section 6) on its true machine, so the
methods are compared on the user's own measurement plan; ballbar pivots
are fitted as nuisance parameters and the output error is the geometry's.

Trials are seeded by their index: the answer is the same in-process, on
--workers N local processes, or on dask (--dask-workers N for a local
cluster, --scheduler tcp://host:port for a running one).  With --out DIR
every finished trial is saved (DIR/trials.jsonl); rerunning with the same
DIR resumes, recomputing only missing trials, and writes the table, the
JSON answer and the figures there.
"""

EXAMPLES = """\
examples:
  bayescal compare --machine examples/prs3/machine.toml --methods ls,ridge,tsvd --trials 500 --out cmp
  bayescal compare --machine m.toml --methods ls,ridge:lam=0.1,ridge:lam=1,tsvd:k=25 --dof 5 --trials 200 --workers 2
  bayescal compare --machine m.toml --methods ridge,tsvd --trials 2000 --dask-workers 8 --out big --json big.json
  bayescal compare --machine m.toml --methods ls,ridge --trials 500 --scheduler tcp://10.0.0.5:8786 --out run1
  bayescal compare --machine m.toml --recording ballbar.csv --methods ridge,tsvd --trials 200
"""


def register(sub) -> None:
    # the registry's own methods (bayescal.compare.METHODS describes them by these words), without importing it
    known = "\n".join(f"  {name:<8}{text}" for name, text in COMPARE_METHODS.items())
    p = sub.add_parser(
        "compare", help=SUMMARIES["compare"], description=HELP.format(methods=known),
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--machine", required=True, help="nominal machine file TOML with [workspace] q_limits")
    p.add_argument("--methods", default="ls,ridge,tsvd", help="comma-separated methods (default ls,ridge,tsvd)")
    p.add_argument("--trials", type=int, default=500, help="Monte Carlo trials (default 500)")
    p.add_argument("--dof", type=int, choices=(6, 5, 3), help="measurement (default 6, or the --recording's)")
    p.add_argument("--poses", type=int, help="measured poses per trial (default 36; not with --recording)")
    p.add_argument("--recording", metavar="CSV",
                   help="re-measure this recording's poses or relations (distances, heights, ballbar) in every trial")
    p.add_argument("--eval-poses", type=int, default=100, help="fresh poses for the output error (default 100)")
    p.add_argument("--free", choices=("auto", "all"), default="auto",
                   help="auto (default): each method resolves it as identify does (ls: the identifiable set of each "
                        "trial; methods with a prior: every parameter the measurement sees); all: every parameter")
    p.add_argument("--metric", choices=METRICS, default="rms_position", help="error the statistics use")
    p.add_argument("--alpha", type=float, default=0.05, help="family-wise significance level (default 0.05)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--tolerance-scale", type=float, default=1.0, help="draw true machines with scaled tolerances")
    p.add_argument("--workers", type=int, default=0, help="local processes (default: in-process)")
    p.add_argument("--dask-workers", type=int, default=0, help="start a dask LocalCluster with N workers")
    p.add_argument("--scheduler", help="address of a running dask scheduler, tcp://host:port")
    p.add_argument("--retries", type=int, default=3, help="dask retries of a trial that raised an exception (default 3); "
                   "a trial whose worker died is rescheduled by dask itself "
                   "(distributed.scheduler.allowed-failures, default 3)")
    p.add_argument("--out", metavar="DIR", help="save trials (resumable), table, JSON and figures here")
    p.add_argument("--json", metavar="PATH", help="write the comparison as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    p.add_argument("--frame", choices=("base", "fit"), default="base",
                   help="only 'base': trials are simulated in the base frame (see docs/real-instruments.md)")
    add_output_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    """The library's :func:`bayescal.compare.verb.compare_files`, written and printed."""
    from ..compare.verb import compare_files, write_comparison_folder
    from ..machines.files import load_machine
    from . import EXIT_FAILED, EXIT_OK

    machine = load_machine(args.machine)
    cmp = compare_files(
        machine, methods=args.methods, trials=args.trials, recording=args.recording, dof=args.dof, poses=args.poses,
        frame=args.frame, alpha=args.alpha, out=args.out, n_eval=args.eval_poses, seed=args.seed, free=args.free,
        tolerance_scale=args.tolerance_scale, metric=args.metric, workers=args.workers,
        dask_workers=args.dask_workers, scheduler=args.scheduler, retries=args.retries,
        progress=not (args.no_progress or args.quiet),
    )
    text = cmp.report()
    if args.out:
        paths = write_comparison_folder(cmp, args.out)
        say(args, f"wrote {paths[0]}, {paths[1]} and {len(paths) - 2} figures in {args.out}")
    write_json(args, cmp.to_dict())
    write_report(args, "compare", cmp, machine=machine)
    if not args.quiet:
        print(text)
    if cmp.failed_everywhere:
        # the computation ran, but says nothing about these methods (docs/cli.md: exit 1)
        print(f"bayescal compare: {', '.join(cmp.failed_everywhere)} failed in every trial (the failures above say "
              "why)", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK
