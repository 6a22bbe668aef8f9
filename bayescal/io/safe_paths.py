"""Which files a run may read and write: regular files only, inputs read once, no input ever overwritten.

The policy every command and every reader of bayescal follows
(docs/cli.md, "Input and output files"):

* **Inputs** are read by :func:`read_input_bytes` / :func:`read_input_text`:
  a regular file (a folder, a named pipe, a device such as ``/dev/zero`` or
  a socket is refused *before* it is opened for reading, so nothing hangs or
  fills the memory), no larger than a stated limit per kind of file
  (:data:`MAX_CSV_BYTES`, :data:`MAX_TOML_BYTES`, ...), read in one go.
  Standard input (``/dev/stdin``) is the one exception to "regular": it may
  be a pipe, is read once (up to the same limit) and its bytes are kept, so
  a reader that looks at the header first and then parses the whole file
  sees the same text twice.
* **Outputs** are checked by :func:`check_outputs` before any computation:
  no output may be an input of the same run (compared by file identity,
  :func:`os.path.samefile`, not by name) and no two outputs may be the same
  file; a target that exists must be a regular file: a symbolic link is
  refused (bayescal neither writes through a link nor replaces it), and so
  are a folder, a device (``/dev/null`` too) and a named pipe; the folder of
  each output must exist (or, asked for, be creatable) and be writable; a
  folder the run writes into (``--figures DIR``, compare's and klipper's
  ``--out DIR``) must not be a symbolic link either
  (:func:`check_output_folder`), checked up front and again when it is made
  (:func:`output_folder`).
  At write time :func:`check_replaceable` applies the same rules again
  (the file system may have changed meanwhile), and inside a run
  (:func:`run_scope`, which the command line enters) every regular file read
  as an input is remembered, so that no write replaces one, whatever option
  or derived name (a hybrid's module files) points there.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import stat
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Mapping

from ..errors import InputError

__all__ = [
    "MAX_CSV_BYTES", "MAX_TOML_BYTES", "MAX_JSON_STATE_BYTES", "MAX_CHECKPOINT_BYTES", "STDIN_NAMES",
    "read_input_bytes", "read_input_text", "check_inputs", "check_outputs", "check_replaceable", "check_figure_path",
    "figure_format", "run_scope", "format_bytes", "file_kind", "check_output_folder", "output_folder",
]

MiB = 1 << 20
#: Largest CSV input (recording, pose file, error table, grid), bytes: 256 MiB, about two million poses.
MAX_CSV_BYTES = 256 * MiB
#: Largest machine file (TOML) or module file, bytes: 16 MiB (a machine file is a few kB).
MAX_TOML_BYTES = 16 * MiB
#: Largest state file of a comparison (``config.json``, ``trials.jsonl``), bytes: 1 GiB.
MAX_JSON_STATE_BYTES = 1024 * MiB
#: Largest MCMC checkpoint (.npz), bytes: 4 GiB.
MAX_CHECKPOINT_BYTES = 4096 * MiB

#: Names under which standard input is read (it may be a pipe; read once per run).
STDIN_NAMES = ("/dev/stdin", "/dev/fd/0", "/proc/self/fd/0")


def format_bytes(n: float) -> str:
    """``1536`` -> ``"1.5 KiB"``: a size for messages."""
    n = float(n)
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.0f} bytes" if unit == "bytes" else f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} EiB"  # pragma: no cover


def file_kind(mode: int) -> str:
    """What a file of ``st_mode`` is, for messages (``"a named pipe (FIFO)"``)."""
    for test, what in ((stat.S_ISREG, "a regular file"), (stat.S_ISDIR, "a folder"), (stat.S_ISLNK, "a symbolic link"),
                       (stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return what
    return "not a regular file"  # pragma: no cover


# ---------------------------------------------------------------------------------------------- run scope
@dataclass
class _Run:
    """What one run has read: the identities of its input files, and standard input's bytes."""

    inputs: dict = field(default_factory=dict)  # (st_dev, st_ino) -> the path as given
    stdin: bytes | None = None
    outputs: dict = field(default_factory=dict)  # (st_dev, st_ino) -> (label, path) of the run's declared outputs


_RUN: contextvars.ContextVar[_Run | None] = contextvars.ContextVar("bayescal_run", default=None)
#: Outside a run scope standard input is still read once per process (it cannot be read twice).
_PROCESS = _Run()


@contextlib.contextmanager
def run_scope(outputs: Mapping[str, str | os.PathLike] | None = None) -> Iterator[None]:
    """Within this block every input read is remembered and no output may replace it (the command line's run).

    ``outputs`` (label -> path, as for :func:`check_outputs`) are the files the run will write: an input
    read within the block that *is* one of them (a hybrid's module file, the URDF a machine file names,
    any file found only by reading another) is refused when it is read, before any computation, instead
    of when the output is written.
    """
    run = _Run()
    for label, path in (outputs or {}).items():
        if path is None or not str(path) or _is_stdin(str(path)):
            continue
        try:
            st = os.stat(path)
        except OSError:  # not there yet: no input can be it
            continue
        run.outputs.setdefault((st.st_dev, st.st_ino), (label, str(path)))
    token = _RUN.set(run)
    try:
        yield
    finally:
        _RUN.reset(token)


def _input_of_run(st: os.stat_result) -> str | None:
    run = _RUN.get()
    return None if run is None else run.inputs.get((st.st_dev, st.st_ino))


# ---------------------------------------------------------------------------------------------- inputs
def _is_stdin(path: str) -> bool:
    return path in STDIN_NAMES


def _read_stdin(limit: int, what: str, err: Callable[[str], Exception]) -> bytes:
    run = _RUN.get() or _PROCESS
    if run.stdin is None:
        try:
            if os.isatty(sys.stdin.fileno()):
                raise err(f"standard input is a terminal; expected {what} piped in (... < file.csv)")
        except (AttributeError, ValueError, OSError):
            pass  # a replaced sys.stdin (tests, embedding) has no descriptor: read it as it is
        stream = getattr(sys.stdin, "buffer", None)
        if stream is None:
            raise err(f"standard input cannot be read; expected {what}")
        data = stream.read(limit + 1)
        run.stdin = data if isinstance(data, bytes) else str(data).encode("utf-8")
    if len(run.stdin) > limit:
        raise err(f"more than the limit of {format_bytes(limit)} for {what}")
    return run.stdin


def read_input_bytes(
    path: str | os.PathLike, what: str, *, limit: int, error: Callable[[str], Exception] | None = None,
    protect: bool = True,
) -> bytes:
    """The bytes of an input file: a regular file of at most ``limit`` bytes, or standard input.

    Parameters
    ----------
    path : path-like
        The file; ``/dev/stdin`` (or ``/dev/fd/0``) reads standard input once per run.
    what : str
        What the file should be, for messages (``"a recording (CSV)"``).
    limit : int
        Largest accepted size, bytes.
    error : callable, optional
        ``error(message) -> Exception`` for the caller's error class (a
        RecordingError naming the file); default ``InputError("<path>: <message>")``.
    protect : bool
        Remember the file as an input of the run (:func:`run_scope`): no output
        may replace it.  False for state a run reads and rewrites (a
        checkpoint, a comparison's saved trials).

    Raises
    ------
    Exception
        From ``error``: a missing or unreadable file, a folder, a named pipe,
        a device or socket, a file larger than ``limit``.
    """
    name = str(path)
    err = error or (lambda message: InputError(f"{name}: {message}"))
    if _is_stdin(name):
        return _read_stdin(limit, what, err)
    try:
        st = os.stat(name)
    except (FileNotFoundError, NotADirectoryError):
        raise err(f"file not found; expected {what}") from None
    except OSError as exc:
        raise err(f"cannot read it ({exc.strerror or exc}); expected {what}") from None
    _check_regular_input(st, limit, what, err)
    try:
        # O_NONBLOCK: had the file been swapped for a named pipe since the stat, opening it would
        # wait for a writer forever; fstat on the open file then refuses it
        fd = os.open(name, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise err(f"cannot read it ({exc.strerror or exc}); expected {what}") from None
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fd)
        _check_regular_input(st, limit, what, err)
        try:
            data = fh.read(limit + 1)
        except OSError as exc:
            raise err(f"cannot read it ({exc.strerror or exc}); expected {what}") from None
    if len(data) > limit:
        raise err(f"more than the limit of {format_bytes(limit)} for {what}")
    run = _RUN.get()
    if protect and run is not None:
        key = (st.st_dev, st.st_ino)
        if key in run.outputs:  # found by reading another input: refused now, before any computation
            label, out = run.outputs[key]
            raise InputError(f"{label} {out}: is {name}, an input of this run ({what}); an output must not replace "
                             "an input (choose another path)")
        run.inputs.setdefault(key, name)
    return data


def _check_regular_input(st: os.stat_result, limit: int, what: str, err) -> None:
    if stat.S_ISDIR(st.st_mode):
        raise err(f"is a folder, expected {what}")
    if not stat.S_ISREG(st.st_mode):
        raise err(f"is {file_kind(st.st_mode)}, not a regular file; expected {what}")
    if st.st_size > limit:
        raise err(f"{format_bytes(st.st_size)}, more than the limit of {format_bytes(limit)} for {what}")


def read_input_text(
    path: str | os.PathLike, what: str, *, limit: int, error: Callable[[str], Exception] | None = None,
    protect: bool = True,
) -> str:
    """:func:`read_input_bytes` decoded as UTF-8 (a leading byte-order mark dropped).

    A file that is not UTF-8 raises ``error("not a UTF-8 text file (...)")``.
    """
    data = read_input_bytes(path, what, limit=limit, error=error, protect=protect)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        name = str(path)
        err = error or (lambda message: InputError(f"{name}: {message}"))
        raise err(f"not a UTF-8 text file ({exc}); expected {what}") from None


def check_inputs(inputs: Mapping[str, str | os.PathLike]) -> None:
    """Refuse, before any work, named inputs that exist but are not regular files (a folder, a pipe, a device).

    ``inputs`` maps labels (``"--machine"``) to paths; standard input is
    allowed, a missing file is left to the reader (which names what it
    expected).  The readers check again when they read.
    """
    for label, path in ((k, str(v)) for k, v in inputs.items() if v is not None and str(v)):
        if _is_stdin(path):
            continue
        try:
            st = os.stat(path)
        except OSError:
            continue
        if not stat.S_ISREG(st.st_mode):
            raise InputError(f"{label} {path}: is {file_kind(st.st_mode)}; expected a regular file")


# ---------------------------------------------------------------------------------------------- outputs
def check_replaceable(path: str | os.PathLike, label: str = "") -> None:
    """Raise InputError unless ``path`` is absent or a regular file that is not an input of the run.

    A symbolic link, a folder, a device (``/dev/null``), a named pipe or a
    socket at ``path`` is refused: bayescal writes outputs only to regular
    files, through a temporary file and a rename, and never writes through
    or replaces a link.  ``label`` (an option, ``"--json"``) prefixes the message.
    """
    where = f"{label} {path}" if label else str(path)
    st = _lstat(path, where, "file")
    if st is None:
        return
    if stat.S_ISLNK(st.st_mode):
        raise InputError(f"{where}: is a symbolic link; outputs are written only to regular files, never through or "
                         "over a link (remove the link, or give the path it points to)")
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{where}: is a folder; expected a file name")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{where}: is {file_kind(st.st_mode)}; outputs are written only to regular files "
                         "(leave the option out if the output is not wanted)")
    if (other := _input_of_run(st)) is not None:
        raise InputError(f"{where}: is {other}, an input of this run; an output must not replace an input "
                         "(choose another path)")


def _lstat(path, where: str, name: str):
    """``os.lstat(path)``, None when nothing is there; InputError (naming ``where``) when it cannot be checked."""
    try:
        return os.lstat(path)
    except FileNotFoundError:
        return None
    except NotADirectoryError:
        raise InputError(f"{where}: a part of the path before the {name} name is not a folder") from None
    except OSError as exc:
        raise InputError(f"{where}: cannot be checked ({exc.strerror or exc})") from None


def check_output_folder(path: str | os.PathLike, label: str = "") -> None:
    """Raise InputError when the output folder ``path`` is a symbolic link or exists and is not a folder.

    Files are written into an output folder by name: through a link they would land wherever it
    points (a planted link), so a link is refused as it is for a single output file
    (:func:`check_replaceable`). A folder that does not exist is fine (it is created).
    """
    where = f"{label} {path}" if label else str(path)
    st = _lstat(path, where, "folder")
    if st is None:
        return
    if stat.S_ISLNK(st.st_mode):
        raise InputError(f"{where}: is a symbolic link; output files are written only into real folders, never "
                         "through a link (remove the link, or give the folder it points to)")
    if not stat.S_ISDIR(st.st_mode):
        raise InputError(f"{where}: exists and is not a folder; expected a folder for the output files")


def output_folder(path: str | os.PathLike, label: str = "") -> Path:
    """The output folder ``path``, checked (:func:`check_output_folder`) and created with its parents if missing."""
    check_output_folder(path, label)
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{(label + ' ') if label else ''}{path}: cannot create the folder ({exc.strerror or exc})") \
            from None
    check_output_folder(out, label)  # not swapped for a link while it was made
    return out


#: Figure formats matplotlib's Agg-based canvas writes, by file suffix.
FIGURE_FORMATS = ("png", "pdf", "svg", "svgz", "eps", "ps", "jpg", "jpeg", "tif", "tiff", "webp", "pgf")


def figure_format(path: str | os.PathLike, label: str = "figure") -> str:
    """The figure format of ``path``'s suffix (``"png"``); InputError naming the path otherwise."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in FIGURE_FORMATS:
        got = f"the suffix '.{suffix}'" if suffix else "no suffix"
        raise InputError(f"{label} {path}: {got}; expected a figure file name ending in "
                         + ", ".join("." + f for f in FIGURE_FORMATS[:4]) + " or another format matplotlib writes")
    return suffix


def check_figure_path(path: str | os.PathLike, label: str = "figure") -> None:
    """A figure output: a suffix matplotlib writes (:func:`figure_format`)."""
    figure_format(path, label)


def _identity(path: str) -> tuple:
    """What makes two output paths the same file: the file's identity if it exists, else its real folder and name."""
    try:
        st = os.stat(path)
        return ("file", st.st_dev, st.st_ino)
    except OSError:
        p = Path(path)
        return ("new", os.path.realpath(p.parent if str(p.parent) else "."), p.name)


def _check_folder(label: str, path: str, folder: Path, mkdir: bool) -> None:
    """The folder ``folder`` of output ``path`` exists and is writable (or, with ``mkdir``, can be created)."""
    probe = folder
    while not probe.exists():
        if not mkdir:
            raise InputError(f"{label} {path}: the folder {folder} does not exist (create it, or add --mkdir)")
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise InputError(f"{label} {path}: {probe} is not a folder")
    if probe.exists() and not os.access(probe, os.W_OK | os.X_OK):
        raise InputError(f"{label} {path}: cannot write into the folder {probe} (permission denied)")


def check_outputs(
    outputs: Mapping[str, str | os.PathLike],
    inputs: Mapping[str, str | os.PathLike] | None = None,
    *,
    folders: Mapping[str, str | os.PathLike] | None = None,
    mkdir: bool = False,
) -> None:
    """Refuse, before any computation, outputs that would overwrite an input, each other, or anything not a file.

    Parameters
    ----------
    outputs : mapping of str to path
        The files a run will write, by label (the option as the user typed
        it, ``"--json"``; derived files by a description).
    inputs : mapping of str to path, optional
        The files it reads, by label.
    folders : mapping of str to path, optional
        Folders the run writes into (``--figures DIR``): created when
        missing; an existing one must be a folder.
    mkdir : bool
        Whether missing folders of ``outputs`` may be created.

    Raises
    ------
    InputError
        Naming both options when an output is an input (same file, also
        through a link or a hard link) or two outputs are the same file;
        naming the option when a target is a link, a folder, a device or a
        named pipe (:func:`check_replaceable`), or its folder is missing or
        not writable; when one of ``folders`` is a link or not a folder.
    """
    inputs = {k: str(v) for k, v in (inputs or {}).items() if v is not None and str(v)}
    folders = {k: str(v) for k, v in (folders or {}).items() if v is not None and str(v)}
    created = {os.path.realpath(v) for v in folders.values()}  # files inside them need no --mkdir
    seen: dict[tuple, tuple[str, str]] = {}
    for label, path in ((k, str(v)) for k, v in outputs.items() if v is not None and str(v)):
        for in_label, in_path in inputs.items():
            if _is_stdin(in_path):
                continue
            try:
                same = os.path.samefile(path, in_path)
            except OSError:  # one of them does not exist (yet): not the same file
                same = False
            if same:
                raise InputError(f"{label} {path} is the same file as {in_label} {in_path}: an output must not "
                                 "replace an input of the same run (choose another output path)")
        check_replaceable(path, label)
        key = _identity(path)
        if key in seen:
            other_label, other = seen[key]
            raise InputError(f"{other_label} {other} and {label} {path} are the same file; give each output its own path")
        seen[key] = (label, path)
        parent = Path(path).parent if str(Path(path).parent) else Path(".")
        _check_folder(label, path, parent, mkdir or os.path.realpath(parent) in created)
    for label, path in folders.items():
        check_output_folder(path, label)  # a link, or a file in the way
        _check_folder(label, path, Path(path), True)
