"""bayescal: kinematic calibration of parallel manipulators, with geometric errors as random variables.

The front door (:mod:`bayescal.api`): ``load``, ``calibrate``, ``predict``,
``grid``, ``diagnose``, ``plan``, ``compare``, ``simulate_session``,
``compensate``, ``load_klipper``: the command line's own policy as functions.  The central object
is a :class:`MeasurementModel` ``y = h(q, theta)`` with its analytic
Jacobian; every solver, filter, sampler and study consumes it.

The names below are imported on first use (``bayescal._lazy``): ``import
bayescal`` alone loads neither numpy nor scipy, so the command line starts
fast.
"""

from ._lazy import lazy_attributes
from .errors import BayescalError, InputError, KinematicsError, MachineFileError, RecordingError

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
    "load_klipper",
    "calibrate",
    "predict",
    "grid",
    "diagnose",
    "plan",
    "compare",
    "simulate_session",
    "compensate",
    "plan_next_session",
]

_lazy_getattr, __dir__ = lazy_attributes(__name__, {
    "Recording": ".io", "read_recording": ".io", "write_recording": ".io",
    "KINDS": ".machines", "Machine": ".machines", "Prs3": ".machines", "Raspm": ".machines",
    "load_machine": ".machines.files", "MeasurementModel": ".measurement",
    "load": ".api", "load_klipper": ".api", "calibrate": ".api", "predict": ".api", "grid": ".api", "plan": ".api",
    "simulate_session": ".api", "compensate": ".api",
    "plan_next_session": ".api",
})


def __getattr__(name):
    if name in ("diagnose", "compare"):
        # the package, callable as the verb (bayescal/diagnose/__init__.py, bayescal/compare/__init__.py):
        # bayescal.diagnose(machine, recording), bayescal.compare(machine, methods=...)
        import importlib

        return importlib.import_module("." + name, __name__)
    return _lazy_getattr(name)
