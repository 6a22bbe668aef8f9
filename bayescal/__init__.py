"""bayescal: kinematic calibration of parallel manipulators, with geometric errors as random variables.

The front door (:mod:`bayescal.api`): ``load``, ``calibrate``, ``predict``,
``diagnose``, the command line's own policy as functions.  The central object
is a :class:`MeasurementModel` ``y = h(q, theta)`` with its analytic
Jacobian; every solver, filter, sampler and study consumes it.
"""

from .errors import BayescalError, InputError, KinematicsError, MachineFileError, RecordingError
from .io import Recording, read_recording, write_recording
from .machines import KINDS, Machine, Prs3, Raspm, load_machine
from .measurement import MeasurementModel

__version__ = "0.1.0"

__all__ = [
    "BayescalError",
    "InputError",
    "KinematicsError",
    "MachineFileError",
    "RecordingError",
    "Recording",
    "read_recording",
    "write_recording",
    "KINDS",
    "Machine",
    "Prs3",
    "Raspm",
    "load_machine",
    "MeasurementModel",
    "load",
    "calibrate",
    "predict",
    "diagnose",
]


def __getattr__(name):
    # the verbs load their machinery on first use (the command line's start-up does not pay for them)
    if name in ("load", "calibrate", "predict"):
        from . import api

        return getattr(api, name)
    if name == "diagnose":
        # the package, callable as the verb (bayescal/diagnose/__init__.py): bayescal.diagnose(machine, recording)
        import importlib

        return importlib.import_module(".diagnose", __name__)
    raise AttributeError(f"module 'bayescal' has no attribute {name!r}")
