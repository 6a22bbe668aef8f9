"""``bayescal identify``: identify geometric errors from a recording."""

from __future__ import annotations

import argparse

from ..identify import identify
from ..io import read_recording, write_json_atomic, write_text_atomic
from ..machines import load_machine
from ..measurement import MeasurementModel
from .bayes_identify import METHODS, add_arguments, run_bayes

HELP = """\
Identify the geometric errors of a machine from a recording of measured poses.

The recording (CSV, see FORMATS.md) holds commanded actuator positions q1..qN
and the measured tool point x, y, z, plus either a rotation vector rx, ry, rz
(6-DOF) or a tool axis nx, ny, nz (5-DOF), or nothing more (position only).
Unidentifiable parameters are found by SVD and fixed at nominal; the report
names the combinations the measurement cannot separate.

Methods: ls (Gauss-Newton least squares), ridge (Tikhonov towards nominal;
--lam 1 is the MAP estimate under the machine file's tolerance prior), tsvd
(least squares on the k best-determined directions), map (the MAP estimate
under the [tolerance] prior, with its Laplace covariance), kalman (a
recursive EKF/UKF, one update per pose, with the uncertainty after each
pose), mcmc (emcee posterior, refused unless converged). See docs/bayes.md.
"""

EXAMPLES = """\
examples:
  bayescal identify examples/prs3/recording.csv --machine examples/prs3/machine.toml
  bayescal identify rec.csv --machine m.toml --method ridge --lam 1 --json answer.json
  bayescal identify rec.csv --machine m.toml --method tsvd --k 25 --dof 5 --write-machine calibrated.toml
  bayescal identify rec.csv --machine m.toml --method map --json map.json
  bayescal identify rec.csv --machine m.toml --method kalman --variant ukf --figures figs/
  bayescal identify rec.csv --machine m.toml --method mcmc --surrogate linear --progress --posterior post.nc --figures figs/
"""


def register(sub) -> None:
    p = sub.add_parser(
        "identify", help="identify geometric errors from a recording", description=HELP, epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recording", help="recording CSV (FORMATS.md section 2)")
    p.add_argument("--machine", required=True, help="machine file TOML (FORMATS.md section 1)")
    p.add_argument("--method", choices=("ls", "ridge", "tsvd", "map") + METHODS, default="ls", help="solver (default: ls)")
    p.add_argument("--lam", type=float, help="ridge parameter, dimensionless (1 = MAP under the tolerance prior)")
    p.add_argument("--k", type=int, help="number of singular values tsvd keeps")
    p.add_argument("--dof", type=int, choices=(6, 5, 3), help="use only this much of the measurement (default: all)")
    p.add_argument(
        "--free", default="auto",
        help="parameters to identify: 'auto' (identifiable set, default), 'all', or comma-separated names",
    )
    p.add_argument("--max-iter", type=int, default=50, help="Gauss-Newton iterations at most (default 50)")
    p.add_argument("--json", metavar="PATH", help="write the answer as JSON (FORMATS.md section 3)")
    p.add_argument("--write-machine", metavar="PATH", help="write the calibrated machine file")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from . import EXIT_FAILED, EXIT_OK

    machine = load_machine(args.machine)
    rec = read_recording(args.recording)
    model = MeasurementModel.from_recording(machine, rec, dof=args.dof)
    free = args.free if args.free in ("auto", "all") else [s.strip() for s in args.free.split(",") if s.strip()]
    if args.method == "ridge" and args.lam is None:
        from ..errors import InputError

        raise InputError("--lam is required with --method ridge (try --lam 1: MAP under the tolerance prior)")
    if args.method == "tsvd" and args.k is None:
        from ..errors import InputError

        raise InputError("--k is required with --method tsvd")
    if args.method in METHODS:
        return run_bayes(args, machine, model, free)
    res = identify(model, method=args.method, lam=args.lam, k=args.k, free=free, max_iter=args.max_iter)
    if not args.quiet:
        print(res.report())
    if args.json:
        write_json_atomic(args.json, res.to_dict())
    if args.write_machine and res.success:
        write_text_atomic(args.write_machine, machine.to_toml(res.theta))
    elif args.write_machine and not args.quiet:
        print(f"\nnot writing {args.write_machine}: the identification did not succeed")
    return EXIT_OK if res.success else EXIT_FAILED
