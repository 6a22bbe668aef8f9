"""What every command does with its output files: --report, --mkdir, and saying what it wrote.

One call per command: :func:`add_output_options` adds ``--report PATH.html``
and ``--mkdir``; :func:`write_json`, :func:`write_calibrated_machine` and
:func:`write_report` write atomically and say on stderr what they wrote
(stdout stays the report text, so it can be piped).  :func:`check_output_folders`
runs before any command: an answer file into a folder that does not exist
is an error naming the folder, before minutes of computing, unless
``--mkdir`` asks for it.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

from ..errors import InputError
from ..io import write_json_atomic, write_text_atomic

__all__ = ["add_output_options", "check_output_folders", "say", "write_json", "write_calibrated_machine", "write_report", "run_inputs"]

#: Options naming one output file whose folder must exist (or --mkdir).
FILE_OUTPUTS = ("json", "report", "write_machine", "truth", "nc", "out_csv", "posterior", "figure")
#: Options naming input files, hashed into the report.
INPUT_FILES = ("recording", "machine", "errors", "grid", "evaluate", "poses_file", "resume_from")


def add_output_options(p: argparse.ArgumentParser, *, report: bool = True) -> None:
    """``--report PATH.html`` (unless ``report=False``) and ``--mkdir``."""
    g = p.add_argument_group("output files")
    if report:
        g.add_argument(
            "--report", metavar="PATH.html",
            help="write a self-contained HTML report (inputs and their sha256, results, figures); open it in any browser",
        )
    g.add_argument("--mkdir", action="store_true", help="create missing folders of the output files (default: error)")


def check_output_folders(args: argparse.Namespace) -> None:
    """An InputError naming the first output file whose folder does not exist (unless ``--mkdir``)."""
    if getattr(args, "mkdir", False):
        return
    for key in FILE_OUTPUTS:
        path = getattr(args, key, None)
        if not isinstance(path, str) or not path:
            continue
        folder = Path(path).parent
        if not folder.is_dir():
            opt = {"truth": "--json/--truth"}.get(key, "--" + key.replace("_", "-"))
            raise InputError(f"{opt} {path}: the folder {folder} does not exist (create it, or add --mkdir)")


def say(args: argparse.Namespace, message: str) -> None:
    """One line on stderr about a file written (nothing with --quiet)."""
    if not getattr(args, "quiet", False):
        print(message, file=sys.stderr)


def write_json(args: argparse.Namespace, data, path: str | None = None) -> Path | None:
    """Write the JSON answer to ``path`` (default ``args.json``) atomically and say so; nothing without a path."""
    path = path or getattr(args, "json", None)
    if not path:
        return None
    out = write_json_atomic(path, data)
    say(args, f"wrote {out} (JSON answer)")
    return out


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def run_inputs(args: argparse.Namespace) -> dict:
    """The inputs of this run for a report: command line, files with sha256, versions."""
    from ..report.context import versions

    files = []
    for key in INPUT_FILES:
        value = getattr(args, key, None)
        if isinstance(value, str) and value and Path(value).is_file():
            files.append({"option": key.replace("_", "-"), "path": value, "sha256": _sha256(Path(value)),
                          "bytes": Path(value).stat().st_size})
    argv = getattr(args, "argv", None)
    command = "bayescal " + " ".join(argv) if argv is not None else "bayescal " + " ".join(sys.argv[1:])
    return {"command": command, "files": files, "versions": versions()}


def write_report(args: argparse.Namespace, kind: str, result, **extra) -> Path | None:
    """Render the HTML report of ``result`` to ``args.report`` (nothing without ``--report``) and say so.

    ``extra`` goes to :func:`bayescal.report.render_report` (machine, model, choice, ...).
    """
    path = getattr(args, "report", None)
    if not path:
        return None
    from ..report import render_report

    html = render_report(kind, result, inputs=run_inputs(args), **extra)
    out = write_text_atomic(path, html)
    say(args, f"wrote {out} (HTML report; open it in a browser)")
    return out


def write_calibrated_machine(args: argparse.Namespace, machine, theta) -> Path | None:
    """Write the calibrated machine (``nominal + theta``) to ``args.write_machine`` and say so.

    Every kind is one file (its ``[effect.*]`` and ``[instrument]`` tables
    kept), except a hybrid machine, which is written in FORMATS.md section
    5's file-per-module form (``<stem>.m<k>.toml`` beside it, listed with
    ``file = ...``) so that any reader of that format reads it; its
    ``[effect.*]`` and ``[instrument]`` tables, if any, go into the main file.
    """
    if not getattr(args, "write_machine", None):
        return None
    from ..machines.files import write_calibrated_machine_files

    paths = write_calibrated_machine_files(args.write_machine, machine, theta)
    if len(paths) == 1:
        say(args, f"wrote {paths[0]} (calibrated machine file)")
        return paths[0]
    say(args, f"wrote {', '.join(str(p) for p in paths)} (calibrated hybrid machine: main file and one file per module)")
    return paths[0]
