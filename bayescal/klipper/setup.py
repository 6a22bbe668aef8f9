"""A Klipper config as a calibration set-up: the machine file and the recording ``bayescal klipper`` writes.

:func:`load_klipper` is what the command line runs (and
:func:`bayescal.load_klipper` in a notebook): the config read as Klipper
reads it, its geometry as a linear-delta machine whose workspace spans the
saved positions, its saved DELTA_CALIBRATE as a constraint recording, and
the two files' texts, so a notebook writes the same bytes as the command.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.constraints import ConstraintRecording, constraints_to_csv
from ..machines.base import Machine
from .printer import SIGMA_DISTANCE, SIGMA_HEIGHT, KlipperDelta, klipper_machine, klipper_recording, read_klipper_delta

__all__ = ["KlipperSetup", "load_klipper", "TOLERANCE_NOTE"]

#: Why the written [tolerance] (the MAP prior) is a printer's, at the top of the machine file.
TOLERANCE_NOTE = """\
# Written by 'bayescal klipper' from a Klipper config (docs/delta-printers.md).
# [tolerance] below is the prior of 'identify --method map': one sigma of how far the true
# printer may be from the config's values. Printer values, not a machine tool's: frames of
# extrusions and moulded brackets, rods cut to about a millimetre, and a delta_radius that folds
# in the joint offsets make radii, endstops and arms good to ~1 mm, tower angles to ~0.5 deg and
# tower tilts to ~0.1 deg. Tighten them if an earlier calibration you trust set the values.
# No [measurement] table: the recording's sigmas weight heights against distances; identify
# --method map estimates one factor on these tolerances against the noise from the data.

"""


@dataclass(frozen=True)
class KlipperSetup:
    """A Klipper config read as a machine and a constraint recording.

    Attributes
    ----------
    config : str
        The printer.cfg read.
    delta : KlipperDelta
        The geometry and step distances as the config states them (mm, degrees).
    machine : Machine
        The linear-delta machine of that geometry, its ``q_limits`` spanning the saved positions.
    recording : ConstraintRecording
        The saved probe heights and printed-object distances (docs/formats.md section 6), mm.
    files_read : tuple of str
        The config and every file it includes, in reading order.
    notes : tuple of str
        What the reader noticed and went on with.
    """

    config: str
    delta: KlipperDelta
    machine: Machine
    recording: ConstraintRecording
    files_read: tuple[str, ...]
    notes: tuple[str, ...]

    @property
    def n_heights(self) -> int:
        return sum(m == "height" for m in self.recording.measure)

    def machine_toml(self) -> str:
        """The machine file's text (docs/formats.md section 1), with why its tolerances are a printer's."""
        return TOLERANCE_NOTE + self.machine.to_toml()

    def recording_csv(self) -> str:
        """The recording's text (docs/formats.md section 6)."""
        return constraints_to_csv(self.recording)

    def write(self, out: str | os.PathLike) -> tuple[Path, Path]:
        """Write ``machine.toml`` and ``recording.csv`` into the folder ``out`` as one unit; their paths."""
        from ..io.answers import write_files_atomic

        out = Path(out)
        paths = (out / "machine.toml", out / "recording.csv")
        # one unit: a machine file never stands beside the recording of another config
        write_files_atomic([(paths[0], self.machine_toml()), (paths[1], self.recording_csv())])
        return paths

    def to_dict(self, out: str | os.PathLike | None = None) -> dict:
        """What ``bayescal klipper --json`` writes (``files`` only with the folder written to)."""
        kd = self.delta
        d = {"machine": self.machine.name, "config": self.config, "delta_radius": kd.delta_radius,
             "angle_deg": kd.angle_deg, "arm_length": kd.arm_length, "position_endstop": kd.position_endstop,
             "step_dist": kd.step_dist, "n_heights": self.n_heights, "n_distances": self.recording.n_rows - self.n_heights,
             "files_read": list(self.files_read), "notes": list(self.notes)}
        if out is not None:
            d["files"] = {"machine": str(Path(out) / "machine.toml"), "recording": str(Path(out) / "recording.csv")}
        return d

    def report(self, out: str | os.PathLike) -> str:
        """What the command prints after writing into ``out``."""
        out = Path(out)
        kd = self.delta
        lines = [f"wrote {out / 'machine.toml'} (linear-delta, delta_radius {kd.delta_radius:g} mm, step_dist "
                 f"{', '.join(f'{s:g}' for s in kd.step_dist)} mm) and {out / 'recording.csv'} "
                 f"({self.n_heights} heights, {self.recording.n_rows - self.n_heights} distances)"]
        lines += [f"note: {note}" for note in self.notes]
        return "\n".join(lines)


def load_klipper(config: str | os.PathLike, *, sigma_height: float | None = None,
                 sigma_distance: float | None = None, missing_includes: str = "skip") -> KlipperSetup:
    """Read a Klipper delta printer's config and saved DELTA_CALIBRATE, as ``bayescal klipper`` does.

    Parameters
    ----------
    config : path
        ``printer.cfg`` with its SAVE_CONFIG block (its ``[include]`` files are read as Klipper reads them).
    sigma_height, sigma_distance : float, optional
        One-sigma noise of a probe height and of a caliper distance, mm (defaults
        :data:`bayescal.klipper.printer.SIGMA_HEIGHT`, :data:`~bayescal.klipper.printer.SIGMA_DISTANCE`):
        weights of heights against distances.
    missing_includes : {"skip", "error"}
        An ``[include FILE]`` without wildcards that names no file: skipped with a note (the default: a
        published config's UI include seldom travels with it; a key then missing names it), or an error as
        Klipper refuses to start without it.

    Returns
    -------
    KlipperSetup
        ``machine``, ``recording``, ``write(out)``, ``to_dict()``; ``bayescal.load(s.machine,
        s.recording)`` is ready for ``bayescal.calibrate``.

    Raises
    ------
    InputError
        A sigma that is not a positive number; the config's errors name its file, line, section and key.
    """
    from .cfg import read_klipper_config

    sh = SIGMA_HEIGHT if sigma_height is None else sigma_height
    sd = SIGMA_DISTANCE if sigma_distance is None else sigma_distance
    for name, v in (("sigma_height (--sigma-height)", sh), ("sigma_distance (--sigma-distance)", sd)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0 or not np.isfinite(v):
            raise InputError(f"{name}: expected a positive number of mm, got {v!r}")
    cfg = read_klipper_config(config, missing_includes=missing_includes)
    kd = read_klipper_delta(cfg)
    rec = klipper_recording(cfg, kd, sigma_height=sh, sigma_distance=sd)
    # the workspace the recording's positions span (a distance's second position where it has one)
    span = np.vstack([rec.qa, rec.qb[np.isfinite(rec.qb).all(axis=1)]])
    machine = klipper_machine(kd, name=f"Klipper delta {Path(config).name}", q_span=span)
    return KlipperSetup(str(config), kd, machine, rec, tuple(cfg.files), tuple(cfg.notes()))
