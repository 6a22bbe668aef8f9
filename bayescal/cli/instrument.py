"""What ``identify`` adds for recordings from real instruments: the fitted frame, plausibility, ``--force``.

Kept apart from the solvers' output so that commands share one rule
(docs/real-instruments.md): an implausible calibration is reported, its
JSON answer says ``"plausible": false`` with the reasons, the command exits
1, and no calibrated machine is written unless ``--force``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # no import of the library (numpy) when a parser is built (issue 31)
    from ..instrument import Plausibility

__all__ = [
    "add_force_argument", "may_write_machine", "refusal_note", "instrument_report", "instrument_frame_line",
]


def add_force_argument(p) -> None:
    p.add_argument(
        "--force", action="store_true",
        help="write --write-machine even when the calibration is not plausible (errors beyond 10 tolerances, "
        "or no residual degrees of freedom)",
    )


def may_write_machine(args, res, plaus: Plausibility) -> bool:
    return bool(args.write_machine) and bool(res.success) and (plaus.plausible or bool(getattr(args, "force", False)))


def write_calibrated_files(args, machine, res, plaus: Plausibility) -> None:
    """``--write-machine``, ``--write-urdf`` and ``--write-klipper`` of a fit, for every method.

    The machine file and the URDF only for a successful fit that is plausible (or ``--force``); the Klipper
    keys only for a plausible one.  ``res.theta`` may hold more than the machine's parameters (a ballbar
    recording's pivots): only the machine's part is written.
    """
    from .outputs import say, write_calibrated_machine

    theta = res.theta[: machine.n_params]
    if may_write_machine(args, res, plaus):
        write_calibrated_machine(args, machine, theta)  # [effect.*] and [instrument] kept
    if getattr(args, "write_klipper", None) and res.success and plaus.plausible:
        from ..io import write_text_atomic
        from ..klipper.keys import klipper_text

        say(args, f"wrote {write_text_atomic(args.write_klipper, klipper_text(machine, theta))} (Klipper keys)")
    if getattr(args, "write_urdf", None) and res.success and (plaus.plausible or getattr(args, "force", False)):
        from ..machines.urdf_write import write_calibrated_urdf

        say(args, f"wrote {write_calibrated_urdf(args.write_urdf, machine, theta)} (calibrated URDF)")


def refusal_note(args, res, plaus: Plausibility) -> str | None:
    """The line printed when ``--write-machine`` was asked for but not written."""
    if not args.write_machine or not res.success or plaus.plausible or getattr(args, "force", False):
        return None
    return f"not writing {args.write_machine}: the calibration is not plausible (--force writes it anyway)"


def instrument_report(extra: dict, plaus: Plausibility) -> str:
    """The report's lines on the instrument frame (if any) and on plausibility."""
    lines = [instrument_frame_line(extra)] if extra.get("frame") or extra.get("frames") else []
    lines.append(plaus.report())
    return "\n".join(lines)


def instrument_frame_line(extra: dict) -> str:
    """Two report lines: the instrument frame and its std."""
    lines = []
    frames = {"": extra["frame"]} if extra.get("frame") is not None else extra.get("frames") or {}
    for label, f in frames.items():
        fmt = lambda v: "[" + ", ".join(f"{x:.6g}" for x in v) + "]"  # noqa: E731
        word = "fitted" if f["fitted"] else "known, from the machine file"
        which = f"station {label!r} " if label else ""
        lines.append(f"  instrument      {which}frame {word}: origin {fmt(f['origin'])} mm, rotation vector "
                     f"{fmt(f['rotation_vector'])} rad")
        if f.get("std"):
            std = lambda v: "[" + ", ".join("-" if x is None else f"{x:.2g}" for x in v) + "]"  # noqa: E731
            lines.append(f"                  std origin {std(f['std']['origin'])} mm, rotation vector {std(f['std']['rotation_vector'])} rad")
    return "\n".join(lines)
