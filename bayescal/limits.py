"""Stated limits on values and sizes: seeds, noise sigmas, and the memory a request may take.

Each limit is one function the readers, the library and the command line
call, so that a value outside it is refused the same way everywhere with a
message that states the limit (docs/cli.md, "Limits"):

* a random seed is an integer from 0 to 2**32 - 1 (:func:`check_seed`):
  numpy's legacy generator, which emcee uses, takes no other;
* a stated noise is within :data:`SIGMA_POSITION_RANGE` mm or
  :data:`SIGMA_ANGLE_RANGE` rad (:func:`sigma_problem`): a sigma of 1e-200
  divides every residual into overflow, one of a metre is no instrument;
* an auxiliary channel of known meaning is at least its
  :data:`AUX_LOWER_BOUNDS` (no negative payload or elapsed time) and at most
  its :data:`AUX_UPPER_BOUNDS` (no payload of 1e300 kg);
* a number in a machine file (a length, an angle, a tolerance, an effect's
  value) is at most :data:`MAX_FILE_NUMBER` in magnitude
  (:func:`file_number_problem`): 1e300 is a typo that overflows the
  kinematics, or passes them and writes a recording of 1e300 mm;
* a request whose arrays would not fit in the memory this machine has
  available is refused before it is allocated (:func:`check_memory`),
  naming the size and the option that sets it; a fit's peak is estimated by
  :func:`fit_memory` and checked by :func:`check_fit_memory` as soon as the
  recording is read, before its poses are solved.  The environment variable
  :data:`BUDGET_ENV` (bytes; suffixes K, M, G) sets the budget instead of the
  memory available.
"""

from __future__ import annotations

import math
import numbers
import os
from pathlib import Path

from .errors import InputError

__all__ = [
    "SEED_MAX", "check_seed", "SIGMA_POSITION_RANGE", "SIGMA_ANGLE_RANGE", "sigma_problem", "memory_budget",
    "check_memory", "check_count", "AUX_LOWER_BOUNDS", "AUX_UPPER_BOUNDS", "BUDGET_ENV", "FIT_COPIES", "fit_memory",
    "check_fit_memory", "finite_real", "MAX_FILE_NUMBER", "file_number_problem", "MAX_LAM", "LAM_RANGE", "lam_problem",
    "check_lam",
]

#: Largest random seed (numpy's legacy RandomState, which emcee draws from, takes 32 bits).
SEED_MAX = 2**32 - 1
#: A stated position noise (one sigma), mm: 1 nm to 1 m.
SIGMA_POSITION_RANGE = (1e-6, 1e3)
#: A stated angle noise (one sigma), rad: 1 nrad to 1 rad.
SIGMA_ANGLE_RANGE = (1e-9, 1.0)


#: Largest magnitude of a number in a machine file, in its unit (mm, rad, um, kg, ...): 1000 km, as for a
#: measured coordinate (bayescal.instrument.units.MAX_COORDINATE).
MAX_FILE_NUMBER = 1e9


def file_number_problem(value: float) -> str | None:
    """What is wrong with a machine file's finite number ``value`` (its magnitude beyond :data:`MAX_FILE_NUMBER`), or None."""
    if abs(value) > MAX_FILE_NUMBER:
        return (f"expected a number of magnitude at most {MAX_FILE_NUMBER:g} (mm, rad or the key's unit; a larger "
                f"value is a typo), got {value!r}")
    return None


#: The smallest value of an auxiliary channel that is physics: no negative payload, nothing below absolute zero,
#: no negative elapsed time (``grid --aux`` values and the recording's channels, docs/formats.md section E5).
AUX_LOWER_BOUNDS = {"payload_kg": 0.0, "temp_C": -273.15, "time_s": 0.0}
#: The largest value of an auxiliary channel that is a calibration's physics: a payload of 100 t, a machine at
#: 1000 degC (a payload of 1e300 kg passed, and the effects' fits died in an eigenvalue solver's traceback).
AUX_UPPER_BOUNDS = {"payload_kg": 1e5, "temp_C": 1e3}


#: Largest ridge parameter: the prior's std is the tolerances over sqrt(lam), so 1e12 already holds every
#: parameter within a millionth of its tolerance of nominal; 1e308 reported stds of 5e-156 mm.
MAX_LAM = 1e12
#: The ridge parameters accepted, by the library (``identify``, ``calibrate``), the command line and ``compare``
#: alike; an automatic rule searches no further (:func:`bayescal.identify.choose.lambda_grid`).
LAM_RANGE = (0.0, MAX_LAM)


def lam_problem(lam) -> str | None:
    """What is wrong with a ridge parameter ``lam`` (dimensionless, 1 = MAP under the tolerance prior), or None."""
    lo, hi = LAM_RANGE
    if not (finite_real(lam) and lo <= float(lam) <= hi):
        return (f"expected a number from {lo:g} to {hi:g} (1: MAP under the tolerance prior; larger holds every "
                f"parameter at nominal with a std of its tolerance over sqrt(lam)), got {lam!r}")
    return None


def check_lam(lam, *, auto: bool = False) -> None:
    """InputError naming ``lam`` and :data:`LAM_RANGE` when ``lam`` is outside it (``auto``: 'auto' is accepted too).

    Parameters
    ----------
    lam : float or str
        A ridge parameter (dimensionless, 1 = MAP under the tolerance prior).
    auto : bool
        Whether the caller also takes ``"auto"`` (a rule chooses ``lam``); the message then says so.
    """
    if auto and isinstance(lam, str) and lam == "auto":
        return
    if (problem := lam_problem(lam)) is not None:
        raise InputError(f"lam: {problem}" + (" (or 'auto')" if auto else ""))


def finite_real(x) -> bool:
    """Whether ``x`` is a finite real number (an int or float, numpy's too; not a bool, not a string)."""
    # numbers.Real holds numpy's integer and floating scalars too (without importing numpy here: start-up)
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x)


def check_seed(seed, option: str = "seed") -> int:
    """``seed`` as an int in 0..2**32-1; InputError naming ``option`` otherwise."""
    if isinstance(seed, bool) or not isinstance(seed, (int,)) and not (hasattr(seed, "__index__")):
        raise InputError(f"{option}: expected an integer from 0 to {SEED_MAX}, got {seed!r}")
    value = int(seed)
    if not 0 <= value <= SEED_MAX:
        raise InputError(f"{option}: expected an integer from 0 to {SEED_MAX}, got {value}")
    return value


def sigma_problem(value: float, kind: str) -> str | None:
    """What is wrong with a stated noise ``value`` (``kind`` ``"position"``, mm, or ``"angle"``, rad), or None."""
    lo, hi = SIGMA_POSITION_RANGE if kind == "position" else SIGMA_ANGLE_RANGE
    unit = "mm" if kind == "position" else "rad"
    if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
        return f"expected a one-sigma {kind} noise from {lo:g} to {hi:g} {unit}, got {value!r}"
    return None


def _cgroup_room() -> float:
    """Memory the control group may still take (cgroup v2 ``memory.max``), bytes; inf without a limit."""
    base = Path("/sys/fs/cgroup")
    try:
        limit = (base / "memory.max").read_text().strip()
        if limit == "max":
            return math.inf
        return max(0.0, float(limit) - float((base / "memory.current").read_text().strip()))
    except (OSError, ValueError):
        return math.inf


#: Environment variable that sets the memory budget, in bytes (``2G``, ``500M``, ``1e9``), instead of the
#: memory available now: to keep a run within a share of a shared machine, or to test the refusals.
BUDGET_ENV = "BAYESCAL_MEMORY_BUDGET"

_SUFFIX = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def _budget_from_env() -> float | None:
    """The budget :data:`BUDGET_ENV` states, bytes, or None when it is not set; InputError when it is not a size."""
    text = os.environ.get(BUDGET_ENV, "").strip()
    if not text:
        return None
    unit = text[-1].upper() if text[-1].upper() in "KMGT" else ""
    try:
        value = float(text[: len(text) - len(unit)]) * _SUFFIX[unit]
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 1):  # 1e-300 was taken, and requests refused for "0 bytes set"
        raise InputError(f"environment variable {BUDGET_ENV}: expected a positive number of bytes, at least 1 (suffix "
                         f"K, M or G allowed, e.g. 2G), got {text!r}")
    return value


def memory_budget() -> float:
    """Bytes a request may take: :data:`BUDGET_ENV` if set, else the memory available now (Linux ``MemAvailable``,
    within a cgroup's limit).

    Where neither can be read: the physical memory, else 8 GiB.
    """
    stated = _budget_from_env()
    if stated is not None:
        return stated
    avail = math.inf
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                avail = float(line.split()[1]) * 1024
                break
    except (OSError, ValueError, IndexError):
        pass
    if not math.isfinite(avail):
        try:
            avail = float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            avail = 8.0 * 2**30
    return min(avail, _cgroup_room())


def check_memory(n_bytes: float, what: str, change: str) -> None:
    """Refuse a request whose arrays would take about ``n_bytes``, more than :func:`memory_budget`.

    Parameters
    ----------
    n_bytes : float
        Estimated peak memory of the request, bytes (an estimate of the
        largest arrays, not an exact account).
    what : str
        The request (``"a grid of 2000^3 nodes"``).
    change : str
        What to change (``"lower --nodes"``).
    """
    from .io.safe_paths import format_bytes

    budget = memory_budget()
    if not n_bytes <= budget:
        source = f"set by {BUDGET_ENV}" if _budget_from_env() is not None else "available"
        raise InputError(f"{what} needs about {format_bytes(n_bytes)} of memory, more than the "
                         f"{format_bytes(budget)} {source}; {change}")


#: Arrays of the Jacobian's size (measured components x parameters, float64) a fit holds at its peak.  Measured
#: (peak resident memory less that of a 36-row run): a 3-PRS with 36 parameters, 6-DOF, ``identify --method map``
#: and ``--method ridge --lam auto``, 5,000 and 20,000 poses: 8.0 and 8.7 such arrays (202 MB and 411 MB at peak);
#: 100,000 poses peaked at 1.45 GB (7.6).  Ten keeps a margin for the robust pass and the fits with effects.
FIT_COPIES = 10


def fit_memory(n_rows: int, n_params: int) -> float:
    """Estimated peak memory of identifying ``n_params`` parameters from ``n_rows`` measured components, bytes.

    :data:`FIT_COPIES` float64 arrays of ``n_rows x n_params`` (the Jacobian,
    its whitened and scaled copies, the SVD's factors).
    """
    return float(FIT_COPIES) * 8.0 * float(n_rows) * float(n_params)


def check_fit_memory(n_rows: int, n_params: int, what: str = "identifying") -> None:
    """Refuse a fit whose arrays (:func:`fit_memory`) would not fit in :func:`memory_budget`.

    Parameters
    ----------
    n_rows : int
        Measured components (poses x components per pose).
    n_params : int
        Parameters of the fit.
    what : str
        What is done, for the message (``"rec.csv: identifying"``).
    """
    check_memory(fit_memory(n_rows, n_params), f"{what} from {n_rows:,} measured components x {n_params} parameters",
                 "identify from a subset of the poses (every k-th row of the recording), or set "
                 f"{BUDGET_ENV} (bytes) if more memory can be taken")


def check_count(value, option: str, *, minimum: int = 1) -> int:
    """An integer option of at least ``minimum``; InputError naming ``option`` otherwise."""
    if isinstance(value, bool) or int(value) != value or value < minimum:
        raise InputError(f"{option}: expected an integer >= {minimum}, got {value!r}")
    return int(value)
