"""``bayescal grid``: a compensation grid with uncertainty at every node, from a recording."""

from __future__ import annotations

import argparse

import numpy as np

from ..errors import InputError
from . import SUMMARIES
from .inputs import add_frame_argument, free_arg, recording_model
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
    p.add_argument("--method", choices=("map", "kalman", "mcmc"), default="map", help="how to identify (default map)")
    p.add_argument("--free", default="all", help="'all' (default), 'auto' or comma-separated names")
    p.add_argument("--nodes", type=int, default=9, help="nodes per actuator within q_limits (default 9)")
    p.add_argument("--dof", type=int, choices=(6, 5, 3), help="use only this much of the measurement")
    p.add_argument("--steps", type=int, default=1000, help="mcmc: steps per walker (default 1000)")
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
    p.add_argument("--fit-effects", action="store_true",
                   help="map, mcmc: identify the machine file's [effect.*] parameters with the geometry; the grid's "
                   "std then carries their uncertainty")
    add_frame_argument(p)
    add_output_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from . import EXIT_FAILED, EXIT_OK
    from ..bayes.grid import compensation_grid
    from ..bayes.kalman import kalman_filter
    from ..bayes.mcmc import sample_posterior
    from ..bayes.priors import map_estimate

    from ..effects.stored import parse_aux_values

    aux = parse_aux_values(args.aux)  # bad --aux is bad input before any work
    machine, rec, model = recording_model(args, constraints=True)
    if aux and not machine.effects:
        raise InputError(f"--aux: {args.machine} carries no [effect.*] tables, so the grid depends on no channel")
    from ..effects.stored import PROBE_CHANNELS

    known = dict.fromkeys([*PROBE_CHANNELS, *rec.aux])
    typo = [k for k in aux if k not in known]
    if typo:  # a misspelt channel would silently leave the effect at its default
        raise InputError(f"--aux {typo[0]}: unknown channel; expected one of: {', '.join(known)}")
    from ..bayes.grid import check_grid_size

    # --nodes checked (at least 2, and arrays that fit in memory) before the identification runs
    check_grid_size(model.machine.geometry_part[0], args.nodes, args.space,
                    n_samples=400 if args.method == "mcmc" else 0)
    if args.fit_effects:
        from .effect_options import joint_effects_model

        model = joint_effects_model(args, machine, rec, model)
    free = free_arg(args.free)
    if args.method == "mcmc" and free == "all":
        free = "auto"  # sampling parameters the measurement does not see only explores the prior
    if args.method == "map":
        res = map_estimate(model, free=free)
        ok, kw = res.success, {"covariance": res.covariance}
    elif args.method == "kalman":
        res = kalman_filter(model, free=free)
        ok, kw = res.success, {"covariance": res.covariance}
    else:
        res = sample_posterior(model, free=free, n_steps=args.steps, seed=args.seed, surrogate=args.surrogate)
        ok, kw = res.success, {"samples": res.samples[:: max(1, res.samples.shape[0] // 400)]}
    if not ok:
        if not args.quiet:
            print(res.report())
        print(f"bayescal grid: the identification did not succeed ({res.message}); no grid written")
        return EXIT_FAILED
    # the grid is over the machine in its base frame: an instrument frame (fitted or known) is left out
    base, theta, free_mask, kw = base_frame_parts(model.machine, res.theta, res.free, kw)
    space = args.space
    if space == "auto":
        # the machine says whether its whole q_limits box assembles (base.Machine.actuator_box_reachable)
        space = "actuator" if base.actuator_box_reachable else "tool"
    ranges = _ranges(args.ranges, space, base.n_actuators)
    if space == "tool":
        from ..bayes.tool_grid import tool_grid

        grid = tool_grid(base, theta, free=free_mask, n=args.nodes, ranges=ranges, aux=aux, **kw)
    else:
        if args.nc:
            raise InputError("--nc goes with --space tool (an NC system compensates tool points)")
        axes = None
        if ranges:
            if base.q_limits is None:
                raise InputError(f"{args.machine}: no [workspace] q_limits to span a grid")
            lim = {f"q{i + 1}": tuple(b) for i, b in enumerate(base.q_limits)}
            lim.update(ranges)
            axes = tuple(np.linspace(*lim[f"q{i + 1}"], args.nodes) for i in range(base.n_actuators))
        grid = compensation_grid(base, theta, free=free_mask, n=args.nodes, axes=axes, aux=aux, **kw)
    # outputs first: a closed stdout (`| head`) must not cost them
    if args.out:
        grid.write_csv(args.out)
        say(args, f"wrote {args.out} (grid CSV, {space} space)")
    if args.nc:
        grid.write_nc_csv(args.nc)
        say(args, f"wrote {args.nc} (NC-loadable grid CSV, docs/formats.md section E8)")
    if args.figure:
        from ..plots.bayes import plot_grid

        plot_grid(grid, args.figure, units=base.actuator_units if space == "actuator" else None)
        say(args, f"wrote {args.figure} (figure)")
    extra = ({"effects": [e.name for e in machine.effects], "aux": aux, "effects_fitted": bool(args.fit_effects)}
             if machine.effects else {})
    write_json(args, {**grid.to_dict(), "method": args.method, **extra})
    write_report(args, "grid", grid, identification=res, machine=machine)
    if not args.quiet:
        print(grid.report())
        if machine.effects:
            at = ", ".join(f"{k} = {v:g}" for k, v in aux.items()) or "no auxiliary channel"
            how = "fitted with the geometry, " if args.fit_effects else ""
            print(f"  effects         {', '.join(e.name for e in machine.effects)} {how}applied at {at}")
    return EXIT_OK


def base_frame_parts(machine, theta, free, kw: dict):
    """The geometry's machine, its part of ``theta`` / ``free``, and of the covariance or samples.

    Nuisance parameters of the model's machine (a fitted instrument frame,
    ballbar pivots: :attr:`bayescal.machines.Machine.geometry_part`) are dropped.
    """
    base, idx = machine.geometry_part
    if idx.size == machine.n_params:
        return base, theta, free, kw
    keep = np.zeros(machine.n_params, dtype=bool)
    keep[idx] = True
    inner = keep[np.flatnonzero(free)]  # which columns of the covariance / samples are the geometry's
    out = {}
    if kw.get("covariance") is not None:
        out["covariance"] = kw["covariance"][np.ix_(inner, inner)]
    if kw.get("samples") is not None:
        out["samples"] = kw["samples"][:, inner]
    return base, np.asarray(theta)[idx], np.asarray(free)[idx], out


def _ranges(items: list[str], space: str, n_act: int) -> dict:
    """``["x=-10:10", "q1=450:500"]`` -> ``{"x": (-10.0, 10.0), ...}``; names checked against the space."""
    names = ("x", "y", "z") if space == "tool" else tuple(f"q{i + 1}" for i in range(n_act))
    out = {}
    for item in items:
        name, eq, span = item.partition("=")
        lo, colon, hi = span.partition(":")
        name = name.strip()
        try:
            if not eq or not colon:
                raise ValueError
            a, b = float(lo), float(hi)
        except ValueError:
            raise InputError(f"--range {item!r}: expected NAME=LO:HI, e.g. {names[0]}=-100:100") from None
        if name not in names:
            raise InputError(f"--range {item!r}: {space} space has the axes {', '.join(names)}")
        if not a < b:
            raise InputError(f"--range {item!r}: expected LO < HI")
        out[name] = (a, b)
    return out
