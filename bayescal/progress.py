"""Progress of long computations, reported only when a caller asks for it.

The library is silent: its long loops (the Gauss-Newton iterations of
:mod:`bayescal.iteration`, the robust pass, the automatic lambda and k rules,
the diagnosis) call :func:`report`, which does nothing unless a sink has been
installed with :func:`reporting`.  The command line installs a
:class:`StderrProgress` (unless ``--quiet``, ``--no-progress`` or
:data:`PROGRESS_ENV` ``=off``), so that a
run on a large recording says what it is doing instead of looking hung
(docs/cli.md, "Limits").

A sink is any callable taking one line of text.  It is held in a context
variable, so a sink installed by one caller is not seen by another thread's
work.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Callable, Iterator, TextIO

__all__ = ["report", "reporting", "StderrProgress", "PROGRESS_DELAY", "PROGRESS_ENV", "progress_wanted"]

_SINK: ContextVar[Callable[[str], None] | None] = ContextVar("bayescal_progress_sink", default=None)

#: Seconds a command runs before its first progress line: a run shorter than this prints none.
PROGRESS_DELAY = 5.0


#: Environment variable that turns the command line's progress lines off (``off``, ``0``, ``no`` or ``false``):
#: for scripts that compare what a command writes on stderr from run to run.
PROGRESS_ENV = "BAYESCAL_PROGRESS"
#: Its values, case and surrounding blanks aside (unset or empty: on).
PROGRESS_OFF = ("off", "0", "no", "false")
PROGRESS_ON = ("", "on", "1", "yes", "true")


def progress_wanted() -> bool:
    """Whether :data:`PROGRESS_ENV` leaves the progress lines on (unset, empty or on) or turns them off.

    Raises
    ------
    InputError
        For any other value: a typo (``BAYESCAL_PROGRESS=of``) left the lines on, silently.
    """
    from .errors import InputError

    raw = os.environ.get(PROGRESS_ENV, "")
    value = raw.strip().lower()
    if value in PROGRESS_OFF:
        return False
    if value in PROGRESS_ON:
        return True
    shown = raw if len(raw) <= 40 else raw[:40] + "..."
    raise InputError(f"environment variable {PROGRESS_ENV}: expected off, 0, no or false (no progress lines) or on, "
                     f"1, yes or true, got {shown!r}")


def report(message: str | Callable[[], str]) -> None:
    """Hand one line of progress to the installed sink, if any (else nothing happens).

    Parameters
    ----------
    message : str or callable
        The line, or a function returning it (formatted only when a sink listens).
    """
    sink = _SINK.get()
    if sink is not None:
        sink(message() if callable(message) else message)


@contextmanager
def reporting(sink: Callable[[str], None] | None) -> Iterator[None]:
    """Send :func:`report`'s lines to ``sink`` within the block (None: keep them silent); then ``sink.close()``, if it has one."""
    token = _SINK.set(sink)
    try:
        yield
    finally:
        _SINK.reset(token)
        close = getattr(sink, "close", None)
        if close is not None:
            close()


class StderrProgress:
    """A sink writing each line as ``bayescal COMMAND: LINE`` on a stream (stderr), once the run has lasted a while.

    Lines are plain lines, never redrawn with carriage returns, so that a log
    file or a pipe reads them as they are.  Nothing is written during the first
    ``delay`` seconds (a quick run stays quiet; the last line reported in them
    is written when they end, if the run goes on), then at most one line every
    ``interval`` seconds.

    Parameters
    ----------
    command : str
        The command's name, for the prefix.
    delay, interval : float
        Seconds.
    stream : file, optional
        Default ``sys.stderr`` (looked up at each line).
    """

    def __init__(self, command: str, *, delay: float = PROGRESS_DELAY, interval: float = 1.0,
                 stream: TextIO | None = None):
        self.prefix = f"bayescal {command}: " if command else "bayescal: "
        self.delay, self.interval, self.stream = float(delay), float(interval), stream
        self.start = time.monotonic()
        self.last = -float("inf")
        self._lock = threading.Lock()
        self._pending: str | None = None
        # a line reported during the delay is written when the delay ends, if nothing newer came: the stage
        # a long run starts with (solving a million poses) says so even though it began in the first seconds
        self._timer = threading.Timer(self.delay, self._flush)
        self._timer.daemon = True
        self._timer.start()

    def __call__(self, line: str) -> None:
        with self._lock:
            now = time.monotonic()
            if now - self.start < self.delay:
                self._pending = line
                return
            if now - self.last < self.interval:
                return
            self._write(line, now)

    def _flush(self) -> None:
        with self._lock:
            if self._pending is not None:
                self._write(self._pending, time.monotonic())
                self._pending = None

    def _write(self, line: str, now: float) -> None:
        self.last = now
        stream = self.stream if self.stream is not None else sys.stderr
        try:
            print(self.prefix + line, file=stream, flush=True)
        except (OSError, ValueError):  # a closed stderr must not cost the computation
            pass

    def close(self) -> None:
        """Stop the delayed line (a run that ended within the delay prints nothing)."""
        self._timer.cancel()
        with self._lock:
            self._pending = None
