"""``bayescal predict``: predict every row of a new recording from a calibrated machine, and score the held-out ones."""

from __future__ import annotations

import argparse

from . import SUMMARIES
from .inputs import add_frame_argument
from .outputs import add_output_options, write_json

HELP = """\
Predict every row of a recording from a calibrated machine file, with a one-sigma
uncertainty per measured component and a 90 % predictive region per row
(docs/formats.md section 8).

The calibrated machine (as identify, diagnose and grid write it: geometry,
[effect.*] tables, the model discrepancy [discrepancy] and the calibration's
covariance [calibration]) is held fixed with its uncertainty. Only what belongs
to the session is fitted, on the rows whose role is 'fit' (all rows without a
role column): with --frame fit, each station's instrument frame. Rows whose
role is 'check' are never fitted: they are predicted and scored.

The summary gives, for the check rows and the fit rows apart, the mean, median
and 95th percentile of the position error (mm) and the share of rows inside
their 90 % region (an ellipsoid for positions). A row that cannot be predicted
(out of reach, a missing input of the discrepancy, a station without fit rows)
says why in the JSON's "error" and is counted apart.
"""

EXAMPLES = """\
examples:
  bayescal identify rec.csv --machine m.toml --method map --discrepancy auto --write-machine calibrated.toml
  bayescal predict new.csv --machine calibrated.toml --json prediction.json
  bayescal predict tracker.csv --machine calibrated.toml --frame fit --json prediction.json
"""


def register(sub) -> None:
    p = sub.add_parser(
        "predict", help=SUMMARIES["predict"],
        description=HELP, epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recording", help="recording CSV (docs/formats.md sections 2, 4 and 8: station and role columns)")
    p.add_argument("--machine", required=True, help="calibrated machine file TOML (written by identify, diagnose, grid)")
    p.add_argument("--dof", type=int, choices=(6, 5, 3), help="use only this much of the measurement (default: all)")
    p.add_argument("--json", metavar="PATH", help="write every row's prediction and the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_frame_argument(p)
    add_output_options(p, report=False)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..api import predict
    from . import EXIT_OK

    # the library's front door: a notebook's bayescal.predict gives this JSON, byte for byte
    result = predict(args.machine, args.recording, frame=args.frame, dof=args.dof)
    write_json(args, result.to_dict())
    if not args.quiet:
        print(result.report())
    return EXIT_OK
