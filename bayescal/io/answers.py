"""Atomic writes: an output file is either complete or absent, never half-written.

Every output of bayescal goes through :func:`write_files_atomic` (or its
one-file forms :func:`write_text_atomic`, :func:`write_bytes_atomic`,
:func:`write_json_atomic`, and :func:`write_with_atomic` for writers that
need a path or a stream: figures, NetCDF, ``.npz``).  What is guaranteed:

* a target that exists must be a regular file that is not an input of the
  run (:func:`bayescal.io.safe_paths.check_replaceable`): a symbolic link,
  a device, a named pipe or a folder is refused, never written through;
* each file is first written to a temporary file with a unique name
  (:func:`tempfile.mkstemp`) in the target's folder, flushed and fsynced;
  a failure while writing removes every temporary file of the call and
  leaves every target as it was;
* only when all temporary files are complete are they renamed onto their
  targets, in the order given (a hybrid machine's module files first, its
  main file last), with SIGINT, SIGTERM and SIGHUP held back until the
  renames are done; a rename that fails puts back what the earlier renames
  replaced (from hard-link backups) and removes what they added, so no new
  file of the set remains.  Only a power cut or SIGKILL within the
  microseconds between two renames can leave part of a set renamed;
* an error names the file the caller asked for, never the temporary file.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import secrets
import signal
import tempfile
import threading
from pathlib import Path
from typing import IO, Any, Callable, Iterator, Sequence, Union

import numpy as np

from ..errors import InputError
from .safe_paths import check_replaceable

__all__ = [
    "write_text_atomic", "write_bytes_atomic", "write_json_atomic", "write_with_atomic", "write_files_atomic",
    "to_jsonable",
]

#: What a file of a set holds: text (UTF-8), bytes, or a function writing to the open binary stream.
Content = Union[str, bytes, Callable[[IO[bytes]], None]]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _cannot(path: Path, exc: OSError) -> InputError:
    return InputError(f"{path}: cannot write it ({exc.strerror or exc})")


def _unlink(path: str | Path | None) -> None:
    if path is not None:
        with contextlib.suppress(OSError):
            os.unlink(path)


def _temp_beside(path: Path, content: Content | None = None, *, to_path: Callable[[str], None] | None = None) -> str:
    """A complete, fsynced temporary file with a unique name beside ``path``; removed again if writing fails."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise _cannot(path, exc) from None
    try:
        # mkstemp creates the file readable by its owner only; give it the mode a plain
        # open() would (0666 less the umask), so other users and programs can read answers
        os.fchmod(fd, 0o666 & ~_umask())
        if to_path is not None:
            os.close(fd)
            to_path(tmp)  # a writer that needs a file name (NetCDF)
            fd = os.open(tmp, os.O_RDONLY)
            os.fsync(fd)
            os.close(fd)
        else:
            with os.fdopen(fd, "wb") as fh:
                if isinstance(content, str):
                    fh.write(content.encode("utf-8"))
                elif isinstance(content, (bytes, bytearray, memoryview)):
                    fh.write(content)
                else:
                    content(fh)
                fh.flush()
                os.fsync(fh.fileno())
    except BaseException as exc:
        _unlink(tmp)
        if isinstance(exc, OSError):
            raise _cannot(path, exc) from None
        raise
    return tmp


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP delivered only after the block (the renames of a set)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []
    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if sig is None or signal.getsignal(sig) is None:  # a handler not set from Python cannot be restored
            continue
        with contextlib.suppress(ValueError, OSError):
            old[sig] = signal.signal(sig, lambda n, _frame: got.append(n))
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        if got:
            signal.raise_signal(got[0])


def _backup(path: Path) -> str | None:
    """A hard link to the current ``path`` (to put it back), None if it does not exist or cannot be linked."""
    if not path.exists():
        return None
    name = str(path.with_name(f".{path.name}.{secrets.token_hex(6)}.bak"))
    try:
        os.link(path, name)
    except OSError:
        return None
    return name


def _commit(pairs: list[tuple[Path, str]]) -> None:
    """Rename every temporary file onto its target, in order; on failure undo the renames done."""
    backups = [_backup(p) for p, _ in pairs] if len(pairs) > 1 else [None]
    existed = [p.exists() for p, _ in pairs]
    done = 0
    try:
        with _signals_held():
            for target, tmp in pairs:
                check_replaceable(target)
                os.replace(tmp, target)
                done += 1
    except BaseException as exc:
        for k in range(done):
            target = pairs[k][0]
            if backups[k] is not None:
                with contextlib.suppress(OSError):
                    os.replace(backups[k], target)
            elif not existed[k]:
                _unlink(target)
        for _, tmp in pairs[done:]:
            _unlink(tmp)
        for b in backups:
            _unlink(b)
        if isinstance(exc, OSError):
            raise _cannot(pairs[done][0] if done < len(pairs) else pairs[-1][0], exc) from None
        raise
    for b in backups:
        _unlink(b)


def write_files_atomic(files: Sequence[tuple[str | os.PathLike, Content]]) -> list[Path]:
    """Write several files as one unit: all complete temporary files first, then the renames (module docstring).

    Parameters
    ----------
    files : sequence of (path, content)
        Content is text (written as UTF-8, no newline translation), bytes, or
        ``writer(stream)`` writing to a binary stream.  Renamed in this order.

    Returns
    -------
    list of Path
        The paths written, in order.

    Raises
    ------
    InputError
        A target that is a link, a device, a named pipe, a folder or an input
        of the run; a file that cannot be written (naming the target).
    """
    paths = [Path(p) for p, _ in files]
    if len({os.path.abspath(p) for p in paths}) != len(paths):
        raise InputError("the same file is listed twice in one set of outputs: " + ", ".join(map(str, paths)))
    for p in paths:
        check_replaceable(p)
    temps: list[str] = []
    try:
        for p, (_, content) in zip(paths, files):
            temps.append(_temp_beside(p, content))
    except BaseException:
        for t in temps:
            _unlink(t)
        raise
    _commit(list(zip(paths, temps)))
    return paths


def write_with_atomic(path: str | os.PathLike, *, stream: Callable[[IO[bytes]], None] | None = None,
                      to_path: Callable[[str], None] | None = None) -> Path:
    """Write one file atomically with a writer: ``stream(binary_file)`` or ``to_path(temporary_path)``."""
    path = Path(path)
    check_replaceable(path)
    tmp = _temp_beside(path, stream, to_path=to_path)
    _commit([(path, tmp)])
    return path


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename."""
    return write_files_atomic([(path, bytes(data))])[0]


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8, newlines as given) to ``path`` through a temporary file in the same folder and a rename."""
    return write_files_atomic([(path, text)])[0]


def to_jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays and non-finite floats to plain JSON values (NaN -> null)."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    return obj


def json_text(data: Any) -> str:
    """``data`` as indented JSON text; NaN and inf become null."""
    return json.dumps(to_jsonable(data), indent=2) + "\n"


def write_json_atomic(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as indented JSON, atomically; NaN and inf become null."""
    return write_text_atomic(path, json_text(data))
