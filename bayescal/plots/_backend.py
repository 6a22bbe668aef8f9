"""The one place the plotting modules get pyplot from and write figure files.

matplotlib is imported lazily with the Agg backend, so importing bayescal
never needs a display; figures are written atomically (a temporary file with a
unique name in the same folder, then a rename), so a reader never sees half a PNG.
"""

from __future__ import annotations

import os
from pathlib import Path


def pyplot():
    """``matplotlib.pyplot`` on the headless Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: str | os.PathLike, *, dpi: int = 100) -> Path:
    """Write ``fig`` to ``path`` atomically (parent folders created), close it, return the path.

    The format comes from the suffix (InputError for one matplotlib does not
    write); the figure goes to a temporary file with a unique name beside
    ``path`` and is renamed onto it (:func:`bayescal.io.answers.write_with_atomic`):
    a link or a device at ``path`` is refused, never written through.
    """
    from ..io.answers import write_with_atomic
    from ..io.safe_paths import figure_format

    path = Path(path)
    try:
        fmt = figure_format(path)
        write_with_atomic(path, stream=lambda fh: fig.savefig(fh, format=fmt, dpi=dpi))
    finally:
        pyplot().close(fig)
    return path
