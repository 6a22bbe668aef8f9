"""How the studies that check targets word them and set their exit code (one rule for all).

A study prints every target with PASS or MISS (NOT TESTED when the run had
nothing to judge it on) and exits 1 if any is missed, 0 only when all are
met (a target not tested is not a miss).  Import as ``from studies.targets
import verdict, exit_code`` (the studies put the repository root on
``sys.path``).
"""

from __future__ import annotations

from typing import Iterable

__all__ = ["PASS", "MISS", "NOT_TESTED", "verdict", "exit_code"]

PASS, MISS, NOT_TESTED = "PASS", "MISS", "NOT TESTED"


def verdict(ok: bool | None) -> str:
    """``PASS`` for a met target, ``MISS`` for a missed one, ``NOT TESTED`` for None (numpy booleans too)."""
    if ok is None:
        return NOT_TESTED
    return PASS if ok else MISS


def exit_code(oks: Iterable[bool | None]) -> int:
    """1 if any target is missed (False), else 0; None (not tested) is no miss."""
    return 1 if any(ok is not None and not ok for ok in oks) else 0
