"""``bayescal simulate``: a simulated recording of a machine with drawn errors."""

from __future__ import annotations

import argparse

from . import SUMMARIES
from .inputs import name_list
from .outputs import add_output_options

HELP = """\
Simulate a measurement session: draw a true machine from the tolerances
(the machine file's [tolerance] table, or the documented defaults), draw
poses uniformly within [workspace] q_limits, and record what the instrument
reads with its noise ([measurement] sigma_position, sigma_angle).

Physics beyond the geometric model can be concealed in the recording with
--effect NAME[:magnitude] (several allowed; magnitudes in the effect's unit:
joint_compliance um/N, thermal_expansion um/m/K, backlash um,
screw_periodic_error um (on a revolute drive urad for um, urad/rad for um/m,
urad/(N m) for um/N), redundancy_preload um of the redundant drive's
offset, only on redundantly actuated machines such as the RASPM-2T1R: drive
stiffnesses of 150-500 N/um turn that offset and the incompatibility the drawn
geometric errors leave into internal forces and deflections;
gravity_deflection um/N, the bending compliance at 1 m of every stage and
long link of a serial chain, which moves the tool (unknown link masses drawn
at 10-30 kg); gravity_backlash um, a dead band taken up on the side of each
joint's gravity load, on serial chains),
and auxiliary channels recorded with --aux
(time_s; temp_C, a warm-up of 5 K; payload_kg, 0-25 kg changed between poses).
Temperature drives thermal_expansion even when it is not recorded.

A machine file with [effect.<name>] tables (diagnose --write-machine)
simulates a machine with those effects at their stored values, driven by the
channels recorded with --aux (payload_kg absent: no payload; thermal
expansion needs temp_C or time_s recorded).

Writes the recording (CSV, docs/formats.md section 2) and, beside it, the truth as JSON
(OUT with suffix .truth.json) and the true machine file (.truth.toml, with
the machine file's [effect.*] tables; concealed --effect values are in the
JSON).
"""

EXAMPLES = """\
examples:
  bayescal simulate --machine examples/prs3/machine.toml --poses 36 --seed 1 --out rec.csv
  bayescal simulate --machine m.toml --poses 60 --seed 7 --dof 5 --tolerance-scale 2 --out rec5.csv
  bayescal simulate --machine m.toml --poses 160 --seed 3 --effect backlash:30 --out rec.csv
  bayescal simulate --machine m.toml --poses 160 --seed 3 --effect joint_compliance:0.5 --aux payload_kg --out rec.csv
  bayescal simulate --machine m.toml --poses 120 --seed 4 --effect thermal_expansion --aux time_s,temp_C --out rec.csv
  bayescal simulate --machine examples/raspm/machine.toml --poses 120 --seed 2 --effect redundancy_preload:200 --out rec.csv
"""


def register(sub) -> None:
    p = sub.add_parser(
        "simulate", help=SUMMARIES["simulate"], description=HELP, epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--machine", required=True, help="nominal machine file TOML (docs/formats.md section 1)")
    p.add_argument("--poses", type=int, help="number of measured poses, drawn within q_limits (or --poses-file)")
    p.add_argument("--poses-file", metavar="CSV",
                   help="simulate at these commanded poses instead: a CSV with columns q1..qN (the plan 'bayescal plan "
                   "--out' writes; other columns are ignored), docs/formats.md section E7")
    p.add_argument("--seed", type=int, required=True, help="random seed (errors, poses and noise)")
    p.add_argument("--out", required=True, help="recording CSV to write")
    p.add_argument("--dof", type=int, choices=(6, 5, 3), default=6, help="measurement type (default 6)")
    p.add_argument("--tolerance-scale", type=float, default=1.0, help="multiply the tolerances by this (default 1)")
    p.add_argument(
        "--effect", action="append", default=[], metavar="NAME[:MAGNITUDE]",
        help="conceal a physical effect (repeatable): joint_compliance, thermal_expansion, backlash, screw_periodic_error, "
        "redundancy_preload",
    )
    p.add_argument("--aux", default="", help="auxiliary channels to record, comma-separated: time_s,temp_C,payload_kg")
    p.add_argument(
        "--truth", "--json", dest="truth", metavar="PATH",
        help="where to write the truth JSON, the answer of this command (default: OUT with .truth.json); "
        "the true machine file goes beside it with suffix .toml",
    )
    p.add_argument(
        "--ballbar", type=float, metavar="RADIUS",
        help="record a ballbar session instead (docs/formats.md section 6): --poses readings per circle of RADIUS mm "
        "about --pivot, one circle per plane of --planes, written as ballbar rows",
    )
    p.add_argument("--pivot", metavar="X,Y,Z", help="ballbar pivot, base frame, mm (default: the tool point at the middle of q_limits)")
    p.add_argument("--planes", default=None, help="ballbar circle planes, comma-separated from xy, xz, yz (default xy)")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_output_options(p, report=False)
    p.set_defaults(func=run)


def run(args) -> int:
    """The library's :func:`bayescal.simulated.simulate_files`, written and printed."""
    from ..simulated import simulate_files
    from . import EXIT_OK

    sim = simulate_files(args.machine, args.poses, seed=args.seed, dof=args.dof, poses_file=args.poses_file,
                         tolerance_scale=args.tolerance_scale, effects=args.effect, aux=name_list(args.aux),
                         ballbar=args.ballbar, pivot=args.pivot,
                         planes=None if args.planes is None else name_list(args.planes))
    sim.write(args.out, args.truth)
    if not args.quiet:
        print(sim.report(args.out, args.truth))
    return EXIT_OK
