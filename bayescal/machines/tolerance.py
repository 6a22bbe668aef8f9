"""One-sigma tolerances of a machine's parameters: per group, and per parameter where the file names one.

A machine file's ``[tolerance]`` table (docs/formats.md, E1) states a
one-sigma tolerance per parameter group (``link_length = 0.05``) and may
override it for single parameters by their names (``"chain2.link_length" =
0.5``, or unquoted, ``chain2.link_length = 0.5``, which TOML reads as a
nested table).  Group names never hold a dot and parameter names always do,
so one table holds both without ambiguity.  The kinds keep both in their
``tolerance_groups`` dict; :func:`tolerance_vector` resolves them.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError

__all__ = ["ToleranceKeyError", "is_parameter_key", "tolerance_vector"]


class ToleranceKeyError(InputError):
    """A per-parameter tolerance names no parameter of the machine (``key``, ``expected``).

    Raised while a machine is built; reading a file turns it into a
    :class:`~bayescal.errors.MachineFileError` naming the file and the key.
    """

    def __init__(self, key: str, expected: str):
        self.key, self.expected = key, expected
        super().__init__(f"tolerance '{key}': {expected}")


def is_parameter_key(key: str) -> bool:
    """Whether a ``[tolerance]`` key names one parameter (it holds a dot) rather than a group."""
    return "." in key


def tolerance_vector(specs: Iterable, tolerance_groups: Mapping[str, float]) -> NDArray:
    """One-sigma tolerance of each parameter (mm or rad), in the order of ``specs``.

    Parameters
    ----------
    specs : iterable of ParamSpec
        The machine's parameters (name, unit, group).
    tolerance_groups : mapping
        Group name -> tolerance, and parameter name -> tolerance for the
        parameters whose own tolerance overrides their group's.

    Raises
    ------
    ToleranceKeyError
        A parameter key that is not one of ``specs``' names.
    """
    specs = tuple(specs)
    names = [s.name for s in specs]
    known = set(names)
    for key in tolerance_groups:
        if is_parameter_key(key) and key not in known:
            groups = sorted(k for k in tolerance_groups if not is_parameter_key(k))
            close = difflib.get_close_matches(key, names, n=1)
            hint = f"did you mean '{close[0]}'? " if close else ""
            raise ToleranceKeyError(key, f"unknown parameter; {hint}expected a group ({', '.join(groups)}) or one of "
                                         f"this machine's {len(names)} parameters: {', '.join(names)}")
    return np.array([float(tolerance_groups.get(s.name, tolerance_groups[s.group])) for s in specs])
