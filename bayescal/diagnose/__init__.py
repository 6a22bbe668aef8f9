"""Model-mismatch diagnosis: locate the mismatch, name the missing physics, model it, verify it out of sample.

Called, ``bayescal.diagnose(machine, recording, frame="base", effects=None, seed=0, n_folds=5,
effect_settings=None)`` is the front door's verb :func:`bayescal.api.diagnose` (files or objects in, a
:class:`~bayescal.diagnose.result.Diagnosis` out; its docstring documents the options, and an unknown one is
refused by name).
"""

from .core import DECISIVE, EXPLAINED_FRACTION, P_MISMATCH, diagnose
from .locate import ChannelDependence, Location, distance_correlation, holm, locate
from .result import Diagnosis, EffectTrial, ParameterValue
from .verb import diagnose_files

__all__ = [
    "diagnose", "diagnose_files", "Diagnosis", "EffectTrial", "ParameterValue", "locate", "Location", "ChannelDependence",
    "distance_correlation", "holm", "DECISIVE", "P_MISMATCH", "EXPLAINED_FRACTION",
]


class _CallablePackage(type(__import__("sys"))):
    """``bayescal.diagnose`` is this package and, called, the front door's verb (:func:`bayescal.api.diagnose`).

    Importing a submodule sets the package as the parent's attribute, so a
    function ``bayescal.diagnose`` could not live beside the package; calling
    the package instead does what the verb does (paths or objects in).
    """

    def __call__(self, machine, recording, **options):
        return diagnose_files(machine, recording, **options)


__import__("sys").modules[__name__].__class__ = _CallablePackage
