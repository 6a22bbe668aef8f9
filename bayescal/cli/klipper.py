"""``bayescal klipper``: a Klipper delta printer's config and saved calibration as machine file and recording."""

from __future__ import annotations

import argparse

from . import SUMMARIES

HELP = """\
Read a Klipper printer.cfg of a linear delta printer with a saved
DELTA_CALIBRATE (the [delta_calibrate] entries height0, height0_pos, ...,
distance0, distance0_pos1, distance0_pos2, ... in the SAVE_CONFIG block at
the end of the file) and write

  DIR/machine.toml    the linear-delta machine of the config's geometry
                      ([printer] delta_radius, [stepper_a/b/c] angle,
                      arm_length, position_endstop), kind = "linear-delta";
  DIR/recording.csv   the probe heights and the printed-object distances as
                      a constraint recording (docs/formats.md section 6).

The config is read as Klipper reads it: [include ...] files and globs
relative to the including file, '#' and ';' comments, values continued on
indented lines, the SAVE_CONFIG block (a key set above it wins). An include
without wildcards that names no file is skipped with a note (a published
config's fluidd.cfg seldom travels with it; a key then missing names it);
--missing-includes error refuses it, as Klipper does (a glob may match
nothing either way). Errors name the file, line,
section and key: include cycles, include trees beyond 200 files or 12
levels, text that is not UTF-8, files that are not regular, saved entries
with gaps, values that are not finite or plausible.

Stable positions (microsteps below each endstop) become carriage travel in
mm with step_dist = rotation_distance / (full_steps_per_rotation *
microsteps): q_i = -steps_i * step_dist_i.  The machine file states no
noise ([measurement] table left out): the rows' sigmas weight heights
against distances, and identify --method map estimates the noise and prior
scales from the data.  Then run
`bayescal identify DIR/recording.csv --machine DIR/machine.toml --method map --free all`
and add --write-klipper PATH for a block of Klipper's keys to paste into
printer.cfg above its SAVE_CONFIG block.  See docs/delta-printers.md.
"""

EXAMPLES = """\
examples:
  bayescal klipper printer.cfg --out calib/
  bayescal identify calib/recording.csv --machine calib/machine.toml --method map --free all --write-klipper calib/klipper.cfg
"""


def register(sub) -> None:
    p = sub.add_parser(
        "klipper", help=SUMMARIES["klipper"], description=HELP, epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("config", help="Klipper printer.cfg (with its SAVE_CONFIG block)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for machine.toml and recording.csv")
    p.add_argument("--sigma-height", type=float, default=None,
                   help="one-sigma noise of a probe height, mm (default 0.02); a weight against the distances, the noise "
                        "scale is estimated by identify")
    p.add_argument("--sigma-distance", type=float, default=None,
                   help="one-sigma noise of a caliper distance, mm (default 0.05); a weight against the heights")
    p.add_argument("--json", metavar="PATH", help="write a summary (geometry read, step distances, counts, files read, notes) as JSON")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--missing-includes", choices=("skip", "error"), default="skip",
                   help="an [include FILE] that names no file: skip it with a note (default; a published config's "
                   "fluidd.cfg seldom travels with it, and a key then missing names it) or refuse it, as Klipper "
                   "refuses to start without it")
    p.add_argument("--skip-missing-includes", dest="missing_includes", action="store_const", const="skip",
                   help="the same as --missing-includes skip (the default)")
    p.set_defaults(func=run)


def run(args) -> int:
    """The library's :func:`bayescal.klipper.setup.load_klipper`, written and printed."""
    from ..io import write_json_atomic
    from ..klipper.setup import load_klipper
    from . import EXIT_OK

    setup = load_klipper(args.config, sigma_height=args.sigma_height, sigma_distance=args.sigma_distance,
                         missing_includes=args.missing_includes)
    setup.write(args.out)
    if args.json:
        write_json_atomic(args.json, setup.to_dict(args.out))
    if not args.quiet:
        print(setup.report(args.out))
    return EXIT_OK
