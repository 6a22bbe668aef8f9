"""Attributes of a package imported on first use (PEP 562), so that ``import bayescal`` stays cheap.

``bayescal --help`` and every command pay for the imports they use, not
for numpy, scipy.stats or filterpy pulled in by a package's ``__init__``
(about 2 s of CPU before anything ran; issue 32).
"""

from __future__ import annotations

import importlib


def lazy_attributes(package: str, where: dict[str, str]):
    """``(__getattr__, __dir__)`` for ``package`` whose names ``where`` maps to their submodule (``".io"``).

    A name not in ``where`` that is a submodule of the package is imported as
    such (``bayescal.machines`` after ``import bayescal``), as an eager
    ``__init__`` that imported it would have made it available.
    """
    module = importlib.import_module(package)

    def __getattr__(name: str):
        if name in where:
            value = getattr(importlib.import_module(where[name], package), name)
            setattr(module, name, value)  # once: later lookups do not come here
            return value
        if not name.startswith("__"):
            try:
                return importlib.import_module(f".{name}", package)
            except ModuleNotFoundError as exc:
                if exc.name != f"{package}.{name}":
                    raise
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__():
        return sorted(set(vars(module)) | set(where))

    return __getattr__, __dir__
