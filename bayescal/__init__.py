"""bayescal: kinematic calibration of parallel manipulators, with geometric errors as random variables.

The central object is a :class:`MeasurementModel` ``y = h(q, theta)`` with
its analytic Jacobian; every solver, filter, sampler and study consumes it.
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
]
