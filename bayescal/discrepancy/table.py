"""The ``[discrepancy]`` table of a calibrated machine file (a bayescal extension of docs/formats.md section 7).

.. code-block:: toml

    [discrepancy]
    kind = "se-ard-inducing"             # squared-exponential kernel, one length scale per input, inducing points
    inputs = ["q1", "q2", "temp_C"]      # actuators q<i>, or auxiliary channels of the recording
    center = [...]                       # standardisation of the inputs: z = (x - center) / scale, inputs' units
    scale = [...]
    length_scales = [...]                # per input, standardised units
    outputs = ["x", "y", "z"]            # base-frame tool point (mm); "rx", "ry", "rz": small rotation (rad)
    output_scales = [...]                # prior std per output, mm or rad
    inducing = [[...], ...]              # m inducing inputs, standardised
    weights = [...]                      # posterior mean of the weights (outputs x inducing), dimensionless
    shift_parameters = [...]             # the projection's mean correction -J c: parameters ...
    shift = [...]                        # ... and c, in their units
    log_evidence_gain = 41.2             # log Bayes factor over no discrepancy
    explained = 0.62                     # share of the whitened residual the mean carries

Its weights' uncertainty (jointly with the geometry) is in ``[calibration]``
under the names ``discrepancy.w0`` ... (:mod:`bayescal.prediction.record`).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError, MachineFileError
from ..io.machine_file import TomlTable, format_toml_value
from .model import Discrepancy

__all__ = ["discrepancy_toml", "read_discrepancy", "KIND"]

KIND = "se-ard-inducing"
_KEYS = {"kind", "inputs", "center", "scale", "length_scales", "outputs", "output_scales", "inducing", "weights",
         "shift_parameters", "shift", "log_evidence_gain", "explained"}
#: Inducing points and inputs a file may hold at most (a larger table is not one bayescal wrote).
MAX_INDUCING, MAX_INPUTS = 2000, 64


def discrepancy_toml(disc: Discrepancy) -> str:
    """The table of ``disc`` (module docstring)."""
    f = format_toml_value
    lines = [
        "[discrepancy]",
        "# model discrepancy: a smooth function of the inputs added to the tool pose (docs/discrepancy.md)",
        f"kind = {f(KIND)}",
        f"inputs = {f(list(disc.inputs))}",
        f"center = {f(disc.center)}",
        f"scale = {f(disc.scale)}",
        f"length_scales = {f(disc.length_scales)}",
        f"outputs = {f(list(disc.outputs))}",
        f"output_scales = {f(disc.output_scales)}",
        "inducing = [" + ", ".join(f(row) for row in disc.inducing) + "]",
        f"weights = {f(disc.weights)}",
        f"shift_parameters = {f(list(disc.shift_names))}",
        f"shift = {f(disc.shift)}",
        f"log_evidence_gain = {f(float(disc.log_evidence_gain))}",
        f"explained = {f(float(disc.explained))}",
        "",
    ]
    return "\n".join(lines)


def _floats(t: TomlTable, key: str, n: int | None = None) -> np.ndarray:
    v = t.data.get(key)
    if not isinstance(v, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        raise t.error(key, "expected a list of numbers")
    a = np.asarray(v, dtype=float)
    if n is not None and a.size != n:
        raise t.error(key, f"expected {n} numbers, got {a.size}")
    if not np.all(np.isfinite(a)):
        raise t.error(key, "expected finite numbers")
    return a


def _names(t: TomlTable, key: str) -> tuple[str, ...]:
    v = t.data.get(key)
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise t.error(key, "expected a list of names")
    return tuple(v)


def read_discrepancy(doc: TomlTable, path: str, machine=None) -> Discrepancy | None:
    """The optional ``[discrepancy]`` table, checked (MachineFileError naming the key)."""
    t = doc.table("discrepancy", required=False)
    if t is None:
        return None
    t.reject_unknown(_KEYS)
    kind = t.string("kind")
    if kind != KIND:
        raise t.error("kind", f"expected {KIND!r}, got {kind!r}")
    inputs = _names(t, "inputs")
    if not 1 <= len(inputs) <= MAX_INPUTS:
        raise t.error("inputs", f"expected 1 to {MAX_INPUTS} input names")
    d = len(inputs)
    outputs = _names(t, "outputs")
    raw = t.data.get("inducing")
    if not isinstance(raw, list) or not raw or len(raw) > MAX_INDUCING:
        raise t.error("inducing", f"expected 1 to {MAX_INDUCING} rows of {d} numbers")
    rows = []
    for i, row in enumerate(raw):
        if not isinstance(row, list) or len(row) != d or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in row):
            raise t.error(f"inducing[{i}]", f"expected {d} numbers")
        rows.append(row)
    U = np.asarray(rows, dtype=float)
    m = U.shape[0]
    shift_names = _names(t, "shift_parameters")
    if machine is not None:
        unknown = [n for n in shift_names if n not in set(machine.layout.names) and not n.startswith("frame.")]
        if unknown:
            raise t.error("shift_parameters", f"not parameters of this machine: {', '.join(unknown[:5])}")
    try:
        return Discrepancy(
            inputs=inputs, center=_floats(t, "center", d), scale=_floats(t, "scale", d),
            length_scales=_floats(t, "length_scales", d), outputs=outputs,
            output_scales=_floats(t, "output_scales", len(outputs)), inducing=U,
            weights=_floats(t, "weights", len(outputs) * m), shift_names=shift_names,
            shift=_floats(t, "shift", len(shift_names)),
            log_evidence_gain=t.number("log_evidence_gain", default=float("nan")),
            explained=t.number("explained", default=float("nan")),
        )
    except InputError as exc:
        raise MachineFileError(path, "discrepancy", str(exc)) from None
