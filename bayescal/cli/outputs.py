"""What every command does with its files: --report, --mkdir, the paths checked up front, saying what it wrote.

One call per command: :func:`add_output_options` adds ``--report PATH.html``
and ``--mkdir``; :func:`write_json`, :func:`write_calibrated_machine` and
:func:`write_report` write atomically and say on stderr what they wrote
(stdout stays the report text, so it can be piped).  :func:`check_run_paths`
runs before any command: it lists the run's input and output files from
the options (and the files a command writes beside them) and applies
:func:`bayescal.io.safe_paths.check_outputs`: an output that is an input,
two outputs that are one file, a link, device or folder as an output, a
figure name matplotlib cannot write, or a folder that does not exist
(unless ``--mkdir``) is an error naming the options, before minutes of
computing.

Importing this module loads no numpy (every command's parser uses it; issue 31): the library is imported
where a file is written.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import sys
from pathlib import Path

from ..errors import InputError

__all__ = [
    "add_output_options", "check_run_paths", "check_option_values", "run_paths", "say", "write_json",
    "write_calibrated_machine", "write_report", "run_inputs", "progress_sink",
]

#: Options naming one output file, by ``dest`` (``--out`` is a folder for the commands in OUT_FOLDERS).
FILE_OUTPUTS = ("json", "report", "write_machine", "write_klipper", "write_urdf", "truth", "nc", "out", "posterior",
                "checkpoint", "figure")
#: Options naming a folder the command writes figures into (created when missing).
FOLDER_OUTPUTS = ("figures",)
#: Options naming a figure file (its suffix must be a format matplotlib writes).
FIGURE_OUTPUTS = ("figure",)
#: Commands whose --out is a folder, and the files they write into it.
OUT_FOLDERS = {
    "compare": ("table.txt", "comparison.json", "config.json", "trials.jsonl"),
    "klipper": ("machine.toml", "recording.csv"),
}
#: Options naming input files, hashed into the report (and never to be overwritten).
INPUT_FILES = ("recording", "machine", "errors", "grid", "evaluate", "poses_file", "given", "separate", "config",
               "resume_from")


def add_output_options(p: argparse.ArgumentParser, *, report: bool = True) -> None:
    """``--report PATH.html`` (unless ``report=False``) and ``--mkdir``."""
    g = p.add_argument_group("output files")
    if report:
        g.add_argument(
            "--report", metavar="PATH.html",
            help="write a self-contained HTML report (inputs and their sha256, results, figures); open it in any browser",
        )
    g.add_argument("--mkdir", action="store_true", help="create missing folders of the output files (default: error)")


def _label(key: str) -> str:
    return key if key in ("recording", "config") else "--" + key.replace("_", "-")


def run_paths(args: argparse.Namespace) -> tuple[dict, dict, dict]:
    """The run's ``(inputs, outputs, folders)`` by label (the option as typed), from the parsed options.

    Outputs include what a command writes beside the named ones: simulate's
    truth JSON and machine file, the files compare and klipper write into
    their ``--out`` folder.
    """
    inputs = {_label(k): v for k in INPUT_FILES if isinstance(v := getattr(args, k, None), str) and v}
    outputs, folders = {}, {}
    command = getattr(args, "command", "")
    for key in FILE_OUTPUTS:
        value = getattr(args, key, None)
        if not isinstance(value, str) or not value:
            continue
        if key == "out" and command in OUT_FOLDERS:
            folders["--out"] = value
            outputs.update({f"--out's {name}": str(Path(value) / name) for name in OUT_FOLDERS[command]})
        else:
            outputs[_label(key)] = value
    if command == "simulate" and getattr(args, "out", None):
        truth = Path(args.truth) if getattr(args, "truth", None) else Path(args.out).with_suffix(".truth.json")
        outputs.setdefault("--truth", str(truth))
        outputs["the true machine file beside --truth"] = str(truth.with_suffix(".toml"))
    folders.update({_label(k): v for k in FOLDER_OUTPUTS if isinstance(v := getattr(args, k, None), str) and v})
    return inputs, outputs, folders


def check_run_paths(args: argparse.Namespace) -> None:
    """Before any command: the output paths and formats checked against the inputs (module docstring)."""
    from ..io.safe_paths import check_figure_path, check_inputs, check_outputs

    inputs, outputs, folders = run_paths(args)
    for label, value in {**outputs, **folders}.items():
        if value == "-":
            # no output goes to standard output (it carries the report): '-' would be written as a file named '-'
            raise InputError(f"{label} -: expected a file name; '-' is not standard output here (stdout carries "
                             "the report: give a file, e.g. answer.json)")
    check_inputs(inputs)  # a named pipe or a device named as an input: refused before it could block or flood
    check_outputs(outputs, inputs, folders=folders, mkdir=bool(getattr(args, "mkdir", False)))
    for key in FIGURE_OUTPUTS:
        if isinstance(value := getattr(args, key, None), str) and value:
            check_figure_path(value, _label(key))
    report = getattr(args, "report", None)
    if isinstance(report, str) and report and Path(report).suffix.lower() not in (".html", ".htm"):
        # an HTML page was written under rep.pdf, which no PDF viewer opens
        raise InputError(f"--report {report}: the report is an HTML page; expected a file name ending in .html")


def check_option_values(args: argparse.Namespace) -> None:
    """Values every command refuses alike: an empty value, a seed outside 0..2**32-1, a number that is NaN or infinite,
    a ``BAYESCAL_PROGRESS`` that says neither on nor off."""
    from ..limits import check_seed
    from ..progress import progress_wanted

    progress_wanted()  # BAYESCAL_PROGRESS: a value it does not know is refused, also when no line would be written
    _check_no_empty_value(getattr(args, "argv", None) or [])
    if getattr(args, "seed", None) is not None:
        check_seed(args.seed, "--seed")
    for key, value in vars(args).items():
        values = value if isinstance(value, list) else [value]
        for v in values:
            if isinstance(v, float) and not math.isfinite(v):
                raise InputError(f"{_label(key)}: expected a finite number, got {v}")


def _check_no_empty_value(words: list) -> None:
    """Refuse a value typed empty (``--json ''``, ``--discrepancy-inputs ''``): it was taken as not given, silently."""
    for i, word in enumerate(words):
        if not isinstance(word, str):
            continue
        if word.startswith("--") and word.endswith("=") and len(word) > 3:
            raise InputError(f"{word[:-1]}: empty value; expected a value (leave the option out for its default)")
        if not word.strip():
            prev = words[i - 1] if i and isinstance(words[i - 1], str) and words[i - 1].startswith("-") else None
            raise InputError(f"{prev}: empty value; expected a value (leave the option out for its default)" if prev
                             else "an empty argument; expected a file name or a value")


def progress_sink(args: argparse.Namespace):
    """Where the library's progress lines go (:mod:`bayescal.progress`): stderr, unless asked for silence.

    ``--quiet``, ``--no-progress`` or ``BAYESCAL_PROGRESS=off`` give None (no lines).  The lines start
    after a few seconds, so a quick run prints none (docs/cli.md, "Limits").
    """
    from ..progress import StderrProgress, progress_wanted

    if getattr(args, "quiet", False) or getattr(args, "progress", None) is False or getattr(args, "no_progress", False):
        return None
    if not progress_wanted():  # BAYESCAL_PROGRESS=off
        return None

    return StderrProgress(getattr(args, "command", "") or "")


def say(args: argparse.Namespace, message: str) -> None:
    """One line on stderr about a file written (nothing with --quiet)."""
    if not getattr(args, "quiet", False):
        print(message, file=sys.stderr)


def write_json(args: argparse.Namespace, data, path: str | None = None) -> Path | None:
    """Write the JSON answer to ``path`` (default ``args.json``) atomically and say so; nothing without a path."""
    path = path or getattr(args, "json", None)
    if not path:
        return None
    from ..io import write_json_atomic

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
    from ..io import write_text_atomic
    from ..report import render_report

    html = render_report(kind, result, inputs=run_inputs(args), **extra)
    out = write_text_atomic(path, html)
    say(args, f"wrote {out} (HTML report; open it in a browser)")
    return out


def write_calibrated_machine(args: argparse.Namespace, machine, theta) -> Path | None:
    """Write the calibrated machine (``nominal + theta``) to ``args.write_machine`` and say so.

    Every kind is one file (its ``[effect.*]`` and ``[instrument]`` tables
    kept), except a hybrid machine, which is written in docs/formats.md section
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
