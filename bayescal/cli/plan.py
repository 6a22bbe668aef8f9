"""``bayescal plan``: choose measurement poses by information."""

from __future__ import annotations

import argparse

from ..constants import CRITERIA, SCALINGS
from ..errors import InputError
from . import SUMMARIES
from .outputs import add_output_options, write_json, write_report

HELP = """\
Plan a measurement session: choose N poses from candidates drawn uniformly
within the machine file's [workspace] q_limits (poses without a forward
solution are rejected), maximising an information criterion of the
whitened, column-scaled identification Jacobian (docs/planning.md):

  D    det(J^T J)^(1/L)                    A    L / trace((J^T J)^-1)
  E    smallest eigenvalue of J^T J        O1   (s1...sL)^(1/L)/sqrt(m)  (Borm & Menq)
  O2   sL/s1 (Driels & Pathre)             O3   sL (Nahvi et al.)
  O4   sL^2/s1 (Nahvi & Hollerbach)        O5   1/(1/s1+...+1/sL) (after Sun &
                                                Hollerbach 2008; formula unverified, see docs)
  EIG  0.5 log det(I + S J^T J S): expected information gain under the tolerance prior
  I    sqrt(trace(Q) / trace(Sigma Q)): root expected mean squared tool-point
       error, sqrt(E[MSE]), over the workspace before / after MAP calibration
       (I-optimality, linearised), with
       Sigma = (I + S J^T J S)^-1 and Q = mean over workspace poses of G^T G
       (G: tool-point Jacobian, mm per tolerance); the one matched to
       'identify --method ridge --lam 1' (MAP) and to the output error

Selection: greedy addition with rank-k updates, then DETMAX exchange; for
criterion I by default the Frank-Wolfe relaxed design, rounded and improved
by exchanges (repeats allowed), with a certified bound on sqrt(E[MSE]) of
every design from the candidates printed beside the plan's.  The
output CSV holds the commanded actuator positions q1..qN and a pose_id
(1-based measurement order): drive the machine there, measure, append the
measured columns (x, y, z, ...), and it is a recording for 'bayescal identify'.
The report compares the plan with the median of random selections.
"""

EXAMPLES = """\
examples:
  bayescal plan --machine examples/prs3/machine.toml --n 36 --out poses.csv
  bayescal plan --machine m.toml --n 24 --criterion EIG --dof 5 --seed 3 --out poses.csv --json plan.json
  bayescal plan --machine m.toml --n 18 --criterion I --out poses.csv
  bayescal plan --machine m.toml --n 10 --criterion I --certify 1 --out poses.csv
  bayescal plan --machine m.toml --n 40 --criterion O4 --candidates 5000 --scaling candidates --out p.csv
  bayescal plan --machine m.toml --separate recording.csv --n 30 --out next.csv
  bayescal plan --machine calib/machine.toml --measure height --given calib/recording.csv --n 6 \
      --centre 0,0,0 --radius 80 --sigma 0.02 --out heights.csv
  bayescal plan --machine calib/machine.toml --measure distance --given calib/recording.csv --n 6 \
      --centre 0,0,0.2 --radius 80 --sigma 0.05 --min-distance 20 --out distances.csv

With --measure height or distance the candidates are relations on a horizontal
grid (--centre, --radius, --spacing): probe heights at grid points, or distances
between two grid points (a printed part measured with a caliper); the selection
starts from the tolerance prior plus the measurements in --given (criterion EIG
by default), and the report lists each parameter's std before and after and
what the data cannot determine (docs/delta-printers.md).  The CSV is a
constraint recording with an empty value column: fill in what you measure.
"""


def register(sub) -> None:
    p = sub.add_parser(
        "plan", help=SUMMARIES["plan"], description=HELP, epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--machine", required=True, help="machine file TOML with [workspace] q_limits (docs/formats.md section 1)")
    p.add_argument("--n", type=int, required=True, help="number of poses to plan")
    p.add_argument("--criterion", type=str.upper, choices=CRITERIA, default=None,
                   help="what to maximise (default D for poses, EIG for heights and distances; I for MAP and the "
                        "tool-point error)")
    p.add_argument("--candidates", type=int, default=20000, help="candidate poses drawn (default 20000)")
    p.add_argument("--dof", type=int, choices=(6, 5, 3), default=6, help="what the instrument measures (default 6)")
    p.add_argument("--scaling", choices=SCALINGS, default="tolerance",
                   help="column scaling: tolerances (default) or unit RMS column norm over the candidates")
    p.add_argument("--seed", type=int, default=0, help="random seed: same seed, same plan (default 0)")
    p.add_argument("--random-sets", type=int, default=20, help="random selections to compare with (default 20)")
    p.add_argument("--no-exchange", action="store_true", help="greedy selection only")
    p.add_argument("--repeats", nargs="?", const="yes", choices=("auto", "yes", "no"), default="auto",
                   help="allow a pose (or relation) to be planned more than once (measure it again): optimal designs "
                        "repeat a few extreme poses. auto (default): yes with --method relaxed, no otherwise; "
                        "a bare --repeats means yes")
    p.add_argument("--method", choices=("auto", "greedy", "relaxed"), default="auto",
                   help="selection: greedy + exchange, or (criterion I) the Frank-Wolfe relaxed design rounded and "
                        "improved by exchanges, which also reports the bound on sqrt(E[MSE]) of every design. "
                        "auto (default): relaxed for I (it beat greedy at every size tried), greedy otherwise")
    p.add_argument("--exact-bound", action="store_true",
                   help="criterion I: also certify a lower bound for designs of whole poses (branch and bound on "
                   "the poses in each orthant of the actuator box; tighter than the relaxed bound at few poses; "
                   "about a minute with 3 actuators at 8-10 poses; refused above 4 actuators)")
    p.add_argument("--certify", type=float, metavar="PCT",
                   help="criterion I: prove the plan's sqrt(E[MSE]) within PCT %% of every design of N whole poses "
                        "(repeats allowed), by branch and bound on cells of the actuator box; a better design it finds "
                        "replaces the plan. Seconds to minutes with 3 actuators; with many actuators it may stop at "
                        "--certify-nodes without an answer")
    p.add_argument("--certify-nodes", type=int, default=5000, metavar="K",
                   help="relaxations allowed per --certify search (default 5000)")
    p.add_argument("--no-box", action="store_true",
                   help="candidates only drawn uniformly; by default the corners, edge midpoints and face centres "
                        "of the q_limits box (and points 1 %% and 5 %% inside them) are candidates too")
    p.add_argument("--measure", choices=("pose", "height", "distance"), default="pose",
                   help="what to plan: poses (default), probe heights or distances between points")
    p.add_argument("--separate", metavar="RECORDING",
                   help="plan a second session that separates the physical effects a diagnosis of RECORDING selects "
                        "from the geometry: --n of its poses under the condition forecast to help most (a heavier "
                        "payload, a tilted mounting, a temperature step; docs/diagnose.md). The pose file carries the "
                        "condition's channels")
    p.add_argument("--condition", choices=("payload", "temperature", "tilt_1", "tilt_2"),
                   help="with --separate: this condition instead of the one forecast to help most")
    p.add_argument("--effects", help="with --separate: comma-separated effects the diagnosis tries (default: every "
                                     "applicable one)")
    p.add_argument("--given", metavar="RECORDING", help="constraint recording already measured (--measure height/distance)")
    p.add_argument("--centre", type=_vector, help="grid centre X,Y,Z in mm (tool point; default: middle of q_limits)")
    p.add_argument("--radius", type=float, default=None, help="grid radius in mm (default 50)")
    p.add_argument("--spacing", type=float, help="grid spacing in mm (default radius/4)")
    p.add_argument("--sigma", type=float, help="noise of a planned measurement in mm (default [measurement] sigma_position)")
    p.add_argument("--min-distance", type=float, default=None, help="shortest distance to plan, mm (default 0)")
    p.add_argument("--out", required=True, help="CSV to write (poses: q1..qN, pose_id, docs/formats.md section E7; relations: a constraint recording)")
    p.add_argument("--json", metavar="PATH", help="write the plan and its criterion values as JSON")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    p.add_argument(
        "--frame", choices=("base", "fit"), default="base",
        help="'fit': plan for a measurement whose instrument frame will be fitted with the geometry "
        "(identify --frame fit): the six frame parameters take part in the criterion (default base)",
    )
    add_output_options(p)
    # the options a plan of new poses or relations uses and --separate does not (its candidates are the recording's
    # poses, its criterion the confound's variance): given with --separate they are refused, not ignored
    unused = ("criterion", "candidates", "dof", "scaling", "random_sets", "no_exchange", "repeats", "method",
              "exact_bound", "certify", "certify_nodes", "no_box", "given", "centre", "radius", "spacing", "sigma",
              "min_distance")
    p.set_defaults(func=run, separate_unused=tuple((d, p.get_default(d)) for d in unused))


def _vector(text: str) -> list[float]:
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in mm, got {text!r}") from None
    if len(v) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z, got {text!r}")
    return v


def _repeats(args) -> bool | None:
    return {"auto": None, "yes": True, "no": False}[args.repeats]


def _options(args) -> dict:
    """The library's keywords from the options given (None: not given, the library's default)."""
    given = {
        "dof": args.dof, "n_candidates": args.candidates, "scaling": args.scaling, "n_random": args.random_sets,
        "exchange": not args.no_exchange, "box": not args.no_box, "exact_bound": args.exact_bound,
        "certify": None if args.certify is None else args.certify / 100, "certify_nodes": args.certify_nodes,
        "given": args.given, "centre": args.centre, "radius": args.radius, "spacing": args.spacing,
        "sigma": args.sigma, "min_distance": args.min_distance,
    }
    return {k: v for k, v in given.items() if v is not None}


def run_relations(args, plan) -> int:
    from ..design.relations import relation_plan_csv
    from ..io import write_text_atomic
    from . import EXIT_OK

    write_text_atomic(args.out, relation_plan_csv(plan))
    write_json(args, plan.to_dict())
    if not args.quiet:
        print(plan.report())
        print(f"\nwrote {args.out} ({plan.recording.n_rows} {args.measure} rows; fill in the value column)")
    return EXIT_OK


def run_separate(args) -> int:
    """``--separate``: the library's :func:`bayescal.api.plan_next_session`, written and printed."""
    from ..api import plan_next_session
    from ..io.answers import write_text_atomic
    from . import EXIT_OK

    if args.measure != "pose":
        raise InputError(f"--separate plans poses; it does not go with --measure {args.measure}")
    for dest, default in args.separate_unused:
        if getattr(args, dest) != default:
            raise InputError(f"--{dest.replace('_', '-')} does nothing with --separate (the recording's poses are the "
                             "candidates, chosen for the confound between effects and geometry); leave it out")
    effects = None if args.effects is None else [e.strip() for e in args.effects.split(",") if e.strip()]
    plan = plan_next_session(args.machine, args.separate, args.n, condition=args.condition, effects=effects,
                             seed=args.seed, frame=args.frame)
    write_text_atomic(args.out, plan.to_csv())
    write_json(args, plan.to_dict())
    if not args.quiet:
        print(plan.report())
        print(f"\nwrote {args.out} ({plan.order.size} poses: q1..q{plan.q.shape[1]}, pose_id, "
              f"{', '.join(plan.channels)})")
    return EXIT_OK


def run(args) -> int:
    """The library's :func:`bayescal.design.verb.plan_files` (or ``plan_next_session``), written and printed."""
    from ..design import write_plan
    from ..design.verb import plan_files
    from ..machines.files import load_machine
    from . import EXIT_OK

    if args.separate is not None:
        return run_separate(args)
    for flag, value in (("--condition", args.condition), ("--effects", args.effects)):
        if value is not None:
            raise InputError(f"{flag} goes with --separate RECORDING; it does nothing for a plan of new poses")
    if args.certify is not None and not 0 < args.certify < 100:
        raise InputError(f"--certify: expected a percentage in (0, 100), got {args.certify}")
    machine = load_machine(args.machine)
    plan = plan_files(machine, args.n, measure=args.measure, criterion=args.criterion, frame=args.frame,
                      seed=args.seed, repeats=_repeats(args), method=None if args.method == "auto" else args.method,
                      **_options(args))
    if args.measure != "pose":
        return run_relations(args, plan)
    write_plan(args.out, plan)
    write_json(args, plan.to_dict())
    write_report(args, "plan", plan, machine=machine)
    if not args.quiet:
        print(plan.report())
        print(f"\nwrote {args.out} ({plan.n_poses} poses: q1..q{plan.q.shape[1]}, pose_id)")
    return EXIT_OK
