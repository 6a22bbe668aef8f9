"""Named parameters with units: the layout of a parameter vector ``theta``."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

__all__ = ["ParamSpec", "ParamLayout"]


@dataclass(frozen=True)
class ParamSpec:
    """One scalar parameter.

    Attributes
    ----------
    name : str
        Stable name, e.g. ``chain1.link_length`` or ``tool.point.z``.
    unit : str
        ``mm``, ``rad`` or the unit the parameter is expressed in.
    group : str
        Tolerance group (a key of the machine file's ``[tolerance]`` table).
    """

    name: str
    unit: str
    group: str


@dataclass(frozen=True)
class ParamLayout:
    """An ordered set of named parameters."""

    specs: tuple[ParamSpec, ...]

    def __post_init__(self) -> None:
        names = [s.name for s in self.specs]
        if len(set(names)) != len(names):
            raise InputError(f"parameter names must be unique, got duplicates in {names}")

    def __len__(self) -> int:
        return len(self.specs)

    def __iter__(self):
        return iter(self.specs)

    # the layout is immutable: its names, units and groups are read many times a fit, and formed once
    @cached_property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs)

    @cached_property
    def units(self) -> tuple[str, ...]:
        return tuple(s.unit for s in self.specs)

    @cached_property
    def groups(self) -> tuple[str, ...]:
        return tuple(s.group for s in self.specs)

    def index(self, name: str) -> int:
        """Position of parameter ``name``; raises InputError naming the choices."""
        try:
            return self.names.index(name)
        except ValueError:
            raise InputError(
                f"unknown parameter '{name}'; expected one of: {', '.join(self.names)}"
            ) from None

    def indices(self, names) -> NDArray:
        return np.array([self.index(n) for n in names], dtype=int)

    def __add__(self, other: "ParamLayout") -> "ParamLayout":
        return ParamLayout(self.specs + other.specs)
