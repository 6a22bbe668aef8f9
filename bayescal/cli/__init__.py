"""The ``bayescal`` command line: argument parsing only; the work is in the library.

Exit codes: 0 success; 1 the computation ran but did not succeed (for
example an identification that did not converge); 2 bad input or usage (a
one-line message on stderr names the file, row or key).
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
import warnings

from ..errors import BayescalError

__all__ = ["main", "build_parser", "EXIT_OK", "EXIT_FAILED", "EXIT_INPUT"]

EXIT_OK, EXIT_FAILED, EXIT_INPUT = 0, 1, 2

#: Subcommand modules, each with ``register(subparsers)`` setting ``func``.
COMMANDS = ("identify", "predict", "simulate", "diagnose", "compensate", "grid", "plan", "compare", "klipper")

#: The one-line help of each command in ``bayescal --help``, which imports no command module; the modules'
#: ``register`` use the same text (tests/cli/test_cli.py checks).  A command module imports no library module
#: either until its ``run`` (its parser's choices come from :mod:`bayescal.constants`; issue 31), so
#: ``bayescal COMMAND --help`` and a usage error load no numpy.
SUMMARIES = {
    "identify": "identify geometric errors from a recording",
    "predict": "predict a new recording from a calibrated machine, with its uncertainty",
    "simulate": "simulate a recording of a machine with drawn errors",
    "diagnose": "locate and name physics the geometric model leaves out",
    "compensate": "write and evaluate BIC grids",
    "grid": "compensation grid with uncertainty per node",
    "plan": "choose measurement poses by information",
    "compare": "compare identification methods statistically",
    "klipper": "read a Klipper delta printer.cfg with a saved calibration",
}

_EPILOG = """\
examples:
  bayescal simulate --machine examples/prs3/machine.toml --poses 36 --seed 1 --out rec.csv
  bayescal identify examples/prs3/recording.csv --machine examples/prs3/machine.toml
  bayescal identify rec.csv --machine m.toml --method tsvd --k 25 --json answer.json

exit codes: 0 success, 1 computed but not successful, 2 bad input or usage.
Run 'bayescal COMMAND --help' for each command.
"""


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line: the error and a hint, not the whole usage.

    A value that starts with a minus sign and a number is a value, not an option: argparse (3.12) took
    ``--pivot -10,0,80``, ``--centre -5,0,0`` and ``--x-range -3e2 3e2`` for options and refused them
    ("expected one argument"); no option of bayescal starts with a digit.

    Options are spelled out: argparse's prefix matching would let a script's ``--fi`` mean ``--figures``
    today and be refused as ambiguous once ``--fix`` exists, or ``--lam`` reach an option added later.
    """

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?([,:;].*)?$")

    def error(self, message: str):  # argparse's hook for every usage error
        # one line, like every other exit-2 error: the hint folded into it
        prog, hint = self._unrecognised(message) if message.startswith("unrecognized arguments") else (self.prog, "")
        self.exit(EXIT_INPUT, f"{prog}: error: {_one_line_text(message)}{hint}; run '{prog} --help' for the options\n")

    def _unrecognised(self, message: str) -> tuple[str, str]:
        """The command whose options an unknown one was meant for (argparse reports it at the top level) and
        the closest of them ("did you mean --method?")."""
        import difflib

        sub = next((a for a in self._actions if isinstance(a, argparse._SubParsersAction)), None)
        words = message.split(":", 1)[-1].split()
        argv = getattr(self, "words", sys.argv[1:])  # main's words (tests call main with their own)
        command = next((sub.choices[w] for w in argv if sub is not None and w in sub.choices), None)
        if command is None:
            return self.prog, ""
        options = [o for a in command._actions for o in a.option_strings if o.startswith("--")]
        close = difflib.get_close_matches(words[0].split("=")[0], options, n=1) if words else []
        return command.prog, f" (did you mean {close[0]}?)" if close else ""


def build_parser(commands=COMMANDS) -> argparse.ArgumentParser:
    """The command line's parser with the full options of ``commands`` (default: every command).

    The other commands are listed with their one-line help only (:data:`SUMMARIES`),
    without importing their modules: :func:`main` registers just the command it runs.
    """
    from .. import __version__

    parser = _Parser(
        prog="bayescal",
        description="Kinematic calibration of parallel manipulators and hybrid machine tools.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"bayescal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        if name in commands:
            importlib.import_module(f".{name}", __name__).register(sub)
        else:
            sub.add_parser(name, help=SUMMARIES[name])
    return parser


def _command_in(argv: list[str]) -> str | None:
    """The command ``argv`` names: its first word that is no option (the top level's take no values)."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit code."""
    words = list(sys.argv[1:] if argv is None else argv)
    command = _command_in(words)
    parser = build_parser(() if command is None else (command,))
    parser.words = words
    args = parser.parse_args(words)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_INPUT
    args.argv = words  # for the report's inputs
    try:
        from ..io.safe_paths import run_scope
        from ..progress import reporting
        from .outputs import check_option_values, check_run_paths, progress_sink, run_paths

        # option values, output paths and formats before any computation; within the run no
        # output may replace a file it read (bayescal.io.safe_paths)
        check_option_values(args)
        check_run_paths(args)
        # ... and an input found only by reading another (a hybrid's module, a URDF) that is an output: when read
        with warnings.catch_warnings(), run_scope(run_paths(args)[1]), reporting(progress_sink(args)):
            # numerical trouble is reported in the result and the exit code, not as a warning dump
            warnings.simplefilter("ignore")
            return int(args.func(args))
    except BayescalError as exc:
        print(f"bayescal {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    except MemoryError as exc:
        # the estimates of bayescal.limits.check_memory refuse large requests up front; this is the rest
        print(f"bayescal {args.command}: error: out of memory{_memory_detail(exc)}; make the request smaller "
              "(fewer nodes, poses, candidates or steps)", file=sys.stderr)
        return EXIT_INPUT
    except RecursionError:
        print(f"bayescal {args.command}: error: an input nested too deeply to read (a file including itself, or "
              "tables nested hundreds deep)", file=sys.stderr)
        return EXIT_INPUT
    except BrokenPipeError:
        # the reader of our output went away (`bayescal ... | head`): stop quietly
        import os

        try:  # and let the interpreter's final flush of stdout go nowhere
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):
            pass
        return 141  # 128 + SIGPIPE, what the shell reports for a program killed by a closed pipe
    except OSError as exc:
        # a file that cannot be read or written (permissions, a folder in the way, a full
        # disk): one line naming the file, like any other bad input, not a traceback
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"bayescal {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print(f"bayescal {args.command}: interrupted", file=sys.stderr)
        return 130


def _one_line(exc: BaseException) -> str:
    """The message on one line (a value quoted from a file may hold line breaks)."""
    return _one_line_text(str(exc))


def _one_line_text(text: str) -> str:
    """``text`` on one line: its line breaks (a quoted value may hold them) become spaces."""
    return " ".join(text.splitlines()) if text else text


def _memory_detail(exc: MemoryError) -> str:
    text = str(exc)
    return f" ({text})" if text else ""


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
