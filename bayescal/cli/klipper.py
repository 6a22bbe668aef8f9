"""``bayescal klipper``: a Klipper delta printer's config and saved calibration as machine file and recording."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..io import write_json_atomic
from ..io.answers import write_files_atomic
from ..io.constraints import constraints_to_csv
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
without wildcards that names no file is an error, as in Klipper (a glob may
match nothing); --skip-missing-includes reads the config without it, with a
note (a published config's fluidd.cfg). Errors name the file, line,
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
    p.add_argument("--skip-missing-includes", action="store_true",
                   help="read the config without an [include FILE] that names no file (a published config's "
                   "fluidd.cfg), with a note; default: an error, as Klipper refuses to start without it")
    p.set_defaults(func=run)


#: Why the written [tolerance] (the MAP prior) is a printer's, at the top of the machine file.
_TOLERANCE_NOTE = """\
# Written by 'bayescal klipper' from a Klipper config (docs/delta-printers.md).
# [tolerance] below is the prior of 'identify --method map': one sigma of how far the true
# printer may be from the config's values. Printer values, not a machine tool's: frames of
# extrusions and moulded brackets, rods cut to about a millimetre, and a delta_radius that folds
# in the joint offsets make radii, endstops and arms good to ~1 mm, tower angles to ~0.5 deg and
# tower tilts to ~0.1 deg. Tighten them if an earlier calibration you trust set the values.
# No [measurement] table: the recording's sigmas weight heights against distances; identify
# --method map estimates one factor on these tolerances against the noise from the data.

"""


def run(args) -> int:
    from ..errors import InputError
    from ..klipper.cfg import read_klipper_config
    from ..klipper.printer import SIGMA_DISTANCE, SIGMA_HEIGHT, klipper_machine, klipper_recording, read_klipper_delta
    from . import EXIT_OK

    sh = SIGMA_HEIGHT if args.sigma_height is None else args.sigma_height
    sd = SIGMA_DISTANCE if args.sigma_distance is None else args.sigma_distance
    for flag, v in (("--sigma-height", sh), ("--sigma-distance", sd)):
        if not v > 0:
            raise InputError(f"{flag}: expected a positive number of mm, got {v!r}")
    cfg = read_klipper_config(args.config, missing_includes="skip" if args.skip_missing_includes else "error")
    kd = read_klipper_delta(cfg)
    rec = klipper_recording(cfg, kd, sigma_height=sh, sigma_distance=sd)
    import numpy as np

    span = np.vstack([rec.qa, rec.qb[np.isfinite(rec.qb).all(axis=1)]])
    machine = klipper_machine(kd, name=f"Klipper delta {Path(args.config).name}", q_span=span)
    out = Path(args.out)
    # one unit: a machine file never stands beside the recording of another config
    write_files_atomic([(out / "machine.toml", _TOLERANCE_NOTE + machine.to_toml()),
                        (out / "recording.csv", constraints_to_csv(rec))])
    n_h = sum(m == "height" for m in rec.measure)
    notes = cfg.notes()
    if args.json:
        write_json_atomic(args.json, {
            "machine": machine.name, "config": str(args.config), "delta_radius": kd.delta_radius,
            "angle_deg": kd.angle_deg, "arm_length": kd.arm_length, "position_endstop": kd.position_endstop,
            "step_dist": kd.step_dist, "n_heights": n_h, "n_distances": rec.n_rows - n_h,
            "files_read": list(cfg.files), "notes": notes,
            "files": {"machine": str(out / "machine.toml"), "recording": str(out / "recording.csv")},
        })
    if not args.quiet:
        print(
            f"wrote {out / 'machine.toml'} (linear-delta, delta_radius {kd.delta_radius:g} mm, step_dist "
            f"{', '.join(f'{s:g}' for s in kd.step_dist)} mm) and {out / 'recording.csv'} "
            f"({n_h} heights, {rec.n_rows - n_h} distances)"
        )
        for note in notes:
            print(f"note: {note}")
    return EXIT_OK
