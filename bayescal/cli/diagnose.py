"""``bayescal diagnose``: locate a model mismatch, name the missing physics, model it, verify it out of sample."""

from __future__ import annotations

import argparse
import sys

from ..constants import EFFECT_NAMES
from ..errors import InputError
from . import SUMMARIES
from .inputs import add_frame_argument, name_list, recording_model
from .outputs import add_output_options, write_json, write_report

HELP = f"""\
Diagnose what the geometric model leaves out.

1. Calibrate the geometry (MAP under the machine file's tolerance prior) and
   test whether the residuals are instrument noise (chi-square test against
   the machine file's [measurement] sigma).
2. Locate: test the residuals' dependence on every auxiliary channel
   (time_s, temp_C, payload_kg, ...), each actuator position (also
   periodically), each actuator's approach direction, the measurement order
   and the pose region (distance correlation, Holm-corrected).
3. Name and verify: fit each physical effect of the library jointly with the
   geometry; keep it when the evidence (log Bayes factor, Laplace) is
   decisive (> ln 100) and the leave-poses-out cross-validated position RMS
   improves; combine effects by greedy forward selection.

A constraint recording (distances, heights, ballbar readings; docs/formats.md
section 6) is diagnosed the same way, one row per measurement: the effects
act on the actuator positions of every pose a row measures (a distance's
pose a, then its pose b, in that time order), the pose region is the tool
point the row measures, and outliers are named by CSV line.

Verdict: an effect name, "none" (noise explains the residuals) or
"unexplained" (structured mismatch that no effect explains; see 'located').

--write-machine PATH writes the calibrated machine: the geometry fitted
jointly with the selected effects, plus those effects as [effect.<name>]
tables, which identify, grid and simulate then apply (docs/formats.md section 7).
Verdict none: the geometry-only calibration. Verdict unexplained: the
geometry fitted with whatever effects were selected (else geometry only),
with a warning on stderr. Effect tables in the --machine file are not
applied: every effect is fitted afresh.
Effects: {", ".join(EFFECT_NAMES)}.
"""

EXAMPLES = """\
examples:
  bayescal simulate --machine examples/prs3/machine.toml --poses 160 --seed 3 --effect backlash:30 --out rec.csv
  bayescal diagnose rec.csv --machine examples/prs3/machine.toml
  bayescal diagnose rec.csv --machine m.toml --json diagnosis.json --figures figs/
  bayescal diagnose rec.csv --machine m.toml --effects thermal_expansion,backlash --seed 2
  bayescal diagnose rec.csv --machine m.toml --json diagnosis.json --write-machine calibrated.toml
"""


def register(sub) -> None:
    p = sub.add_parser(
        "diagnose", help=SUMMARIES["diagnose"], description=HELP,
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recording", help="recording CSV (docs/formats.md section 2, or a constraint recording, section 6), rows in measurement order")
    p.add_argument("--machine", required=True, help="nominal machine file TOML (docs/formats.md section 1)")
    p.add_argument("--json", metavar="PATH", help="write the answer as JSON (docs/formats.md section 3)")
    p.add_argument("--figures", metavar="DIR", help="write residual-against-channel figures (PNG) here")
    p.add_argument("--effects", help="comma-separated effects to try (default: every applicable one)")
    p.add_argument("--seed", type=int, default=0, help="seed of the cross-validation folds and of the location tests' blocks from 1,000 poses on (default 0)")
    p.add_argument(
        "--write-machine", metavar="PATH",
        help="write the calibrated machine: the geometry fitted jointly with the selected effects, and those effects "
        "as [effect.*] tables (verdict none: the geometry-only calibration; unexplained: written with a warning)",
    )
    p.add_argument(
        "--effect-input", action="append", default=[], metavar="NAME.KEY=VALUE",
        help="state an input of an effect, e.g. joint_compliance.platform_mass_kg=45 or "
        "joint_compliance.gravity=0,0,-1 (repeatable; default: the inputs stated in the machine file's "
        "[effect.NAME] tables, else the effect's documented defaults)",
    )
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_frame_argument(p)
    add_output_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..diagnose import diagnose
    from ..effects import EFFECTS
    from . import EXIT_OK

    machine, rec, _ = recording_model(args, constraints=True)
    effects = None
    if args.effects is not None:
        effects = name_list(args.effects)
        if not effects:
            raise InputError("--effects: expected comma-separated effect names, e.g. backlash,thermal_expansion")
        unknown = [e for e in effects if e not in EFFECTS]
        if unknown:
            raise InputError(f"--effects: unknown effect(s) {', '.join(unknown)}; expected some of {', '.join(EFFECTS)}")
        if len(set(effects)) != len(effects):
            raise InputError(f"--effects {args.effects}: an effect named twice; expected each effect once")
    if machine.effects and not args.quiet:
        print(f"note: the [effect.*] tables of {args.machine} are not applied: the diagnosis fits every effect afresh")
    result = diagnose(machine, rec, effects=effects, seed=args.seed, effect_settings=effect_inputs(machine, args.effect_input))
    calibrated = None
    if args.write_machine:
        from ..diagnose.calibrated import calibrated_machine

        calibrated = calibrated_machine(machine, result)
    answer = result.to_dict()  # with --frame fit, the fitted instrument frame's keys (docs/formats.md section 4)
    if calibrated is not None:
        answer["written_machine"] = {
            "path": str(args.write_machine), "effects": list(calibrated.effects), "warning": calibrated.warning,
        }
    write_json(args, answer)
    if calibrated is not None:
        _write_calibrated(args, machine, result, calibrated)
        if calibrated.warning:
            print(f"bayescal diagnose: warning: {calibrated.warning}", file=sys.stderr)
    write_report(args, "diagnose", result, machine=machine)
    written = []
    if args.figures:
        from ..plots.diagnose import plot_diagnosis

        written = plot_diagnosis(result, args.figures)
    if not args.quiet:
        print(result.report())
        if result.frame:
            from .instrument import instrument_frame_line

            print(instrument_frame_line(result.frame))
        for path in written:
            print(f"figure: {path}")
        if calibrated is not None:
            print(calibrated.summary(args.write_machine))
    return EXIT_OK


def effect_inputs(machine, items: list[str]) -> dict[str, dict]:
    """Stated effect inputs: the machine file's ``[effect.*]`` inputs, overridden by ``--effect-input NAME.KEY=VALUE``.

    Returns
    -------
    dict of str to dict
        ``{effect name: {input key: float or list of float}}``.

    Raises
    ------
    InputError
        An item not of the form ``NAME.KEY=VALUE``, an unknown effect or
        input key, a value that is not a number or comma-separated numbers.
    """
    from ..effects import EFFECTS, get_effect

    out: dict[str, dict] = {e.name: dict(e.settings) for e in machine.effects if e.settings}
    for item in items:
        key, sep, value = item.partition("=")
        name, dot, k = key.strip().partition(".")
        if not sep or not dot:
            raise InputError(f"--effect-input {item!r}: expected NAME.KEY=VALUE, e.g. joint_compliance.platform_mass_kg=45")
        if name not in EFFECTS:
            raise InputError(f"--effect-input {item!r}: unknown effect {name!r}; expected one of {', '.join(EFFECTS)}")
        keys = EFFECTS[name].settings_keys
        if k not in keys:
            raise InputError(f"--effect-input {item!r}: {name} has no input {k!r}; expected one of {', '.join(keys) or '(none)'}")
        try:
            nums = [float(x) for x in value.split(",")]
        except ValueError:
            raise InputError(f"--effect-input {item!r}: expected a number or comma-separated numbers after '='") from None
        out.setdefault(name, {})[k] = nums if len(nums) > 1 else nums[0]
    for name, stated in out.items():
        try:
            get_effect(name, **stated)  # the effect's own checks (a positive mass, a 3-vector, ...)
        except (TypeError, ValueError) as exc:
            raise InputError(f"--effect-input: {name} inputs {stated}: {exc}") from None
    return out


def _write_calibrated(args, machine, result, calibrated) -> None:
    """Write the calibrated machine: one file, or a hybrid in docs/formats.md section 5's file-per-module form
    (:meth:`bayescal.diagnose.calibrated.CalibratedMachine.write`)."""
    calibrated.write(args.write_machine)

