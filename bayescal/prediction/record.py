"""What a calibrated machine file keeps of its calibration: the parameters' covariance and the noise scale.

``bayescal predict`` holds a calibrated machine fixed *with its
uncertainty* (docs/formats.md section 8), so the machine file written by
``identify``, ``diagnose`` and ``grid`` carries a ``[calibration]`` table (a
bayescal extension; other readers ignore it):

.. code-block:: toml

    [calibration]
    method = "map"
    noise_scale = 1.0                      # factor on the [measurement] sigma the data supported
    parameters = ["chain1.link_length", ...]  # the file's own parameter names (perturbations of this geometry)
    std = [0.012, ...]                     # their one-sigma uncertainty, unit of each parameter
    covariance_f64le_b64 = "..."           # the full covariance, float64 little-endian, row-major, base64

The parameters are perturbations of the *calibrated* geometry in the file
(the same names and units as the identification answer); to first order
the covariance of the errors about the nominal is that of the calibrated
geometry's perturbations.  A model-discrepancy term (``[discrepancy]``,
:mod:`bayescal.discrepancy`) appends its weights ``discrepancy.w<k>`` to
``parameters``, so that the covariance is the joint one.

A machine parameter the record does not hold (one the calibration did not
estimate) keeps its prior: its tolerance is its one-sigma uncertainty,
independent of the others (:func:`covariance_with_prior`).
"""

from __future__ import annotations

import base64
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import MachineFileError
from ..io.machine_file import TomlTable, format_toml_value

__all__ = ["CalibrationRecord", "calibration_toml", "read_calibration", "covariance_with_prior",
           "unknown_parameters_message", "effect_parameter_names", "EFFECT_PREFIX"]

#: How the record names an ``[effect.*]`` table's parameter (as the joint model's layout does).
EFFECT_PREFIX = "effect."

#: Largest covariance a machine file may carry (parameters): 4,000 gives 128 MB of float64.
MAX_PARAMETERS = 4000


@dataclass(frozen=True)
class CalibrationRecord:
    """The covariance of a calibrated machine's parameters and the noise scale it was fitted with.

    Attributes
    ----------
    names : tuple of str
        Parameter names (the machine's layout names, then ``discrepancy.w<k>``).
    covariance : ndarray, shape (n, n)
        In the parameters' units (mm, rad; products for off-diagonal entries).
    noise_scale : float
        Factor on the machine file's ``[measurement]`` sigma that the
        calibration's residuals supported (1: the stated noise fits).
    method : str
    variance_factor : float
        ``kappa >= 1`` on every predictive covariance: how much the
        calibration's own left-out poses said its regions must widen
        (:mod:`bayescal.prediction.loo`).
    """

    names: tuple[str, ...]
    covariance: NDArray
    noise_scale: float = 1.0
    method: str = ""
    variance_factor: float = 1.0

    @property
    def std(self) -> NDArray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def covariance_for(self, names) -> NDArray:
        """The covariance over ``names`` (any order); names the record does not hold get zero variance."""
        pos = {n: i for i, n in enumerate(self.names)}
        idx = np.array([pos.get(n, -1) for n in names])
        out = np.zeros((len(idx), len(idx)))
        have = idx >= 0
        out[np.ix_(have, have)] = self.covariance[np.ix_(idx[have], idx[have])]
        return out

    def missing(self, names) -> tuple[str, ...]:
        """Which of ``names`` the record does not hold."""
        have = set(self.names)
        return tuple(n for n in names if n not in have)


def calibration_toml(record: CalibrationRecord) -> str:
    """The ``[calibration]`` table of a machine file (module docstring)."""
    C = np.ascontiguousarray(np.asarray(record.covariance, dtype="<f8"))
    f = format_toml_value
    return "\n".join([
        "[calibration]",
        "# the calibration's uncertainty, for bayescal predict: covariance of the parameters below (perturbations",
        "# of this file's geometry), float64 little-endian row-major, base64",
        f"method = {f(record.method)}",
        f"noise_scale = {f(float(record.noise_scale))}",
        f"variance_factor = {f(float(record.variance_factor))}",
        f"parameters = {f(list(record.names))}",
        f"std = {f(record.std)}",
        f"covariance_f64le_b64 = {f(base64.b64encode(C.tobytes()).decode('ascii'))}",
        "",
    ])


def read_calibration(doc: TomlTable, path: str) -> CalibrationRecord | None:
    """The optional ``[calibration]`` table, checked (MachineFileError naming the key)."""
    t = doc.table("calibration", required=False)
    if t is None:
        return None
    t.reject_unknown({"method", "noise_scale", "variance_factor", "parameters", "std", "covariance_f64le_b64"})
    names = t.data.get("parameters")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names) or not names:
        raise t.error("parameters", "expected a non-empty list of parameter names")
    if len(set(names)) != len(names):
        raise t.error("parameters", "expected distinct names")
    n = len(names)
    if n > MAX_PARAMETERS:
        raise t.error("parameters", f"{n} parameters; at most {MAX_PARAMETERS} are read")
    raw = t.data.get("covariance_f64le_b64")
    if not isinstance(raw, str):
        raise t.error("covariance_f64le_b64", "expected a base64 string of n x n float64 values")
    try:
        buf = base64.b64decode(raw.encode("ascii"), validate=True)
    except (ValueError, UnicodeEncodeError):
        raise t.error("covariance_f64le_b64", "not valid base64") from None
    if len(buf) != 8 * n * n:
        raise t.error("covariance_f64le_b64", f"{len(buf)} bytes; expected {8 * n * n} ({n} x {n} float64 values)")
    C = np.frombuffer(buf, dtype="<f8").reshape(n, n).astype(float)
    big = float(np.max(np.abs(C))) if C.size else 0.0
    if not np.all(np.isfinite(C)) or np.max(np.abs(C - C.T), initial=0.0) > 1e-9 * big or np.any(np.diag(C) < 0):
        raise t.error("covariance_f64le_b64", "expected a finite, symmetric covariance with non-negative variances")
    _check_covariance(t, names, C)
    scale = t.number("noise_scale", default=1.0, positive=True)
    if not math.isfinite(scale) or not 1e-6 <= scale <= 1e6:
        raise t.error("noise_scale", f"expected a factor between 1e-6 and 1e6, got {scale!r}")
    method = t.string("method", default="")
    kappa = t.number("variance_factor", default=1.0, positive=True)
    if not 1.0 <= kappa <= 1e4:
        raise t.error("variance_factor", f"expected a factor from 1 to 1e4, got {kappa!r}")
    return CalibrationRecord(tuple(names), C, float(scale), method, float(kappa))


#: Largest one-sigma a record may state for a parameter (mm, rad or a weight's unit): 1 km is no calibration.
MAX_RECORD_STD = 1e6


def _check_covariance(t: TomlTable, names: list, C: NDArray) -> None:
    """Refuse a covariance no calibration writes: a variance beyond :data:`MAX_RECORD_STD`, not positive
    semi-definite, or a ``std`` list that is not the square root of its diagonal (an edited file).

    A variance of 1e300 passed the finite-and-symmetric check and ended in a singular-matrix traceback.
    """
    d = np.diag(C)
    worst = int(np.argmax(d)) if d.size else 0
    if d.size and not np.sqrt(d[worst]) <= MAX_RECORD_STD:
        raise t.error("covariance_f64le_b64", f"parameter {names[worst]!r} has a std of {np.sqrt(d[worst]):.3g}; expected at "
                      f"most {MAX_RECORD_STD:g} (mm, rad or the parameter's unit)")
    lo = float(np.linalg.eigvalsh(C)[0]) if d.size else 0.0
    if lo < -1e-9 * max(float(d.max(initial=0.0)), 1e-300):
        raise t.error("covariance_f64le_b64", f"not positive semi-definite (smallest eigenvalue {lo:.3g}); expected a "
                      "covariance as identify, diagnose or grid write it")
    std = t.data.get("std")
    if std is None:
        return
    ok = isinstance(std, list) and len(std) == len(names) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0 for v in std)
    if not ok:
        raise t.error("std", f"expected {len(names)} finite non-negative numbers, one per parameter")
    off = np.abs(np.asarray(std, dtype=float) - np.sqrt(d))
    bad = np.flatnonzero(off > 1e-6 * np.sqrt(d) + 1e-300)
    if bad.size:
        i = int(bad[0])
        raise t.error("std", f"{names[i]!r}: {std[i]!r} is not the square root of its variance in the covariance "
                      f"({np.sqrt(d[i]):.6g}); the table was edited: write it again with identify --write-machine")


def record_from_result(machine, names_all, free, covariance, *, noise_scale: float = 1.0, method: str = "",
                       extra_names=(), extra_cov=None, variance_factor: float = 1.0,
                       held=(), effect_names=()) -> CalibrationRecord | None:
    """The record of an identification: the covariance of the machine's own parameters among the free ones.

    Parameters
    ----------
    machine : Machine
        The machine written: its layout names are kept, and the parameters of its ``[effect.*]`` tables
        (``effect.<effect>.<parameter>``, fitted with the geometry); frames and pivots drop out.
    names_all : sequence of str
        The model's parameter names (layout order).
    free : ndarray of bool
    covariance : ndarray, shape (n_free, n_free) or None
    extra_names, extra_cov :
        A joint covariance to use instead (discrepancy weights appended): ``extra_cov`` over
        ``[free names..., extra_names...]``.
    held : sequence of str
        Parameters the user held at nominal (``fix``): stated known, so recorded at zero variance (left out,
        predict would give them their tolerance).
    effect_names : sequence of str
        Effect parameters to keep besides those of ``machine``'s own tables (a diagnosis writes its tables later).
    """
    if covariance is None and extra_cov is None:
        return None
    keep_names = set(machine.layout.names) | set(effect_parameter_names(machine.effects)) | set(effect_names)
    free_names = [n for n, f in zip(names_all, np.asarray(free, dtype=bool)) if f]
    C = np.asarray(covariance if extra_cov is None else extra_cov, dtype=float)
    all_names = free_names + list(extra_names)
    sel = [i for i, n in enumerate(all_names) if n in keep_names or n in set(extra_names)]
    if not sel or not np.all(np.isfinite(C[np.ix_(sel, sel)])):
        return None
    Cs = C[np.ix_(sel, sel)]
    names = [all_names[i] for i in sel]
    pinned = [n for n in held if n in keep_names and n not in set(names)]
    names += pinned
    Cs = np.pad(Cs, ((0, len(pinned)), (0, len(pinned))))
    if method == "ls" and not extra_names:  # (a discrepancy needs a prior: least squares carries none)
        # least squares fixes the parameters it cannot tell from the free ones (the gauge,
        # bayescal.identifiability): the free ones absorbed their effect, so a prediction does not depend on their
        # true values and they are exact given that choice. Left out, predict would give them their tolerance
        # (covariance_with_prior) and count the absorbed effect twice (the 3-PRS example's z std 0.034 -> 0.060 mm)
        from ..machines.framed import is_frame_parameter

        fixed = [n for n in machine.layout.names if n not in set(names) and not is_frame_parameter(n)
                 and n in set(names_all)]
        names += fixed
        Cs = np.pad(Cs, ((0, len(fixed)), (0, len(fixed))))
    return CalibrationRecord(tuple(names), 0.5 * (Cs + Cs.T), float(noise_scale), method, float(variance_factor))


def effect_parameter_names(effects) -> tuple[str, ...]:
    """``effect.<effect>.<parameter>`` of every value of the ``[effect.*]`` tables ``effects`` (StoredEffect)."""
    return tuple(f"{EFFECT_PREFIX}{st.name}.{k}" for st in effects for k, _ in st.values)


def unknown_parameters_message(path: str, missing) -> str:
    """The note when a record lacks some parameters: their tolerances (prior std) are taken as their uncertainty."""
    shown = ", ".join(list(missing)[:5]) + (" ..." if len(missing) > 5 else "")
    return (f"{path}: [calibration] holds no uncertainty for {len(missing)} parameter(s) ({shown}); their "
            "tolerances (the prior, not calibrated) are taken as their one-sigma uncertainty")


def covariance_with_prior(record: CalibrationRecord, names, prior_std, path: str = "") -> tuple[NDArray, tuple]:
    """The covariance over ``names``: the record's, and the prior variance for parameters it does not hold.

    A record lacks a parameter the calibration did not estimate (``--free auto`` leaves out what the
    measurement does not see; a list of ``--free`` names leaves out the rest): that parameter stayed at
    the file's value, known no better than its tolerance, so its honest uncertainty is the prior
    ``N(0, tolerance^2)``, independent of the estimated ones (the data did not see it). Taking it as
    exact made every prediction that depends on it far too confident.

    Parameters
    ----------
    record : CalibrationRecord
    names : sequence of str
        The machine's parameters wanted (frame parameters of a session excluded by the caller).
    prior_std : array_like, shape (len(names),)
        Their one-sigma tolerances (the machine file's ``[tolerance]`` or the documented defaults), unit
        of each parameter.
    path : str
        The machine file, for the error.

    Returns
    -------
    (ndarray, tuple of str)
        The covariance, shape (len(names), len(names)), and the names the record lacked.

    Raises
    ------
    MachineFileError
        When a parameter the record lacks has no finite positive tolerance: its uncertainty is unknown
        (one line naming the parameters).
    """
    names = list(names)
    prior_std = np.asarray(prior_std, dtype=float)
    if prior_std.shape != (len(names),):
        raise ValueError(f"covariance_with_prior: {prior_std.size} tolerances for {len(names)} parameters")
    C = record.covariance_for(names)
    missing = record.missing(names)
    held = set(missing)
    unknown = [n for n, s in zip(names, prior_std) if n in held and not (math.isfinite(s) and s > 0)]
    if unknown:
        shown = ", ".join(unknown[:5]) + (" ..." if len(unknown) > 5 else "")
        raise MachineFileError(path, "calibration.parameters",
                               f"holds no uncertainty for {len(unknown)} parameter(s) ({shown}) and the machine states "
                               "no positive tolerance for them; expected them in [calibration] (write the machine "
                               "again with identify --write-machine)")
    for i, n in enumerate(names):
        if n in held:
            C[i, i] = prior_std[i] ** 2
    return C, missing


def check_record(record: CalibrationRecord, path: str) -> None:
    """Refuse a record whose covariance is not positive semi-definite (to rounding)."""
    w = np.linalg.eigvalsh(0.5 * (record.covariance + record.covariance.T))
    if w.size and w[0] < -1e-9 * max(w[-1], 1e-300):
        raise MachineFileError(path, "calibration.covariance_f64le_b64",
                               f"not positive semi-definite (smallest eigenvalue {w[0]:.3g})")
