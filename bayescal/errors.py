"""Errors and warnings raised by bayescal.

Every error a user can cause derives from :class:`BayescalError`, and also
from the builtin it resembles (``ValueError`` for bad input), so callers can
catch either.  Messages name the file, the row or key, and what was expected.
"""

from __future__ import annotations

__all__ = [
    "BayescalError",
    "InputError",
    "MachineFileError",
    "RecordingError",
    "KinematicsError",
    "IdentificationError",
    "BayescalWarning",
    "ConvergenceWarning",
    "refuse_unknown_options",
]


class BayescalError(Exception):
    """Root of every error bayescal raises on purpose."""


class InputError(BayescalError, ValueError):
    """An argument or file does not have the expected form."""


class MachineFileError(InputError):
    """A machine file (TOML) is malformed.

    Parameters
    ----------
    path : str
        The file.
    key : str
        The key (dotted, e.g. ``chain[2].link_length``) that is wrong, or ``""``.
    expected : str
        What was expected and what arrived.
    """

    def __init__(self, path: str, key: str, expected: str):
        self.path, self.key, self.expected = str(path), key, expected
        where = f"{self.path}: key '{key}'" if key else self.path
        super().__init__(f"{where}: {expected}")


class RecordingError(InputError):
    """A recording (CSV) is malformed.

    Parameters
    ----------
    path : str
        The file.
    row : int or None
        1-based line number in the file (the header is line 1), or None.
    column : str or None
        The column name, or None.
    expected : str
        What was expected and what arrived.
    """

    def __init__(self, path: str, row: int | None, column: str | None, expected: str):
        self.path, self.row, self.column, self.expected = str(path), row, column, expected
        where = self.path
        if row is not None:
            where += f": line {row}"
        if column is not None:
            where += f", column '{column}'"
        super().__init__(f"{where}: {expected}")


class KinematicsError(BayescalError, ArithmeticError):
    """A pose could not be solved (unreachable, singular, or no convergence)."""


class IdentificationError(BayescalError, ArithmeticError):
    """An identification problem cannot be set up (for example too few poses)."""


class BayescalWarning(UserWarning):
    """Root of bayescal's warnings."""


class ConvergenceWarning(BayescalWarning):
    """A numerical solve did not converge; the result says success=False."""


def refuse_unknown_options(what: str, options, *functions) -> None:
    """Refuse an option that none of ``functions`` takes as a keyword, naming it, the closest and the accepted ones.

    A verb that passes ``**options`` on would otherwise end in Python's ``TypeError`` naming an internal function.

    Raises
    ------
    InputError
        ``"{what}: unknown option 'methd' (did you mean 'method'?); expected one of: ..."``.
    """
    import difflib
    import inspect

    known: list[str] = []
    for f in functions:
        for name, p in inspect.signature(f).parameters.items():
            if p.kind == p.KEYWORD_ONLY and not name.startswith("_") and name not in known:
                known.append(name)
    bad = [o for o in options if o not in known]
    if bad:
        close = difflib.get_close_matches(bad[0], known, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise InputError(f"{what}: unknown option {bad[0]!r}{hint}; expected one of: {', '.join(known)}")
