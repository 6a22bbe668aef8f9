"""``bayescal compensate``: write and evaluate a bilinear interpolation compensation (BIC) grid."""

from __future__ import annotations

import argparse

from . import SUMMARIES
from .outputs import add_output_options, write_json, write_report

HELP = """\
Build a bilinear interpolation compensation (BIC) grid from a table of
measured residual position errors, write it as the NC-loadable CSV
(i,j,x,z,ex,ez,std_ex,std_ez; docs/redundant.md), and evaluate a grid on
fresh measured points (errors before and after compensation).

The error table is a CSV with columns x,z,ex,ez (mm): the residual error at
points of the planar translation range. Node values are interpolated from it
by scipy's linear interpolation (exact where the points are the nodes).
"""

EXAMPLES = """\
examples:
  bayescal compensate --errors node_errors.csv --x-range -300 300 --z-range -200 200 --n 5 --out bic_grid.csv
  bayescal compensate --errors node_errors.csv --x-range -300 300 --z-range -200 200 --node-std 0.00065 --out bic_grid.csv
  bayescal compensate --grid bic_grid.csv --evaluate fresh_errors.csv --json eval.json
"""


def register(sub) -> None:
    p = sub.add_parser("compensate", help=SUMMARIES["compensate"], description=HELP, epilog=EXAMPLES,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--errors", help="CSV x,z,ex,ez (mm) of measured residual errors to build a grid from")
    p.add_argument("--x-range", nargs=2, type=float, metavar=("MIN", "MAX"), help="translation range along x, mm")
    p.add_argument("--z-range", nargs=2, type=float, metavar=("MIN", "MAX"), help="translation range along z, mm")
    p.add_argument("--n", type=int, default=5, help="nodes per axis (default 5)")
    p.add_argument("--node-std", type=float, metavar="MM",
                   help="one-sigma of each measured node value (the instrument's reading error, mm): written to std_ex, std_ez")
    p.add_argument("--out", help="write the grid CSV here")
    p.add_argument("--grid", help="an existing grid CSV to evaluate")
    p.add_argument("--evaluate", help="CSV x,z,ex,ez of fresh measured errors: report them before/after compensation")
    p.add_argument("--json", help="write the evaluation as JSON")
    add_output_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    """The library's :func:`bayescal.compensation.compensate_files`, written and printed."""
    from ..compensation import compensate_files, write_grid
    from . import EXIT_OK

    c = compensate_files(errors=args.errors, grid=args.grid, evaluate=args.evaluate, x_range=args.x_range,
                         z_range=args.z_range, n=args.n, node_std=args.node_std)
    if c.built:
        if args.out:  # before printing: a closed stdout (`| head`) must not cost the grid
            write_grid(args.out, c.grid)
        print(c.grid.report())
    ans = c.evaluation
    if ans is not None:
        write_json(args, ans)
        print(f"fresh points: max |error| {ans['max_before_mm']:.4f} mm -> {ans['max_after_mm']:.4f} mm after BIC")
    write_report(args, "compensate", c.grid, evaluation=ans)
    return EXIT_OK
