"""Shared helpers of the study tests: load a script of studies/ as a module."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

STUDIES = Path(__file__).resolve().parents[2] / "studies"


def load_study(name: str, *, siblings: bool = False) -> ModuleType:
    """Execute ``studies/<name>.py`` and return it as the module ``name``.

    The module is registered in :data:`sys.modules` before it runs: a study's
    dataclasses (with postponed annotations) look their module up there.
    With ``siblings``, ``studies/`` is on :data:`sys.path` while it runs, for a
    study that imports another one at its top (as it does when run as a script).
    """
    spec = importlib.util.spec_from_file_location(name, STUDIES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    if siblings:
        sys.path.insert(0, str(STUDIES))
    try:
        spec.loader.exec_module(mod)
    finally:
        if siblings:
            sys.path.remove(str(STUDIES))
    return mod
