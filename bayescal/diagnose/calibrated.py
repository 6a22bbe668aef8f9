"""The calibrated machine a diagnosis writes: its final geometry, the selected effects as ``[effect.*]`` tables.

Every verdict also writes the calibration's uncertainty (``[calibration]``:
the covariance of the parameters, the noise scale the residuals supported,
the leave-one-out variance factor) and, when the diagnosis kept one, the
model discrepancy (``[discrepancy]``), so that ``bayescal predict`` predicts
new recordings with honest regions.

``bayescal diagnose --write-machine PATH`` (docs/formats.md section 7):

* verdict an effect: the geometry fitted jointly with every selected effect
  (the verdict's first), and those effects at their fitted values, so that
  the geometry no longer absorbs them;
* verdict ``"none"``: the geometry-only calibration (MAP under the
  tolerance prior), no effect tables;
* verdict ``"discrepancy"``: the geometry fitted jointly with the model
  discrepancy (``[discrepancy]``), which predicts what no effect of the
  library explains;
* verdict ``"unexplained"``: written all the same, with a warning: the
  geometry fitted with the effects that were selected (if any), else the
  geometry-only calibration.  A structured mismatch remains that this
  machine does not model; refusing would leave the user with no
  calibration at all, while the best model found still predicts better
  than the nominal one.  The warning says so and names where the mismatch
  lives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..effects.stored import StoredEffect, machine_file_text
from ..errors import InputError
from ..machines.base import Machine
from .result import Diagnosis

__all__ = ["CalibratedMachine", "calibrated_machine"]


@dataclass(frozen=True)
class CalibratedMachine:
    """Machine-file text of a diagnosis' calibrated machine, checked by reading it back.

    Attributes
    ----------
    text : str
        The machine file (TOML).
    machine : Machine
        ``text`` read back (with its effects).
    effects : tuple of str
        Names of the ``[effect.*]`` tables written.
    warning : str
        Why this machine should be used with care (``""`` when there is none).
    """

    text: str
    machine: Machine
    effects: tuple[str, ...]
    warning: str = ""

    def write(self, path) -> list:
        """Write the calibrated machine to ``path``: one file, or a hybrid in docs/formats.md section 5's form.

        A hybrid's ``text`` holds its modules inline (``[module.machine]``),
        which bayescal reads but the format contract does not specify; it is
        written as every ``--write-machine`` writes a hybrid, from
        :attr:`machine` (module files beside the main file, which keeps the
        ``[effect.*]`` and ``[instrument]`` tables and the header comment).

        Returns
        -------
        list of Path
            The files written, the main file first.
        """
        from ..io.answers import write_text_atomic
        from ..machines.files import write_calibrated_machine_files, written_as_modules

        if not written_as_modules(self.machine):
            return [write_text_atomic(path, self.text)]
        header = self.text.split("\n", 1)[0] + "\n" if self.text.startswith("#") else ""  # where it came from
        return write_calibrated_machine_files(path, self.machine, None, header=header)

    def summary(self, path: str) -> str:
        """One line saying what was written to ``path``."""
        disc = self.machine.discrepancy is not None
        extra = (", the model discrepancy [discrepancy]" if disc else "") + (
            " and the calibration's uncertainty [calibration]" if self.machine.calibration is not None else "")
        if self.effects:
            tables = ", ".join(f"[effect.{e}]" for e in self.effects)
            return f"wrote {path}: the geometry fitted jointly with {', '.join(self.effects)}, and {tables}{extra}"
        what = "with a model discrepancy" if disc else "geometry-only calibration (MAP under the tolerance prior)"
        return f"wrote {path}: the {what}, no effect tables{extra}"


def calibrated_machine(machine: Machine, diagnosis: Diagnosis) -> CalibratedMachine:
    """The calibrated machine of a diagnosis (see the module docstring for each verdict).

    Parameters
    ----------
    machine : Machine
        The nominal machine the diagnosis ran on (effects it carries are
        replaced: the diagnosis fitted them afresh).
    diagnosis : Diagnosis
        From :func:`bayescal.diagnose.diagnose`.

    Returns
    -------
    CalibratedMachine

    Raises
    ------
    InputError
        A diagnosis without its fitted geometry.
    """
    if diagnosis.theta_final is None or diagnosis.theta_geometric is None:
        raise InputError("this diagnosis carries no fitted geometry (theta_final); run bayescal.diagnose.diagnose")
    base = machine.with_effects(())
    selected = tuple(diagnosis.selected)
    # the final model's geometry: with the selected effects and the discrepancy; the geometric MAP when neither
    theta = np.asarray(diagnosis.theta_final, float)
    trials = {t.name: t for t in diagnosis.effects}
    stored = tuple(
        StoredEffect(
            name,
            tuple((p.name, float(p.value)) for p in trials[name].parameters),
            tuple(p.unit for p in trials[name].parameters),
            source="<diagnosis>",
            settings=tuple((k, np.asarray(v, float).tolist() if np.ndim(v) else float(v))
                           for k, v in diagnosis.effect_settings.get(name, {}).items()),
        )
        for name in selected
    )
    disc = diagnosis.discrepancy
    base = base.with_calibration(diagnosis.record, disc.fit.discrepancy if disc is not None and disc.kept else None)
    text = machine_file_text(base, theta, stored)
    header = _header(diagnosis)
    text = header + text
    from ..machines.files import machine_from_text

    again = machine_from_text(text, path="<calibrated machine of the diagnosis>")  # round trip: refuse to write what cannot be read
    warning = ""
    if diagnosis.verdict == "unexplained":
        where = diagnosis.located.channel if diagnosis.located is not None else "the residuals"
        modelled = f"the geometry fitted with {', '.join(selected)}" if selected else "the geometry-only calibration"
        warning = (
            f"verdict unexplained: a structured mismatch (located: {where}) remains that this machine does not model; "
            f"written is {modelled}. Use it with care and look at {where}."
        )
    return CalibratedMachine(text=text, machine=again, effects=selected, warning=warning)


def _header(d: Diagnosis) -> str:
    """Comment lines naming where the calibration came from (TOML comments: ignored when read)."""
    what = f"with {', '.join(d.selected)}" if d.selected else "geometry only"
    line = f"calibrated by bayescal diagnose from {d.recording} ({d.n_poses} poses, {d.dof}-DOF): verdict {d.verdict}, {what}"
    return "# " + " ".join(line.split()) + "\n"  # one comment line, whatever the path holds
