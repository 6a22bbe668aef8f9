"""``bayescal grid``: a compensation grid with uncertainty at every node, from a recording."""

from __future__ import annotations

import argparse

from ..constants import GRID_METHODS
from ..errors import InputError
from . import SUMMARIES
from .inputs import add_frame_argument, bound_args, free_arg, inputs_with_session, name_list
from .outputs import add_output_options, say, write_json, write_report

HELP = """\
Identify the geometric errors (MAP under the tolerance prior, or the Kalman
filter), then write a compensation grid over the actuator range: at every
node the predicted tool-point correction (mm) and its one-sigma uncertainty
(mm, from the linearised covariance or from MCMC posterior draws), as CSV
with columns q1..qN, dx, dy, dz, sx, sy, sz, and optionally a heat map.

With --free all (default) every parameter is estimated under its prior, so
the std also carries what the measurement cannot separate; --free auto is the
same except that parameters the measurement does not see at all are taken as
exactly nominal (the prior decides what the data cannot separate; see
docs/cli.md, identify --free).

A machine file with [effect.<name>] tables (diagnose --write-machine) has
them applied: in the identification, driven by the recording's channels,
and in the grid (actuator or tool space), under the channels stated with
--aux NAME=VALUE (a compensation under a payload or temperature). A
channel not given is absent, as in a recording without it; a table fitted
with a channel needs it: joint compliance fitted with a payload needs
--aux payload_kg=... (0: no payload), thermal expansion --aux temp_C=... .
Grid nodes have no approach direction, so backlash is not in the grid
(compensate it on reversal).  With --fit-effects (map, mcmc) the tables'
parameters are identified with the geometry (identify --fit-effects), the
grid applies the fitted values, and its std carries their uncertainty.

A constraint recording (distances, heights, ballbar readings; docs/formats.md
section 6) gives the grid of the geometry it calibrates; ballbar pivots are
nuisance parameters, fitted and left out of the grid (so is a fitted
instrument frame).

--space tool spans the grid over the nominal tool point instead (x, y, z in
mm, the coordinates the actuators set; nominal inverse kinematics at every
node): at each node the residual error (actual minus commanded) and its
std.  --nc CSV writes it in the NC-loadable format (docs/formats.md section E8: the BIC
columns i,j,x,z,ex,ez,std_ex,std_ez for a planar machine such as the
RASPM-2T1R, otherwise i,j,k,x,y,z,ex,ey,ez,std_ex,std_ey,std_ez).  The
default space is 'actuator' where every actuator vector within q_limits
assembles, and 'tool' for a machine that declares otherwise (a linear delta,
whose q_limits box holds carriage positions the arms cannot join; a
redundantly actuated machine, whose actuators are not independent).  --range NAME=LO:HI narrows
an axis (q1..qN in actuator space, x, y, z in tool space; repeatable).

The calibration is judged by identify's plausibility rule (docs/real-instruments.md):
one that is not plausible (one pose, copied rows, errors beyond 10 tolerances)
is reported, nothing is written and the command exits 1, as identify does;
--force writes the grid anyway (still exit 1).
"""

EXAMPLES = """\
examples:
  bayescal grid examples/prs3/recording.csv --machine examples/prs3/machine.toml --out grid.csv --figure grid.png
  bayescal grid rec.csv --machine m.toml --nodes 15 --method kalman --json grid.json
  bayescal grid rec.csv --machine m.toml --method mcmc --surrogate linear --out grid.csv
  bayescal grid rec.csv --machine calibrated.toml --aux payload_kg=5 --aux temp_C=25 --out grid.csv
  bayescal grid rec.csv --machine m.toml --space tool --nodes 5 --nc nc_grid.csv
  bayescal grid rec.csv --machine examples/raspm/machine.toml --range x=-200:200 --range z=-500:-250 --nc bic.csv
  bayescal grid rec.csv --machine m.toml --range q1=460:540 --nodes 5 --out grid.csv
"""


def register(sub) -> None:
    p = sub.add_parser(
        "grid", help=SUMMARIES["grid"], description=HELP, epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recording", help="recording CSV (docs/formats.md section 2, or a constraint recording, section 6)")
    p.add_argument("--machine", required=True, help="machine file TOML with [workspace] q_limits (docs/formats.md section 1)")
    p.add_argument("--method", choices=GRID_METHODS, default="map", help="how to identify (default map)")
    p.add_argument("--free", default="all", help="'all' (default), 'auto' or comma-separated names")
    p.add_argument("--fix", metavar="NAMES", help="comma-separated parameters held at nominal (identify --fix)")
    p.add_argument("--bound", action="append", metavar="NAME=LO:HI",
                   help="keep a parameter inside [LO, HI] (identify --bound; map and mcmc; repeatable)")
    p.add_argument("--nodes", type=int, default=9, help="nodes per actuator within q_limits (default 9)")
    p.add_argument("--dof", type=int, choices=(6, 5, 3), help="use only this much of the measurement")
    p.add_argument("--steps", type=int, default=1000, help="mcmc: steps per walker (default 1000)")
    p.add_argument("--ess", type=float, metavar="N",
                   help="mcmc: stop the sampler once its checks pass with bulk and tail ESS >= N (identify --ess; "
                        "--steps is then the most steps)")
    p.add_argument("--surrogate", choices=("none", "linear"), default="none", help="mcmc: sample the linearised model")
    p.add_argument("--seed", type=int, default=0, help="mcmc: random seed")
    p.add_argument(
        "--aux", action="append", default=[], metavar="NAME=VALUE",
        help="auxiliary channel at which the machine file's [effect.*] tables act at every node (repeatable), "
        "e.g. --aux payload_kg=5 --aux temp_C=25; a channel not given is absent, and a table fitted with it "
        "(payload_kg, temp_C) then asks for it",
    )
    p.add_argument("--space", choices=("auto", "actuator", "tool"), default="auto",
                   help="grid over actuator positions or over the tool point (default auto: tool for a machine whose "
                   "q_limits box is not all reachable, e.g. a linear delta or a redundantly actuated machine; "
                   "actuator otherwise)")
    p.add_argument("--range", action="append", default=[], metavar="NAME=LO:HI", dest="ranges",
                   help="narrow one grid axis (repeatable): q1..qN (actuator unit) or x, y, z (mm)")
    p.add_argument("--nc", metavar="CSV", help="tool space: write the NC-loadable grid CSV (docs/formats.md section E8)")
    p.add_argument("--out", metavar="CSV", help="write the grid as CSV")
    p.add_argument("--figure", metavar="PNG", help="draw correction and std heat maps")
    p.add_argument("--json", metavar="PATH", help="write a summary as JSON")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    p.add_argument("--force", action="store_true",
                   help="write the grid even when the calibration is not plausible (identify's rule: errors beyond "
                   "10 tolerances, or no residual degrees of freedom, e.g. one pose or copied rows)")
    p.add_argument("--fit-effects", action="store_true",
                   help="map, mcmc: identify the machine file's [effect.*] parameters with the geometry; the grid's "
                   "std then carries their uncertainty")
    add_frame_argument(p)
    add_output_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from . import EXIT_FAILED, EXIT_OK
    from ..bayes.recording_grid import grid_space, recording_grid
    from ..effects.stored import parse_aux_values

    aux = parse_aux_values(args.aux)  # bad --aux is bad input before any work
    for flag, given in (("--steps", args.steps != 1000), ("--surrogate", args.surrogate != "none"),
                        ("--ess", args.ess is not None)):
        if given and args.method != "mcmc":  # they were ignored, silently
            raise InputError(f"{flag} goes with --method mcmc; it does nothing with --method {args.method}")
    ranges = _ranges(args.ranges)
    machine, _, model, _, session = inputs_with_session(args, constraints=True)
    if args.nc and grid_space(model.machine, args.space) != "tool":
        raise InputError("--nc goes with --space tool (an NC system compensates tool points)")
    # the checks, the identification and the grid: one library call, so a notebook gets this grid and JSON
    answer = recording_grid(session if session is not None else model, method=args.method, free=free_arg(args.free),
                            nodes=args.nodes, space=args.space, ranges=ranges, aux=aux, steps=args.steps,
                            surrogate=args.surrogate, seed=args.seed, fit_effects=args.fit_effects, ess=args.ess,
                            fix=name_list(args.fix) if args.fix is not None else None, bounds=bound_args(args.bound))
    res, grid = answer.identification, answer.grid
    if grid is None:
        if not args.quiet:
            print(res.report())
        print(f"bayescal grid: the identification did not succeed ({res.message}); no grid written")
        return EXIT_FAILED
    if not answer.plausible and not args.force:
        # identify's rule and refusal (bayescal.instrument.plausibility): reported, nothing written, exit 1
        if not args.quiet:
            print(answer.report())
        print("bayescal grid: the calibration is not plausible; no grid written (--force writes it anyway)")
        return EXIT_FAILED
    # outputs first: a closed stdout (`| head`) must not cost them
    if args.out:
        answer.write_csv(args.out, force=args.force)
        say(args, f"wrote {args.out} (grid CSV, {answer.space} space)")
    if args.nc:
        answer.write_nc_csv(args.nc, force=args.force)
        say(args, f"wrote {args.nc} (NC-loadable grid CSV, docs/formats.md section E8)")
    if args.figure:
        from ..plots.bayes import plot_grid

        plot_grid(grid, args.figure, units=answer.machine.actuator_units if answer.space == "actuator" else None)
        say(args, f"wrote {args.figure} (figure)")
    write_json(args, answer.to_dict())
    write_report(args, "grid", grid, identification=res, machine=machine)
    if not args.quiet:
        print(answer.report())
    return EXIT_OK if answer.plausible else EXIT_FAILED  # forced: written, but not a success (as identify)


def _ranges(items: list[str]) -> dict:
    """``["x=-10:10", "q1=450:500"]`` -> ``{"x": (-10.0, 10.0), ...}`` (the names are checked by the library)."""
    out = {}
    for item in items:
        name, eq, span = item.partition("=")
        lo, colon, hi = span.partition(":")
        try:
            if not eq or not colon or not name.strip():
                raise ValueError
            value = (float(lo), float(hi))
        except ValueError:
            raise InputError(f"--range {item!r}: expected NAME=LO:HI, e.g. x=-100:100 or q1=450:550") from None
        if name.strip() in out:
            # the last one won, silently
            raise InputError(f"--range {name.strip()}: given twice; expected one LO:HI per axis")
        out[name.strip()] = value
    return out
