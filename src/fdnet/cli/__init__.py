"""`fdnet` command line: a thin layer over the package.

Each sub-command lives in its own module under ``fdnet.cli`` and exposes
``register(subparsers)``, which adds its parser and sets ``func`` (called with the parsed args).
Modules import heavy dependencies inside ``func`` so ``fdnet --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import shlex
import sys

from fdnet.errors import FdnetError
from fdnet.io import forget_inputs
from fdnet.logs import command_logging, level_for
from fdnet.version import __version__

# Order = order in `fdnet --help`.
COMMAND_MODULES = [
    "synth",
    "train",
    "extract",
    "export",
    "evaluate",
    "calibrate",
    "match",
    "database",
    "loop_closure",
    "groundtruth",
    "vocabulary",
    "methods",
    "choose_trunk",
    "benchmark",
    "reproduce",
    "table",
    "demo",
]


class _Parser(argparse.ArgumentParser):
    """argparse's parser, whose "expected one argument" also says how to give a value that starts
    with '-' (a file named -x.csv reads as a flag otherwise). Sub-commands inherit it."""

    def error(self, message):
        if "expected one argument" in message:
            message += " (a value that starts with '-' is given with '=', e.g. --out=-x.csv)"
        super().error(message)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="fdnet",
        description="Appearance-invariant visual place recognition (FDNet and baselines).",
    )
    parser.add_argument("--version", action="version", version=f"fdnet {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        module_name = f"fdnet.cli.{name}"
        if importlib.util.find_spec(module_name) is None:
            continue
        importlib.import_module(module_name).register(sub)
    _add_source_arguments(sub)
    _add_logging_arguments(sub)
    return parser


def _add_logging_arguments(subparsers) -> None:
    """--quiet and --verbose on every (sub-)command (:mod:`fdnet.logs`)."""
    for parser in set(subparsers.choices.values()):
        nested = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        for action in nested:
            _add_logging_arguments(action)
        if not nested:
            group = parser.add_mutually_exclusive_group()
            group.add_argument(
                "-q",
                "--quiet",
                action="store_true",
                help="only warnings and errors on standard error (no progress bars)",
            )
            group.add_argument("-v", "--verbose", action="store_true", help="debug messages too")
            # so that an argument no command takes is refused by the command's parser, whose
            # message names it ("fdnet database build: error: unrecognized arguments: ...")
            parser.set_defaults(command_parser=parser)


def _add_source_arguments(subparsers) -> None:
    """The video/bag sampling flags on every (sub-)command that takes images
    (:func:`fdnet.cli.common.add_source_arguments`)."""
    from fdnet.cli.common import add_source_arguments

    for parser in set(subparsers.choices.values()):
        nested = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        for action in nested:
            _add_source_arguments(action)
        if not nested:
            add_source_arguments(parser)


def _one_line(message) -> str:
    """An error as one line: a library's own text may span several (PyYAML's caret under the
    offending column, a traceback-like detail); a command's error never does."""
    text = str(message)
    return " ".join(text.split()) if "\n" in text or "\r" in text else text


def _reader_left() -> int:
    """The reader of standard output closed it (``fdnet ... | head``): end quietly, as Unix tools
    do, with the shell's code for SIGPIPE; output still buffered goes nowhere instead of raising
    again when Python flushes at exit."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no real stdout (a test's capture): nothing to redirect
        pass
    return 141


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        (getattr(args, "command_parser", None) or parser).error(f"unrecognized arguments: {' '.join(unknown)}")
    # what was typed, for records that name the command (a run's changes.yaml and lock file)
    args.command_line = shlex.join(["fdnet", *(sys.argv[1:] if argv is None else argv)])
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        # the library's messages: standard error, "fdnet COMMAND: ..." (fdnet.logs)
        with command_logging(args.command, level_for(getattr(args, "quiet", False), getattr(args, "verbose", False))):
            forget_inputs()  # the files this command reads are protected from its outputs (fdnet.io)
            if hasattr(args, "fps"):  # a command that takes images: its video/bag sampling flags
                from fdnet.cli.common import source_options
                from fdnet.data.sources import using_options

                with using_options(source_options(args)):
                    result = args.func(args)
            else:
                result = args.func(args)
            sys.stdout.flush()  # a reader that left (| head) is met here, not at the interpreter's exit
    except BrokenPipeError:
        return _reader_left()
    except FdnetError as exc:
        _traceback_when_verbose(exc, args)
        _error_line(f"fdnet {args.command}: error: {_one_line(exc)}")
        return 2
    except Exception as exc:  # noqa: BLE001 (re-raised below unless it is the environment's)
        # The one place where a full disk, a read-only folder, a permission or a file name that
        # is not UTF-8 becomes one line (whatever command and library call met it); anything
        # else is a bug and keeps its traceback.
        message = _environment_message(exc, args)
        if message is None:
            raise
        _traceback_when_verbose(exc, args)
        _error_line(f"fdnet {args.command}: error: {_one_line(message)}")
        return 2
    except KeyboardInterrupt:
        print(f"fdnet {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(result or 0)


def _traceback_when_verbose(exc: BaseException, args: argparse.Namespace) -> None:
    """With ``--verbose``, the traceback of a refused command, its causes chained (what raised
    first: the OS error, the parser's ValueError), before the one error line."""
    if getattr(args, "verbose", False):
        import traceback

        sys.stderr.write("".join(traceback.format_exception(exc)))


def _error_line(text: str) -> None:
    """One error line in one write: processes of a torchrun group share standard error, and a
    line written as message then newline could run into another process's."""
    sys.stderr.write(text + "\n")
    sys.stderr.flush()


#: arguments naming what a command writes, named in an error that carries no path of its own
OUTPUT_ARGUMENTS = ("out", "json", "plots", "db")


def _environment_message(exc: BaseException, args: argparse.Namespace) -> str | None:
    from fdnet.errors import os_error_message

    if isinstance(exc, MemoryError):
        return f"out of memory ({exc or 'an allocation failed'}); use smaller inputs or settings"
    outputs = tuple(getattr(args, name) for name in OUTPUT_ARGUMENTS if isinstance(getattr(args, name, None), str))
    return os_error_message(exc, outputs)


def run(argv: list[str] | None = None) -> None:
    """The ``fdnet`` command: :func:`main`, then the exit that a process of a torchrun group needs
    (:func:`fdnet.torchrun.exit_process`)."""
    from fdnet.torchrun import exit_process

    exit_process(main(argv))


if __name__ == "__main__":  # pragma: no cover
    run()
