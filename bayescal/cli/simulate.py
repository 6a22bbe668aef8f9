"""``bayescal simulate``: a simulated recording of a machine with drawn errors."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from ..effects.stored import machine_file_text
from ..errors import InputError
from ..io.answers import json_text, write_files_atomic
from ..io.recording import recording_to_csv
from ..machines.files import load_machine
from ..simulate import simulate_recording
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


def read_poses_file(path: str, n_actuators: int) -> np.ndarray:
    """The commanded poses of a plan CSV: columns ``q1..qN`` (any order, other columns ignored), rows in order."""
    from ..errors import RecordingError
    from ..io.recording import parse_table, read_csv_rows

    want = [f"q{i + 1}" for i in range(n_actuators)]
    header, col, rows = read_csv_rows(path, None, f"a pose file with columns {','.join(want)}")
    missing = [c for c in want if c not in col]
    if missing:
        raise RecordingError(path, 1, None, f"columns {', '.join(missing)} missing; expected {','.join(want)} (and e.g. pose_id)")
    extra = [c for c in header if re.fullmatch(r"q\d+", c) and c not in want]
    if extra:
        # a plan of a machine with more actuators: its q4 was ignored, silently
        raise RecordingError(path, 1, extra[0], f"an actuator column beyond the machine's {n_actuators} actuators; "
                             f"expected {','.join(want)} (a pose file of another machine?)")
    if not rows:
        raise RecordingError(path, 2, None, "no data rows")
    for i, r in enumerate(rows):
        if len(r) != len(header):
            raise RecordingError(path, i + 2, None, f"{len(r)} cells, expected {len(header)} (one per header column)")
    return parse_table(path, want, [[r[col[c]] for c in want] for r in rows])


def run(args) -> int:
    from . import EXIT_OK

    if args.ballbar is None and (args.pivot is not None or args.planes is not None):
        # options of a ballbar session, ignored without one
        raise InputError(f"{'--pivot' if args.pivot is not None else '--planes'} goes with --ballbar RADIUS; it does "
                         "nothing for a recording of poses")
    machine = load_machine(args.machine)
    q = None
    if args.poses_file:
        if args.ballbar is not None:
            raise InputError("--ballbar drives circles about its pivot; it does not take --poses-file (give --poses N, "
                             "the readings per circle)")
        q = read_poses_file(args.poses_file, machine.n_actuators)
        if machine.q_limits is not None:
            # a recording outside q_limits is refused by every consumer: refuse it here, naming the line
            from ..io.recording import check_q_limits

            check_q_limits(args.poses_file, q, machine.q_limits, machine_path=args.machine)
        if args.poses is not None and args.poses != q.shape[0]:
            raise InputError(f"--poses {args.poses} but {args.poses_file} holds {q.shape[0]} poses; give one of them")
        if args.effect or args.aux:
            raise InputError("--poses-file cannot be combined with --effect or --aux yet; simulate them with --poses N")
        args.poses = q.shape[0]
    if args.poses is None:
        raise InputError("give --poses N (poses drawn within q_limits) or --poses-file CSV (planned poses)")
    if args.poses < 1:
        raise InputError(f"--poses: expected a positive number, got {args.poses}")
    if not args.tolerance_scale > 0:
        raise InputError(f"--tolerance-scale: expected a positive number, got {args.tolerance_scale}")
    aux = name_list(args.aux)
    if args.ballbar is not None:
        return _run_ballbar(args, machine)
    # a machine file's [effect.*] tables act on the simulated machine, driven by the recorded channels
    stored = []
    if machine.effects:
        from ..effects.stored import StoredEffectsTransform

        stored = [StoredEffectsTransform(machine, machine.effects)]
    if machine.discrepancy is not None:
        # a calibrated machine's model discrepancy moves its simulated tool as it moves the real one
        from ..discrepancy.model import DiscrepancyTransform

        stored.append(DiscrepancyTransform(machine.discrepancy))
    if args.effect or aux:
        from ..effects.simulate import parse_effect_spec, simulate_with_effects

        specs = [parse_effect_spec(s) for s in args.effect]
        sim = simulate_with_effects(
            machine, args.poses, seed=args.seed, dof=args.dof, effects=specs, record=aux,
            tolerance=machine.tolerance * args.tolerance_scale, extra=stored,
        )
    else:
        sim = simulate_recording(
            machine, args.poses, seed=args.seed, dof=args.dof, tolerance=machine.tolerance * args.tolerance_scale, q=q,
            effects=stored,
        )
    out = Path(args.out)
    truth = Path(args.truth) if args.truth else out.with_suffix(".truth.json")
    # one unit: the recording never stands beside the truth of another run (bayescal.io.answers)
    write_files_atomic([
        (out, recording_to_csv(sim.recording)),
        (truth, json_text({"machine": machine.name, "dof": args.dof, **sim.truth_dict()})),
        # with its [effect.*] and [discrepancy], not the calibration's uncertainty (this is the truth, not an estimate)
        (truth.with_suffix(".toml"), machine_file_text(machine.with_calibration(None, machine.discrepancy),
                                                       sim.theta_true)),
    ])
    if not args.quiet:
        err = np.linalg.norm(sim.recording.position - machine.forward(sim.recording.q).position, axis=1)
        print(
            f"wrote {out} ({args.poses} poses, {args.dof}-DOF), truth {truth} and {truth.with_suffix('.toml')}\n"
            f"position error of the nominal model on these poses: RMS {np.sqrt(np.mean(err**2)):.4f} mm, "
            f"max {err.max():.4f} mm"
        )
    return EXIT_OK


def _run_ballbar(args, machine) -> int:
    """``simulate --ballbar``: circles about a pivot, read as distances (a constraint recording)."""
    from . import EXIT_OK
    from ..io.constraints import constraints_to_csv
    from ..constraints.simulate import simulate_ballbar

    if args.effect or args.aux or args.dof != 6:
        raise InputError("--ballbar records distances to a pivot; it does not take --effect, --aux or --dof")
    pivot = None
    if args.pivot:
        try:
            pivot = [float(v) for v in args.pivot.split(",")]
        except ValueError:
            pivot = []
        if len(pivot) != 3:
            raise InputError(f"--pivot: expected X,Y,Z in mm, got {args.pivot!r}")
    sim = simulate_ballbar(
        machine, args.ballbar, n_points=args.poses, pivot=pivot, planes=tuple(name_list(args.planes or "xy")), seed=args.seed,
        tolerance=machine.tolerance * args.tolerance_scale,
    )
    out = Path(args.out)
    truth = Path(args.truth) if args.truth else out.with_suffix(".truth.json")
    write_files_atomic([
        (out, constraints_to_csv(sim.recording)),
        (truth, json_text({"machine": machine.name, "measure": "ballbar", **sim.truth_dict(machine)})),
        (truth.with_suffix(".toml"), machine.to_toml(sim.theta_true)),
    ])
    if not args.quiet:
        print(f"wrote {out} ({sim.recording.n_rows} ballbar readings of {args.ballbar:g} mm), truth {truth}")
    return EXIT_OK
